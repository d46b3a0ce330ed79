"""Static HTTP server for the web viewer (clients/web/) plus GET /config.json pointing it at the WebSocket."""

from __future__ import annotations

import json
import threading
from functools import partial
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import urlsplit

import streamer

WEB_DIR = Path(streamer.__file__).resolve().parents[1] / "clients" / "web"


class _Handler(SimpleHTTPRequestHandler):
    ws_port: int = 0
    token_required: bool = False

    def do_GET(self) -> None:  # noqa: N802 (http.server naming)
        if self.path.split("?", 1)[0] == "/config.json":
            # The browser reaches the WebSocket on the host it loaded this page from.
            host = urlsplit("//" + (self.headers.get("Host") or "127.0.0.1")).hostname or "127.0.0.1"
            host = f"[{host}]" if ":" in host else host  # IPv6 literal
            body = json.dumps({"ws_url": f"ws://{host}:{self.ws_port}/", "token_required": self.token_required}).encode()
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)
            return
        if not Path(self.directory).is_dir():
            self.send_error(404, f"web viewer not found at {self.directory}")
            return
        super().do_GET()

    def log_message(self, format, *args) -> None:  # keep stderr for the status line
        pass


class ViewerServer:
    """Runs in a daemon thread; `url` is where to point a browser."""

    def __init__(self, host: str, port: int, ws_port: int | None, token_required: bool, web_dir: Path = WEB_DIR):
        handler = type("Handler", (_Handler,), {"ws_port": ws_port or 0, "token_required": token_required})
        self.httpd = ThreadingHTTPServer((host, port), partial(handler, directory=str(web_dir)))
        self.httpd.daemon_threads = True
        self.host, self.port = host, self.httpd.server_address[1]
        self.web_dir = web_dir
        self.thread = threading.Thread(target=self.httpd.serve_forever, name="http", daemon=True)

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/"

    def start(self) -> None:
        self.thread.start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
