"""`dimgestor convert IN OUT`: motion between formats, BEAT2 / SMPL-X takes (`.npz`) and BVH (`.bvh`).

A take is read with the generic SMPL-X skeleton, or with `--smplx-model` the exact one of its betas from the
user's own body-model file; a BVH on the SMPL-X skeleton (as this command writes one) goes back to a take. The
rotations are carried exactly (to 1e-6 degrees in the BVH text), the pelvis to 1e-8 m. A BVH on another skeleton
(e.g. `serve --record`'s, or `generate`'s) is retargeted onto the generic SMPL-X skeleton by its bones' names.
"""
from __future__ import annotations

import argparse
from pathlib import Path

FORMATS = (".npz", ".bvh")


def convert(src: str | Path, dst: str | Path, smplx_model: str | Path | None = None) -> str:
    """Convert `src` into `dst` by their suffixes; returns a line saying what was written."""
    from dimgestor import smplx
    from dimgestor.bvh import read_bvh, write_bvh

    src, dst = Path(src), Path(dst)
    for p in (src, dst):
        if p.suffix.lower() not in FORMATS:
            raise ValueError(f"{p}: convert reads and writes {' and '.join(FORMATS)} (BEAT2 / SMPL-X takes and BVH)")
    extra: dict = {}
    if src.suffix.lower() == ".npz":
        motion, extra = smplx.read_smplx(src, smplx_model)
    else:
        if smplx_model is not None:
            raise ValueError("--smplx-model shapes the skeleton of a .npz take; a BVH carries its own")
        motion = read_bvh(src)
    if dst.suffix.lower() == ".bvh":
        write_bvh(dst, motion)
    elif not smplx.is_smplx(motion.skeleton):  # another rig: onto SMPL-X by its bones' names
        from dimgestor.retarget.export import write_motion

        try:
            return f"wrote {dst}: " + write_motion(dst, motion)
        except ValueError as e:
            raise ValueError(f"{src}: its skeleton cannot be retargeted onto SMPL-X: {e}") from e
    else:
        smplx.write_smplx(dst, motion, betas=extra.get("betas"), expressions=extra.get("expressions"),
                          gender=str(extra.get("gender", "neutral")))
    skeleton = "SMPL-X" if smplx.is_smplx(motion.skeleton) else f"{motion.skeleton.num_joints} joints"
    return f"wrote {dst}: {motion.num_frames} frames at {motion.fps:g} fps, {skeleton}"


def register(subparsers) -> argparse.ArgumentParser:
    """Add the `convert` subcommand to the `dimgestor` CLI."""
    from dimgestor.cli_help import examples

    p = subparsers.add_parser("convert", help="motion between formats: BEAT2 / SMPL-X takes (.npz) and BVH",
                              description=__doc__.split("\n\n")[1].replace("\n", " "),
                              epilog=examples("dimgestor convert 2_scott_0_1_1.npz scott.bvh",
                                              "dimgestor convert take.npz take.bvh --smplx-model SMPLX_NEUTRAL_2020.npz",
                                              "dimgestor convert take.bvh take.npz",
                                              "dimgestor convert recording.bvh recording.npz"))
    p.add_argument("input", metavar="IN", help="a BEAT2 / SMPL-X take (.npz) or a BVH file (.bvh)")
    p.add_argument("output", metavar="OUT", help="the file to write, its format by its suffix (.npz or .bvh)")
    p.add_argument("--smplx-model", default=None, metavar="PATH",
                   help="your SMPL-X body-model file (SMPLX_NEUTRAL_2020.npz, from its authors): the exact skeleton "
                        "of the take's betas (default: a generic adult skeleton)")
    p.set_defaults(func=lambda args: print(convert(args.input, args.output, args.smplx_model)) or 0)
    return p
