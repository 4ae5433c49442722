"""The viewer's HTTP server: serves the page, the vendored three.js files and one scene's
generated files, from memory, read-only (GET and HEAD only). URLs are looked up by exact name
in a fixed table built at start (and the scene's computed answers, e.g. a point avatar's pose),
so no path reaches the file system (no traversal). Binds to 127.0.0.1 unless told otherwise."""

from __future__ import annotations

import errno
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from headforge.errors import HeadforgeError
from headforge.viewer.scene import Scene, manifest_json

STATIC = Path(__file__).parent / "static"
TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8", ".json": "application/json",
         ".glb": "model/gltf-binary", ".bin": "application/octet-stream", ".css": "text/css; charset=utf-8"}


def site(scene: Scene) -> dict[str, tuple[bytes, str]]:
    """URL path -> (body, content type): the static files shipped with the package (page and
    vendored three.js) and the scene's manifest and files."""
    table = {}
    for path in sorted(STATIC.rglob("*")):
        if path.is_file() and path.suffix in TYPES:
            table["/" + path.relative_to(STATIC).as_posix()] = (path.read_bytes(), TYPES[path.suffix])
    table["/"] = table["/index.html"]
    table["/scene.json"] = (manifest_json(scene), TYPES[".json"])
    for name, body in scene.files.items():
        table["/" + name] = (body, TYPES.get(Path(name).suffix, TYPES[".bin"]))
    return table


class _Handler(BaseHTTPRequestHandler):
    table: dict[str, tuple[bytes, str]] = {}
    handlers: dict = {}

    def _lookup(self) -> tuple[bytes, str] | None:
        from urllib.parse import parse_qsl, urlsplit

        url = urlsplit(self.path)
        handler = self.handlers.get(url.path.lstrip("/"))
        if handler is not None and url.path.count("/") == 1:
            try:
                return handler(dict(parse_qsl(url.query[:100_000]))), TYPES[".bin"]
            except (ValueError, KeyError) as exc:
                self.send_error(HTTPStatus.BAD_REQUEST, str(exc)[:200])
                return b"", ""
        return self.table.get(url.path)

    def do_GET(self) -> None:  # noqa: N802 (http.server's names)
        self._answer(body=True)

    def do_HEAD(self) -> None:  # noqa: N802
        self._answer(body=False)

    def _answer(self, body: bool) -> None:
        found = self._lookup()
        if found is None:
            self.send_error(HTTPStatus.NOT_FOUND)
            return
        data, kind = found
        if not kind:  # answered with an error already
            return
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        if body:
            self.wfile.write(data)

    def _refuse(self) -> None:
        self.send_error(HTTPStatus.METHOD_NOT_ALLOWED, "the viewer is read-only")

    do_POST = do_PUT = do_DELETE = do_PATCH = _refuse  # noqa: N815

    def log_message(self, format, *args) -> None:  # quiet: the command prints its URL once
        pass


class ViewerServer:
    """``ViewerServer(scene, host, port)``: bound at construction (one-line errors for a port in
    use or a bad host); ``url``; ``serve_forever()`` or ``start()`` (a daemon thread) and ``stop()``."""

    def __init__(self, scene: Scene, host: str = "127.0.0.1", port: int = 8765):
        if not 0 <= port <= 65535:
            raise HeadforgeError(f"--port must be in 0..65535, got {port}")
        handler = type("Handler", (_Handler,), {"table": site(scene), "handlers": dict(scene.handlers)})
        try:
            self.httpd = ThreadingHTTPServer((host, port), handler)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise HeadforgeError(f"port {port} on {host} is in use: choose another with --port") from None
            raise HeadforgeError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
        self.httpd.daemon_threads = True
        self.host, self.port = self.httpd.server_address[:2]
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def serve_forever(self) -> None:
        try:
            self.httpd.serve_forever()
        finally:
            self.httpd.server_close()

    def start(self) -> "ViewerServer":
        self._thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        if self._thread is not None:
            self._thread.join(timeout=5)
