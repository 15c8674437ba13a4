"""A fit of a Mitsuba scene to reference images that a page watches and steers: the
scene's parameter table, one fit at a time in a worker thread (the same
pipeline.fit.scene_fit.fit_scene as `pipeline fit`), its live log, a preview of any
view, Pause, Resume and Stop.

Every Dr.Jit call runs in the worker thread (the fit and its previews); the server's
threads read only what the worker published under the session's lock. A preview is
rendered between two steps, with the values of the step just taken, at
``PREVIEW_SPP``, every ``PREVIEW_EVERY`` steps and when the page picks another view.
Stop ends the fit as its own stopping rule would: in the best state, whose values
are written (scene, params.json, log.jsonl, loss.png) as `pipeline fit` writes them.

Limitations: one fit at a time; time spent paused counts toward the fit's time
budget; a preview costs a render of one view (a kernel compile the first time).
"""

from __future__ import annotations

import dataclasses
import json
import re
import threading
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline import logger
from pipeline.cli.fit import FitOptions, scene_fit_request
from pipeline.core.config import Range, build_section, describe_type, field_docs
from pipeline.core.errors import ConfigError, PipelineError
from pipeline.fit import engine
from pipeline.fit.scene_fit import (
    USER_STOP,
    FitWatcher,
    check_out_dir,
    check_patterns,
    describe_parameters,
    selects,
)
from pipeline.fit.settings import FitSettings
from pipeline.imaging.photo_io import list_photos, srgb_encode

PREVIEW_SPP = 16
"""Samples per pixel of a preview render: enough to judge a material by eye."""
PREVIEW_EVERY = 5
"""Steps between two previews of the view the page shows (each costs a render)."""
PAGE_OPTIONS = ("max_size", "coarse_to_fine", "lr")
"""`pipeline fit`'s options the page sets besides the loop's settings (the scene, the
references, the output folder and the variant come from the command line; the
parameters, their bounds and the held-out images from the page's tables)."""
OUTPUT_FILES = ("params.json", "log.jsonl", "loss.png")
"""What a finished fit offers for download besides the fitted scene."""


def settings_schema() -> list[dict[str, Any]]:
    """The fit settings the page shows: `pipeline fit`'s own options (names, types,
    defaults, ranges and documentation from pipeline.cli.fit.FitOptions and
    pipeline.fit.settings.FitSettings, the one source)."""
    rows = []
    for cls, names in ((FitOptions, PAGE_OPTIONS), (FitSettings, [f.name for f in dataclasses.fields(FitSettings)])):
        hints = typing.get_type_hints(cls, include_extras=True)
        docs = field_docs(cls)
        defaults = cls.__dataclass_fields__
        for name in names:
            hint = hints[name]
            extras = typing.get_args(hint)[1:] if typing.get_origin(hint) is typing.Annotated else ()
            bare = typing.get_args(hint)[0] if extras else hint
            bounds = next((e for e in extras if isinstance(e, Range)), None)
            default = defaults[name].default
            rows.append(
                {
                    "name": name,
                    "group": "loop" if cls is FitSettings else "fit",
                    "kind": _kind(bare),
                    "choices": list(typing.get_args(bare)) if typing.get_origin(bare) is typing.Literal else None,
                    "default": default,
                    "lo": bounds.lo if bounds else None,
                    "hi": bounds.hi if bounds else None,
                    "type": describe_type(hint),
                    "doc": docs.get(name, ""),
                }
            )
    return rows


def _kind(hint: Any) -> str:
    if type(None) in typing.get_args(hint):  # left to the fit (None) or given
        hint = next(a for a in typing.get_args(hint) if a is not type(None))
    if typing.get_origin(hint) is typing.Literal:
        return "choice"
    if hint is bool:
        return "bool"
    if hint is int:
        return "int"
    return "float"


@dataclass
class FitState:
    """What the page polls: the fit's status, its log and how it ended."""

    status: str = "idle"
    """idle, running, paused, stopping, done or failed."""
    log: list[dict] = field(default_factory=list)
    level: int = 0
    levels: list[int] = field(default_factory=list)
    views: list[dict] = field(default_factory=list)
    """Each view's name and whether it is held out."""
    stopped: str | None = None
    error: str | None = None
    outputs: list[str] = field(default_factory=list)
    preview_version: int = 0
    preview_of: str | None = None
    """The view the current preview images show (the picker's choice once rendered)."""


class FitSession(FitWatcher):
    """One scene and its references; one fit at a time."""

    def __init__(self, scene: Path, references: Path, out_dir: Path, variant: str = "auto"):
        self.scene, self.references, self.out_dir, self.variant = scene, references, out_dir, variant
        self.parameters = describe_parameters(scene, variant)
        self.reference_names = [path.stem for path in list_photos(references)] if references.is_dir() else []
        if not self.reference_names:
            raise ConfigError(f"--references {references} holds no images: name the folder of reference images")
        check_out_dir(out_dir, scene, references)
        self.state = FitState(views=[{"name": name, "heldout": False} for name in self.reference_names])
        self._lock = threading.Lock()
        self._worker: threading.Thread | None = None
        self._stop = threading.Event()
        self._running = threading.Event()  # cleared while paused
        self._views: list[engine.FitView] = []
        self._preview_view = self.reference_names[0]
        self._preview_due = True
        self._previews: dict[str, bytes] = {}

    # The page's requests (server threads).

    def describe(self) -> dict[str, Any]:
        return {
            "mode": "fit",
            "scene": str(self.scene),
            "references": str(self.references),
            "out": str(self.out_dir),
            "parameters": self.parameters,
            "views": self.reference_names,
            "settings": settings_schema(),
        }

    def matching(self, words: list[str]) -> list[str]:
        """The parameter keys any of ``words`` selects, as ``--params`` does (no words: all)."""
        check_patterns(words)
        return [row["key"] for row in self.parameters if not words or any(selects(w, row["key"]) for w in words)]

    def start(self, form: dict[str, Any]) -> None:
        """Start a fit of the ticked parameters with the page's settings; a bad form
        raises ConfigError with the CLI's message."""
        with self._lock:
            if self._worker is not None and self._worker.is_alive():
                raise ConfigError("a fit is running: stop it before starting another")
            request = scene_fit_request(self.options(form))
            self._stop.clear()
            self._running.set()
            heldout = set(request.heldout)
            self.state = FitState(
                status="running", views=[{"name": n, "heldout": n in heldout} for n in self.reference_names]
            )
            self._previews, self._preview_due = {}, True
            self._worker = threading.Thread(target=self._fit, args=(request,), name="studio-fit", daemon=True)
            self._worker.start()

    def options(self, form: dict[str, Any]) -> FitOptions:
        """`pipeline fit`'s options from the page's form, checked as the command line's are."""
        keys = form.get("params") or []
        if not keys:
            raise ConfigError("tick at least one parameter to fit")
        known = {row["key"] for row in self.parameters if row["fittable"]}
        unknown = [key for key in keys if key not in known]
        if unknown:
            raise ConfigError(f"{unknown[0]} is not a fittable parameter of {self.scene}")
        settings = dict(form.get("settings") or {})
        loop = build_section("fit", FitSettings, {k: v for k, v in settings.items() if k not in PAGE_OPTIONS})
        spans = (form.get("bounds") or {}).items()
        bounds = tuple(f"{key}={':'.join(str(v) for v in span)}" for key, span in spans if key in keys)
        engine.parse_bounds(bounds, "bounds")  # a bad pair ends here, with the command line's message
        values = {k: v for k, v in settings.items() if k in PAGE_OPTIONS}
        return build_section(
            "fit",
            FitOptions,
            values
            | {
                "scene": str(self.scene),
                "references": str(self.references),
                "params": tuple(f"^{re.escape(key)}$" for key in keys),
                "settings": loop,
                "bound": bounds,
                "heldout": tuple(form.get("heldout") or ()),
                "variant": self.variant,
                "out": str(self.out_dir),
            },
        )

    def pause(self) -> None:
        with self._lock:
            if self.state.status == "running":
                self._running.clear()
                self.state.status = "paused"

    def resume(self) -> None:
        with self._lock:
            if self.state.status == "paused":
                self.state.status = "running"
                self._running.set()

    def stop(self) -> bool:
        """Ask a running or paused fit to end in its best state; whether there was one."""
        with self._lock:
            if self.state.status in ("running", "paused"):
                self.state.status = "stopping"
                self._stop.set()
                self._running.set()
                return True
            return False

    def wait(self, timeout: float | None = None) -> None:
        """Until the worker has written its results (or ``timeout`` seconds)."""
        if self._worker is not None:
            self._worker.join(timeout)

    def show_view(self, name: str) -> None:
        if name not in self.reference_names:
            raise ConfigError(f"no view {name}: the views are {', '.join(self.reference_names)}")
        with self._lock:
            self._preview_view, self._preview_due = name, True

    def snapshot(self, since: int = 0) -> dict[str, Any]:
        """The state the page polls, with the log entries from ``since`` on: only those
        are copied, so a poll costs the same at step 10 and at step 10,000."""
        with self._lock:
            log, self.state.log = self.state.log, []
            try:
                state = dataclasses.asdict(self.state)
            finally:
                self.state.log = log
            state["log"] = log[since:]
        state["since"] = since
        state["preview_view"] = self._preview_view
        return state

    def preview(self, kind: str) -> bytes | None:
        with self._lock:
            return self._previews.get(kind)

    def output_file(self, name: str) -> Path:
        """A finished fit's file, by name: only those the fit wrote into --out."""
        allowed = {*OUTPUT_FILES, self.scene.name}
        if name not in allowed or name not in self.state.outputs:
            raise ConfigError(
                f"{name} is not one of this fit's results ({', '.join(self.state.outputs) or 'none yet'})"
            )
        return self.out_dir / name

    # The worker thread.

    def _fit(self, request) -> None:
        from pipeline.fit.scene_fit import fit_scene

        try:
            params_json = fit_scene(request, watcher=self)
            stopped = json.loads(params_json.read_text())["stopped"]
            with self._lock:
                self.state.stopped = stopped
        except PipelineError as error:
            with self._lock:
                self.state.status, self.state.error = "failed", str(error)
            logger.error("studio: %s", error)
        finally:
            with self._lock:
                if self.state.status != "failed":
                    written = [n for n in (*OUTPUT_FILES, self.scene.name) if (self.out_dir / n).is_file()]
                    self.state.status = "done" if self.state.stopped else "failed"
                    self.state.outputs = written
                    if self.state.stopped is None:
                        self.state.error = "the fit ended unexpectedly: its traceback is in the studio's terminal"
            self._views = []

    def level_started(self, level: int, levels: list[int], views: list[engine.FitView]) -> None:
        with self._lock:
            self.state.level, self.state.levels = level, list(levels)
            self._views, self._preview_due = views, True

    def step(self, entry: dict) -> str | None:
        with self._lock:
            self.state.log.append(finite(entry))
            due = self._preview_due or entry["iteration"] % PREVIEW_EVERY == 0
        if due:
            self._render_preview(entry["iteration"])
        while not self._running.wait(0.2):
            if self._preview_due:  # the page picked another view while paused
                self._render_preview(entry["iteration"])
        if self._stop.is_set():
            with self._lock:
                self.state.stopped = f"{USER_STOP} at step {entry['iteration']}"
            return self.state.stopped
        return None

    def _render_preview(self, iteration: int) -> None:
        import drjit as dr
        import mitsuba as mi

        from pipeline.fit.loop import seed

        with self._lock:
            name, self._preview_due = self._preview_view, False
        view = next((v for v in self._views if v.name == name), None)
        if view is None:
            return
        with dr.suspend_grad():
            image = mi.render(
                view.scene, sensor=view.sensor, integrator=view.integrator, spp=PREVIEW_SPP, seed=seed(iteration)
            )
            render = np.asarray(image, dtype=np.float32)[..., :3]
        previews = preview_images(render, view.reference)
        with self._lock:
            self._previews = previews
            self.state.preview_version += 1
            self.state.preview_of = name


def preview_images(render: np.ndarray, reference: np.ndarray) -> dict[str, bytes]:
    """PNGs of a render, its reference (sRGB) and their absolute difference (x4, so that
    a few per cent shows)."""
    import cv2

    def png(linear: np.ndarray) -> bytes:
        encoded = (np.clip(srgb_encode(np.clip(linear, 0, None)), 0, 1) * 255 + 0.5).astype(np.uint8)
        return cv2.imencode(".png", np.ascontiguousarray(encoded[..., ::-1]))[1].tobytes()

    difference = np.abs(render - reference).mean(axis=2, keepdims=True).repeat(3, axis=2) * 4
    return {"render": png(render), "reference": png(reference), "difference": png(difference)}


def finite(value: Any) -> Any:
    """``value`` (a log entry) with every NaN and infinity as None: what JSON can carry to
    the page (a step's loss can be NaN when every gradient of a step was dropped)."""
    if isinstance(value, dict):
        return {key: finite(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite(item) for item in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value
