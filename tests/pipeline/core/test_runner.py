import hashlib
import json
import os
import subprocess
import sys
import textwrap
from dataclasses import replace
from pathlib import Path

import pytest

from pipeline.core import hashing
from pipeline.core.config import load_config
from pipeline.core.errors import ConfigError
from pipeline.core.runner import Runner, Selection
from pipeline.core.sections import schema
from pipeline.core.stage import StageResult
from tests.support.toy_stages import RUNS, make_capture, make_stages, run_toy, toy_runner


@pytest.fixture(autouse=True)
def clear_runs():
    RUNS.clear()


def runner(capture: Path, presets_dir: Path, *overrides: str, version: int = 1, preset: str = "standard"):
    return toy_runner(capture, presets_dir, *overrides, version=version, preset=preset)


def run(capture, presets_dir, *overrides, selection=Selection(), version=1):
    return run_toy(capture, presets_dir, *overrides, selection=selection, version=version)


def test_first_run_computes_everything_and_exports(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    plan = run(capture, presets_dir)
    assert RUNS == ["ingest", "double", "meta", "report"]
    assert (capture / "output" / "report.txt").read_text() == "result 12.0\n"
    manifest = json.loads((capture / "output" / "manifest.json").read_text())
    assert manifest["report.txt"]["key"] == plan["report"].key
    assert plan["ingest"].metrics == {"files": 3}


def test_second_run_is_fully_cached(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    run(capture, presets_dir)
    plan = run(capture, presets_dir)
    assert RUNS == []
    assert {p.action for p in plan.values()} == {"cached"}


def test_setting_change_reruns_stage_and_downstream_only(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    run(capture, presets_dir)
    plan = run(capture, presets_dir, "double.factor=5")
    assert RUNS == ["double", "report"]
    assert plan["double"].reason == "setting double.factor: 2 -> 5"
    assert plan["report"].reason == "upstream double changed"
    assert (capture / "output" / "report.txt").read_text() == "result 30.0\n"


def test_reverting_a_setting_hits_the_cache(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    run(capture, presets_dir)
    run(capture, presets_dir, "double.factor=5")
    run(capture, presets_dir)
    assert RUNS == []
    assert (capture / "output" / "report.txt").read_text() == "result 12.0\n"


def test_input_content_change_reruns_readers(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    run(capture, presets_dir)
    (capture / "images" / "001.txt").write_text("20")
    plan = run(capture, presets_dir)
    assert RUNS == ["ingest", "double", "meta", "report"]
    assert plan["ingest"].reason == "input changed: images/001.txt"


def test_added_input_is_named(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    run(capture, presets_dir)
    (capture / "images" / "009.txt").write_text("1")
    assert run(capture, presets_dir)["ingest"].reason == "input added: images/009.txt"


def test_touch_without_content_change_recomputes_nothing(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    run(capture, presets_dir)
    touched = capture / "images" / "000.txt"
    os.utime(touched, ns=(touched.stat().st_atime_ns, touched.stat().st_mtime_ns + 10**9))
    run(capture, presets_dir)
    assert RUNS == []


def test_unchanged_files_are_not_reread(tmp_path, presets_dir, monkeypatch):
    capture = make_capture(tmp_path)
    run(capture, presets_dir)
    second = runner(capture, presets_dir)
    second.plan()
    assert second.hasher.files_read == 3  # written within the clock's resolution of their hashing: racy
    monkeypatch.setattr(hashing, "RACY_NS", 0)  # as if they had been written long before
    third = runner(capture, presets_dir)
    third.plan()
    assert third.hasher.files_read == 0


def test_a_file_replaced_with_the_same_size_and_mtime_is_hashed_again(tmp_path, presets_dir, monkeypatch):
    """``cp -p`` over a photo keeps its size and mtime; its ctime tells."""
    monkeypatch.setattr(hashing, "RACY_NS", 0)
    capture = make_capture(tmp_path)
    run(capture, presets_dir)
    photo = capture / "images" / "001.txt"
    before = photo.stat()
    photo.write_text("7.0")  # same size as "2.0"
    os.utime(photo, ns=(before.st_atime_ns, before.st_mtime_ns))
    assert photo.stat().st_mtime_ns == before.st_mtime_ns and photo.stat().st_size == before.st_size
    assert run(capture, presets_dir)["ingest"].reason == "input changed: images/001.txt"
    assert (capture / "output" / "report.txt").read_text() == "result 22.0\n"


def test_a_file_rewritten_within_the_clock_resolution_of_its_hashing_is_hashed_again(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    photo = capture / "images" / "001.txt"
    hasher = hashing.FileHasher(tmp_path / "memo.json")
    hasher.hash(photo)
    stamp = photo.stat()
    photo.write_text("7")
    os.utime(photo, ns=(stamp.st_atime_ns, stamp.st_mtime_ns))
    assert hasher.hash(photo) == hashlib.sha256(b"7").hexdigest()


def test_version_bump_reruns_stage_and_downstream(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    run(capture, presets_dir)
    plan = run(capture, presets_dir, version=2)
    assert RUNS == ["ingest", "double", "meta", "report"]
    assert plan["ingest"].reason == "stage version 1 -> 2"


def test_capture_toml_layer_sits_between_preset_and_overrides(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    (capture / "capture.toml").write_text("[double]\nfactor = 4\n")
    assert runner(capture, presets_dir).config["double"].factor == 4
    assert runner(capture, presets_dir, "double.factor=7").config["double"].factor == 7
    assert runner(capture, presets_dir, preset="draft").config["double"].factor == 4


@pytest.mark.parametrize(
    "selection, expected",
    [
        (Selection(until="double"), []),  # cached; see the fresh-capture test below
        (Selection(only="double"), ["double"]),
        (Selection(start="double"), ["double", "report"]),
        (Selection(force=("ingest",)), ["ingest", "double", "meta", "report"]),
        (Selection(force=("meta",)), ["meta"]),
        (Selection(force=("all",), until="meta"), ["ingest", "meta"]),
    ],
)
def test_selection_runs_the_right_stages(tmp_path, presets_dir, selection, expected):
    capture = make_capture(tmp_path)
    run(capture, presets_dir)
    run(capture, presets_dir, selection=selection)
    assert RUNS == expected


def test_until_on_fresh_capture_computes_only_ancestors(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    plan = run(capture, presets_dir, selection=Selection(until="double"))
    assert RUNS == ["ingest", "double"]
    assert set(plan) == {"ingest", "double"}


def test_only_requires_cached_upstream(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    with pytest.raises(ConfigError, match="stage ingest has no cached result.*--until ingest"):
        run(capture, presets_dir, selection=Selection(only="double"))
    assert RUNS == []


def test_unknown_stage_in_selection_is_a_usage_error(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    with pytest.raises(ConfigError, match="--from mesh: no such stage; stages are ingest"):
        run(capture, presets_dir, selection=Selection(start="mesh"))


def test_a_from_after_the_until_is_a_usage_error_not_an_empty_run(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    with pytest.raises(ConfigError, match="--from report is not upstream of --until double: nothing lies between"):
        run(capture, presets_dir, selection=Selection(start="report", until="double"))
    assert not (capture / ".pipeline" / "cache").exists()


def committed_entries(capture: Path, stage: str) -> list[Path]:
    stage_dir = capture / ".pipeline" / "cache" / stage
    return [p for p in stage_dir.iterdir() if not p.name.startswith(".")] if stage_dir.exists() else []


def test_failing_stage_commits_nothing_and_is_redone_next_time(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    run(capture, presets_dir, "double.factor=3")
    with pytest.raises(RuntimeError, match="failed on purpose"):
        run(capture, presets_dir, "ingest.fail='raise'")
    assert RUNS == ["ingest"]
    assert len(committed_entries(capture, "ingest")) == 1  # only the earlier, good one
    failed_logs = list((capture / ".pipeline" / "failed" / "ingest").glob("*/log.txt"))
    assert len(failed_logs) == 1 and "Traceback" not in failed_logs[0].read_text()
    # the earlier results are intact and a later good run redoes exactly what is missing
    run(capture, presets_dir, "double.factor=3")
    assert RUNS == []
    run(capture, presets_dir, "ingest.scale=2")
    assert RUNS == ["ingest", "double", "meta", "report"]


def test_a_stage_failing_twice_in_one_second_keeps_both_logs(tmp_path, presets_dir, monkeypatch):
    """A process that runs the stages twice (a script calling the runner) can fail a stage
    twice within the second that names the failed folder: the second failure still ends
    in its own error."""
    import time

    monkeypatch.setattr(time, "strftime", lambda fmt, *_: "20260101-000000")
    capture = make_capture(tmp_path)
    for _ in range(2):
        with pytest.raises(RuntimeError, match="failed on purpose"):
            run(capture, presets_dir, "ingest.fail='raise'")
    assert len(list((capture / ".pipeline" / "failed" / "ingest").glob("*/log.txt"))) == 2


def test_sigkilled_stage_leaves_no_entry_and_is_redone(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    run(capture, presets_dir, selection=Selection(until="ingest"))
    script = textwrap.dedent(
        f"""
        import sys
        from pathlib import Path
        from tests.support.toy_stages import make_stages
        from pipeline.core.config import load_config
        from pipeline.core.runner import Runner
        from pipeline.core.sections import schema
        stages = make_stages()
        config = load_config(schema(stages), Path({str(capture)!r}), "standard",
                             ["ingest.fail='sigkill'", "ingest.scale=3"], Path({str(presets_dir)!r}))
        Runner(Path({str(capture)!r}), stages, config).run()
        """
    )
    # Run from the repository root, where the tests package is importable.
    killed = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, cwd=Path(__file__).parents[3]
    )
    assert killed.returncode == -9, killed.stderr
    assert len(committed_entries(capture, "ingest")) == 1
    assert list((capture / ".pipeline" / "cache" / "ingest").glob(".tmp-*"))  # the killed run
    plan = run(capture, presets_dir, "ingest.scale=3")
    assert RUNS == ["ingest", "double", "meta", "report"]
    assert plan["ingest"].reason == "setting ingest.scale: 1.0 -> 3.0"
    # and with the original settings nothing at all is recomputed
    run(capture, presets_dir, selection=Selection(until="ingest"))
    assert RUNS == []


def test_status_json_records_inputs_config_and_versions(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    plan = run(capture, presets_dir)
    status = plan["ingest"].entry.status
    assert status["components"]["files"].keys() == {"images/000.txt", "images/001.txt", "images/002.txt"}
    assert status["effective_config"]["double"] == {"factor": 2}
    assert "python" in status["libraries"] and status["seconds"] >= 0
    assert (plan["ingest"].entry.path / "log.txt").read_text().count("stage ingest") == 2
    runs = list((capture / ".pipeline" / "runs").glob("*.json"))
    assert len(runs) == 1


def test_forced_rerun_exports_again_under_the_same_key(tmp_path, presets_dir):
    # A forced rerun keeps its cache key; what it exports must still replace the old copy.
    capture = make_capture(tmp_path)
    run(capture, presets_dir)
    (capture / "output" / "report.txt").write_text("stale\n")
    run(capture, presets_dir, selection=Selection(force=("report",)))
    assert (capture / "output" / "report.txt").read_text() == "result 12.0\n"


def test_a_stage_sees_exactly_the_outputs_it_needs(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    plan = run(capture, presets_dir)
    # meta writes how many of ingest's outputs it was handed: the one it declared.
    assert (plan["meta"].entry.outputs["meta"]).read_text() == "1 outputs"


def test_a_stage_returning_undeclared_outputs_fails_and_commits_nothing(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    stages = tuple(replace(s, outputs=("total", "extra")) if s.name == "ingest" else s for s in make_stages())
    config = load_config(schema(stages), capture, "standard", [], presets_dir)
    with pytest.raises(RuntimeError, match=r"stage ingest returned outputs \['total'\] but declares"):
        Runner(capture, stages, config).run(Selection(until="ingest"))
    assert not list((capture / ".pipeline" / "cache" / "ingest").glob("[!.]*"))


SEEN_SHARED: dict[str, dict] = {}


def _records_shared(conf, inputs, out_dir):
    SEEN_SHARED["double"] = dict(inputs.shared)
    (out_dir / "doubled.txt").write_text("0")
    RUNS.append("double")
    return StageResult({"doubled": out_dir / "doubled.txt"})


def test_a_stage_sharing_one_setting_sees_it_and_reruns_only_when_it_changes(tmp_path, presets_dir):
    """sfm reads capture.rig, not the capture's free-text description or material:
    editing those must not recompute the poses."""
    capture = make_capture(tmp_path)
    stages = tuple(
        replace(s, main=_records_shared, shared=("capture.rig",))
        if s.name == "double"
        else replace(s, shared=("capture",))
        if s.name == "meta"
        else s
        for s in make_stages()
    )

    def rerun(*overrides):
        RUNS.clear()
        config = load_config(schema(stages), capture, "standard", list(overrides), presets_dir)
        return {p.stage.name: p for p in Runner(capture, stages, config).run()}

    rerun()
    assert SEEN_SHARED["double"] == {"capture.rig": "handheld"}
    rerun("capture.material=opaque", "capture.description=edited")
    assert RUNS == ["meta"]  # the stage sharing the whole section, only
    plan = rerun("capture.rig=turntable")
    assert RUNS == ["double", "meta", "report"]
    assert plan["double"].reason == "setting capture.rig: 'handheld' -> 'turntable'"
    assert SEEN_SHARED["double"] == {"capture.rig": "turntable"}


def test_sharing_a_setting_no_section_has_is_refused():
    stages = tuple(replace(s, shared=("capture.colour",)) if s.name == "double" else s for s in make_stages())
    with pytest.raises(ValueError, match="stage double shares capture.colour: no such shared section or setting"):
        schema(stages)
