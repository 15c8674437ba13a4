"""A capture as the studio shows it: its stages (`pipeline status --json`'s table with
the reasons to rerun), a run started from the page, that run's log and, while a fit
stage runs, its steps; the photos with their masks, the cameras, the current mesh and
the report.

A run is `pipeline run` in a child process (``python -m pipeline run CAPTURE --preset
P -s ...``): it takes the capture's lock as the command does (a capture another run
holds is reported, not raced), and the studio's Stop sends it SIGINT, after which the
run keeps its finished stages and fit checkpoints as an interrupted run does. A fit
stage's steps are read from the live log its checkpoint keeps
(pipeline.fit.checkpoint, ``NN.steps.jsonl``).

Everything read comes from the capture's own folder: the stages' cached results for
the current settings (the plan's entries), output/ and the checkpoints.
"""

from __future__ import annotations

import ctypes
import io
import json
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline import logger
from pipeline.cli.registry import ConfigLayers, capture_dir, registered_stages
from pipeline.cli.stages import make_runner, status_summary
from pipeline.core.config import DEFAULT_PRESET, confine_input_files, parse_override, preset_names
from pipeline.core.errors import ConfigError
from pipeline.core.lock import holder
from pipeline.core.sections import schema
from pipeline.fit.scene_fit import set_values
from pipeline.formats.cameras import read_views
from pipeline.formats.pinhole import linear_photos, read_photos
from pipeline.formats.scene_description import SceneDescription
from pipeline.imaging.photo_io import read_photo
from pipeline.render import mitsuba_variant
from pipeline.studio.fit_session import PREVIEW_SPP, finite, preview_images

STOP_WAIT_S = 120.0
"""Seconds a run stopped from the studio may take to end before it is sent SIGTERM
(a stage ends at its next step: a render or a COLMAP call at most)."""
THUMBNAIL_PX = 320
"""Longer side of a photo's thumbnail."""
LOG_LINES = 2000
"""Lines of a run's log the studio keeps (the oldest go first)."""


@dataclass
class RunState:
    """A run started from the page."""

    command: list[str] = field(default_factory=list)
    log: list[str] = field(default_factory=list)
    dropped: int = 0
    """Log lines dropped from the front (past LOG_LINES)."""
    exit_code: int | None = None


def _interrupt_with_parent() -> None:
    """In the run's process before it starts: Linux sends it SIGINT when the studio dies
    (even by SIGKILL), so that no orphaned run goes on holding the capture's lock."""
    PR_SET_PDEATHSIG = 1
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGINT)


class CaptureSession:
    """One capture folder; at most one run from the page at a time.

    Settings from the page are confined as capture.toml's are: a file they name must
    lie inside the capture folder (pipeline.core.config.confine_input_files), unless the
    same override was given on the studio's own command line."""

    def __init__(self, capture: str, preset: str = DEFAULT_PRESET, overrides: tuple[str, ...] = ()):
        self.folder = capture_dir(capture)
        self.command_line = tuple(overrides)
        self.layers = self._layers(preset, list(overrides))
        self._runner()  # a bad preset, -s or capture.toml fails here, before the page opens
        self.run_state = RunState()
        self._process: subprocess.Popen | None = None
        self._lock = threading.Lock()
        self._render_lock = threading.Lock()  # one Dr.Jit render at a time
        self._results: dict[str, dict[str, Path]] | None = None
        """Each stage's current results, planned once per stage table (not per thumbnail)."""
        self._preview: tuple[tuple[str, int], dict[str, bytes]] | None = None

    def _layers(self, preset: str, overrides: list[str]) -> ConfigLayers:
        if preset not in preset_names():
            raise ConfigError(f"preset {preset!r} does not exist: use one of {', '.join(preset_names())}")
        for override in overrides:
            parse_override(override)
        from_page = [override for override in overrides if override not in self.command_line]
        confine_input_files(schema(registered_stages()), self.folder, from_page, "the studio's page")
        return ConfigLayers(preset, tuple(overrides))

    def _runner(self, layers: ConfigLayers | None = None):
        return make_runner(str(self.folder), layers or self.layers)

    def describe(self) -> dict[str, Any]:
        return {
            "mode": "capture",
            "capture": str(self.folder),
            "preset": self.layers.preset,
            "presets": preset_names(),
            "set": list(self.layers.set),
        }

    def stages(self, preset: str | None = None, overrides: list[str] | None = None) -> dict[str, Any]:
        """`pipeline status --json`'s summary under the page's settings (the session's
        own when ``preset`` is None), and who holds the capture's lock. Only a run
        keeps the page's settings: looking changes nothing."""
        layers = self.layers if preset is None else self._layers(preset, overrides or [])
        self._results = None  # the page reloads what the stages made after its table
        return status_summary(self._runner(layers)) | {"locked_by": holder(self.folder)}

    # A run.

    def start_run(self, preset: str | None = None, overrides: list[str] | None = None) -> None:
        """`pipeline run` under ``preset`` and ``overrides`` (the session's when None),
        which become the session's."""
        layers = self.layers if preset is None else self._layers(preset, overrides or [])
        self._runner(layers)  # a setting the configuration refuses ends here, with its message
        with self._lock:
            if self._process is not None and self._process.poll() is None:
                raise ConfigError("a run started here is still going: stop it or wait for it")
            busy = holder(self.folder)
            if busy is not None:
                raise ConfigError(f"{self.folder} is in use by {busy}: wait for it to finish")
            self.layers = layers
            command = [sys.executable, "-m", "pipeline", "run", str(self.folder), "--preset", layers.preset]
            for override in layers.set:
                command += ["-s", override]
            self.run_state = RunState(command)
            self._process = subprocess.Popen(
                command,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
                bufsize=1,
                preexec_fn=_interrupt_with_parent,
            )
            threading.Thread(target=self._read_log, args=(self._process,), daemon=True).start()

    def stop_run(self) -> bool:
        """SIGINT, as Ctrl-C: the run keeps its finished stages and checkpoints. Whether
        a run was going."""
        with self._lock:
            if self._process is not None and self._process.poll() is None:
                self._process.send_signal(signal.SIGINT)
                return True
            return False

    def wait(self, timeout: float = STOP_WAIT_S) -> None:
        """Until the run has ended (after stop_run); one that outlasts ``timeout`` seconds
        is sent SIGTERM, then killed, so that the studio never leaves it holding the lock."""
        if self._process is None:
            return
        for then in (signal.SIGTERM, signal.SIGKILL):
            try:
                self._process.wait(timeout)
                return
            except subprocess.TimeoutExpired:
                logger.warning("studio: the run did not end in %.0f s: sending %s", timeout, then.name)
                self._process.send_signal(then)
        self._process.wait()

    def _read_log(self, process: subprocess.Popen) -> None:
        for line in process.stdout:
            with self._lock:
                self.run_state.log.append(line.rstrip("\n"))
                if len(self.run_state.log) > LOG_LINES:
                    del self.run_state.log[0]
                    self.run_state.dropped += 1
        code = process.wait()
        with self._lock:
            self.run_state.exit_code = code

    def run_snapshot(self, since: int = 0) -> dict[str, Any]:
        """The run's log lines from line ``since`` on, its exit code, and the steps of
        the fit running now (or last seen) with its stage."""
        with self._lock:
            state = self.run_state
            start = max(since - state.dropped, 0)
            result = {
                "running": self._process is not None and state.exit_code is None,
                "command": state.command,
                "log": state.log[start:],
                "next": state.dropped + len(state.log),
                "exit_code": state.exit_code,
            }
        return result | self.live_fit()

    def live_fit(self) -> dict[str, Any]:
        """The steps of the newest fit checkpoint's live log: the stage fitting now."""
        logs = sorted(
            (self.folder / ".pipeline" / "checkpoints").glob("*/*.steps.jsonl"), key=lambda p: p.stat().st_mtime
        )
        if not logs:
            return {"fit_stage": None, "fit_log": []}
        newest = logs[-1]
        stage = newest.parent.name.rsplit("-", 1)[0]
        entries: dict[int, dict] = {}
        for line in newest.read_text().splitlines():
            try:
                entry = json.loads(line)
            except json.JSONDecodeError:
                break  # the line being written
            entries[entry["iteration"]] = finite(entry)  # a resumed fit redoes the steps after its checkpoint
        steps = [entries[i] for i in sorted(entries)]
        return {"fit_stage": f"{stage} (fit {newest.name.split('.')[0]})", "fit_log": steps}

    def fit_preview(self, view: str) -> dict[str, bytes] | None:
        """The running fit stage's latest values rendered in ``view``'s scene file (the
        scene stage's) beside its photo: render, photo and |difference| x4 (PNGs); None
        when no fit stage is running or there is no scene yet. Values the scene file
        cannot take as they are logged (a texture logs its mean; a shape fit logs
        nothing) are left as the scene has them."""
        live = self.live_fit()
        scene_dir = self._outputs("scene").get("scene_dir")
        if not live["fit_log"] or scene_dir is None:
            return None
        entry = live["fit_log"][-1]
        wanted = (view, live["fit_stage"], entry["iteration"])
        with self._render_lock:
            if self._preview is not None and self._preview[0] == wanted:
                return self._preview[1]
            description = SceneDescription.read(scene_dir / "scene.json")
            if view not in description.views:
                raise ConfigError(f"no view {view} in {scene_dir / 'scene.json'}")
            render = self._render(scene_dir / description.views[view].xml, description, entry.get("params") or {})
            photo = read_photo(linear_photos(self._outputs("undistort")["pinhole"])[view], "linear").pixels[..., :3]
            if photo.shape != render.shape:
                import cv2

                photo = cv2.resize(photo, render.shape[1::-1], interpolation=cv2.INTER_AREA)
            self._preview = (wanted, preview_images(render, photo))
            return self._preview[1]

    @staticmethod
    def _render(view_xml: Path, description: SceneDescription, values: dict[str, list[float]]) -> np.ndarray:
        mitsuba_variant.activate("auto")
        import mitsuba as mi

        scene = mi.load_file(str(view_xml))
        params = mi.traverse(scene)
        plain = {mi.Color3f: 3, mi.Float: 1}  # what a logged value can be written into
        keys = {name: description.parameters[name].key for name in values if name in description.parameters}
        set_values(
            params,
            {
                key: values[name]
                for name, key in keys.items()
                if key in params and plain.get(type(params[key])) == len(values[name])
            },
        )
        return np.asarray(mi.render(scene, spp=PREVIEW_SPP), dtype=np.float32)[..., :3]

    # What the stages made.

    def _outputs(self, stage: str) -> dict[str, Path]:
        """The stage's current results ({} when it has none); planned again when it had
        none, since a run may have made them since."""
        if self._results is None or stage not in self._results:
            plan = self._runner().plan()
            self._results = {item.stage.name: item.entry.outputs for item in plan if item.entry is not None}
        return self._results.get(stage, {})

    def _photos(self) -> dict[str, dict]:
        pinhole = self._outputs("undistort").get("pinhole")
        return read_photos(pinhole) if pinhole is not None else {}

    def photos(self) -> list[str]:
        """The undistorted photos' names (as images/ has them)."""
        return sorted(self._photos())

    def photo(self, name: str) -> bytes:
        """A photo's thumbnail (undistorted), its mask's outside tinted when there is one."""
        import cv2

        photos = self._photos()
        if name not in photos:
            raise ConfigError(f"no undistorted photo {name} in {self.folder} (run the undistort stage)")
        image = cv2.imread(str(photos[name]["srgb"]), cv2.IMREAD_COLOR)
        masks = self._outputs("masks").get("masks")
        mask_file = masks / f"{Path(name).stem}.png" if masks is not None else None
        if mask_file is not None and mask_file.is_file():
            mask = cv2.imread(str(mask_file), cv2.IMREAD_GRAYSCALE)
            if mask is not None and mask.shape == image.shape[:2]:
                outside = mask < 128
                image[outside] = (image[outside] * 0.25 + np.array([120, 0, 0]) * 0.75).astype(np.uint8)
        scale = THUMBNAIL_PX / max(image.shape[:2])
        if scale < 1:
            image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        return cv2.imencode(".jpg", image)[1].tobytes()

    def cameras(self) -> list[dict[str, Any]]:
        """Each posed photo's camera as a frustum (its centre and the four corners of its
        image plane at a tenth of the cameras' spread) in the pipeline's world frame."""
        path = self._outputs("sfm").get("cameras")
        if path is None or not path.is_file():
            return []
        views = read_views(path)
        centres = np.array([pose.center for _, pose in views.values()])
        depth = 0.15 * max(float(np.median(np.linalg.norm(centres - centres.mean(axis=0), axis=1))), 1e-6)
        frusta = []
        for name, (intrinsics, pose) in sorted(views.items()):
            w, h = intrinsics.width, intrinsics.height
            corners = []
            for u, v in ((0, 0), (w, 0), (w, h), (0, h)):
                ray = np.array([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy, 1.0])
                corners.append((pose.center + depth * pose.R.T @ ray).tolist())
            frusta.append({"name": name, "centre": pose.center.tolist(), "corners": corners})
        return frusta

    def mesh_glb(self) -> bytes | None:
        """The current result's mesh as glTF: export's glb (textured when the texture was
        fitted), else the newest mesh a stage made, untextured."""
        glb = self._outputs("export").get("glb")
        if glb is not None and glb.is_file():
            return glb.read_bytes()
        import trimesh

        for stage in reversed([stage.name for stage in self._runner().stages]):
            mesh = self._outputs(stage).get("mesh")
            if mesh is not None and mesh.is_file() and mesh.suffix == ".ply":
                buffer = io.BytesIO()
                # normals written: a glTF viewer shades a mesh without them black
                trimesh.load(mesh, force="mesh", process=False).export(buffer, file_type="glb", include_normals=True)
                return buffer.getvalue()
        return None

    def output_file(self, relative: str) -> Path:
        """A file under the capture's output/ (the report and what it links to); any
        other path is refused."""
        output = (self.folder / "output").resolve()
        path = (output / relative).resolve()
        if not path.is_relative_to(output) or not path.is_file():
            raise ConfigError(f"{relative} is not a file in {self.folder / 'output'}")
        return path
