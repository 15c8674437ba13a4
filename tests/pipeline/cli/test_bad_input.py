"""Bad input as users give it: each case ends in one clear message naming the file or
key (no traceback), the documented exit code (2: usage and configuration, 1: data),
a JSON error object with --json, and nothing computed earlier lost.

The capture-level cases run the real CLI over the toy stage graph after one good
run, then check that the good run's results are still there."""

import json
import os
import shutil
import signal
import time
from pathlib import Path

import pytest

from pipeline.core.lock import CaptureBusy, CaptureLock
from tests.support.toy_stages import RUNS, hold_lock, make_capture, start_toy_cli


@pytest.fixture
def ran_capture(tmp_path, toy_cli):
    """A toy capture after one good run."""
    capture = make_capture(tmp_path)
    assert toy_cli(["--quiet", "run", str(capture)]) == 0
    return capture


def _toml(text):
    def write(capture):
        (capture / "capture.toml").write_text(text)

    return write


def _lock_held(capture):
    return hold_lock(capture, 30)


# (id, setup(capture) -> anything, argv after the command (CAPTURE is replaced), exit code, message)
RUN_CASES = [
    ("unknown-preset", None, ["--preset", "fastest"], 2, "unknown preset 'fastest'"),
    ("unknown-section", _toml("[sfmm]\nx = 1\n"), [], 2, "unknown section [sfmm]"),
    ("invalid-toml", _toml("[double\nfactor = 2\n"), [], 2, "capture.toml: invalid TOML"),
    ("out-of-range", None, ["-s", "double.factor=0"], 2, "double.factor = 0 is out of range"),
    ("nan", None, ["-s", "ingest.scale=nan"], 2, "ingest.scale = nan is not a finite number"),
    ("inf", None, ["-s", "ingest.scale=inf"], 2, "ingest.scale = inf is not a finite number"),
    ("wrong-type", None, ["-s", "double.factor='two'"], 2, "double.factor = 'two' has the wrong type"),
    ("unknown-key", None, ["-s", "double.fact=3"], 2, "unknown key double.fact"),
    ("override-shape", None, ["-s", "factor=3"], 2, "must look like section.key=value"),
    ("choice", None, ["-s", "ingest.fail=maybe"], 2, "ingest.fail = 'maybe' is not allowed"),
    ("unknown-stage", None, ["--until", "mesh"], 2, "--until mesh: no such stage"),
    ("only-uncached", None, ["--only", "report", "-s", "double.factor=9"], 2, "has no cached result"),
    ("outside-file", _toml("[ingest]\nextra = '../../../../etc/passwd'\n"), [], 2, "points outside the capture"),
    ("absolute-file", _toml("[ingest]\nextra = '/etc/passwd'\n"), [], 2, "points outside the capture"),
    ("missing-file", None, ["-s", "ingest.extra='nope.txt'"], 2, "ingest.extra = 'nope.txt' is not a file"),
    ("user-error-in-stage", None, ["-s", "ingest.fail=user"], 1, "000.txt: not a number; fix the file"),
    ("locked", _lock_held, ["--no-wait"], 1, "is in use by pid"),
]


@pytest.mark.parametrize("case", RUN_CASES, ids=[c[0] for c in RUN_CASES])
@pytest.mark.parametrize("as_json", [False, True], ids=["text", "json"])
def test_bad_run_input_fails_clearly_and_loses_nothing(ran_capture, toy_cli, capsys, case, as_json):
    _, setup, argv, code, message = case
    before = (ran_capture / "output" / "report.txt").read_text()
    entries = sorted((ran_capture / ".pipeline" / "cache").glob("*/*"))
    held = setup(ran_capture) if setup else None
    capsys.readouterr()
    try:
        assert toy_cli(["run", str(ran_capture), *argv, *(["--json"] if as_json else [])]) == code
    finally:
        if held is not None:
            held.kill()
    out, err = capsys.readouterr()
    assert message in err and "Traceback" not in err
    if as_json:
        error = json.loads(out)
        assert error["exit_code"] == code and message in error["error"]
    assert (ran_capture / "output" / "report.txt").read_text() == before
    assert set(entries) <= set((ran_capture / ".pipeline" / "cache").glob("*/*"))


def _damage_memo(capture):
    (capture / ".pipeline" / "file_hashes.json").write_text("{")


def _damage_status(capture):
    (entry,) = (capture / ".pipeline" / "cache" / "double").iterdir()
    (entry / "status.json").write_text("")


def _delete_cached_file(capture):
    (entry,) = (capture / ".pipeline" / "cache" / "ingest").iterdir()
    (entry / "total.txt").unlink()


def _damage_manifest(capture):
    (capture / "output" / "manifest.json").write_text("{")


def _leave_killed_run(capture):
    (capture / ".pipeline" / "cache" / "double" / ".tmp-0123-99999").mkdir()


RECOVER_CASES = [
    ("damaged-hash-memo", _damage_memo, [], "file_hashes.json is damaged"),
    ("damaged-status", _damage_status, ["double"], "damaged status.json"),  # same result: report reused
    ("deleted-cached-file", _delete_cached_file, ["ingest"], "total.txt is missing"),
    ("damaged-manifest", _damage_manifest, [], ""),
    ("killed-run-leftovers", _leave_killed_run, [], "removed 1 unfinished result folder"),
]


@pytest.mark.parametrize("case", RECOVER_CASES, ids=[c[0] for c in RECOVER_CASES])
def test_damaged_state_is_rebuilt_with_a_warning(ran_capture, toy_cli, caplog, capsys, case):
    _, damage, recomputed, warning = case
    damage(ran_capture)
    RUNS.clear()
    assert toy_cli(["run", str(ran_capture)]) == 0
    assert RUNS == recomputed and warning in caplog.text + capsys.readouterr().err
    assert (ran_capture / "output" / "report.txt").read_text() == "result 12.0\n"
    assert json.loads((ran_capture / "output" / "manifest.json").read_text())["report.txt"]["stage"] == "report"
    assert not list((ran_capture / ".pipeline" / "cache").glob("*/.tmp-*"))


def test_output_being_a_file_is_refused_before_anything_runs(tmp_path, toy_cli, capsys):
    capture = make_capture(tmp_path)
    (capture / "output").write_text("my notes")
    assert toy_cli(["run", str(capture)]) == 2
    assert "output is a file" in capsys.readouterr().err and RUNS == []
    assert (capture / "output").read_text() == "my notes"


def test_a_read_only_capture_can_be_inspected_but_not_run(tmp_path, toy_cli, capsys, monkeypatch):
    capture = make_capture(tmp_path)
    # The tests may run as root, whom permissions do not stop: simulate the refusal.
    monkeypatch.setattr(os, "access", lambda path, mode: False)
    assert toy_cli(["status", str(capture)]) == 0
    assert toy_cli(["run", str(capture), "--dry-run"]) == 0
    assert not (capture / ".pipeline").exists()  # neither wrote anything
    real_open = os.open

    def read_only_open(path, flags, *args):
        if str(path).startswith(str(capture)) and flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            raise PermissionError(13, "Read-only file system", str(path))
        return real_open(path, flags, *args)

    monkeypatch.setattr(os, "open", read_only_open)
    monkeypatch.setattr(Path, "mkdir", lambda self, *a, **k: None)
    assert toy_cli(["run", str(capture)]) == 1
    err = capsys.readouterr().err
    assert "capture must be writable for pipeline run" in err and "Traceback" not in err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["new", "FILE"], "is a file: name a new folder"),
        (["new", "FULL"], "already exists and is not empty"),
        (["run", "FILE"], "is a file: give the capture's folder"),
        (["status", "MISSING"], "does not exist"),
        (["clean", "MISSING"], "does not exist"),
        (["fit", "scene.xml", "--references", "refs", "--params", "(", "--out", "out"], "is not a regular expression"),
        (["fit", "scene.xml", "--references", "refs", "--params", "eta", "--out", "FILE"], "is a file: name a folder"),
        (["fit", "scene.xml", "--batch", "0"], "fit.batch = 0 is out of range"),
        (["fit", "scene.xml", "--iterations", "-1"], "fit.iterations = -1 is out of range"),
        (["fit", "scene.xml", "--spp", "0"], "fit.spp = 0 is out of range"),
        (["fit", "scene.xml", "--lr", "nan"], "is not a finite number"),
        (["batch", "MISSING"], "does not exist"),
        (["batch", "FILE", "--workers", "0"], "batch.workers = 0 is out of range"),
    ],
    ids=lambda value: "-".join(value) if isinstance(value, list) else None,
)
def test_bad_command_lines_exit_2_with_the_fix(tmp_path, toy_cli, capsys, argv, message):
    (tmp_path / "FILE").write_text("x")
    (tmp_path / "FULL").mkdir()
    (tmp_path / "FULL" / "keep.txt").write_text("x")
    names = {"FILE": tmp_path / "FILE", "FULL": tmp_path / "FULL", "MISSING": tmp_path / "missing"}
    assert toy_cli([str(names.get(a, a)) for a in argv]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert (tmp_path / "FILE").read_text() == "x" and (tmp_path / "FULL" / "keep.txt").exists()


def _wait_for(condition, seconds=30.0):
    deadline = time.time() + seconds
    while not condition():
        assert time.time() < deadline, "timed out"
        time.sleep(0.05)


@pytest.mark.parametrize("signum, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)], ids=["ctrl-c", "sigterm"])
def test_a_signal_during_a_stage_ends_in_one_line_and_cleans_up(ran_capture, presets_dir, signum, code):
    cache = ran_capture / ".pipeline" / "cache"
    run = start_toy_cli(presets_dir, "run", str(ran_capture), "-s", "ingest.fail='sleep'")
    _wait_for(lambda: list(cache.glob("ingest/.tmp-*/waiting")))
    run.send_signal(signum)
    out, err = run.communicate(timeout=30)
    assert run.returncode == code
    assert err.strip().splitlines()[-1].startswith("E interrupted; finished stages")
    assert "Traceback" not in err and "stack trace" not in err
    assert not list(cache.glob("*/.tmp-*"))  # the partial folder is gone, its log kept
    (failed,) = (ran_capture / ".pipeline" / "failed" / "ingest").iterdir()
    assert [p.name for p in failed.iterdir()] == ["log.txt"]
    with CaptureLock(ran_capture, "check", wait=False):
        pass  # released
    assert (ran_capture / "output" / "report.txt").read_text() == "result 12.0\n"


def test_ctrl_c_while_waiting_for_the_lock_ends_in_one_line(ran_capture, presets_dir):
    holder = hold_lock(ran_capture, 30)
    try:
        run = start_toy_cli(presets_dir, "run", str(ran_capture))
        _wait_for(lambda: run.stderr.readline().find("waiting for it to finish") >= 0)
        run.send_signal(signal.SIGINT)
        out, err = run.communicate(timeout=30)
    finally:
        holder.kill()
    assert run.returncode == 130 and "interrupted" in err and "Traceback" not in err


def test_a_second_signal_stops_a_run_stuck_after_the_first(ran_capture, presets_dir):
    """A stage that does not come back after the first Ctrl-C (a long native call)."""
    cache = ran_capture / ".pipeline" / "cache"
    run = start_toy_cli(presets_dir, "run", str(ran_capture), "-s", "ingest.fail='stubborn'")
    _wait_for(lambda: list(cache.glob("ingest/.tmp-*/waiting")))
    run.send_signal(signal.SIGINT)
    time.sleep(0.5)
    run.send_signal(signal.SIGINT)
    out, err = run.communicate(timeout=10)
    assert run.returncode == 130 and "interrupted twice: stopping at once" in err
    # Whether the stage's folder was left (for the next run to remove) depends on which
    # thread won; either way the next run finishes clean.
    again = start_toy_cli(presets_dir, "run", str(ran_capture))
    out, err = again.communicate(timeout=60)
    assert again.returncode == 0 and not list(cache.glob("*/.tmp-*")), err


def test_a_full_disk_in_a_stage_ends_in_one_message(ran_capture, toy_cli, capsys):
    assert toy_cli(["run", str(ran_capture), "-s", "ingest.fail='diskfull'"]) == 1
    err = capsys.readouterr().err
    assert "is full" in err and "partial files" in err and "every earlier result kept" in err
    assert "Traceback" not in err
    assert (ran_capture / "output" / "report.txt").read_text() == "result 12.0\n"


def test_clean_waits_for_a_run_to_write_its_report(ran_capture, presets_dir, toy_cli, monkeypatch):
    """The report is written under the lock: a clean queued behind a run cannot empty the
    cache between the run's publishing and its report."""
    from pipeline import report as html_report

    calls = []
    monkeypatch.setattr(html_report, "write", lambda capture, *rest: calls.append(lock_is_held(capture)))
    monkeypatch.setattr(html_report, "records", lambda *args: [])
    assert toy_cli(["--quiet", "run", str(ran_capture)]) == 0
    assert calls == [True]


def lock_is_held(capture):
    try:
        with CaptureLock(capture, "probe", wait=False):
            return False
    except CaptureBusy:
        return True


def test_a_plain_folder_of_photos_is_named_as_such_and_made_a_capture_in_one_command(tmp_path, capsys):
    import cv2
    import numpy as np

    from pipeline.cli import main

    folder = tmp_path / "photos"
    folder.mkdir()
    for index in range(3):
        cv2.imwrite(str(folder / f"IMG_{index:04d}.jpg"), np.full((8, 8, 3), 100 * index, np.uint8))
    before = sorted(p.name for p in folder.iterdir())
    for command in (["run"], ["check"], ["status"]):
        assert main([*command, str(folder)]) == 2
        err = capsys.readouterr().err
        assert "holds 3 photos but no images/ folder" in err and f"pipeline new CAPTURE --photos {folder}" in err
    assert sorted(p.name for p in folder.iterdir()) == before  # no .pipeline/ left in the user's folder
    capture = tmp_path / "capture"
    assert main(["new", str(capture), "--photos", str(folder)]) == 0
    assert "with the 3 photos of" in capsys.readouterr().out
    assert sorted(p.name for p in (capture / "images").iterdir()) == before
    assert (capture / "images" / before[0]).read_bytes() == (folder / before[0]).read_bytes()
    assert sorted(p.name for p in folder.iterdir()) == before
    assert main(["new", str(tmp_path / "other"), "--photos", str(tmp_path / "capture" / "masks")]) == 2
    assert "holds no photos" in capsys.readouterr().err and not (tmp_path / "other").exists()


def test_an_unreadable_images_folder_is_named_not_reported_empty(tiny_capture, request, capfd, monkeypatch):
    """As nobody, whom a chmod 000 stops (root is not stopped by it)."""
    from pipeline.cli import main
    from tests.support.as_user import as_user, give, nobody, reachable_folder

    user = nobody()
    shared = reachable_folder(request, "unreadable-images-")
    capture = Path(shutil.copytree(tiny_capture, shared / "capture", ignore=shutil.ignore_patterns(".pipeline")))
    give(capture, user)
    os.chmod(capture / "images", 0)
    # the child may not read root's Python installation or the package's metadata (a clone
    # in a folder of root's alone): what the command imports and the stages, loaded here
    from pipeline.cli import build_parser, registry
    from pipeline.core import config

    build_parser()
    stages = registry.registered_stages()
    monkeypatch.setattr(registry, "registered_stages", lambda: stages)
    monkeypatch.setattr(config, "PRESETS_DIR", Path(shutil.copytree(config.PRESETS_DIR, shared / "configs")))
    capfd.readouterr()
    assert as_user(user, lambda: os._exit(main(["run", str(capture), "--until", "calibrate"]))) == 1
    err = capfd.readouterr().err
    assert f"{capture / 'images'} cannot be read (Permission denied)" in err and "no photos" not in err
    assert "Traceback" not in err
