"""`pipeline batch` on a real local Dask cluster (worker processes) with tiny captures."""

import json
import shutil

import pytest

from pipeline import cli

pytestmark = pytest.mark.slow


def test_batch_runs_every_capture_and_one_failure_stops_no_other(tiny_capture, tmp_path, capfd):
    good = [
        shutil.copytree(tiny_capture, tmp_path / name, ignore=shutil.ignore_patterns(".pipeline", "output"))
        for name in ("first", "second")
    ]
    broken = shutil.copytree(good[0], tmp_path / "broken")
    for photo in (broken / "images").iterdir():
        photo.write_bytes(b"not an image")
    report = tmp_path / "batch.json"
    argv = ["batch", *map(str, [good[0], broken, good[1]]), "--until", "undistort", "--workers", "2"]
    assert cli.main([*argv, "--report", str(report)]) == 1
    result = json.loads(report.read_text())
    by_name = {r["capture"].rsplit("/", 1)[-1]: r for r in result["captures"]}
    assert [r["capture"].rsplit("/", 1)[-1] for r in result["captures"]] == ["first", "broken", "second"]
    assert by_name["first"]["status"] == by_name["second"]["status"] == "ok"
    assert by_name["first"]["figures"] == {}  # no fit stage ran: no held-out error to show
    assert by_name["broken"]["status"] == "failed" and "cannot read this image" in by_name["broken"]["error"]
    assert (result["succeeded"], result["failed"]) == (2, 1)
    for capture in good:
        assert (capture / ".pipeline" / "cache" / "undistort").is_dir()
    table = capfd.readouterr().err
    assert "broken" in table and "failed" in table and "no fit stage ran" in table
    assert "first: undistort run in" in table and "second: calibrate run in" in table  # each stage as it ends
    assert "dashboard" in table
    # everything cached now: the good captures alone succeed
    assert cli.main(["batch", *map(str, good), "--until", "undistort", "--report", str(report)]) == 0
    # The workers exit cleanly: no heap corruption or stack dump at their shutdown.
    err = capfd.readouterr().err
    assert not [word for word in ("malloc", "Aborted", "SIGABRT", "stack trace") if word in table + err]


def test_batch_refuses_a_missing_capture_before_starting(tmp_path, capsys):
    assert cli.main(["batch", str(tmp_path / "nope"), "--report", str(tmp_path / "b.json")]) == 2
    assert "capture folder" in capsys.readouterr().err and not (tmp_path / "b.json").exists()


def test_the_summary_shows_the_last_fit_stages_held_out_error():
    from types import SimpleNamespace

    from pipeline.cli.batch import heldout_figures

    def item(stage, metrics):
        return SimpleNamespace(stage=SimpleNamespace(name=stage), metrics=metrics)

    plan = [
        item("fit_material", {"validation_mse": 0.004, "model": "principled"}),
        item("fit_geometry", {"validation_mse": 0.003, "validation_mse_start": 0.004}),
        item("export", {"triangles": 20000}),
    ]
    assert heldout_figures(plan) == {"heldout_mse": 0.003, "heldout_stage": "fit_geometry"}
    assert heldout_figures(plan[2:]) == {}
