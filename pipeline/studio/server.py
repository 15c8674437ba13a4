"""The studio's web app: FastAPI routes over a FitSession or a CaptureSession, the
page and its scripts (static/, shipped with the package: nothing is fetched at run
time), served by uvicorn on one socket.

The page polls ``/api/.../state`` twice a second; every answer is small JSON (log
entries since the last poll) or an image. Errors a user can cause (a bad setting, a
scene Mitsuba cannot load, a reference folder that does not match the sensors) are
PipelineErrors and come back as ``{"error": message}`` with status 400, the message
the command line would print; the page shows it.

Files: only what the sessions name (the fit's outputs in --out by name, the capture's
photos by name, files under the capture's output/ after a path check), the page's own
static files and the three.js bundle. Nothing else on the disk is reachable.

Who may ask (``StudioGuard``, as Jupyter's server does it): the studio is a server on
this machine that starts runs and serves files, so a web page on another site must not
reach it through the user's browser.

- Host must name the address the studio serves (a loopback name and its port): a
  foreign Host is DNS rebinding, answered 403.
- Origin, where a browser sends one, must be the studio's own; a cross-site fetch is
  403 before any route sees it.
- A token made at each start, in the address the studio prints and opens
  (``/?token=...``), is needed for everything but the page's static files: the page
  gets it as a cookie (HttpOnly, SameSite=Strict) and in a meta tag, and sends it as
  the ``X-Studio-Token`` header with every request that changes state (POST), which a
  form or a plain link on another site cannot do. No GET changes state.
- A request's body is at most ``MAX_BODY`` bytes (413 otherwise, read no further), and
  a malformed one is a 400 with the first problem's place, never the body echoed back.
"""

from __future__ import annotations

import contextlib
import hmac
import secrets
import signal
import socket
from dataclasses import dataclass
from http.cookies import SimpleCookie
from pathlib import Path
from typing import Any, Literal
from urllib.parse import parse_qs

from fastapi import FastAPI, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, ConfigDict, Field, StrictBool, StrictFloat, StrictInt, StrictStr
from starlette.exceptions import HTTPException as StarletteHTTPException

from pipeline import __version__, logger
from pipeline.core.errors import PipelineError
from pipeline.studio.capture_session import CaptureSession
from pipeline.studio.fit_session import FitSession

STATIC = Path(__file__).parent / "static"
THREE_BUNDLE = Path(__file__).parents[1] / "viewer" / "three_bundle.js"
NO_CACHE = {"Cache-Control": "no-store"}
MAX_BODY = 1 << 20
"""Bytes a request's body may have: the largest form the page sends is a few kB."""
TOKEN_HEADER = "x-studio-token"
PUBLIC_PATHS = ("/static/", "/three_bundle.js")
"""What is served without the token: the page's own code, nothing of the user's."""
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")
SHUTDOWN_GRACE_S = 5
"""Seconds the server waits for requests in flight when it quits."""


@dataclass(frozen=True)
class Access:
    """Who may ask: the addresses the studio answers to and this start's token."""

    hosts: frozenset[str]
    """Host headers accepted (``name:port``)."""
    token: str

    @staticmethod
    def serving(host: str, port: int, token: str | None = None) -> "Access":
        """The Host names of a studio listening on ``host``:``port``: the loopback names,
        and the address itself when it is another (a studio on a LAN address is reached
        by that address)."""
        names = {*LOOPBACK_NAMES, f"[{host}]" if ":" in host else host}
        if host in ("0.0.0.0", "::"):
            names |= {socket.gethostname(), socket.getfqdn()}
        return Access(frozenset(f"{name}:{port}".lower() for name in names), token or secrets.token_urlsafe(24))

    @property
    def cookie(self) -> str:
        """The cookie's name: one per port, since a browser shares cookies across ports."""
        port = next(iter(self.hosts)).rsplit(":", 1)[1]
        return f"studio-token-{port}"

    def url(self, host: str, port: int) -> str:
        return f"http://{'[' + host + ']' if ':' in host else host}:{port}/?token={self.token}"

    def origins(self) -> frozenset[str]:
        return frozenset(f"http://{host}" for host in self.hosts)


class StudioGuard:
    """ASGI middleware: Host, Origin, token and body size checked before any route (the
    module's docstring says why)."""

    def __init__(self, app, access: Access):
        self.app, self.access = app, access

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers = {name.decode("latin-1").lower(): value.decode("latin-1") for name, value in scope["headers"]}
        refusal = self.refusal(scope, headers)
        if refusal is not None:
            status, message = refusal
            return await JSONResponse({"error": message}, status_code=status)(scope, receive, send)
        return await self.app(scope, self._capped(receive), send)

    def refusal(self, scope, headers: dict[str, str]) -> tuple[int, str] | None:
        """(status, why) for a request the studio does not answer; None to go on."""
        if headers.get("host", "").lower() not in self.access.hosts:
            return 403, "unknown Host: open the address the studio printed"
        origin = headers.get("origin")
        if origin is not None and origin.lower() not in self.access.origins():
            return 403, "requests from other sites are refused"
        if headers.get("sec-fetch-site") == "cross-site":
            return 403, "requests from other sites are refused"
        path, method = scope["path"], scope["method"]
        if method not in ("GET", "HEAD", "POST"):
            return 405, f"{method} is not answered"
        if method == "POST":
            if not hmac.compare_digest(headers.get(TOKEN_HEADER, ""), self.access.token):
                return 403, "a change needs the studio's token: reload the page from the address the studio printed"
            length = headers.get("content-length", "0")
            if "transfer-encoding" in headers or not length.isdigit():
                return 411, "a request's body needs its length (Content-Length)"
            if int(length) > MAX_BODY:
                return 413, f"a request's body may have {MAX_BODY} bytes at most"
        elif not path.startswith(PUBLIC_PATHS) and not self._token_given(scope, headers):
            return 403, "this needs the studio's token: open the address the studio printed (it ends in ?token=...)"
        return None

    def _token_given(self, scope, headers: dict[str, str]) -> bool:
        cookie = SimpleCookie(headers.get("cookie", ""))
        given = [
            headers.get(TOKEN_HEADER, ""),
            cookie[self.access.cookie].value if self.access.cookie in cookie else "",
            *parse_qs(scope.get("query_string", b"").decode("latin-1")).get("token", []),
        ]
        return any(hmac.compare_digest(value, self.access.token) for value in given if value)

    @staticmethod
    def _capped(receive):
        """``receive`` that ends a body longer than its Content-Length said (the
        guard checked that length): no request reads more than MAX_BODY bytes."""
        taken = 0

        async def capped():
            nonlocal taken
            message = await receive()
            taken += len(message.get("body", b""))
            if taken > MAX_BODY:
                raise PipelineError(f"a request's body may have {MAX_BODY} bytes at most")
            return message

        return capped


# The page's requests, as typed bodies: a malformed one is refused by its shape (400).
Setting = StrictBool | StrictInt | StrictFloat | StrictStr | None


class _Form(BaseModel):
    model_config = ConfigDict(extra="forbid")


class FitForm(_Form):
    params: list[StrictStr] = Field(default_factory=list, max_length=10_000)
    settings: dict[StrictStr, Setting] = Field(default_factory=dict)
    bounds: dict[StrictStr, list[StrictFloat | StrictInt]] = Field(default_factory=dict)
    heldout: list[StrictStr] = Field(default_factory=list)


class ViewForm(_Form):
    name: StrictStr


class RunForm(_Form):
    preset: StrictStr | None = None
    set: list[StrictStr] = Field(default_factory=list)


def create_app(
    session: FitSession | CaptureSession | None, access: Access, startup_error: str | None = None
) -> StudioGuard:
    """The app for one session behind its guard; ``startup_error`` (no session): a page
    that shows why the studio could not open its scene or capture."""
    app = FastAPI(title="pipeline studio", version=__version__, docs_url=None, redoc_url=None, openapi_url=None)

    @app.exception_handler(PipelineError)
    async def user_error(request: Request, error: PipelineError) -> JSONResponse:
        return JSONResponse({"error": str(error)}, status_code=400)

    @app.exception_handler(StarletteHTTPException)
    async def not_answered(request: Request, error: StarletteHTTPException) -> JSONResponse:
        return JSONResponse({"error": f"{error.detail}: {request.url.path}"}, status_code=error.status_code)

    @app.exception_handler(RequestValidationError)
    async def malformed(request: Request, error: RequestValidationError) -> JSONResponse:
        first = error.errors()[0] if error.errors() else {}
        where = ".".join(str(part) for part in first.get("loc", ()))
        return JSONResponse({"error": f"malformed request: {where}: {first.get('msg', 'invalid')}"}, status_code=400)

    @app.get("/")
    def page() -> HTMLResponse:
        """The page, with this start's token for its scripts, and the token as a cookie
        for its images and the report's files."""
        html = (STATIC / "index.html").read_text()
        html = html.replace("<head>", f'<head>\n<meta name="studio-token" content="{access.token}">', 1)
        response = HTMLResponse(html, headers=NO_CACHE)
        response.set_cookie(access.cookie, access.token, httponly=True, samesite="strict", path="/")
        return response

    @app.get("/three_bundle.js")
    def three() -> FileResponse:
        return FileResponse(THREE_BUNDLE, media_type="text/javascript")

    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    @app.get("/api/session")
    def describe() -> dict[str, Any]:
        if session is None:
            return {"mode": "error", "error": startup_error}
        return session.describe()

    if isinstance(session, FitSession):
        _fit_routes(app, session)
    elif isinstance(session, CaptureSession):
        _capture_routes(app, session)
    return StudioGuard(app, access)


def _fit_routes(app: FastAPI, session: FitSession) -> None:
    @app.get("/api/fit/match")
    def match(words: str = "") -> dict[str, Any]:
        return {"keys": session.matching(words.split())}

    @app.post("/api/fit/start")
    def start(form: FitForm) -> dict[str, Any]:
        session.start(form.model_dump())
        return {"started": True}

    @app.post("/api/fit/view")
    def view(form: ViewForm) -> dict[str, Any]:
        session.show_view(form.name)
        return {"view": form.name}

    @app.post("/api/fit/{action}")
    def control(action: Literal["pause", "resume", "stop"]) -> dict[str, Any]:
        {"pause": session.pause, "resume": session.resume, "stop": session.stop}[action]()
        return {"status": session.snapshot()["status"]}

    @app.get("/api/fit/state")
    def state(since: int = Query(0, ge=0)) -> JSONResponse:
        return JSONResponse(session.snapshot(since), headers=NO_CACHE)

    @app.get("/api/fit/preview/{kind}")
    def preview(kind: str) -> Response:
        return _made(session.preview(kind), "image/png")

    @app.get("/api/fit/download/{name}")
    def download(name: str) -> FileResponse:
        return FileResponse(session.output_file(name), filename=name)


def _capture_routes(app: FastAPI, session: CaptureSession) -> None:
    @app.get("/api/capture/stages")
    def stages(preset: str | None = None, overrides: list[str] = Query(default=[], alias="set")) -> JSONResponse:
        """The table under the page's settings, which only a run (POST) keeps."""
        return JSONResponse(session.stages(preset, overrides), headers=NO_CACHE)

    @app.post("/api/capture/run")
    def run(form: RunForm) -> dict[str, Any]:
        session.start_run(form.preset or session.layers.preset, form.set)
        return {"started": True}

    @app.post("/api/capture/stop")
    def stop() -> dict[str, Any]:
        session.stop_run()
        return {"stopping": True}

    @app.get("/api/capture/run")
    def run_state(since: int = Query(0, ge=0)) -> JSONResponse:
        return JSONResponse(session.run_snapshot(since), headers=NO_CACHE)

    @app.get("/api/capture/fit-preview/{kind}")
    def fit_preview(kind: str, view: str) -> Response:
        images = session.fit_preview(view)
        return _made(images.get(kind) if images else None, "image/png")

    @app.get("/api/capture/photos")
    def photos() -> dict[str, Any]:
        return {"photos": session.photos()}

    @app.get("/api/capture/photo/{name}")
    def photo(name: str) -> Response:
        return Response(session.photo(name), media_type="image/jpeg")

    @app.get("/api/capture/cameras")
    def cameras() -> dict[str, Any]:
        return {"cameras": session.cameras()}

    @app.get("/api/capture/mesh.glb")
    def mesh() -> Response:
        return _made(session.mesh_glb(), "model/gltf-binary")

    @app.get("/output/{relative:path}")
    def output(relative: str) -> FileResponse:
        return FileResponse(session.output_file(relative), headers=NO_CACHE)


def _made(content: bytes | None, media_type: str) -> Response:
    """Something made on request (a preview, a mesh): 204 while there is none yet."""
    if content is None:
        return Response(status_code=204)
    return Response(content, media_type=media_type, headers=NO_CACHE)


def listening_socket(host: str, port: int) -> socket.socket:
    """A socket bound to ``host``:``port`` (0: a free port) and listening, so that the
    address is known, and taken, before the server starts."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind((host, port))
    sock.listen(64)
    return sock


def serve(app: StudioGuard, sock: socket.socket) -> int | None:
    """Serve until Ctrl-C, SIGTERM or SIGHUP; returns the signal that ended it."""
    import uvicorn

    class Server(uvicorn.Server):
        """uvicorn's server with our signal handling: uvicorn's own raises the signal
        again once it has shut down, which the CLI's watcher (pipeline.core.interrupts)
        counts as a second Ctrl-C and ends the process before the studio's fit or run
        is written and stopped."""

        received: int | None = None

        @contextlib.contextmanager
        def capture_signals(self):
            def quit(signum, frame) -> None:
                self.received, self.should_exit = signum, True

            stops = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
            previous = {stop: signal.signal(stop, quit) for stop in stops}
            try:
                yield
            finally:
                for stop, handler in previous.items():
                    signal.signal(stop, handler)

    # a request stuck in a native call must not keep the studio from quitting on one Ctrl-C
    config = uvicorn.Config(
        app, log_level="warning", access_log=False, lifespan="off", timeout_graceful_shutdown=SHUTDOWN_GRACE_S
    )
    server = Server(config)
    server.run(sockets=[sock])
    if server.received is not None:
        logger.info("studio: %s received, quitting", signal.Signals(server.received).name)
    return server.received
