"""`dimgestor generate`: a checkpoint (or the embedded default model) + a WAV -> a 20 fps BVH, glTF binary or VRM
Animation, on our skeleton or retargeted onto the user's rig (and, with --face-csv, the face track of the same frames as
a CSV)."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from dimgestor.audio import SAMPLE_RATE, AudioError, wav_stream
from dimgestor.bvh import BvhMotion, BvhWriter
from dimgestor.cli_help import smoothing_from_flag
from dimgestor.face.stream import LISTENERS
from dimgestor.features import features_to_motion
from dimgestor.model.diffusion import check_guidance
from dimgestor.streaming.checkpoint import Bundle, load_checkpoint

__all__ = ["generate_motion", "generate_face", "register", "BLOCK_S", "WHOLE_MAX_S"]

BLOCK_S = 10.0  # a .bvh is made this much audio at a time: a recording of any length in bounded memory
WHOLE_MAX_S = 5400.0  # a .glb or .vrma holds its whole animation in memory (~1 GB an hour): up to an hour and a half


def generate_motion(bundle: Bundle, audio: np.ndarray, steps: int | None = None, seed: int = 0, sampler: str = "ddim",
                    eta: float = 0.0, smoothing="config", root: str = "free", tether_s: float = 5.0,
                    guidance: float | None = None) -> BvhMotion:
    """16 kHz mono audio -> motion on the checkpoint's skeleton at its feature rate (len(audio) * fps // SAMPLE_RATE frames)."""
    features = bundle.generate(audio, steps=steps, seed=seed, sampler=sampler, eta=eta, smoothing=smoothing,
                               guidance=guidance)
    return features_to_motion(features, bundle.skeleton, bundle.feature_spec, root=root, tether_s=tether_s)


def generate_face(audio: np.ndarray, frames: int, fps: int, lookahead_s: float, seed: int = 0,
                  listener: str = "net") -> np.ndarray:
    """The face of `frames` body frames (frames, len(FACE_LABELS)): a `FaceStream` over the whole audio with the
    model's lookahead, as a `serve` session makes it (streaming equals offline), so the same rows as its recording."""
    from dimgestor.face import FaceOptions, FaceStream

    lookahead = np.floor(min(lookahead_s, 0.3) * 100 + 1e-6) / 100  # as Session: on the listener's 10 ms grid
    face = FaceStream(fps, lookahead, FaceOptions(seed=seed, listener=listener))
    face.push(audio)
    face.finish()
    return face.take(frames)


def generate_motion_onnx(bundle: Bundle, audio: np.ndarray, onnx_dir, seed: int = 0, smoothing="config",
                         root: str = "free", tether_s: float = 5.0) -> BvhMotion:
    """`generate_motion` on ONNX Runtime: the exported frame step (`dimgestor export-onnx`) streamed over the audio
    (its K and guidance are the export's). The same frames as the torch backend to < 1e-4 (tests/test_onnx.py)."""
    from dimgestor.export.onnx_export import check_export
    from dimgestor.export.onnx_stream import load_manifest, ort_stream

    check_export(load_manifest(onnx_dir), bundle)
    stream = ort_stream(onnx_dir, seed=seed, smoothing=smoothing)
    features = bundle.denormalize(np.concatenate([stream.push(audio), stream.finish()]))
    return features_to_motion(features, bundle.skeleton, bundle.feature_spec, root=root, tether_s=tether_s)


def register(subparsers) -> None:
    from dimgestor.cli_help import deprecated_alias, examples

    p = subparsers.add_parser(
        "generate", help="generate a BVH for a WAV file (offline, as fast as the machine goes)",
        description="Generate the motion for a speech WAV file, offline (the same frames as `dimgestor serve "
                    "--record` on that file, seed and steps), and write it as a BVH, a glTF binary (.glb: Blender, "
                    "Unity, Unreal, three.js) or a VRM Animation (.vrma, with the face), on our skeleton or "
                    "retargeted onto your rig (--target). A .bvh (and its --face-csv) is made and written 10 s of "
                    "audio at a time, for a recording of any length in a few hundred MB; a .glb or .vrma holds the "
                    "whole animation (about 1 GB an hour), for recordings up to an hour and a half.",
        epilog=examples("dimgestor generate --audio speech.wav --out motion.bvh",
                        "dimgestor generate --audio speech.wav --out motion.bvh --face-csv face.csv",
                        "dimgestor generate --audio speech.wav --out motion.vrma",
                        "dimgestor generate --audio speech.wav --out mine.glb --target my_avatar.vrm",
                        "dimgestor generate --audio speech.wav --out take.npz",
                        "dimgestor generate --audio speech.wav --out motion.bvh --target mannequin.bvh --target-map map.json",
                        "dimgestor generate --audio speech.wav --out motion.bvh --checkpoint live --steps 4 --seed 3",
                        "dimgestor generate --audio speech.wav --out motion.bvh --checkpoint runs/mine --device cuda",
                        deprecated="--face OUT.csv (now --face-csv; --face names a face's name set in serve)"))
    g = p.add_argument_group("input and output")
    g.add_argument("--audio", required=True, metavar="FILE.wav", help="speech WAV (any rate, mono or stereo)")
    g.add_argument("--out", required=True, metavar="OUT.bvh|.glb|.vrma|.npz",
                   help="output file, by its suffix: .bvh (motion capture), .glb (glTF 2.0 binary: a skinned skeleton "
                        "with one animation, or your --target GLB/VRM with the animation added), .vrma (VRM "
                        "Animation: plays on any VRM, the face's expressions included), .npz (a BEAT2 / SMPL-X take "
                        "on the generic SMPL-X skeleton, or a SMPL-X --target BVH; body only)")
    g.add_argument("--target", default=None, metavar="RIG.bvh|.glb|.vrm",
                   help="retarget onto this rig, whatever its rest pose (A-pose, T-pose), bone lengths and names "
                        "(Mixamo, Unreal Mannequin, SMPL-X, VRoid, VRM): a BVH skeleton (for .bvh, .glb or .npz output) "
                        "or a glTF/GLB/VRM (for .glb output) (default: our training skeleton)")
    g.add_argument("--target-map", default=None, metavar="MAP.json",
                   help="which joint of --target is which humanoid bone, over the names recognised: "
                        "{\"leftUpperArm\": \"arm_L\", \"rightToes\": null, ...} (VRM 1.0 bone names)")
    face_csv = g.add_argument("--face-csv", default=None, metavar="OUT.csv",
                   help="also write the face made from the same speech (mouth, blinks, brows) as a CSV: a header "
                        "`time,A,I,U,E,O,...` (seconds, then the VRM 0 names, then ARKit's 52), one row per BVH "
                        "frame (the format `dimgestor serve --record` writes beside its BVH)")
    g.add_argument("--face-listener", default="net", choices=LISTENERS,
                   help="what hears the mouth in the speech: the face's own network (shipped in the package), "
                        "pocketsphinx's English phone recognizer, where it is installed, or both, their mouths "
                        "averaged (docs/face.md) (default: net)")
    # one release: `--face` meant this file here and a name set everywhere else (serve, client.py, pipecat)
    deprecated_alias(p, "--face", face_csv, note=" (--face is a name set in serve; the old spelling goes in the "
                                                 "next release)")
    g = p.add_argument_group("model and sampling")
    g.add_argument("--checkpoint", default=None,
                   help="checkpoint folder, a file in it, a run folder (its latest), or `live` (the embedded live "
                        "model) (default: the embedded default model)")
    g.add_argument("--steps", type=int, default=None, metavar="K",
                   help="DDIM steps K (ignored by ddpm, which uses all N) (default: the checkpoint's sample_steps)")
    g.add_argument("--sampler", choices=("ddim", "ddpm"), default="ddim",
                   help="'ddim': K steps (deterministic with --eta 0); 'ddpm': the model's whole chain, stochastic")
    g.add_argument("--seed", type=int, default=0, help="noise seed; same seed + audio + steps = same motion")
    g.add_argument("--speaker", default=None, metavar="NAME",
                   help="play this speaker's style, for a model trained with --speaker-condition (`dimgestor info "
                        "--checkpoint DIR` lists its speakers; default: no speaker in particular)")
    g.add_argument("--eta", type=float, default=0.0, help="DDIM stochasticity (0 = deterministic)")
    g.add_argument("--guidance", type=float, default=None, metavar="S",
                   help="classifier-free guidance scale: 1 = unguided, > 1 follows the audio more (needs a model "
                        "trained with --cond-drop; costs a second batch row) (default: the checkpoint's)")
    g.add_argument("--smooth", type=float, default=None, metavar="HZ",
                   help="One Euro output filter cutoff in Hz, 0 = off (default: the checkpoint's setting)")
    g.add_argument("--root", choices=("free", "tether", "lock"), default="free",
                   help="root ground motion: as generated, pulled back to the start, or locked "
                        "(as `dimgestor serve --root`)")
    g.add_argument("--tether-s", type=float, default=5.0, metavar="S", help="time constant of --root tether, in seconds")
    g = p.add_argument_group("compute")
    g.add_argument("--device", default="cpu", help="torch device: cpu, cuda, cuda:1, ...")
    g.add_argument("--backend", choices=("torch", "onnxruntime"), default="torch",
                   help="onnxruntime: the ONNX export streamed on ONNX Runtime's CPU provider (DDIM, eta 0; the "
                        "`onnx` extra)")
    g.add_argument("--onnx", default=None, metavar="DIR",
                   help="with --backend onnxruntime: this checkpoint's `dimgestor export-onnx` folder (its K and "
                        "guidance) (default: the export in --onnx-cache)")
    g.add_argument("--onnx-cache", default=None, metavar="DIR",
                   help="with --backend onnxruntime: where the model's export is kept; the first run with a model, K "
                        "or guidance exports it (minutes), later runs reuse it (default: as `dimgestor serve`'s)")
    p.set_defaults(func=_run)


def _run(args) -> int:
    if args.steps is not None and args.steps < 1:
        raise ValueError(f"--steps must be >= 1, got {args.steps}")
    if args.eta < 0:
        raise ValueError(f"--eta must be >= 0, got {args.eta}")
    smoothing = smoothing_from_flag(args.smooth)
    if args.guidance is not None:
        check_guidance(args.guidance)
    if not args.tether_s > 0:
        raise ValueError(f"--tether-s must be > 0, got {args.tether_s}")
    from dimgestor.retarget import load_target
    from dimgestor.retarget.export import check_output, write_motion

    out = Path(args.out)
    check_output(out, args.target)
    if args.target_map is not None and args.target is None:
        raise ValueError("--target-map needs --target (the rig it maps)")
    target = None
    if args.target is not None:  # read and map the rig once, before the model runs: a bad rig fails at once
        target = load_target(args.target, args.target_map)
        check_output(out, target)
    if not out.parent.exists():
        raise FileNotFoundError(f"--out {out}: folder {out.parent} does not exist")
    face_out = Path(args.face_csv) if args.face_csv is not None else None
    if face_out is not None:
        if not face_out.parent.exists():
            raise FileNotFoundError(f"--face-csv {face_out}: folder {face_out.parent} does not exist")
        if face_out.is_dir():
            raise IsADirectoryError(f"--face-csv {face_out}: is a folder, expected a .csv path")
        if face_out.resolve() == out.resolve():
            raise ValueError(f"--face-csv {face_out}: the same path as --out")
    if (face_out is not None or out.suffix.lower() == ".vrma") and "pocketsphinx" in args.face_listener:
        from dimgestor.face.listener import unavailable  # (a .vrma carries the face)

        if (why := unavailable()) is not None:
            raise ValueError(f"{'--face-csv' if face_out is not None else out}: {why}")
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"--device {args.device}: CUDA is not available on this machine")
    if args.speaker is not None and args.backend == "onnxruntime":
        raise ValueError("--speaker: the ONNX export plays no speaker in particular; use the torch backend")
    bundle = load_checkpoint(args.checkpoint, device=args.device)
    if args.speaker is not None:
        bundle.model.use_speaker(args.speaker)
    steps_given = args.steps is not None
    if args.steps is None:
        args.steps = bundle.config.sample_steps
    if args.steps > bundle.config.n_steps:
        raise ValueError(f"--steps {args.steps} exceeds the model's {bundle.config.n_steps} diffusion steps")
    fps = bundle.feature_spec.fps
    samples, blocks = wav_stream(args.audio, SAMPLE_RATE, BLOCK_S)
    seconds = samples / SAMPLE_RATE
    if samples * fps // SAMPLE_RATE == 0:  # `dimgestor serve` refuses it too
        raise AudioError(f"{args.audio}: {samples} audio samples, shorter than one motion frame "
                         f"({1000 / fps:g} ms): nothing to generate")
    if out.suffix.lower() == ".bvh":  # made and written a block at a time
        what, face_frames = _stream_bvh(args, bundle, blocks, samples, smoothing, steps_given, out, target, face_out)
        print(f"wrote {out} ({what}) at {fps:g} fps ({seconds:.2f} s of audio) from {bundle.path}")
        if face_out is not None:
            print(f"wrote {face_out}: the face of the same {face_frames} frames")
        return 0
    if seconds > WHOLE_MAX_S:
        raise ValueError(f"--out {out}: a {out.suffix.lower()} holds the whole animation in memory, and "
                         f"{args.audio} is {_hms(seconds)} long (at most {_hms(WHOLE_MAX_S)}): write a .bvh, made a "
                         "block at a time for any length")
    motion, face = _stream_motion(args, bundle, blocks, samples, smoothing, steps_given,
                                  face_out is not None or out.suffix.lower() == ".vrma")
    expressions = None
    if out.suffix.lower() == ".vrma":
        from dimgestor.face.names import convert, names_of

        expressions = dict(zip(names_of("vrm1"), convert(face, "vrm1").T))
    what = write_motion(out, motion, target, face=expressions)
    print(f"wrote {out} ({what}) at {1 / motion.frame_time:g} fps ({seconds:.2f} s of audio) from {bundle.path}")
    if face_out is not None:
        from dimgestor.face.track import write_track

        write_track(face_out, face, fps)
        print(f"wrote {face_out}: the face of the same {len(face)} frames")
    return 0


def _make_stream(args, bundle: Bundle, smoothing, steps_given: bool):
    """The stream the audio goes through: the model's own, or its ONNX export on ONNX Runtime."""
    if args.backend == "onnxruntime":
        return _onnx_stream(args, bundle, smoothing, steps_given)
    return bundle.stream(steps=args.steps, seed=args.seed, sampler=args.sampler, eta=args.eta, smoothing=smoothing,
                         guidance=args.guidance)


def _face_stream(bundle: Bundle, seed: int, listener: str = "net"):
    """The face as `generate_face` (and a `serve` session) makes it."""
    from dimgestor.face import FaceOptions, FaceStream

    lookahead = np.floor(min(bundle.model.lookahead_s, 0.3) * 100 + 1e-6) / 100  # on the listener's 10 ms grid
    return FaceStream(bundle.feature_spec.fps, lookahead, FaceOptions(seed=seed, listener=listener))


def _stream_motion(args, bundle: Bundle, blocks, samples: int, smoothing, steps_given: bool, with_face: bool):
    """(the motion, the face or None) of the audio `blocks`, the model streamed over them a block at a time: only
    the motion and the face are held whole (a .glb or .vrma holds them all), not the recording nor the model's
    work on all of it at once."""
    total = int(samples * bundle.feature_spec.fps // SAMPLE_RATE)
    stream = _make_stream(args, bundle, smoothing, steps_given)
    face = _face_stream(bundle, args.seed, args.face_listener) if with_face else None
    frames, rows = [], []
    try:
        for block in blocks:
            frames.append(stream.push(block))
            if face is not None:
                face.push(block)
                rows.append(face.take(face.frames_ready))
        frames.append(stream.finish())
        if face is not None:
            face.finish()
            rows.append(face.take(face.frames_ready))
    finally:
        if face is not None:
            face.close()
    features = bundle.denormalize(np.concatenate(frames)[:total])
    motion = features_to_motion(features, bundle.skeleton, bundle.feature_spec, root=args.root, tether_s=args.tether_s)
    return motion, (np.concatenate(rows)[:total] if face is not None else None)


def _hms(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


def _stream_bvh(args, bundle: Bundle, blocks, samples: int, smoothing, steps_given: bool, out: Path, target,
                face_out: Path | None) -> tuple[str, int]:
    """The motion (and the face) of the audio `blocks` made and written a block at a time: the same frames as the
    whole recording at once (streaming equals offline), in the memory of one block. -> (what was written, the face
    frames written)."""
    from dimgestor.features import PoseDecoder

    fps, sk = bundle.feature_spec.fps, bundle.skeleton
    total = int(samples * fps // SAMPLE_RATE)
    stream = _make_stream(args, bundle, smoothing, steps_given)
    decoder = PoseDecoder(sk, bundle.feature_spec, root=args.root, tether_s=args.tether_s)
    retarget, skeleton, what = None, sk, "BVH"
    if target is not None:
        from dimgestor.retarget import Rig, RigError
        from dimgestor.retarget.transfer import Retarget, resolve_map

        source = Rig.from_skeleton(sk, "ours")
        retarget = Retarget(source, target.rig, resolve_map(source, what="source"), target.bones)
        skeleton = target.rig.skeleton
        if skeleton is None:
            raise RigError(f"{target.path}: not a BVH rig; write it as glTF instead")
        for k, j in enumerate(retarget.target_joints):
            if len(skeleton.rotation_order(int(j))) != 3:
                raise RigError(f"{target.path}: joint {skeleton.names[j]!r} ({retarget.labels[k]}) has no three "
                               "rotation channels to carry its motion")
        what = f"BVH on {Path(target.path).name} ({len(retarget.bones)} bones mapped)"
    face = face_file = None
    if face_out is not None:
        from dimgestor.face.track import track_header, track_rows

        face = _face_stream(bundle, args.seed, args.face_listener)
        face_file = open(face_out, "w")
        face_file.write(track_header())
    done = faced = 0
    try:
        with BvhWriter(out, skeleton, 1.0 / fps, total) as bvh:
            def emit(frames: np.ndarray) -> None:
                nonlocal done
                frames = frames[:total - done]
                if not len(frames):
                    return
                pose = decoder.decode(bundle.denormalize(frames))
                t = np.broadcast_to(sk.offsets, pose.rotations.shape[:2] + (3,)).copy()
                t[:, 0] = pose.root_pos
                bvh.write(*(retarget(pose.rotations, t) if retarget is not None else (pose.rotations, t)))
                done += len(frames)

            def faces(n: int) -> None:
                nonlocal faced
                take = min(n, face.frames_ready) if face is not None else 0
                if take:
                    face_file.write("".join(track_rows(face.take(take), fps, faced)))
                    faced += take
            for block in blocks:
                emit(stream.push(block))
                if face is not None:
                    face.push(block)
                    faces(total - faced)
            emit(stream.finish())
            if face is not None:
                face.finish()
                faces(total - faced)
    finally:
        if face_file is not None:
            face_file.close()
        if face is not None:
            face.close()
    return f"{what}, {done} frames", faced


def _onnx_folder(args, bundle: Bundle, steps_given: bool):
    """The ONNX export to run: --onnx (checked against --steps and --guidance), or the cached one."""
    if args.sampler != "ddim" or args.eta != 0 or args.device != "cpu":
        raise ValueError("--backend onnxruntime runs deterministic DDIM (--eta 0) on the CPU")
    if args.onnx:
        from dimgestor.export.onnx_stream import load_manifest

        sampler = load_manifest(args.onnx)["sampler"]
        if (steps_given and args.steps != sampler["steps"]
                or args.guidance is not None and args.guidance != sampler["guidance"]):
            raise ValueError(f"--onnx {args.onnx} was exported with K={sampler['steps']} and guidance "
                             f"{sampler['guidance']:g}; pass those (or export again)")
        return args.onnx
    from dimgestor.export.onnx_cache import cached_export

    guidance = bundle.config.guidance if args.guidance is None else args.guidance
    return cached_export(bundle, args.steps, guidance, root=args.onnx_cache,
                         log=lambda text: print(f"dimgestor: {text}", file=sys.stderr, flush=True))


def _onnx_stream(args, bundle: Bundle, smoothing, steps_given: bool):
    from dimgestor.export.onnx_export import check_export
    from dimgestor.export.onnx_stream import load_manifest, ort_stream

    folder = _onnx_folder(args, bundle, steps_given)
    check_export(load_manifest(folder), bundle)
    return ort_stream(folder, seed=args.seed, smoothing=smoothing)
