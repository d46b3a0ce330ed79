"""`dimgestor web`: the viewer with the model running inside the browser (onnxruntime-web), no inference server.

It exports the checkpoint's frame step into a folder (`dimgestor export-onnx`: frame_step.onnx + manifest.json),
writes web.json beside it (the hello `dimgestor serve` would send for this checkpoint, the feature layout the
page decodes, the root mode) and serves clients/web at "/" and that folder at "/model/" over plain HTTP:
static files only, so any static server would do as well. The page is `/?local=model/`
(clients/web/local-engine.js). Responses carry COOP/COEP, so the page is cross-origin isolated and
onnxruntime-web may use threads (`?threads=N`).
"""
from __future__ import annotations

import json
import sys
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from streamer.viewer import ISOLATION, WEB_DIR, ViewerFiles

__all__ = ["prepare_model", "web_json", "make_server", "register", "run"]

def web_json(checkpoint: str | None, root: str = "tether", tether_s: float = 5.0,
             humanoid_map: str | None = None) -> dict:
    """What the page needs beside the graph: the hello (skeleton, humanoid map), the feature layout, the root."""
    from dimgestor.streaming.checkpoint import load_checkpoint
    from streamer import protocol as P
    from streamer.pose import HumanoidRig, load_humanoid_map

    bundle = load_checkpoint(checkpoint)
    sk, spec, c = bundle.skeleton, bundle.feature_spec.resolve(bundle.skeleton), bundle.config
    rig = HumanoidRig.build(sk.names, sk.parents, sk.offsets, load_humanoid_map(humanoid_map))
    fps = int(spec.fps) if float(spec.fps).is_integer() else spec.fps
    hello = P.hello(P.SkeletonInfo.from_skeleton(sk), rig.mapping(sk.names), fps, bundle.model.lookahead_s,
                    accepts_audio=True, source="local")
    features = {"joints": spec.joint_indices(sk), "numJoints": sk.num_joints, "heading": spec.heading,
                "fps": spec.fps, "dim": spec.dim}
    if spec.dim != c.motion_dim:
        raise ValueError(f"checkpoint features ({spec.dim}) and model ({c.motion_dim}) disagree")
    return {"format": 1, "hello": hello, "features": features, "root": root, "tether_s": tether_s}


def prepare_model(folder: str | Path, checkpoint: str | None = None, steps: int | None = 4, frames: int = 2,
                  root: str = "tether", tether_s: float = 5.0, export: bool | None = None) -> Path:
    """folder/ with frame_step.onnx, manifest.json, the face's face_step.onnx and face_manifest.json, and web.json;
    exports unless a graph is there (export None)."""
    from dimgestor.export.onnx_export import GRAPH, export_onnx
    from dimgestor.export.onnx_face import FACE_GRAPH, export_face

    folder = Path(folder)
    if export or (export is None and not (folder / GRAPH).exists()):
        export_onnx(checkpoint, folder, steps, None, frames)
    manifest = json.loads((folder / "manifest.json").read_text())
    fps = manifest["call"]["fps"]
    if not (folder / FACE_GRAPH).exists() and round(100 / fps) * fps == 100:  # the face's listener beside it
        export_face(folder, int(fps), manifest["call"]["frames_per_call"])
    # (written whole, then renamed into place: a page reading the folder meanwhile sees the old file or the new one)
    part = folder / "web.json.part"
    part.write_text(json.dumps(web_json(manifest["checkpoint"]["path"], root, tether_s)))
    part.replace(folder / "web.json")
    return folder


def make_server(host: str, port: int, model: Path) -> ThreadingHTTPServer:
    """HTTP server for clients/web at "/" and the model folder at "/model/" (GET and HEAD, cross-origin isolated)."""
    files = ViewerFiles({"/": WEB_DIR, "/model/": Path(model)})

    class Handler(BaseHTTPRequestHandler):
        def _answer(self):
            a = files.answer(self.command, self.path)
            self.send_response(a.status)
            self.send_header("Content-Type", a.content_type)
            self.send_header("Content-Length", str(len(a.body)))
            self.send_header("Cache-Control", "no-cache")
            self.send_header("X-Content-Type-Options", "nosniff")
            for k, v in ISOLATION:
                self.send_header(k, v)
            self.end_headers()
            if not a.head_only:
                self.wfile.write(a.body)

        do_GET = do_HEAD = _answer

        def log_message(self, *args):  # quiet: a page load is ~40 requests
            pass

    return ThreadingHTTPServer((host, port), Handler)


def register(sub) -> None:
    """Add `web` to the `dimgestor` subcommands."""
    from dimgestor.cli_help import examples

    p = sub.add_parser("web", help="serve the viewer with the model running in the browser (no inference server)",
                       description="Export the model for the browser (onnxruntime-web) into a folder and serve the "
                                   "viewer and that folder over plain HTTP: static files only, inference runs in the "
                                   "page. Open the address it prints.",
                       epilog=examples("dimgestor web                        # then open http://127.0.0.1:8766/?local=model/",
                                       "dimgestor web --checkpoint live --steps 2 --model live-web-model"))
    model = p.add_argument_group("model and sampling")
    model.add_argument("--model", default="web-model", metavar="DIR",
                       help="folder for the exported model (exported if it has none)")
    model.add_argument("--checkpoint", default=None,
                       help="checkpoint or run folder, or `live` (default: the embedded default model)")
    model.add_argument("--steps", type=int, default=4, metavar="K", help="DDIM steps K in the exported graph")
    model.add_argument("--frames", type=int, default=2, help="motion frames per call (2: 100 ms windows)")
    model.add_argument("--export", action="store_true", help="export again even if the folder has a graph")
    model.add_argument("--root", choices=("tether", "free", "lock"), default="tether",
                       help="root ground motion (as serve's --root)")
    model.add_argument("--tether-s", type=float, default=5.0, metavar="S",
                       help="time constant of --root tether, in seconds")
    network = p.add_argument_group("network")
    network.add_argument("--host", default="127.0.0.1",
                         help="address to serve on; 127.0.0.1 keeps it local, 0.0.0.0 opens it to the network")
    network.add_argument("--port", type=int, default=8766, help="HTTP port (0 = any free)")
    p.set_defaults(func=run)


def run(args) -> int:
    folder = prepare_model(args.model, args.checkpoint, args.steps, args.frames, args.root, args.tether_s,
                           export=args.export or None)
    server = make_server(args.host, args.port, folder)
    host, port = server.server_address[:2]
    print(f"dimgestor web: open http://{'127.0.0.1' if host == '0.0.0.0' else host}:{port}/?local=model/ "
          f"(model: {folder}; inference runs in the browser)", file=sys.stderr, flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
    return 0
