"""The studio's web server: FastAPI on uvicorn, bound to 127.0.0.1, one random token per run.

Security (docs/studio.md):

- it listens on 127.0.0.1 unless ``--host`` names another address (the command warns);
- every request needs the token: in the URL's query (the page's address, and the URLs of its
  own files and photos, which the server writes into the page), or in the ``X-Studio-Token``
  header (the page's API calls); without it the answer is 403.  No cookie: a browser sends a
  127.0.0.1 cookie to every port, so any local service the browser visits would see it.  The
  page drops the token from its address (history), and a browser is opened on a private
  redirect file, not on the URL (a command line is readable by every local user);
- the ``Host`` header must be the address the server listens on (no DNS rebinding), and a
  state-changing request (POST) must come from the page's own ``Origin`` with a JSON body of at
  most :data:`MAX_BODY` bytes, validated against a schema (pydantic) — else a 4xx;
- no path from the page is ever opened: photos are ids, the page's files a fixed list, and a
  request whose path holds ``..``, a backslash or an encoded slash is refused;
- the engine writes only under ``--out``.
"""

from __future__ import annotations

import contextlib
import hmac
import json
import secrets
import socket
import threading
import urllib.parse
from concurrent.futures import ThreadPoolExecutor
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

import uvicorn
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response
from pydantic import BaseModel, ConfigDict, Field, StringConstraints
from starlette.exceptions import HTTPException as StarletteHTTPException

from mbcal.errors import MbcalError
from mbcal.studio.engine import MAX_CLICKS, MAX_RESTARTS_STUDIO, Engine, error_json

__all__ = ["check_address", "create_app", "StudioServer", "MAX_BODY", "TOKEN_HEADER"]

WILDCARDS = ("0.0.0.0", "::", "[::]", "")
"""Addresses that listen everywhere: refused (see :func:`check_address`)."""

MAX_BODY = 2 * 1024 * 1024
_POOL = ThreadPoolExecutor(max_workers=4, thread_name_prefix="mbcal-studio-camera")
TOKEN_HEADER = "X-Studio-Token"
"""The header that carries the token in the page's API calls."""
STATIC = {"studio.js": "text/javascript", "studio.css": "text/css"}
SECURITY_HEADERS = {
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
    "Content-Security-Policy": (
        "default-src 'self'; img-src 'self' data: blob:; style-src 'self'; script-src 'self'; "
        "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'"
    ),
}

# Names (points, cameras, configurations, ids, globs) are never used as paths; still no slashes,
# backslashes or control characters.
Name = Annotated[str, StringConstraints(min_length=1, max_length=300, pattern=r"^[^\x00-\x1f/\\]+$")]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ClickBody(_Strict):
    id: Name
    camera: Name
    config: Name
    point: Name
    u: Annotated[float, Field(allow_inf_nan=False, ge=-1e6, le=1e6)]
    v: Annotated[float, Field(allow_inf_nan=False, ge=-1e6, le=1e6)]
    sigma: Annotated[float, Field(allow_inf_nan=False, gt=0, le=1e4)] = 1.0
    sigma_v: Annotated[float, Field(allow_inf_nan=False, gt=0, le=1e4)] | None = None


class SessionBody(_Strict):
    clicks: Annotated[list[ClickBody], Field(max_length=MAX_CLICKS)]
    estimate: Annotated[list[Name], Field(max_length=200)] = []
    values: Values = {}
    hidden: Annotated[list[Name], Field(max_length=2000)] = []


PhotoId = Annotated[str, StringConstraints(pattern=r"^p[0-9]{1,4}$")]
Values = Annotated[dict[Name, FiniteFloat], Field(max_length=2000)]


class OverlayBody(_Strict):
    photos: Annotated[list[PhotoId], Field(min_length=1, max_length=64)]
    values: Values | None = None
    occlusion: bool = True


class SolidBody(_Strict):
    photo: PhotoId
    values: Values | None = None


class SolveBody(_Strict):
    restarts: Annotated[int, Field(ge=1, le=MAX_RESTARTS_STUDIO)] = 16
    seed: Annotated[int, Field(ge=0, le=2**31)] = 0


class SaveBody(_Strict):
    format: Literal["csv", "json"] = "csv"


class EmptyBody(_Strict):
    pass


def _static(name: str) -> bytes:
    return resources.files("mbcal.studio").joinpath("static", name).read_bytes()


def _refuse(status: int, message: str) -> JSONResponse:
    return JSONResponse({"error": {"message": message, "location": None}}, status_code=status, headers=SECURITY_HEADERS)


def _same(given: str, token: str) -> bool:
    """Constant-time comparison of text from a request (any characters) with the token."""
    return hmac.compare_digest(given.encode("utf-8", "surrogateescape"), token.encode())


def create_app(engine: Engine, token: str, hosts: list[str]) -> FastAPI:
    """The studio's application for ``engine``; ``hosts`` are the ``host:port`` it answers to."""
    app = FastAPI(title="mbcal studio", docs_url=None, redoc_url=None, openapi_url=None)
    origins = {f"http://{h}" for h in hosts}
    # The page with the token written in: its own files' URLs carry it, and a meta tag gives it
    # to the script for the API's header.
    page = (
        _static("index.html")
        .decode("utf-8")
        .replace("<head>", f'<head>\n<meta name="studio-token" content="{token}">', 1)
        .replace('href="/static/studio.css"', f'href="/static/studio.css?token={token}"')
        .replace('src="/static/studio.js"', f'src="/static/studio.js?token={token}"')
        .encode("utf-8")
    )

    @app.middleware("http")
    async def guard(request: Request, call_next):
        raw = request.scope.get("raw_path", b"").decode("latin-1")
        path = urllib.parse.unquote(raw)
        if ".." in path or "\\" in path or "//" in path or "%2f" in raw.lower() or "%5c" in raw.lower():
            return _refuse(400, "paths with '..', '//', '\\' or encoded slashes are refused")
        if request.headers.get("host", "") not in hosts:
            return _refuse(403, "wrong Host header")
        given = request.query_params.get("token") or request.headers.get(TOKEN_HEADER)
        if given is None or not _same(given, token):
            return _refuse(403, "the studio's token is missing or wrong: open the URL the command printed")
        if request.method not in ("GET", "HEAD"):
            if request.headers.get("origin") not in origins:
                return _refuse(403, "requests from another origin are refused")
            if request.headers.get("content-type", "").split(";")[0].strip() != "application/json":
                return _refuse(415, "the body must be JSON (Content-Type: application/json)")
            length = request.headers.get("content-length")
            if length is None or not length.isdigit():
                return _refuse(411, "a Content-Length is required")
            if int(length) > MAX_BODY:
                return _refuse(413, f"the body is larger than {MAX_BODY} bytes")
        response = await call_next(request)
        for k, v in SECURITY_HEADERS.items():
            response.headers.setdefault(k, v)
        return response

    @app.exception_handler(MbcalError)
    async def mbcal_error(_request: Request, err: MbcalError):
        return JSONResponse({"error": error_json(err)}, status_code=400)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(_request: Request, err: StarletteHTTPException):
        # FastAPI's own refusals (a body that is not JSON, or nested too deep) in the page's format.
        return _refuse(err.status_code, f"invalid request: {err.detail}")

    @app.exception_handler(Exception)
    async def crashed(_request: Request, err: Exception):
        # Never a bare traceback page: the message, the page's format, the security headers.
        return _refuse(500, f"the studio failed: {type(err).__name__}: {err}")

    @app.exception_handler(RequestValidationError)
    async def invalid(_request: Request, err: RequestValidationError):
        problems = []
        for e in err.errors()[:5]:
            where = ".".join(str(x) for x in e.get("loc", ()))
            problems.append(f"{where}: {e.get('msg')}")
        return JSONResponse(
            {"error": {"message": "invalid request: " + "; ".join(problems), "location": None}}, status_code=422
        )

    @app.get("/")
    def index():
        return Response(page, media_type="text/html; charset=utf-8")

    @app.get("/static/{name}")
    def static(name: str):
        if name not in STATIC:
            return _refuse(404, "no such file")
        return Response(_static(name), media_type=STATIC[name])

    @app.get("/api/state")
    def state():
        return engine.state()

    @app.get("/api/photo/{photo_id}")
    def photo(photo_id: str):
        p = engine.photos.get(photo_id)
        if p is None:
            return _refuse(404, "no such photo")
        return FileResponse(p.path, media_type=p.media_type)

    @app.post("/api/overlay")
    def overlay(body: OverlayBody):
        # Wireframes are long lists of numbers: encoded here at once, not walked by FastAPI's encoder.
        ids = list(dict.fromkeys(body.photos))
        # The cameras in parallel: the projections spend their time in compiled code, without the GIL.
        done = list(_POOL.map(lambda pid: engine.projection(pid, body.values, occlusion=body.occlusion), ids))
        views = dict(zip(ids, done))
        return Response(json.dumps({"views": views}, allow_nan=False), media_type="application/json")

    @app.post("/api/solid")
    def solid(body: SolidBody):
        return Response(engine.solid(body.photo, body.values), media_type="image/png")

    @app.post("/api/session")
    def session(body: SessionBody):
        return engine.set_session([c.model_dump() for c in body.clicks], body.estimate, body.values, body.hidden)

    @app.post("/api/reload")
    def reload(_body: EmptyBody):
        return engine.reload()

    @app.post("/api/observe")
    def observe(_body: EmptyBody):
        return engine.observe()

    @app.post("/api/solve")
    def solve(body: SolveBody):
        engine.start_solve(body.restarts, body.seed)
        return {"started": True}

    @app.get("/api/solve")
    def solve_status():
        return engine.solve_status()

    @app.post("/api/save")
    def save(body: SaveBody):
        return engine.save(body.format)

    return app


def check_address(host: str, port: int = 0) -> None:
    """Refuse an address the studio cannot serve on: called by ``mbcal studio`` before anything
    else (no warning about a host, no folder made, for an address that is refused anyway)."""
    if not 0 <= port <= 65535:
        raise MbcalError(f"--port must be 0 (any free port) to 65535, got {port}")
    if host in WILDCARDS:
        raise MbcalError(
            f"--host {host} listens on every address but answers to one Host name, so a browser "
            "elsewhere could not use it: name the address to listen on (this machine's, as the "
            "other machine reaches it)"
        )


class StudioServer:
    """The studio served on a socket: ``run()`` blocks; ``start()`` runs it in a thread (tests)."""

    def __init__(self, engine: Engine, host: str = "127.0.0.1", port: int = 0):
        check_address(host, port)
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.sock = socket.socket(family, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self.sock.bind((host, port))
        except OSError as err:
            self.sock.close()
            raise MbcalError(f"cannot listen on {host}:{port}: {err.strerror}") from None
        # Listening from here on, before the URL is printed: a browser that opens it at once waits
        # in the backlog until uvicorn accepts, instead of being refused while uvicorn starts up
        # (CI caught ERR_CONNECTION_REFUSED; uvicorn's own listen() on the socket is harmless).
        self.sock.listen(128)
        self.port = self.sock.getsockname()[1]
        self.host = host
        self.token = secrets.token_urlsafe(24)
        shown = f"[{host}]" if ":" in host else host
        hosts = [f"{shown}:{self.port}"]
        if host == "127.0.0.1":
            hosts.append(f"localhost:{self.port}")
        self.app = create_app(engine, self.token, hosts)
        config = uvicorn.Config(self.app, log_level="warning", access_log=False, lifespan="off")
        self.server = uvicorn.Server(config)
        self.thread: threading.Thread | None = None
        self.url = f"http://{shown}:{self.port}/?token={self.token}"

    def run(self) -> None:
        self.server.run(sockets=[self.sock])

    def start(self) -> StudioServer:
        self.thread = threading.Thread(target=self.run, name="mbcal-studio", daemon=True)
        self.thread.start()
        while not self.server.started:
            if not self.thread.is_alive():
                raise MbcalError("the studio's server did not start")
            threading.Event().wait(0.02)
        return self

    def stop(self) -> None:
        self.server.should_exit = True
        if self.thread is not None:
            self.thread.join(timeout=10)
        self.sock.close()


def serve_forever(engine: Engine, host: str, port: int, *, open_browser: bool, say=print) -> int:
    """Run the studio until interrupted (``mbcal studio``)."""
    server = StudioServer(engine, host, port)
    say(f"mbcal studio: {server.url}")
    say(f"  writing under {engine.out}/ (session saved after every edit); Ctrl+C stops")
    opener = _open_browser(server.url, engine.out) if open_browser else None
    try:
        server.run()
    finally:
        if opener is not None:
            with contextlib.suppress(OSError):
                opener.unlink()
    return 0


def _open_browser(url: str, out) -> Path:
    """Open ``url`` in the user's browser through a private redirect file (mode 0600, in the
    studio's folder): the browser's command line then names the file, not the token."""
    import os
    import tempfile
    import webbrowser  # only when a browser is to be opened
    from html import escape

    fd, name = tempfile.mkstemp(prefix=".studio-open-", suffix=".html", dir=out)
    with os.fdopen(fd, "w", encoding="utf-8") as f:  # mkstemp makes it 0600
        f.write(
            f'<!doctype html><meta charset="utf-8"><meta http-equiv="refresh" content="0; url={escape(url)}">'
            f'<a href="{escape(url)}">open the studio</a>\n'
        )
    path = Path(name).resolve()
    webbrowser.open(path.as_uri())

    def remove() -> None:  # once the browser has read it (and at the latest when the studio stops)
        with contextlib.suppress(OSError):
            path.unlink()

    timer = threading.Timer(30.0, remove)
    timer.daemon = True
    timer.start()
    return path
