"""`streamer` command line: `streamer serve` (audio in, gestures out) and `streamer devices`."""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys

from streamer.options import ServeError, ServeOptions
from streamer.redact import RedactTokens
from streamer.sources import DEMO_WAV, SourceError

EXIT_USAGE = 2


def _hostport(text: str, default_host: str = "127.0.0.1") -> tuple[str, int]:
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


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("dimgestor")
    except PackageNotFoundError:
        return "unknown"


def _http_addr(text: str) -> tuple[str | None, int]:
    """--http [HOST:]PORT; no host -> None (serve beside the WebSocket)."""
    host, port = _hostport(text)
    return (host if ":" in text else None), port


def _flag(parser: argparse.ArgumentParser, flag: str, **kw) -> None:
    """A `streamer serve` flag for the ServeOptions field of the same name, with that field's default (one
    default per option, shown by --help as the flag would be written)."""
    default = ServeOptions.model_fields[flag.lstrip("-").replace("-", "_")].default
    if kw.get("type") is _hostport and default is not None:
        default = f"{default[0]}:{default[1]}"
    elif kw.get("type") is _root_pose:
        default = ",".join(f"{v:g}" for v in default)
    elif kw.get("action") == "append":
        default = list(default)  # (argparse appends to a copy of it)
    parser.add_argument(flag, default=default, **kw)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="streamer", description="Real-time co-speech gesture streamer (DiM-Gestor).")
    ap.add_argument("--version", action="version", version=f"streamer (dimgestor) {_version()}")
    sub = ap.add_subparsers(dest="command", required=True)
    s = sub.add_parser("serve", help="turn live or file audio into gestures; send them over WebSocket/OSC/BVH",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter,
                       description="Audio in (microphone, WAV file, or WebSocket clients' own audio), gesture "
                                   "frames out to WebSocket clients (protocol: docs/protocol.md), a VMC/OSC "
                                   "receiver and/or a BVH file. Ctrl-C stops cleanly and finishes the recording.")
    for group in (_source_flags, _output_flags, _model_flags, _server_flags):
        group(s)
    s.add_argument("-v", "--verbose", action="store_true", help="log debug information")
    sub.add_parser("devices", help="list audio input devices (for --source mic --device N)")
    from streamer import web

    web.register(sub)
    return ap


def _source_flags(s: argparse.ArgumentParser) -> None:
    _flag(s, "--source",
              help=f"audio source: 'mic' (see --device), 'demo' (the bundled clip {DEMO_WAV.name}), "
                   "a WAV file path, or 'ws' (no server audio: only clients' own audio)")
    _flag(s, "--device",
              help="input device index or name substring for --source mic (list them: streamer devices)")
    _flag(s, "--rate", type=int, metavar="HZ",
              help="capture rate for --source mic (default: the device's own; resampled to 16 kHz either way)")
    _flag(s, "--gain", type=float, metavar="DB", help="input gain for --source mic, in dB")
    _flag(s, "--gate", type=float, metavar="DBFS",
              help="noise gate for --source mic: mute input quieter than this (e.g. -45) so background noise "
                   "does not make the avatar gesture; the status line shows the mic level to pick it")
    _flag(s, "--fast", action="store_true",
              help="read a file source as fast as inference allows instead of in real time")
    _flag(s, "--loop", action="store_true", help="repeat a file source forever instead of exiting at its end")


def _output_flags(s: argparse.ArgumentParser) -> None:
    _flag(s, "--osc", type=_hostport, metavar="HOST:PORT",
              help="send VMC protocol (OSC/UDP) to a Marionette at HOST:PORT (usual port 39539)")
    _flag(s, "--vmc-positions", choices=("hips", "all"),
              help="bone positions in the VMC stream: 'hips' moves only the Hips by position (every other bone "
                   "carries its fixed rest offset, so a receiver keeps to rotations); 'all' sends every bone's "
                   "posed position (this skeleton's proportions)")
    _flag(s, "--vmc-hips-height", type=float, metavar="M",
              help="scale VMC positions so the standing Hips are M metres high (your avatar's; default: the "
                   "model skeleton's own size)")
    _flag(s, "--vmc-root", type=_root_pose, metavar="X,Y,Z[,YAW]",
              help="the /VMC/Ext/Root/Pos sent each frame: position in metres (Unity axes) and yaw in degrees")
    _flag(s, "--vmc-bones", choices=("all", "upper"),
              help="'upper': spine, chest, shoulders, arms, hands and fingers only (no hips, legs, neck or head), "
                   "to mix with face tracking")
    _flag(s, "--vmc-max-bytes", type=int, metavar="N",
              help="split each frame's VMC bundle into bundles of at most N bytes (e.g. 1400 for a LAN); 0 = one bundle")
    _flag(s, "--vmc-jitter-ms", type=float, metavar="MS",
              help="VMC jitter buffer: frames are sent this long after the earliest they could be (default: one window, "
                   "--window-ms)")
    _flag(s, "--record", metavar="OUT.bvh",
              help="write the generated motion of the server's source to this BVH file as it is generated "
                   "(a valid BVH at all times: a crash loses at most the last ~0.5 s)")
    _flag(s, "--humanoid-map", metavar="FILE.json",
              help="{HumanBodyBones name: joint name} map for OSC and the hello; default streamer/maps/zeggs.json")
    _flag(s, "--status-every", type=float, metavar="S",
              help="seconds between status lines on stderr (0 = none)")
    _flag(s, "--max-seconds", type=float, metavar="S",
              help="stop (cleanly, as on Ctrl-C) after S seconds of running")


def _model_flags(s: argparse.ArgumentParser) -> None:
    _flag(s, "--checkpoint", metavar="PATH",
              help="checkpoint folder or run folder (latest checkpoint), or `live`: the embedded live model (150 ms "
                   "sooner, for a live microphone); default: the embedded default model")
    _flag(s, "--steps", type=int,
              help="DDIM denoising steps K, fewer is faster (default: the checkpoint's sample_steps)")
    _flag(s, "--seed", type=int, help="noise seed; same seed + audio + steps = same motion")
    _flag(s, "--guidance", type=float, metavar="S",
              help="classifier-free guidance scale: 1 = unguided, > 1 follows the audio more (needs a model "
                   "trained with --cond-drop; each stream then takes two batch rows); default: the checkpoint's")
    _flag(s, "--root", choices=("tether", "free", "lock"),
              help="root ground motion: 'tether' follows the model's steps and turns but removes any steady "
                   "walk or spin and drifts back to the start position and heading (time constant "
                   "--tether-s), so the avatar faces its start on average; 'free' integrates it as "
                   "generated (what `dimgestor generate` writes); 'lock' keeps position and heading fixed")
    _flag(s, "--tether-s", type=float, help="time constant of --root tether, seconds")
    _flag(s, "--smooth", type=float, metavar="HZ",
              help="One Euro output filter cutoff in Hz, 0 = off (default: the checkpoint's setting)")
    _flag(s, "--window-ms", type=int,
              help="audio gathered per inference call (10..5000 ms): smaller = lower latency, more overhead")
    _flag(s, "--no-batch", action="store_true",
              help="infer each stream's windows alone (default: the windows of all streams due at once run "
                   "as one batched forward per sampler step)")
    _flag(s, "--backend", choices=("torch", "onnxruntime"),
              help="torch (default), or onnxruntime: the model's ONNX export (dimgestor export-onnx) on ONNX "
                   "Runtime's CPU provider, the due windows of all streams as calls of its batched graphs "
                   "(--no-batch: each alone); the same frames to < 1e-4")
    _flag(s, "--onnx", metavar="DIR",
              help="with --backend onnxruntime: the checkpoint's export-onnx folder (its K and guidance; "
                   "export it with --batch B... for batches of B streams a call); default: export it at start")


def _server_flags(s: argparse.ArgumentParser) -> None:
    """The WebSocket server (and the viewer on its port)."""
    _flag(s, "--ws", type=_hostport, metavar="HOST:PORT",
              help="WebSocket address; 127.0.0.1 keeps it local, 0.0.0.0 opens it to the network; port 0 = any free")
    _flag(s, "--no-ws", action="store_true", help="do not run the WebSocket server")
    _flag(s, "--max-sessions", type=int, metavar="N",
              help="most WebSocket clients sending their own audio at once (one more gets a 'busy' "
                   "error). How many keep real time depends on the CPU and K: see benchmarks/README.md")
    _flag(s, "--token",
              help="require clients to connect to ws://HOST:PORT/?token=TOKEN (others get HTTP 401); other "
                   "users of this machine can read a command line: prefer --token-file or $STREAMER_TOKEN")
    _flag(s, "--token-file", metavar="FILE",
              help="read the token from this file (surrounding whitespace ignored)")
    _flag(s, "--allow-origin", action="append", metavar="ORIGIN",
              help="also accept browser pages from this origin, e.g. http://myapp.example:3000 (repeatable; "
                   "'*' = any). By default only the viewer's own pages (served on the --ws port), and "
                   "clients that send no Origin (Unity, Unreal, Python), may connect")
    _flag(s, "--http", type=_http_addr, metavar="[HOST:]PORT",
              help="deprecated: the web viewer (clients/web) is served on the --ws port itself (open "
                   "http://127.0.0.1:8765/); --http also serves it, and the WebSocket, at HOST:PORT (a bare "
                   "PORT: on the --ws host)")
    _flag(s, "--wait-client", action="store_true",
              help="start the server's source only once a first WebSocket client is connected")
    _flag(s, "--no-client-audio", action="store_true", help="refuse audio sent by WebSocket clients")
    _flag(s, "--ping-interval", type=float, metavar="S",
              help="WebSocket keepalive: ping each client every S seconds (0 = no keepalive)")
    _flag(s, "--ping-timeout", type=float, metavar="S",
              help="WebSocket keepalive: close a client not heard from for --ping-interval + S seconds (time "
                   "while the server itself holds the client's audio unread, and its frames flow, does not count)")
    _flag(s, "--state-store", metavar="URL",
              help="where sessions are saved when this worker stops (SIGTERM), for the client to resume on any "
                   "worker: redis://HOST:PORT/DB (a cluster; pip install 'dimgestor[cluster]') or memory (this "
                   "process). Without it a stopping worker ends its sessions (docs/protocol.md, goaway)")
    _flag(s, "--state-ttl", type=float, metavar="S",
              help="seconds a saved session waits to be resumed")
    _flag(s, "--save-state-every", type=float, metavar="S",
              help="also save each session to the state store every S seconds of its audio (between two windows; "
                   "the client is told with session_saved): after a crash (SIGKILL, a lost machine) the client "
                   "resumes from the last save, exactly. Needs --state-store")
    _flag(s, "--no-metrics", action="store_true",
              help="do not serve /metrics (Prometheus text format, no token needed) on the --ws port; /healthz "
                   "and /readyz (also without the token) are always served")


def _devices() -> int:
    from streamer.sources import list_input_devices

    try:
        devices = list_input_devices()
    except SourceError as e:
        print(f"streamer: {e}", file=sys.stderr)
        return EXIT_USAGE
    if not devices:
        print("No input devices found.", file=sys.stderr)
        return 0
    for d in devices:
        mark = "*" if d["default"] else " "
        print(f"{mark} {d['index']:3d}  {d['name']}  ({d['hostapi']}, {d['channels']} ch, {d['rate']:.0f} Hz)")
    print("(* = default; pick one with `streamer serve --source mic --device INDEX` or a unique part of its name)",
          file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "devices":
        return _devices()
    if args.command == "web":
        from streamer import web

        return web.run(args)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    for handler in logging.getLogger().handlers:
        handler.addFilter(RedactTokens())
    from streamer.server import serve

    try:
        options = ServeOptions.parse(**{k: v for k, v in vars(args).items() if k in ServeOptions.model_fields})
        return asyncio.run(serve(options))
    except (ServeError, SourceError) as e:
        print(f"streamer: {e}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:  # a second Ctrl-C while shutting down
        return 130


if __name__ == "__main__":
    sys.exit(main())
