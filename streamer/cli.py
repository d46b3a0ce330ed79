"""`dimgestor serve` (audio in, gestures out) and `dimgestor devices`, registered into the `dimgestor` command
(`register_serve`, `register_devices`); `streamer ...`, the old name, is `dimgestor_app.cli.streamer_main`."""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys

from dimgestor.face.stream import LISTENERS
from streamer.options import ServeError, ServeOptions, flag_of

EXIT_USAGE = 2


def host_port(text: str, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """A HOST:PORT (or PORT) flag's value -> (host, port): an argparse `type`, so a bad one is a usage error."""
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = default_host, text
    try:
        p = int(port)
        if not 0 <= p <= 65535:
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT or PORT, got {text!r}") from None
    return host.strip("[]") or default_host, p


def _root_pose(text: str) -> tuple[float, float, float, float]:
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) not in (3, 4):
        raise argparse.ArgumentTypeError(f"expected X,Y,Z or X,Y,Z,YAW_DEG, got {text!r}")
    return (*v, 0.0)[:4] if len(v) == 3 else tuple(v)


def _http_addr(text: str) -> tuple[str | None, int]:
    """--http [HOST:]PORT; no host -> None (serve beside the WebSocket)."""
    host, port = host_port(text)
    return (host if ":" in text else None), port


def _flag(group, flag: str, field: str | None = None, **kw) -> argparse.Action:
    """A `dimgestor serve` flag for a ServeOptions field (by default the one of the same name), with that field's
    default (one default per option, shown by --help as the flag would be written)."""
    field = field or flag.lstrip("-").replace("-", "_")
    assert flag_of(field) == flag, (flag, field)  # options.py names it the same
    default = ServeOptions.model_fields[field].default
    if kw.get("type") is host_port and default is not None:
        default = f"{default[0]}:{default[1]}"
    elif kw.get("type") is _root_pose:
        default = ",".join(f"{v:g}" for v in default)
    elif kw.get("action") == "append":
        default = list(default)  # (argparse appends to a copy of it)
    return group.add_argument(flag, dest=field, default=default, **kw)


SERVE_EXAMPLES = (
    "dimgestor serve                                   # the demo clip: open http://127.0.0.1:8765/",
    "dimgestor serve --source mic --input-device 2 --checkpoint live --vmc 127.0.0.1:39539",
    "dimgestor serve --source talk.wav --record talk.bvh --steps 4",
    "dimgestor serve --source ws --ws 0.0.0.0:8765 --token-file token.txt --max-sessions 8",
)


def register_serve(sub) -> argparse.ArgumentParser:
    """Add `serve` to the `dimgestor` subcommands."""
    from dimgestor.cli_help import deprecated_alias, examples

    s = sub.add_parser("serve", help="turn live or file audio into gestures; send them over WebSocket, VMC or BVH",
                       description="Audio in (microphone, WAV file, or WebSocket clients' own audio), gesture "
                                   "frames out to WebSocket clients (protocol: docs/protocol.md), a VMC receiver "
                                   "and/or a BVH file. Ctrl-C stops cleanly and finishes the recording.",
                       epilog=examples(*SERVE_EXAMPLES, deprecated="--osc (now --vmc)"))
    actions = {}
    for title, flags in (("input", _input_flags), ("model and sampling", _model_flags), ("outputs", _output_flags),
                         ("network and security", _network_flags), ("operations", _operations_flags)):
        actions |= flags(s.add_argument_group(title))
    deprecated_alias(s, "--osc", actions["osc"])
    s.set_defaults(func=run_serve)
    return s


def _input_flags(g) -> dict[str, argparse.Action]:
    from streamer.sources import DEMO_WAV

    return {a.dest: a for a in (
        _flag(g, "--source", metavar="mic|demo|FILE.wav|ws",
              help=f"audio source: 'mic' (see --input-device), 'demo' (the bundled clip {DEMO_WAV.name}), a WAV "
                   "file path, or 'ws' (no server audio: only clients' own audio)"),
        _flag(g, "--input-device", "device", metavar="N|NAME",
              help="audio input device for --source mic: its index or a unique part of its name (list them: "
                   "dimgestor devices; default: the system's default input)"),
        _flag(g, "--rate", type=int, metavar="HZ",
              help="capture rate for --source mic (default: the device's own; resampled to 16 kHz either way)"),
        _flag(g, "--gain", type=float, metavar="DB", help="input gain for --source mic, in dB"),
        _flag(g, "--gate", type=float, metavar="DBFS",
              help="noise gate for --source mic: mute input quieter than this (e.g. -45) so background noise "
                   "does not make the avatar gesture; the status line shows the mic level to pick it "
                   "(default: no gate)"),
        _flag(g, "--fast", action="store_true",
              help="read a file source as fast as inference allows instead of in real time"),
        _flag(g, "--loop", action="store_true", help="repeat a file source forever instead of exiting at its end"),
    )}


def _model_flags(g) -> dict[str, argparse.Action]:
    return {a.dest: a for a in (
        _flag(g, "--checkpoint", metavar="PATH",
              help="checkpoint folder or run folder (its latest checkpoint), or `live`: the embedded live model "
                   "(150 ms sooner, for a live microphone) (default: the embedded default model)"),
        _flag(g, "--steps", type=int, metavar="K",
              help="DDIM denoising steps K, fewer is faster (default: the checkpoint's sample_steps)"),
        _flag(g, "--seed", type=int, help="noise seed; same seed + audio + steps = same motion"),
        _flag(g, "--guidance", type=float, metavar="S",
              help="classifier-free guidance scale: 1 = unguided, > 1 follows the audio more (needs a model "
                   "trained with --cond-drop; each stream then takes two batch rows) (default: the checkpoint's)"),
        _flag(g, "--speaker", metavar="NAME",
              help="sessions play this speaker's style unless a client's hello asks another, for a model trained "
                   "with --speaker-condition (`dimgestor info --checkpoint DIR` lists them; ONNX Runtime: an export "
                   "of that speaker, for every client) (default: no speaker in particular)"),
        _flag(g, "--root", choices=("tether", "free", "lock"),
              help="root ground motion: 'tether' follows the model's steps and turns but removes any steady "
                   "walk or spin and drifts back to the start position and heading (time constant "
                   "--tether-s), so the avatar faces its start on average; 'free' integrates it as "
                   "generated (what `dimgestor generate` writes); 'lock' keeps position and heading fixed"),
        _flag(g, "--tether-s", type=float, metavar="S", help="time constant of --root tether, in seconds"),
        _flag(g, "--smooth", type=float, metavar="HZ",
              help="One Euro output filter cutoff in Hz, 0 = off (default: the checkpoint's setting)"),
        _flag(g, "--window-ms", type=int, metavar="MS",
              help="audio gathered per inference call (10..5000 ms): smaller = lower latency, more overhead"),
        _flag(g, "--no-batch", action="store_true",
              help="infer each stream's windows alone (without it, the windows of all streams due at once run "
                   "as one batched forward per sampler step)"),
        _flag(g, "--device", "compute_device", metavar="cpu|cuda|cuda:N",
              help="where the model runs: the CPU, or an NVIDIA GPU (torch's CUDA build; with --backend "
                   "onnxruntime, the onnxruntime-gpu package), the windows of all streams batched as on the CPU; "
                   "the face's listener stays on the CPU. The microphone is --input-device"),
        _flag(g, "--backend", choices=("torch", "onnxruntime"),
              help="torch, or onnxruntime: the model's ONNX export (dimgestor export-onnx) on ONNX Runtime's CPU "
                   "provider, the due windows of all streams as calls of its batched graphs (--no-batch: each "
                   "alone); the same frames to < 1e-4"),
        _flag(g, "--onnx", metavar="DIR",
              help="with --backend onnxruntime: the checkpoint's export-onnx folder (its K and guidance; export it "
                   "with --batch B... for batches of B streams a call) (default: the export in --onnx-cache)"),
        _flag(g, "--onnx-cache", metavar="DIR",
              help="with --backend onnxruntime: where the model's export is kept; the first start with a model, "
                   "K, guidance or batch sizes exports it (minutes), later starts reuse it (default: "
                   "$DIMGESTOR_CACHE/onnx, else ~/.cache/dimgestor/onnx or $XDG_CACHE_HOME/dimgestor/onnx; "
                   "%%LOCALAPPDATA%%\\dimgestor\\onnx on Windows)"),
    )}


def _output_flags(g) -> dict[str, argparse.Action]:
    return {a.dest: a for a in (
        _flag(g, "--vmc", "osc", type=host_port, metavar="HOST:PORT",
              help="send the VMC protocol (OSC over UDP) to a receiver at HOST:PORT: VSeeFace, Warudo, a "
                   "Marionette... (usual port 39539) (default: no VMC output)"),
        _flag(g, "--vmc-positions", choices=("hips", "all"),
              help="bone positions in the VMC stream: 'hips' moves only the Hips by position (every other bone "
                   "carries its fixed rest offset, so a receiver keeps to rotations); 'all' sends every bone's "
                   "posed position (this skeleton's proportions)"),
        _flag(g, "--vmc-hips-height", type=float, metavar="M",
              help="scale VMC positions so the standing Hips are M metres high (your avatar's) (default: the "
                   "model skeleton's own size)"),
        _flag(g, "--vmc-root", type=_root_pose, metavar="X,Y,Z[,YAW]",
              help="the /VMC/Ext/Root/Pos sent each frame: position in metres (Unity axes) and yaw in degrees"),
        _flag(g, "--vmc-bones", choices=("all", "upper"),
              help="'all' bones, or 'upper': spine, chest, shoulders, arms, hands and fingers only (no hips, "
                   "legs, neck or head), to mix with face tracking"),
        _flag(g, "--vmc-max-bytes", type=int, metavar="N",
              help="split each frame's VMC bundle into bundles of at most N bytes (e.g. 1400 for a LAN); "
                   "0 = one bundle"),
        _flag(g, "--vmc-jitter-ms", type=float, metavar="MS",
              help="VMC jitter buffer: frames are sent this long after the earliest they could be (default: one "
                   "window, --window-ms)"),
        _flag(g, "--face", choices=("vrm0", "vrm1", "arkit", "oculus", "none"),
              help="the face (mouth, blinks, brows) made from the same speech as the body, and the blendshape "
                   "names it is sent with over VMC and to WebSocket clients that do not choose their own: 'vrm0' "
                   "(A I U E O Blink Blink_L Blink_R Joy), 'vrm1' (aa ih ou ee oh blink...), 'arkit' (its 52), "
                   "'oculus' (viseme_sil... as Ready Player Me names them), 'none' (no face: bones only)"),
        _flag(g, "--smile", type=float, metavar="W",
              help="a smile held under the speech, 0..1 (WebSocket clients may set their own)"),
        _flag(g, "--face-listener", choices=LISTENERS,
              help="what hears the mouth in the speech: 'net' (the face's own network, shipped in the package; "
                   "default), 'pocketsphinx' (its English phone recognizer, where it is installed) or "
                   "'net+pocketsphinx' (both, their mouths averaged: closer to real voices, at both costs; "
                   "docs/face.md)"),
        _flag(g, "--face-process", action="store_true",
              help="make the sessions' faces in a second process beside the inference thread, on a core of their "
                   "own: with many faces on a machine of two or more cores, more avatars keep real time "
                   "(docs/performance.md)"),
        _flag(g, "--record", metavar="OUT.bvh|.glb|.vrma|.npz",
              help="write the generated motion of the server's source to this BVH file as it is generated "
                   "(a valid BVH at all times: a crash loses at most the last ~0.5 s), and its face beside it, "
                   "OUT.face.csv (as `dimgestor generate --face-csv` writes it; none with --face none); OUT.glb, "
                   "OUT.vrma or OUT.npz (a BEAT2 / SMPL-X take): that file too, made from OUT.bvh when the source "
                   "ends (.bvh and .glb on --target where it fits: a BVH target for .bvh, a SMPL-X BVH for .npz)"),
        _flag(g, "--target", metavar="RIG.bvh|.glb|.vrm",
              help="send the motion on this rig, retargeted whatever its rest pose (A-pose, T-pose), bone lengths "
                   "and names: WebSocket clients get its joints in the hello and its local rotations in every "
                   "frame, VMC receivers its humanoid bones (default: the model's skeleton)"),
        _flag(g, "--target-map", metavar="MAP.json",
              help="which joint of --target is which humanoid bone, over the names recognised "
                   "({\"leftUpperArm\": \"arm_L\", ...}, VRM 1.0 bone names)"),
        _flag(g, "--humanoid-map", metavar="FILE.json",
              help="{HumanBodyBones name: joint name} map for VMC and the hello (default: streamer/maps/zeggs.json)"),
    )}


def _network_flags(g) -> dict[str, argparse.Action]:
    """The WebSocket server (and the viewer on its port)."""
    return {a.dest: a for a in (
        _flag(g, "--ws", type=host_port, metavar="HOST:PORT",
              help="WebSocket and web viewer address; 127.0.0.1 keeps it local, 0.0.0.0 opens it to the network; "
                   "port 0 = any free"),
        _flag(g, "--no-ws", action="store_true", help="do not run the WebSocket server"),
        _flag(g, "--max-sessions", type=int, metavar="N",
              help="most WebSocket clients sending their own audio at once (one more gets a 'busy' "
                   "error). How many keep real time depends on the CPU and K: see docs/performance.md"),
        _flag(g, "--faces-beyond-capacity", choices=("busy", "no-face"),
              help="a client asking for a face when one more face would not keep real time on this worker: 'busy' "
                   "(refused, told to try again after retry_after_s) or 'no-face' (its session is admitted without a "
                   "face, and it is told so: a 'face_withheld' notice)"),
        _flag(g, "--token",
              help="require clients to connect to ws://HOST:PORT/?token=TOKEN (others get HTTP 401); other "
                   "users of this machine can read a command line: prefer --token-file or $STREAMER_TOKEN"),
        _flag(g, "--token-file", metavar="FILE",
              help="read the token from this file (surrounding whitespace ignored)"),
        _flag(g, "--allow-origin", action="append", metavar="ORIGIN",
              help="also accept browser pages from this origin, e.g. http://myapp.example:3000 (repeatable; "
                   "'*' = any). By default only the viewer's own pages (served on the --ws port), and "
                   "clients that send no Origin (Unity, Unreal, Python), may connect"),
        _flag(g, "--http", type=_http_addr, metavar="[HOST:]PORT",
              help="deprecated: the web viewer (clients/web) is served on the --ws port itself (open "
                   "http://127.0.0.1:8765/); --http also serves it, and the WebSocket, at HOST:PORT (a bare "
                   "PORT: on the --ws host)"),
        _flag(g, "--wait-client", action="store_true",
              help="start the server's source only once a first WebSocket client is connected"),
        _flag(g, "--no-client-audio", action="store_true", help="refuse audio sent by WebSocket clients"),
        _flag(g, "--ping-interval", type=float, metavar="S",
              help="WebSocket keepalive: ping each client every S seconds (0 = no keepalive)"),
        _flag(g, "--ping-timeout", type=float, metavar="S",
              help="WebSocket keepalive: close a client not heard from for --ping-interval + S seconds (time "
                   "while the server itself holds the client's audio unread, and its frames flow, does not count)"),
        _flag(g, "--no-metrics", action="store_true",
              help="do not serve /metrics (Prometheus text format, no token needed) on the --ws port; /healthz "
                   "and /readyz (also without the token) are always served"),
    )}


def _operations_flags(g) -> dict[str, argparse.Action]:
    actions = {a.dest: a for a in (
        _flag(g, "--state-store", metavar="URL",
              help="where sessions are saved when this worker stops (SIGTERM), for the client to resume on any "
                   "worker: redis://HOST:PORT/DB (a cluster; pip install 'dimgestor[cluster]') or memory (this "
                   "process). Without it a stopping worker ends its sessions (docs/protocol.md, goaway)"),
        _flag(g, "--state-ttl", type=float, metavar="S", help="seconds a saved session waits to be resumed"),
        _flag(g, "--save-state-every", type=float, metavar="S",
              help="also save each session to the state store every S seconds of its audio (between two windows; "
                   "the client is told with session_saved): after a crash (SIGKILL, a lost machine) the client "
                   "resumes from the last save, exactly. Needs --state-store"),
        _flag(g, "--state-max-bytes", type=int, metavar="N",
              help="the largest session state the store takes: a larger one is not saved (counted in /metrics; "
                   "the default model's is ~1.2 MB)"),
        _flag(g, "--state-secret-file", metavar="FILE",
              help="a file holding the secret every worker of the cluster shares (or $DIMGESTOR_STATE_SECRET): saved "
                   "sessions are sealed with it (HMAC-SHA256) and a state not sealed with it is refused. Without "
                   "one the seal (SHA-256) detects corruption, not forgery: anyone who can write to the store "
                   "can forge a state (docs/deploy.md, The state store)"),
        _flag(g, "--status-every", type=float, metavar="S", help="seconds between status lines on stderr (0 = none)"),
        _flag(g, "--max-seconds", type=float, metavar="S",
              help="stop (cleanly, as on Ctrl-C) after S seconds of running (default: run until stopped)"),
    )}
    g.add_argument("-v", "--verbose", action="store_true", help="log debug information")
    return actions


def register_devices(sub) -> argparse.ArgumentParser:
    """Add `devices` to the `dimgestor` subcommands."""
    from dimgestor.cli_help import examples

    p = sub.add_parser("devices", help="list audio input devices (for serve --source mic --input-device N)",
                       description="List the audio input devices PortAudio sees, the default one marked with *.",
                       epilog=examples("dimgestor devices", "dimgestor serve --source mic --input-device 2"))
    p.set_defaults(func=run_devices)
    return p


def run_devices(args=None) -> int:
    from streamer.sources import SourceError, list_input_devices

    try:
        devices = list_input_devices()
    except SourceError as e:
        print(f"dimgestor: {e}", file=sys.stderr)
        return EXIT_USAGE
    if not devices:
        print("No input devices found.", file=sys.stderr)
        return 0
    for d in devices:
        mark = "*" if d["default"] else " "
        print(f"{mark} {d['index']:3d}  {d['name']}  ({d['hostapi']}, {d['channels']} ch, {d['rate']:.0f} Hz)")
    print("(* = default; pick one with `dimgestor serve --source mic --input-device INDEX` or a unique part of its "
          "name)", file=sys.stderr)
    return 0


def run_serve(args) -> int:
    from streamer.redact import RedactTokens
    from streamer.server import serve
    from streamer.sources import SourceError

    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    for handler in logging.getLogger().handlers:
        handler.addFilter(RedactTokens())
    try:
        options = ServeOptions.parse(**{k: v for k, v in vars(args).items() if k in ServeOptions.model_fields})
        return asyncio.run(serve(options))
    except (ServeError, SourceError) as e:
        print(f"dimgestor: {e}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:  # a second Ctrl-C while shutting down
        return 130
