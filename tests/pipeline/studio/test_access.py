"""The studio is a server on this machine that starts runs and serves files: what it
refuses (another site's page, a foreign Host, a request without the start's token, a
huge or malformed body, a file outside the capture), and how it ends on a signal (the
fit written, the run stopped and its lock released). Real HTTP against `pipeline
studio` in a process of its own."""

import json
import os
import signal
import time
import urllib.request
from pathlib import Path

import pytest

from pipeline.core.errors import ConfigError
from pipeline.core.lock import holder
from tests.pipeline.studio.test_studio import request, studio
from tests.support.studio_kit import write_kit

pytestmark = pytest.mark.slow

MALFORMED = [
    ("api/fit/start", b"{"),
    ("api/fit/start", b"[]"),
    ("api/fit/start", {"params": "mat.roughness.value"}),
    ("api/fit/start", {"params": [1, 2]}),
    ("api/fit/start", {"params": ["mat.roughness.value"], "settings": [1]}),
    ("api/fit/start", {"params": ["mat.roughness.value"], "settings": {"spp": {"a": 1}}}),
    ("api/fit/start", {"params": ["mat.roughness.value"], "bounds": {"mat.roughness.value": [0.1, 0.2, 0.3]}}),
    ("api/fit/start", {"params": ["mat.roughness.value"], "bounds": {"mat.roughness.value": "0.1:0.2"}}),
    ("api/fit/start", {"params": ["mat.roughness.value"], "bounds": {"mat.roughness.value": [1e309, 2]}}),
    ("api/fit/start", {"params": ["mat.roughness.value"], "heldout": "1_side"}),
    ("api/fit/start", {"params": ["mat.roughness.value"], "settings": {"nonsense": 1}}),
    ("api/fit/start", {"params": ["mat.roughness.value"], "extra": 1}),
    ("api/fit/view", {"name": None}),
    ("api/fit/view", {}),
    ("api/fit/view", {"name": "no such view"}),
    ("api/fit/jump", {}),
    ("api/fit/state?since=-1", None),
    ("api/fit/state?since=abc", None),
    ("api/fit/match?words=(", None),
    ("api/fit/preview/../../etc/passwd", None),
    ("api/fit/download/..%2Fkit%2Fscene%2Fscene.xml", None),
]


def announce_body(url: str, path: str, length: int) -> tuple[int, dict]:
    """A POST whose headers announce a body of ``length`` bytes, none of which is sent:
    the answer the studio gives before reading a body. (Sending it all races the
    studio's closing of the connection: the client's write then fails, as a browser's
    does, before it reads the answer.)"""
    import http.client

    base, _, query = url.partition("?")
    host, port = base.split("//")[1].rstrip("/").split(":")
    connection = http.client.HTTPConnection(host, int(port), timeout=60)
    try:
        connection.putrequest("POST", "/" + path)
        for name, value in (
            ("X-Studio-Token", query.removeprefix("token=")),
            ("Content-Type", "application/json"),
            ("Content-Length", str(length)),
        ):
            connection.putheader(name, value)
        connection.endheaders()
        response = connection.getresponse()
        return response.status, json.loads(response.read() or b"null")
    finally:
        connection.close()


def test_only_the_studios_own_page_with_its_token_is_answered(mi, tmp_path):
    scene, references = write_kit(tmp_path / "kit")
    with studio(str(scene), "--references", str(references), "--out", str(tmp_path / "out"), cwd=tmp_path) as (
        url,
        _,
    ):
        port = url.split(":")[2].split("/")[0]
        assert request(url, "api/session")[0] == 200
        # DNS rebinding: another name for this machine's address
        for path, body in (("api/session", None), ("api/fit/stop", {})):
            status, answer = request(url, path, body, headers={"Host": "attacker.example"})
            assert status == 403 and "Host" in answer["error"]
        # another site's page, through the user's browser
        status, answer = request(url, "api/fit/stop", {}, headers={"Origin": "http://attacker.example"})
        assert status == 403 and "other sites" in answer["error"]
        status, _ = request(url, "api/fit/stop", {}, headers={"Sec-Fetch-Site": "cross-site"})
        assert status == 403
        assert request(url, "api/fit/stop", {}, headers={"Origin": f"http://127.0.0.1:{port}"})[0] == 200
        # no token: nothing but the page's own code
        assert request(url, "api/session", token=False)[0] == 403
        assert request(url, "api/fit/stop", {}, token=False)[0] == 403
        assert request(url, "api/fit/download/params.json", token=False)[0] == 403
        with urllib.request.urlopen(url.partition("?")[0] + "static/studio.js") as script:
            assert script.status == 200  # the page's own code needs no token
        status, answer = announce_body(url, "api/fit/start", 2 << 20)
        assert status == 413 and len(json.dumps(answer)) < 200  # refused before reading, nothing echoed
        for path, body in MALFORMED:
            status, answer = request(url, path, body)
            assert status in (400, 404, 405), (path, body, status, answer)
            assert "error" in (answer or {"error": ""}) and len(json.dumps(answer)) < 400, (path, answer)
        status, state = request(url, "api/fit/state")
        assert status == 200 and state["status"] in ("idle", "failed")


def test_the_view_picker_switches_the_preview(mi, tmp_path):
    scene, references = write_kit(tmp_path / "kit")
    with studio(str(scene), "--references", str(references), "--out", str(tmp_path / "out"), cwd=tmp_path) as (
        url,
        _,
    ):
        assert request(url, "api/fit/view", {"name": "1_side"}) == (200, {"view": "1_side"})
        assert request(url, "api/fit/state")[1]["preview_view"] == "1_side"


def test_ctrl_c_on_the_studio_during_a_fit_writes_its_best_state(mi, tmp_path):
    scene, references = write_kit(tmp_path / "kit")
    out = tmp_path / "out"
    processes = []
    args = (str(scene), "--references", str(references), "--out", str(out))
    with studio(*args, cwd=tmp_path, process_out=processes) as (url, log):
        form = {"params": ["mat.roughness.value"], "settings": {"iterations": 100000, "still_threshold": 0}}
        assert request(url, "api/fit/start", form)[0] == 200
        deadline = time.monotonic() + 120
        while len(request(url, "api/fit/state")[1]["log"]) < 5:
            assert time.monotonic() < deadline
            time.sleep(0.2)
        processes[0].send_signal(signal.SIGINT)
        assert processes[0].wait(120) == 0
    assert not any("interrupted twice" in line for line in log), log
    params = json.loads((out / "params.json").read_text())
    assert params["stopped"].startswith("stopped by the user") and params["iterations"] >= 5
    assert (out / "scene.xml").is_file()


def test_sigterm_on_the_studio_stops_its_run_and_releases_the_capture(tiny_capture, tmp_path):
    import shutil

    capture = Path(shutil.copytree(tiny_capture, tmp_path / "capture"))
    processes = []
    with studio(str(capture), cwd=tmp_path, process_out=processes) as (url, log):
        assert request(url, "api/capture/run", {"preset": "draft", "set": []})[0] == 200
        deadline = time.monotonic() + 120
        while holder(capture) is None:  # the run has taken the capture's lock
            assert time.monotonic() < deadline
            time.sleep(0.1)
        child = request(url, "api/capture/run")[1]
        assert child["running"]
        processes[0].send_signal(signal.SIGTERM)
        assert processes[0].wait(180) == 0
    assert holder(capture) is None
    assert not [pid for pid in os.listdir("/proc") if pid.isdigit() and _runs(pid, capture)]


def _runs(pid: str, capture: Path) -> bool:
    """Whether process ``pid`` is a `pipeline run` of ``capture``."""
    try:
        words = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return False
    return b"run" in words and str(capture).encode() in words


def test_the_pages_settings_name_only_files_inside_the_capture(tiny_capture, tmp_path):
    import shutil

    from pipeline.studio.capture_session import CaptureSession

    capture = Path(shutil.copytree(tiny_capture, tmp_path / "capture"))
    outside = tmp_path / "secret.exr"
    outside.write_bytes(b"x")
    given = f"light.environment_map={outside}"
    session = CaptureSession(str(capture))
    with pytest.raises(ConfigError, match="points outside the capture folder"):
        session.stages("standard", [given])
    with pytest.raises(ConfigError, match="points outside the capture folder"):
        session.start_run("standard", ["light.environment_map=../secret.exr"])
    # looking at another preset's table changes nothing that a run would use
    session.stages("draft", [])
    assert session.describe()["preset"] == "standard"
    # the same override given on the studio's own command line is the user's choice
    trusted = CaptureSession(str(capture), overrides=(given,))
    assert trusted.stages("standard", [given])["stages"]


def test_a_poll_of_the_fit_copies_only_the_new_log_entries(mi, tmp_path):
    from pipeline.studio.fit_session import FitSession

    scene, references = write_kit(tmp_path / "kit")
    session = FitSession(scene, references, tmp_path / "out")
    session.state.log = [{"iteration": i, "loss": 1.0 / i} for i in range(1, 13_501)]
    state = session.snapshot(since=13_498)
    assert [entry["iteration"] for entry in state["log"]] == [13_499, 13_500]
    assert len(session.state.log) == 13_500  # the session's own log is kept whole
    assert state["log"][0] is session.state.log[13_498]  # handed over, not copied
