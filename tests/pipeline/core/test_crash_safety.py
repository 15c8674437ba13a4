"""Kills, damage and concurrency: nothing computed is lost, nothing damaged is trusted."""

import json
import time

import pytest

from pipeline.core.cache import STATUS_FILE
from pipeline.core.errors import ConfigError
from pipeline.core.lock import CaptureBusy, CaptureLock
from pipeline.core.runner import Selection
from tests.support.toy_stages import RUNS, hold_lock, make_capture, run_python, run_toy, toy_runner


@pytest.fixture(autouse=True)
def clear_runs():
    RUNS.clear()


def entry_dir(capture, stage):
    (path,) = [p for p in (capture / ".pipeline" / "cache" / stage).iterdir() if not p.name.startswith(".")]
    return path


def published(capture):
    return (capture / "output" / "report.txt").read_text(), json.loads(
        (capture / "output" / "manifest.json").read_text()
    )


def killed_run_script(capture, presets_dir, overrides, patch=""):
    return f"""
        from pathlib import Path
        from tests.support.toy_stages import toy_runner
        {patch}
        toy_runner(Path({str(capture)!r}), Path({str(presets_dir)!r}), *{overrides!r}).run()
        """


KILL_IN_COPY = """
import os, shutil, signal
import pipeline.core.publish as publish
copy = shutil.copy2
def copy_then_die(*args, **kwargs):
    copy(*args, **kwargs)
    os.kill(os.getpid(), signal.SIGKILL)
publish.shutil.copy2 = copy_then_die
"""

KILL_BEFORE_SWAP = """
import os, signal
import pipeline.core.publish as publish
link = os.symlink
def link_then_die(*args):
    link(*args)
    os.kill(os.getpid(), signal.SIGKILL)
publish.os.symlink = link_then_die
"""


@pytest.mark.parametrize("patch", [KILL_IN_COPY, KILL_BEFORE_SWAP], ids=["while-copying", "before-the-swap"])
def test_a_kill_while_publishing_leaves_the_old_output_whole(tmp_path, presets_dir, patch):
    capture = make_capture(tmp_path)
    run_toy(capture, presets_dir)
    before = published(capture)
    script = killed_run_script(capture, presets_dir, ["double.factor=3"], patch.replace("\n", "\n        "))
    killed = run_python(script)
    assert killed.returncode == -9, killed.stderr
    assert published(capture) == before  # the old version, complete
    run_toy(capture, presets_dir, "double.factor=3")
    assert RUNS == []  # the killed run's stages had committed; only publishing was lost
    text, manifest = published(capture)
    assert text == "result 18.0\n" and manifest["report.txt"]["stage"] == "report"
    versions = list((capture / ".pipeline" / "published").iterdir())
    assert len(versions) == 1 and not list(capture.glob(".output.tmp-*"))  # leftovers removed


def test_output_holds_each_name_from_the_last_valid_stage(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    run_toy(capture, presets_dir)
    # --until a stage before report after a full run keeps report's valid result published
    run_toy(capture, presets_dir, selection=Selection(until="double"))
    assert published(capture)[0] == "result 12.0\n"
    # after a change upstream, the report of the old settings is no longer published
    run_toy(capture, presets_dir, "double.factor=5", selection=Selection(until="double"))
    assert not (capture / "output" / "report.txt").exists()


def test_a_damaged_or_partial_cache_entry_is_recomputed_with_a_warning(tmp_path, presets_dir, caplog):
    capture = make_capture(tmp_path)
    run_toy(capture, presets_dir)
    (entry_dir(capture, "double") / "doubled.txt").unlink()
    run_toy(capture, presets_dir)
    assert RUNS == ["double"] and "doubled.txt is missing" in caplog.text
    (entry_dir(capture, "ingest") / "total.txt").write_text("999")
    run_toy(capture, presets_dir)
    assert RUNS == ["ingest"] and "total.txt has changed" in caplog.text  # same total: downstream reused
    (entry_dir(capture, "report") / STATUS_FILE).write_text('{"outputs": {')
    run_toy(capture, presets_dir)
    assert RUNS == ["report"] and "damaged status.json" in caplog.text
    assert published(capture)[0] == "result 12.0\n"


def test_damaged_state_files_are_rebuilt_not_fatal(tmp_path, presets_dir, caplog):
    capture = make_capture(tmp_path)
    run_toy(capture, presets_dir)
    (capture / ".pipeline" / "file_hashes.json").write_text("{not json")
    (capture / "output" / "manifest.json").write_text("[1, 2")
    run_toy(capture, presets_dir)
    assert RUNS == [] and "file_hashes.json is damaged" in caplog.text
    assert published(capture)[1]["report.txt"]["stage"] == "report"


def test_unfinished_folders_of_killed_runs_are_removed(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    killed = run_python(killed_run_script(capture, presets_dir, ["ingest.fail='sigkill'"]))
    assert killed.returncode == -9
    assert list((capture / ".pipeline" / "cache" / "ingest").glob(".tmp-*"))
    run_toy(capture, presets_dir)
    assert not list((capture / ".pipeline" / "cache").glob("*/.*"))


def test_a_second_run_fails_clearly_with_no_wait_and_waits_otherwise(tmp_path, presets_dir, caplog):
    capture = make_capture(tmp_path)
    holder = hold_lock(capture, 1.5)
    with pytest.raises(CaptureBusy, match=rf"in use by pid {holder.pid} .*test holder"):
        toy_runner(capture, presets_dir, wait=False).run()
    assert RUNS == []
    started = time.time()
    toy_runner(capture, presets_dir).run()
    assert time.time() - started > 0.5 and "waiting for it to finish" in caplog.text
    assert RUNS == ["ingest", "double", "meta", "report"]
    holder.wait()


def test_a_lock_left_by_a_killed_run_is_taken_over(tmp_path, presets_dir, caplog):
    capture = make_capture(tmp_path)
    holder = hold_lock(capture, 60)
    holder.kill()
    holder.wait()
    toy_runner(capture, presets_dir, wait=False).run()
    assert f"took over the lock of pid {holder.pid}" in caplog.text
    with CaptureLock(capture, "again", wait=False):
        pass  # released in good order: no takeover the next time
    assert caplog.text.count("took over") == 1


def test_a_file_named_by_a_setting_is_part_of_the_cache_key(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    (capture / "extra.txt").write_text("4")
    run_toy(capture, presets_dir, "ingest.extra='extra.txt'")
    assert published(capture)[0] == "result 20.0\n"
    (capture / "extra.txt").write_text("6")
    plan = run_toy(capture, presets_dir, "ingest.extra='extra.txt'")
    assert plan["ingest"].reason == "the file ingest.extra names changed"
    assert published(capture)[0] == "result 24.0\n"


@pytest.mark.parametrize("value", ["/etc/passwd", "../../../../etc/passwd", "../outside.txt"])
def test_capture_toml_cannot_name_a_file_outside_the_capture(tmp_path, presets_dir, value):
    capture = make_capture(tmp_path)
    (tmp_path / "outside.txt").write_text("1")
    (capture / "capture.toml").write_text(f"[ingest]\nextra = {value!r}\n")
    with pytest.raises(
        ConfigError, match=r"ingest.extra = .* points outside the capture folder .*-s ingest.extra=PATH"
    ):
        toy_runner(capture, presets_dir)
    assert not (capture / ".pipeline").exists()


def test_the_command_line_may_name_a_file_outside_the_capture(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    (tmp_path / "outside.txt").write_text("1")
    run_toy(capture, presets_dir, f"ingest.extra='{tmp_path / 'outside.txt'}'")
    assert published(capture)[0] == "result 14.0\n"
    with pytest.raises(ConfigError, match=r"ingest.extra = 'missing.txt' is not a file"):
        toy_runner(capture, presets_dir, "ingest.extra='missing.txt'")


def test_warnings_name_the_folder_a_result_ends_in(tmp_path, presets_dir, caplog):
    capture = make_capture(tmp_path)
    plan = run_toy(capture, presets_dir)
    (message,) = [r.getMessage() for r in caplog.records if r.getMessage().startswith("meta wrote")]
    assert message == f"meta wrote {plan['meta'].entry.path / 'meta.txt'}" and ".tmp-" not in message
    assert (plan["meta"].entry.path / "meta.txt").is_file()


def test_an_output_folder_of_an_older_pipeline_is_moved_aside_and_kept(tmp_path, presets_dir, caplog):
    capture = make_capture(tmp_path)
    (capture / "output").mkdir()
    (capture / "output" / "my-notes.txt").write_text("keep me")
    run_toy(capture, presets_dir)
    assert (capture / "output").is_symlink() and published(capture)[0] == "result 12.0\n"
    (legacy,) = (capture / ".pipeline" / "published").glob("legacy-*")
    run_toy(capture, presets_dir, "double.factor=3")  # a later publish keeps it too
    assert (legacy / "my-notes.txt").read_text() == "keep me" and "was moved to" in caplog.text
