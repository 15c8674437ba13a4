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
"""

from __future__ import annotations

import socket
from pathlib import Path
from typing import Any

from fastapi import Body, FastAPI, Query, Request
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles

from pipeline import __version__
from pipeline.core.errors import PipelineError
from pipeline.studio.capture_session import CaptureSession
from pipeline.studio.fit_session import FitSession

STATIC = Path(__file__).parent / "static"
THREE_BUNDLE = Path(__file__).parents[1] / "viewer" / "three_bundle.js"
NO_CACHE = {"Cache-Control": "no-store"}


def create_app(session: FitSession | CaptureSession | None, startup_error: str | None = None) -> FastAPI:
    """The app for one session; ``startup_error`` (no session): a page that shows why
    the studio could not open its scene or capture."""
    app = FastAPI(title="pipeline studio", version=__version__, docs_url=None, redoc_url=None, openapi_url=None)

    @app.exception_handler(PipelineError)
    async def user_error(request: Request, error: PipelineError) -> JSONResponse:
        return JSONResponse({"error": str(error)}, status_code=400)

    @app.get("/")
    def page() -> FileResponse:
        return FileResponse(STATIC / "index.html", headers=NO_CACHE)

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
    return app


def _fit_routes(app: FastAPI, session: FitSession) -> None:
    @app.get("/api/fit/match")
    def match(words: str = "") -> dict[str, Any]:
        return {"keys": session.matching(words.split())}

    @app.post("/api/fit/start")
    def start(form: dict[str, Any] = Body(...)) -> dict[str, Any]:
        session.start(form)
        return {"started": True}

    @app.post("/api/fit/{action}")
    def control(action: str) -> dict[str, Any]:
        actions = {"pause": session.pause, "resume": session.resume, "stop": session.stop}
        if action not in actions:
            raise PipelineError(f"no action {action}: pause, resume or stop")
        actions[action]()
        return {"status": session.snapshot()["status"]}

    @app.post("/api/fit/view")
    def view(body: dict[str, Any] = Body(...)) -> dict[str, Any]:
        session.show_view(str(body.get("name", "")))
        return {"view": body.get("name")}

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
        return JSONResponse(session.stages(preset, overrides), headers=NO_CACHE)

    @app.post("/api/capture/run")
    def run(body: dict[str, Any] = Body(...)) -> dict[str, Any]:
        session.stages(str(body.get("preset") or session.layers.preset), list(body.get("set") or []))
        session.start_run()
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


def serve(app: FastAPI, sock: socket.socket) -> None:
    """Serve until Ctrl-C (uvicorn's own signal handling)."""
    import uvicorn

    config = uvicorn.Config(app, log_level="warning", access_log=False, lifespan="off")
    uvicorn.Server(config).run(sockets=[sock])
