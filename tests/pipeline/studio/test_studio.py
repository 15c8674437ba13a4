"""`pipeline studio` in a real browser (Playwright driving Debian's chromium, which
bin/test installs): a scene's fit started, watched and stopped from the page, and a
capture's stages, photos, cameras and a run from the page; and what the studio
refuses."""

import json
import os
import re
import shutil
import subprocess
import sys
import urllib.error
import urllib.request
from contextlib import contextmanager
from pathlib import Path

import pytest

from pipeline.cli import main as cli_main
from pipeline.core.errors import ConfigError, PipelineError
from pipeline.core.lock import CaptureLock
from tests.support.byo_capture import byo_capture
from tests.support.studio_kit import START, TRUTH, write_kit

pytestmark = pytest.mark.slow

SCREENSHOTS = os.environ.get("STUDIO_SCREENSHOTS")
"""A folder to copy the pages' screenshots into (docs/ holds them: bench/tools/studio_screenshots.sh)."""


def _chromium() -> str:
    for candidate in ("/usr/lib/chromium/chromium", shutil.which("chromium")):
        if candidate and Path(candidate).is_file():
            return candidate
    pytest.skip("chromium is not installed (bin/test installs Debian's package)")


@contextmanager
def studio(*args: str, cwd: Path, process_out: list | None = None):
    """`pipeline studio ARGS --no-browser` on a free port; yields the address it prints
    (with its token) and its log; ``process_out`` receives the process."""
    process = subprocess.Popen(
        [sys.executable, "-m", "pipeline", "studio", *args, "--no-browser"],
        cwd=cwd,
        stderr=subprocess.PIPE,
        text=True,
    )
    if process_out is not None:
        process_out.append(process)
    lines = []
    try:
        for line in process.stderr:
            lines.append(line)
            if found := re.search(r"studio at (http://\S+)", line):
                break
        else:
            pytest.fail("the studio did not start:\n" + "".join(lines))
        yield found.group(1), lines
    finally:
        if process.poll() is None:
            process.terminate()
        lines += process.stderr.readlines()
        process.wait(60)


@contextmanager
def browser_page():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=_chromium(), args=["--no-sandbox", "--use-gl=swiftshader", "--enable-unsafe-swiftshader"]
        )
        page = browser.new_page(viewport={"width": 1400, "height": 1200})
        errors = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        yield page
        browser.close()
        assert not errors, errors


def _screenshot(page, path: Path) -> None:
    page.screenshot(path=str(path), full_page=True)
    if SCREENSHOTS:
        shutil.copy(path, Path(SCREENSHOTS) / path.name)


def request(url: str, path: str, body=None, token: bool = True, headers: dict | None = None) -> tuple[int, dict]:
    """A request to the studio at ``url``, as its page makes them (the token as its
    header; a POST when there is a body): the status and the JSON answer."""
    base, _, query = url.partition("?")
    sent = {"X-Studio-Token": query.removeprefix("token=")} if token else {}
    data = None if body is None else (body if isinstance(body, bytes) else json.dumps(body).encode())
    if data is not None:
        sent["Content-Type"] = "application/json"
    call = urllib.request.Request(base + path.lstrip("/"), data=data, headers=sent | (headers or {}))
    try:
        with urllib.request.urlopen(call, timeout=60) as response:
            return response.status, json.loads(response.read() or b"null")
    except urllib.error.HTTPError as error:
        return error.code, json.loads(error.read() or b"null")


def test_a_fit_started_watched_and_stopped_in_the_page_moves_toward_the_truth(mi, tmp_path):
    scene, references = write_kit(tmp_path / "kit")
    out = tmp_path / "out"
    with studio(str(scene), "--references", str(references), "--out", str(out), cwd=tmp_path) as (url, _):
        with browser_page() as page:
            page.goto(url)
            page.wait_for_selector("#params tbody tr")
            page.fill("#filter", "roughness base_color")
            page.wait_for_function("document.querySelectorAll('#params tbody tr:not([hidden])').length === 2")
            for key in ("mat.roughness.value", "mat.base_color.value"):
                page.locator(f'tr[data-key="{key}"] input.tick').check()
            page.locator('tr[data-view="1_side"] input.heldout').check()
            page.fill("#settings input[name=iterations]", "5000")
            page.fill("#settings input[name=still_threshold]", "0")  # runs until Stop
            page.click("#start")
            page.wait_for_function("Number(document.getElementById('loss-plot').dataset.points) >= 30", timeout=120_000)
            page.wait_for_function("document.getElementById('preview-render').naturalWidth === 32")
            page.select_option("#preview-view", "1_side")
            page.wait_for_function("document.getElementById('preview-images').dataset.view === '1_side'")
            assert page.locator("#error").is_hidden()  # the picker's request answered
            page.click("#pause")
            page.wait_for_selector("#status >> text=paused")
            steps = page.evaluate("document.getElementById('loss-plot').dataset.points")
            page.wait_for_timeout(1500)
            assert page.evaluate("document.getElementById('loss-plot').dataset.points") == steps
            page.click("#pause")  # Resume
            page.wait_for_selector("#status >> text=running")
            _screenshot(page, tmp_path / "studio-fit.png")
            page.click("#stop")
            page.wait_for_selector("#downloads li >> text=params.json", timeout=120_000)
            assert page.inner_text("#stopped").startswith("Stopped: stopped by the user")
            assert page.locator("#trajectories canvas").count() == 2
    params = json.loads((out / "params.json").read_text())
    assert params["heldout"] == ["1_side"] and params["best_iteration"] > 0
    rough = params["params"]["mat.roughness.value"][0]
    assert abs(rough - TRUTH["rough"]) < abs(START["rough"] - TRUTH["rough"]) / 2
    for fitted, truth, start in zip(params["params"]["mat.base_color.value"], TRUTH["colour"], START["colour"]):
        assert abs(fitted - truth) < abs(start - truth) / 2
    assert (out / "scene.xml").is_file() and "stopped by the user" in params["stopped"]


def test_a_capture_shows_the_stage_table_of_status_json_its_photos_and_cameras_and_runs(
    run_stages, tiny_capture, tmp_path, capsys
):
    capture = byo_capture(tiny_capture, tmp_path / "capture")  # its cameras and mesh given: no SfM on 96 px
    overrides = ("cameras.source='external'", "mesh.source='ground_truth/mesh.ply'")
    given = [word for override in overrides for word in ("-s", override)]
    run_stages(capture, "sfm", *overrides)
    capsys.readouterr()
    assert cli_main(["status", str(capture), *given, "--json"]) == 0
    status = json.loads(capsys.readouterr().out)
    expected = [(row["stage"], row["state"], row["reason"]) for row in status["stages"]]
    with studio(str(capture), *given, cwd=tmp_path) as (url, _):
        with browser_page() as page:
            page.goto(url)
            page.wait_for_selector("#stages tbody[data-loaded='1']")
            shown = [
                tuple(row.locator("td").nth(i).inner_text() for i in range(3))
                for row in page.locator("#stages tbody tr").all()
            ]
            assert shown == expected
            page.wait_for_selector("#view3d[data-cameras='6']")
            assert page.locator("#photos img").count() == 6
            page.click("#run")  # the rest of the DAG, stopped once a stage has finished
            page.wait_for_function(
                "/mesh\\s+[\\d.]+ s/.test(document.getElementById('run-log').textContent)", timeout=300_000
            )
            # during the run, the table follows the stages as they finish
            page.wait_for_function(
                "document.querySelector('#stages tr[data-stage=\"mesh\"] .state').textContent === 'cached'"
            )
            assert page.inner_text("#run-status") == "running"
            page.click("#run-stop")
            page.wait_for_function(
                "/exit code/.test(document.getElementById('run-status').textContent)", timeout=120_000
            )
            page.wait_for_function(
                "document.querySelector('#stages tr[data-stage=\"mesh\"] .state').textContent === 'cached'"
            )
            page.wait_for_selector("#view3d-note >> text=the current mesh")
            # each line of the run's log once, however the polls overlapped, and long lines
            # wrapped inside the page rather than widening it
            finished = [line for line in page.inner_text("#run-log").splitlines() if " done in " in line]
            assert finished and len(finished) == len(set(finished))
            assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth")
            _screenshot(page, tmp_path / "studio-capture.png")


def test_a_scene_mitsuba_cannot_load_shows_the_cli_message_in_the_page(tmp_path):
    bad = tmp_path / "bad.xml"
    bad.write_text("<scene version='3.0.0'><shape type='nonsense'/></scene>")
    (tmp_path / "refs").mkdir()
    with studio(str(bad), "--references", str(tmp_path / "refs"), "--host", "0.0.0.0", cwd=tmp_path) as (url, log):
        assert any("other machines can reach the studio" in line for line in log)
        status, session = request(url, "api/session")
        assert status == 200 and session["mode"] == "error"
        assert "Mitsuba cannot load" in session["error"] and str(bad) in session["error"]


def test_a_target_that_is_neither_scene_nor_capture_ends_at_once(tmp_path, capsys):
    assert cli_main(["studio", str(tmp_path / "nope.xml"), "--no-browser"]) == 2
    assert cli_main(["studio", str(tmp_path), "--no-browser", "--preset", "nope"]) == 2  # nothing to show either
    (tmp_path / "scene.xml").write_text("<scene version='3.0.0'/>")
    assert cli_main(["studio", str(tmp_path / "scene.xml"), "--no-browser"]) == 2  # no --references
    assert "needs --references DIR" in capsys.readouterr().err


def test_the_studio_listens_on_this_machine_only_unless_told():
    from pipeline.cli.studio import StudioOptions
    from pipeline.studio.server import listening_socket

    sock = listening_socket(StudioOptions("scene.xml").host, StudioOptions("scene.xml").port)
    try:
        host, port = sock.getsockname()[:2]
        assert host == "127.0.0.1" and port > 0  # a free port, taken before the server starts
    finally:
        sock.close()


def test_a_fit_offers_only_its_own_results(mi, tmp_path):
    from pipeline.studio.fit_session import FitSession

    scene, references = write_kit(tmp_path / "kit")
    session = FitSession(scene, references, tmp_path / "out")
    for name in ("../kit/scene/scene.xml", "params.json", "scene.xml"):  # nothing written yet
        with pytest.raises(ConfigError, match="is not one of this fit's results"):
            session.output_file(name)
    with pytest.raises(ConfigError, match="fit.spp = 0 is out of range"):
        session.options({"params": ["mat.roughness.value"], "settings": {"spp": 0}})
    with pytest.raises(PipelineError, match="has lower >= upper"):
        session.options({"params": ["mat.roughness.value"], "bounds": {"mat.roughness.value": [0.9, 0.1]}})
    session.start({"params": ["mat.roughness.value"], "heldout": ["nope"]})  # checked in the worker, shown in the page
    session.wait(120)
    state = session.snapshot()
    assert state["status"] == "failed" and state["error"].startswith("--heldout nope: no such image")


def test_a_capture_another_run_holds_is_reported_not_raced(tiny_capture, tmp_path):
    from pipeline.studio.capture_session import CaptureSession

    capture = Path(shutil.copytree(tiny_capture, tmp_path / "capture"))
    session = CaptureSession(str(capture))
    with CaptureLock(capture, "pipeline run"):
        assert "pipeline run" in session.stages()["locked_by"]
        with pytest.raises(ConfigError, match="in use by pid"):
            session.start_run()
    assert session.stages()["locked_by"] is None
    with pytest.raises(ConfigError, match="is not a file in"):
        session.output_file("../capture.toml")


def test_a_running_fit_stage_is_rendered_with_its_latest_values_beside_the_photo(run_stages, tiny_capture, tmp_path):
    """The studio reads a stage's fit from the live log its checkpoint keeps; here one is
    written by hand, as the fit loop writes it, into the scene stage's results."""
    import cv2
    import numpy as np

    from pipeline.formats.scene_description import SceneDescription
    from pipeline.studio.capture_session import CaptureSession

    capture = byo_capture(tiny_capture, tmp_path / "capture")
    # few faces: unwrapping the given mesh is most of the stages' time
    overrides = ("cameras.source='external'", "mesh.source='ground_truth/mesh.ply'", "cleanup.target_faces=2000")
    outputs = run_stages(capture, "scene", *overrides)
    description = SceneDescription.read(outputs["scene"]["scene_dir"] / "scene.json")
    name = next(n for n, p in description.parameters.items() if len(p.value) == 3)  # the base colour
    view = sorted(description.views)[0]
    session = CaptureSession(str(capture), overrides=overrides)
    assert session.fit_preview(view) is None  # no fit running
    live = capture / ".pipeline" / "checkpoints" / "fit_material-0123456789abcdef" / "00.steps.jsonl"
    live.parent.mkdir(parents=True)
    means = []
    for iteration, colour in enumerate(([0.9, 0.1, 0.1], [0.1, 0.1, 0.9]), start=1):
        with live.open("a") as f:
            f.write(json.dumps({"iteration": iteration, "loss": 0.1, "params": {name: colour}}) + "\n")
        images = session.fit_preview(view)
        assert set(images) == {"render", "reference", "difference"}
        render = cv2.imdecode(np.frombuffer(images["render"], np.uint8), cv2.IMREAD_COLOR)
        means.append(render.reshape(-1, 3).mean(axis=0))  # BGR
    assert means[0][2] > means[1][2] and means[1][0] > means[0][0]  # red, then blue
    assert session.run_snapshot()["fit_stage"] == "fit_material (fit 00)"


def test_a_step_logged_with_nan_reaches_the_page_as_json():
    from pipeline.studio.fit_session import finite

    entry = {"iteration": 3, "loss": float("nan"), "params": {"a": [float("inf"), 0.5]}}
    assert json.loads(json.dumps(finite(entry), allow_nan=False)) == {
        "iteration": 3,
        "loss": None,
        "params": {"a": [None, 0.5]},
    }
