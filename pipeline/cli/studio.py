"""``pipeline studio``: the original tool's interactive fit in a browser, or a live
view of a capture (pipeline.studio)."""

from __future__ import annotations

import threading
import webbrowser
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

from pipeline import logger
from pipeline.cli.options import Arg
from pipeline.cli.registry import ConfigLayers, command
from pipeline.core.config import Range
from pipeline.core.errors import ConfigError, PipelineError

LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")


@dataclass(frozen=True)
class StudioOptions:
    """Open a scene's fit (SCENE.xml --references DIR) or a capture folder in the browser."""

    target: Annotated[str, Arg(positional=True, metavar="SCENE.xml|CAPTURE")]
    """A Mitsuba scene file to fit (with --references), or a capture folder to watch and run."""
    references: Annotated[str | None, Arg(metavar="DIR")] = None
    """The scene's reference images, one per sensor, matched by sorted file name."""
    out: str = "fit_out"
    """Folder a scene's fit writes its fitted scene, params.json, log.jsonl and loss.png into."""
    variant: Literal["auto", "cuda_ad_rgb", "llvm_ad_rgb"] = "auto"
    """Mitsuba variant (auto: cuda_ad_rgb if it works, else llvm_ad_rgb)."""
    config: ConfigLayers = field(default_factory=ConfigLayers)
    """A capture's preset and overrides (the page can change them)."""
    host: str = "127.0.0.1"
    """Address to listen on. Anything but this machine's loopback lets other machines
    reach the studio, its files and its runs: only on a network you trust."""
    port: Annotated[int, Range(0, 65535)] = 0
    """Port to listen on (0: a free one)."""
    no_browser: bool = False
    """Print the address instead of opening the browser."""


def _check_target(options: StudioOptions) -> None:
    """What the command line names must exist: nothing to show otherwise."""
    target = Path(options.target)
    if target.is_dir():
        return
    if target.suffix.lower() != ".xml" or not target.is_file():
        raise ConfigError(f"{target} is neither a capture folder nor a Mitsuba scene file (.xml)")
    if not options.references:
        raise ConfigError("pipeline studio SCENE.xml needs --references DIR (one image per sensor)")


def _session(options: StudioOptions):
    """The session the page shows, and why it has none: a capture whose settings are
    wrong ends the command (the CLI's message, exit 2); a scene or reference folder the
    fit cannot open is shown in the page, where the user is looking."""
    from pipeline.studio.capture_session import CaptureSession
    from pipeline.studio.fit_session import FitSession

    if Path(options.target).is_dir():
        return CaptureSession(options.target, options.config.preset, options.config.set), None
    try:
        return FitSession(Path(options.target), Path(options.references), Path(options.out), options.variant), None
    except PipelineError as failure:
        logger.error("%s", failure)
        return None, str(failure)


@command("studio", StudioOptions, "fit a scene interactively, or watch and run a capture, in the browser")
def studio(options: StudioOptions) -> int:
    from pipeline.studio.server import Access, create_app, listening_socket, serve

    if options.host not in LOCAL_HOSTS:
        logger.warning(
            "listening on %s: other machines can reach the studio, read its scene's or capture's files and "
            "start runs; use only on a network you trust",
            options.host,
        )
    _check_target(options)
    session, error = _session(options)
    try:
        sock = listening_socket(options.host, options.port)
    except OSError as failure:
        raise ConfigError(f"cannot listen on {options.host}:{options.port} ({failure.strerror}): pick another --port")
    host, port = sock.getsockname()[:2]
    access = Access.serving(host, port)
    url = access.url(host, port)
    logger.info("studio at %s (Ctrl-C to quit)", url)
    if not options.no_browser:
        threading.Timer(0.5, webbrowser.open, [url]).start()
    try:
        serve(create_app(session, access, error), sock)
    finally:
        _finish(session)
    return 0 if error is None else 2


def _finish(session) -> None:
    """On quitting (Ctrl-C, SIGTERM, SIGHUP): a running fit stops and writes its best
    state; a run from the page is interrupted as Ctrl-C would (its finished stages
    kept) and waited for, so that its lock is released before the studio ends."""
    from pipeline.studio.fit_session import FitSession

    if isinstance(session, FitSession):
        if session.stop():
            logger.info("studio: stopping the fit; its best state so far goes to %s", session.out_dir)
        session.wait()
    elif session is not None:
        if session.stop_run():
            logger.info("studio: stopping the run started from the page; its finished stages are kept")
        session.wait()
