"""Writing a motion as a file engines and tools open: BVH (ours or on a target BVH skeleton), glTF binary (on our
skeleton, a target BVH's, or added to the user's own GLB/VRM) and VRM Animation; what `dimgestor generate` and the
recorder call."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dimgestor.bvh import BvhMotion, write_bvh
from dimgestor.retarget import gltf as io
from dimgestor.retarget.rig import Rig
from dimgestor.retarget.transfer import Retarget, Target, load_target, resolve_map
from dimgestor.retarget.vrma import write_vrma

__all__ = ["OUT_SUFFIXES", "check_output", "write_motion", "metres_per_unit"]

OUT_SUFFIXES = (".bvh", ".glb", ".vrma", ".npz")


def metres_per_unit(rig: Rig) -> float:
    """A BVH's unit, guessed from its rest height: over 20 units tall is centimetres, else metres; glTF is metres."""
    if rig.skeleton is None:
        return 1.0
    _, p = rig.rest_world()
    return 0.01 if np.ptp(p[:, 1]) > 20 else 1.0


def check_output(out: Path, target: Target | str | Path | None) -> None:
    """Refuse an output/target pair that cannot be written, before any work (a `Target` read already: its
    skeleton too)."""
    suffix = out.suffix.lower()
    if isinstance(target, Target) and suffix == ".npz" and target.rig.skeleton is not None:
        from dimgestor import smplx

        if not smplx.is_smplx(target.rig.skeleton):
            raise ValueError(f"--target {target.path}: not on the SMPL-X skeleton (its 55 joints by name); a .npz "
                             "take needs one")
    target = target.path if isinstance(target, Target) else target
    if suffix not in OUT_SUFFIXES:
        raise ValueError(f"--out {out}: expected a .bvh, .glb, .vrma or .npz (BEAT2 / SMPL-X) path")
    if target is not None and suffix == ".vrma":
        raise ValueError(f"--out {out}: a VRM Animation plays on any VRM as it is; --target is for .bvh and .glb")
    if target is not None and suffix in (".bvh", ".npz") and Path(target).suffix.lower() != ".bvh":
        if suffix == ".npz":
            raise ValueError(f"--target {target}: a .npz take is on the SMPL-X skeleton: leave --target out (the "
                             "generic one) or give a SMPL-X BVH (`dimgestor convert YOUR_TAKE.npz rig.bvh`)")
        raise ValueError(f"--target {target}: a .bvh output needs a BVH target skeleton; write .glb for a glTF/VRM rig")


def write_motion(out: str | Path, motion: BvhMotion, target: Target | str | Path | None = None,
                 target_map: str | Path | None = None, face: dict[str, np.ndarray] | None = None) -> str:
    """Write `motion` (on our skeleton) to `out` by its suffix, on our skeleton or on `target` (a `Target` as
    read once, or a rig's path with `target_map`); returns what was written, for the user."""
    out = Path(out)
    check_output(out, target)
    source = Rig.from_skeleton(motion.skeleton, "ours")
    q, t = motion.rotations(), motion.translations()
    suffix = out.suffix.lower()
    if suffix == ".vrma":
        write_vrma(out, source, resolve_map(source, what="source"), q, t, motion.fps, metres_per_unit(source), face)
        return f"VRM Animation, {len(q)} frames" + (f", {len(face)} expressions" if face else "")
    if suffix == ".npz":
        return _write_smplx(out, motion, source, target, target_map)
    if target is None:
        if suffix == ".bvh":
            write_bvh(out, motion)
            return f"BVH, {motion.num_frames} frames"
        return _write_glb(out, source, q, t, motion.fps, moved=_moving(source))
    target = target if isinstance(target, Target) else load_target(target, target_map)
    rig = target.rig
    rt = Retarget(source, rig, resolve_map(source, what="source"), target.bones)
    what = f"on {Path(target.path).name} ({len(rt.bones)} bones mapped)"
    if suffix == ".bvh":
        write_bvh(out, rt.motion(motion))
        return f"BVH {what}, {motion.num_frames} frames"
    tq, tt = rt(q, t)
    moved = sorted(set(int(j) for j in rt.target_joints)), [j for j in range(rig.num_joints)
                                                              if np.ptp(tt[:, j], axis=0).max() > 1e-9]
    if rig.nodes is None:
        return _write_glb(out, rig, tq, tt, motion.fps, moved) + f" {what}"
    gltf = io.load_for_animation(rig)
    io.add_animation(gltf, rig.nodes, motion.fps, tq, tt, rotate=moved[0], translate=moved[1])
    io.save_glb(gltf, out)
    return f"glTF binary: {Path(target.path).name} with the animation added ({len(rt.bones)} bones mapped), {len(tq)} frames"


def _write_smplx(out: Path, motion: BvhMotion, source: Rig, target: Target | str | Path | None, target_map) -> str:
    """A BEAT2 / SMPL-X take of `motion` retargeted onto the SMPL-X skeleton: the generic one, or `target` (a BVH on
    the SMPL-X skeleton, e.g. a take converted with the user's body model)."""
    from dimgestor import smplx

    if target is None:
        rig = Rig.from_skeleton(smplx.skeleton(), "the generic SMPL-X skeleton")
        target = Target(rig, resolve_map(rig))
    target = target if isinstance(target, Target) else load_target(target, target_map)
    if target.rig.skeleton is None or not smplx.is_smplx(target.rig.skeleton):
        raise ValueError(f"--target {target.rig.path}: not on the SMPL-X skeleton (its 55 joints by name); a .npz "
                         "take needs one")
    rt = Retarget(source, target.rig, resolve_map(source, what="source"), target.bones)
    smplx.write_smplx(out, rt.motion(motion))
    return (f"BEAT2 / SMPL-X take on {Path(target.rig.path).name} ({len(rt.bones)} bones mapped), "
            f"{motion.num_frames} frames")


def _moving(rig: Rig) -> tuple[list[int], list[int]]:
    """A BVH rig's joints with rotation channels and with position channels."""
    sk = rig.skeleton
    return ([j for j in range(sk.num_joints) if sk.rotation_order(j)],
            [j for j in range(sk.num_joints) if sk.has_position(j)])


def _write_glb(out: Path, rig: Rig, q: np.ndarray, t: np.ndarray, fps: float, moved) -> str:
    units = metres_per_unit(rig)
    gltf, nodes = io.skeleton_gltf(rig, units)
    io.add_animation(gltf, nodes, fps, q, t * units, rotate=moved[0], translate=moved[1])
    io.save_glb(gltf, out)
    return f"glTF binary, {rig.num_joints} joints skinned to a stick figure, {len(q)} frames"
