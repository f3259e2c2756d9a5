"""The image workspace's HTTP server: the page (static/), its JSON API and the image tiles,
served by the viewer's process on its own port (standard library only).

Every request gets an answer the page can show: JSON, tile bytes, or an error of one line
({"error": ...}, status 400 bad input, 404 unknown, 409 the state changed, 503 busy); a bug
is logged on the console with its traceback and reaches the page as one line too.

A POST must be JSON (Content-Type application/json), and an upload carries the header
X-Aerec-Workspace: a web page of another site cannot send either without the browser asking
this server first (a CORS preflight, which it does not answer), so it cannot edit the GCPs of a
viewer running on the operator's machine. On a loopback address the Host header must name the
loopback too (no DNS rebinding).
"""

from __future__ import annotations

import json
import logging
import math
import threading
import traceback
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import TYPE_CHECKING, Callable
from urllib.parse import parse_qs, urlsplit

from .api import ApiError, WorkspaceApi, bad

if TYPE_CHECKING:
    from ..app import ViewerApp

log = logging.getLogger("aerec.workspace")

STATIC = Path(__file__).resolve().parent / "static"
COUNTER = "frames.html"           # the 3D page's frame counter (framerate.py), framed by viser's page
CONTENT_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                 ".css": "text/css; charset=utf-8", ".png": "image/png", ".svg": "image/svg+xml"}
MAX_JSON_BYTES = 64 * 1024
MAX_CSV_BYTES = 5 * 1024 * 1024
PORT_TRIES = 20                  # a busy port moves to the next one, as viser's does
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")
MAX_NUDGE_PX = 100.0
MAX_NAME = 300                   # characters of a GCP id or an image name


# -- input ------------------------------------------------------------------------------------
def text(params: dict, name: str) -> str:
    """A required non-empty string parameter."""
    v = params.get(name)
    if not isinstance(v, str) or not v.strip():
        raise bad(f"{name}: give a non-empty string")
    if len(v) > MAX_NAME:
        raise bad(f"{name}: longer than {MAX_NAME} characters")
    return v


def number(params: dict, name: str, lo: float = -math.inf, hi: float = math.inf,
           default: float | None = None) -> float:
    """A finite number parameter within [lo, hi] (a JSON number, or a query string's text)."""
    v = params.get(name, default)
    if v is None:
        raise bad(f"{name}: missing (a number)")
    if isinstance(v, bool) or not isinstance(v, (int, float, str)):
        raise bad(f"{name}: {v!r} is not a number")
    try:
        x = float(v)
    except ValueError:
        raise bad(f"{name}: {v!r} is not a number") from None
    if not math.isfinite(x) or not lo <= x <= hi:
        raise bad(f"{name}: {v!r} is outside {lo:g} .. {hi:g}")
    return x


def integer(params: dict, name: str, lo: int, hi: int, default: int | None = None) -> int:
    """A whole-number parameter within [lo, hi]."""
    x = number(params, name, lo, hi, default)
    if x != int(x):
        raise bad(f"{name}: {params.get(name)!r} is not a whole number")
    return int(x)


def query(path: str) -> dict[str, str]:
    """A URL's query parameters (the last value of each)."""
    return {k: v[-1] for k, v in parse_qs(urlsplit(path).query, keep_blank_values=True).items()}


# -- routes -----------------------------------------------------------------------------------
def get_routes(api: WorkspaceApi) -> dict[str, Callable[[dict], tuple[str, bytes, dict]]]:
    """GET path -> handler(query) -> (content type, body, extra headers)."""
    def js(obj) -> tuple[str, bytes, dict]:
        return "application/json", json.dumps(obj, allow_nan=False).encode(), {}

    def tile(q: dict) -> tuple[str, bytes, dict]:
        fmt = q.get("fmt", "png")
        if fmt not in ("png", "jpg"):
            raise bad("fmt: png or jpg")
        body = api.tile(text(q, "image"), integer(q, "level", 0, 40), integer(q, "tx", 0, 1 << 20),
                        integer(q, "ty", 0, 1 << 20), contrast=number(q, "contrast", 0.1, 20.0, 1.0),
                        brightness=number(q, "brightness", -1.0, 1.0, 0.0),
                        gamma=number(q, "gamma", 0.1, 10.0, 2.0), fmt=fmt)
        return f"image/{'png' if fmt == 'png' else 'jpeg'}", body, {"Cache-Control": "private, max-age=3600"}

    def export(q: dict) -> tuple[str, bytes, dict]:
        name, body = api.export_csv()
        return "text/csv; charset=utf-8", body, {"Content-Disposition": f'attachment; filename="{name}"'}

    return {
        "/api/version": lambda q: js({"version": api.version()}),
        "/api/state": lambda q: ("application/json", api.state_json(), {}),
        "/api/tile": tile,
        "/api/predict": lambda q: js(api.predict(text(q, "gcp"), text(q, "image"))),
        "/api/export.csv": export,
    }


def post_routes(api: WorkspaceApi) -> dict[str, Callable[[dict], dict]]:
    """POST path -> handler(JSON body) -> JSON answer. Every edit names its GCP and image."""
    def px(b: dict, name: str) -> float:
        return number(b, name, -1e7, 1e7)

    return {
        "/api/observe": lambda b: api.observe(text(b, "gcp"), text(b, "image"), px(b, "col"), px(b, "row"),
                                              integer(b, "version_seen", 0, 1 << 62)),
        "/api/nudge": lambda b: api.nudge(text(b, "gcp"), text(b, "image"),
                                          number(b, "dcol", -MAX_NUDGE_PX, MAX_NUDGE_PX),
                                          number(b, "drow", -MAX_NUDGE_PX, MAX_NUDGE_PX)),
        "/api/remove": lambda b: api.remove(text(b, "gcp"), text(b, "image")),
        "/api/undo": lambda b: api.undo(),
        "/api/redo": lambda b: api.redo(),
        "/api/frames": lambda b: api.frames(integer(b, "client", 0, 1 << 31), number(b, "now", 0.0, 1e12),
                                            b.get("frames")),
    }


# -- the server -------------------------------------------------------------------------------
class WorkspaceServer:
    """The workspace on `host` (the viewer's), from `port` on (0: any free one)."""

    def __init__(self, app: "ViewerApp", host: str = "127.0.0.1", port: int = 0, viewer_port: int = 0):
        self.api = WorkspaceApi(app)
        self.httpd = _bind(host, port, _handler_class(self.api, host, viewer_port))
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        return int(self.httpd.server_address[1])

    @property
    def url(self) -> str:
        host = self.httpd.server_address[0]
        host = "127.0.0.1" if host in ("0.0.0.0", "", "::") else host
        return f"http://{host}:{self.port}/"

    def start(self) -> "WorkspaceServer":
        self._thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="aerec-workspace", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        if self._thread is not None:
            self.httpd.shutdown()
            self._thread.join(5.0)
        self.httpd.server_close()


def _bind(host: str, port: int, handler) -> ThreadingHTTPServer:
    """A ThreadingHTTPServer on the first free port from `port` (any free one for 0)."""
    last: OSError | None = None
    for p in ([0] if port == 0 else range(port, min(port + PORT_TRIES, 65536))):
        try:
            httpd = ThreadingHTTPServer((host, p), handler)
        except OSError as exc:
            last = exc
            continue
        httpd.daemon_threads = True
        return httpd
    raise OSError(f"no free port for the image workspace from {port}: {last}")


def _handler_class(api: WorkspaceApi, host: str, viewer_port: int = 0):
    """The request handler bound to the API (http.server makes one instance per request). Pages
    are never framed, but the frame counter (static/frames.html) is, by viser's page only."""
    gets, posts = get_routes(api), post_routes(api)
    loopback = host in ("127.0.0.1", "localhost", "::1")

    class Handler(BaseHTTPRequestHandler):
        server_version = "aerec-workspace"
        protocol_version = "HTTP/1.1"
        timeout = 30                # a request that stalls mid-way lets go of its thread

        def log_message(self, format: str, *args) -> None:        # noqa: A002 (http.server's name)
            log.debug("%s " + format, self.address_string(), *args)

        def do_GET(self) -> None:
            self._answer(self._get)

        def do_POST(self) -> None:
            self._answer(self._post)

        def _get(self) -> None:
            path = urlsplit(self.path).path
            if path in gets:
                ctype, body, headers = gets[path](query(self.path))
                self._send(200, ctype, body, {"Cache-Control": "no-store", **headers})
                return
            name = "index.html" if path in ("/", "/index.html") else path.removeprefix("/static/")
            f = STATIC / name
            if "/" in name or not f.is_file() or f.suffix not in CONTENT_TYPES:
                raise ApiError(404, f"no such page: {path}")
            framed = name == COUNTER and viewer_port > 0
            self._send(200, CONTENT_TYPES[f.suffix], f.read_bytes(), {"Cache-Control": "no-cache"},
                       framed_by=f"http://*:{viewer_port} https://*:{viewer_port}" if framed else None)

        def _post(self) -> None:
            path = urlsplit(self.path).path
            if self.headers.get("Transfer-Encoding"):
                raise ApiError(411, "send a Content-Length, not a chunked body")
            origin = self.headers.get("Origin")
            if origin is not None and urlsplit(origin).netloc != self.headers.get("Host", ""):
                # a browser names the page that sends a request, cross-site no-cors ones too
                raise ApiError(403, "edits come from the workspace's own page only")
            if path == "/api/import":
                if not self.headers.get("X-Aerec-Workspace"):
                    raise bad("an upload needs the header X-Aerec-Workspace (sent by the page)")
                name = query(self.path).get("name") or "markers.csv"
                out = api.import_csv(name[:MAX_NAME], self._body(MAX_CSV_BYTES))
            elif path in posts:
                if self.headers.get_content_type() != "application/json":
                    raise bad("send JSON (Content-Type: application/json)")
                try:
                    body = json.loads(self._body(MAX_JSON_BYTES) or b"{}")
                except ValueError as exc:
                    raise bad(f"the body is not JSON: {exc}") from None
                if not isinstance(body, dict):
                    raise bad("the body must be a JSON object")
                out = posts[path](body)
            else:
                raise ApiError(404, f"no such action: {path}")
            self._send(200, "application/json", json.dumps(out, allow_nan=False).encode(),
                       {"Cache-Control": "no-store"})

        def _body(self, limit: int) -> bytes:
            try:
                n = int(self.headers.get("Content-Length", "0"))
            except ValueError:
                raise bad("Content-Length is not a number") from None
            if not 0 <= n <= limit:
                raise ApiError(413, f"the body is larger than {limit // 1024} KB")
            return self.rfile.read(n)

        def _answer(self, fn: Callable[[], None]) -> None:
            """Run a route; any refusal or failure becomes one line of JSON for the page."""
            try:
                if loopback and self.headers.get("Host", "").rsplit(":", 1)[0] not in LOOPBACK_NAMES:
                    raise ApiError(403, "this workspace answers only on 127.0.0.1 / localhost")
                fn()
            except ApiError as exc:
                self._error(exc.status, exc.message)
            except (BrokenPipeError, ConnectionResetError):
                pass                                   # the tab went away mid-answer
            except Exception as exc:                   # a bug: the console gets the traceback
                log.error("image workspace: %s failed:\n%s", self.path, traceback.format_exc())
                self._error(500, f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}")

        def _error(self, status: int, message: str) -> None:
            # a refused request's body may be unread: the connection ends with this answer, so
            # nothing left in it is ever read as a request of its own
            self.close_connection = True
            line = " ".join(message.split())
            try:
                self._send(status, "application/json", json.dumps({"error": line}).encode(),
                           {"Cache-Control": "no-store"})
            except (BrokenPipeError, ConnectionResetError):
                pass

        def _send(self, status: int, ctype: str, body: bytes, headers: dict,
                  framed_by: str | None = None) -> None:
            self.send_response(status)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("X-Content-Type-Options", "nosniff")
            if framed_by is None:                                  # click-to-edit: never framed
                self.send_header("X-Frame-Options", "DENY")
            # the counter has nothing to click: framed by viser's page (any host, its port)
            self.send_header("Content-Security-Policy", "frame-ancestors " + (framed_by or "'none'"))
            if self.close_connection:
                self.send_header("Connection", "close")
            for k, v in headers.items():
                self.send_header(k, v)
            self.end_headers()
            if self.command != "HEAD":
                self.wfile.write(body)

    return Handler
