"""Kills, damage and concurrency: nothing computed is lost, nothing damaged is trusted."""

import errno
import json
import os
import shutil
import time
from pathlib import Path

import pytest

from pipeline import report as html_report
from pipeline.core import fsutil, publish
from pipeline.core.cache import STATUS_FILE
from pipeline.core.errors import ConfigError, DiskFull
from pipeline.core.lock import CaptureBusy, CaptureLock
from pipeline.core.runner import Selection
from tests.support.as_user import as_user, give, nobody, reachable_folder
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
publish._swap_in = lambda staging, output: os.kill(os.getpid(), signal.SIGKILL)
"""

KILL_AFTER_SWAP = """
import os, signal
import pipeline.core.publish as publish
swap = publish._swap_in
def swap_then_die(staging, output):
    swap(staging, output)
    os.kill(os.getpid(), signal.SIGKILL)
publish._swap_in = swap_then_die
"""


@pytest.mark.parametrize(
    "patch, whole",
    [(KILL_IN_COPY, "old"), (KILL_BEFORE_SWAP, "old"), (KILL_AFTER_SWAP, "new")],
    ids=["while-copying", "before-the-swap", "after-the-swap"],
)
def test_a_kill_while_publishing_leaves_one_whole_output(tmp_path, presets_dir, patch, whole):
    capture = make_capture(tmp_path)
    run_toy(capture, presets_dir)
    before = published(capture)
    script = killed_run_script(capture, presets_dir, ["double.factor=3"], patch.replace("\n", "\n        "))
    killed = run_python(script)
    assert killed.returncode == -9, killed.stderr
    if whole == "old":
        assert published(capture) == before  # the old version, complete
    else:
        assert published(capture)[0] == "result 18.0\n"
    run_toy(capture, presets_dir, "double.factor=3")
    assert RUNS == []  # the killed run's stages had committed; only publishing was lost
    text, manifest = published(capture)
    assert text == "result 18.0\n" and manifest["report.txt"]["stage"] == "report"
    assert not list(capture.glob(".output.tmp-*"))  # leftovers removed


def test_output_holds_real_files_that_outlive_the_cache(tmp_path, presets_dir, toy_cli):
    capture = make_capture(tmp_path)
    run_toy(capture, presets_dir)
    assert (capture / "output").is_dir() and not (capture / "output").is_symlink()
    shutil.copytree(capture / "output", tmp_path / "backup")
    shutil.rmtree(capture / ".pipeline")
    assert published(capture)[0] == "result 12.0\n"
    assert (tmp_path / "backup" / "report.txt").read_text() == "result 12.0\n"
    assert toy_cli(["--quiet", "status", str(capture)]) == 0
    run_toy(capture, presets_dir)  # recomputed, republished in place
    assert published(capture)[0] == "result 12.0\n"


def test_an_edited_or_removed_output_file_is_restored_and_the_edit_kept(tmp_path, presets_dir, caplog):
    capture = make_capture(tmp_path)
    run_toy(capture, presets_dir)
    (capture / "output" / "report.txt").write_text("result 99.0\n")
    run_toy(capture, presets_dir)
    assert RUNS == [] and published(capture)[0] == "result 12.0\n"
    assert (capture / "output" / "report.edited.txt").read_text() == "result 99.0\n"
    assert "output/report.txt was edited after it was published" in caplog.text
    (capture / "output" / "report.txt").unlink()
    run_toy(capture, presets_dir)
    assert published(capture)[0] == "result 12.0\n" and "was removed after it was published" in caplog.text
    assert (capture / "output" / "report.edited.txt").is_file()  # a user's file, kept


def test_files_a_user_puts_in_output_are_kept(tmp_path, presets_dir, caplog):
    capture = make_capture(tmp_path)
    (capture / "output" / "notes").mkdir(parents=True)
    (capture / "output" / "notes" / "my-notes.txt").write_text("keep me")
    (capture / "output" / "report.txt").write_text("my own report")  # the name a stage's result takes
    run_toy(capture, presets_dir)
    run_toy(capture, presets_dir, "double.factor=3")
    assert (capture / "output" / "notes" / "my-notes.txt").read_text() == "keep me"
    assert (capture / "output" / "report.yours.txt").read_text() == "my own report"
    assert "output/report.txt was not the pipeline's: kept as report.yours.txt" in caplog.text
    assert published(capture)[0] == "result 18.0\n"


def test_the_output_link_of_an_older_pipeline_becomes_a_folder(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    versions = capture / ".pipeline" / "published"
    (versions / "20250101-000000-1").mkdir(parents=True)
    (versions / "20250101-000000-1" / "report.txt").write_text("old\n")
    (versions / "legacy-20240101").mkdir()
    (versions / "legacy-20240101" / "my-notes.txt").write_text("keep me")
    (capture / "output").symlink_to(Path(".pipeline") / "published" / "20250101-000000-1")
    run_toy(capture, presets_dir)
    assert not (capture / "output").is_symlink() and published(capture)[0] == "result 12.0\n"
    assert [p.name for p in versions.iterdir()] == ["legacy-20240101"]


def test_a_full_disk_while_a_stage_writes_removes_its_partial_files_and_says_so(tmp_path, presets_dir):
    capture = make_capture(tmp_path)
    run_toy(capture, presets_dir)
    with pytest.raises(DiskFull, match=r"the disk holding .* is full \(\d+ MB free\) while stage ingest wrote its"):
        run_toy(capture, presets_dir, "ingest.fail='diskfull'")
    (failed,) = (capture / ".pipeline" / "failed" / "ingest").iterdir()
    assert [p.name for p in failed.iterdir()] == ["log.txt"]  # partial.txt removed
    assert not list((capture / ".pipeline" / "cache").glob("*/.tmp-*"))
    assert published(capture)[0] == "result 12.0\n"


def test_a_full_disk_while_publishing_keeps_the_old_output(tmp_path, presets_dir, monkeypatch):
    capture = make_capture(tmp_path)
    run_toy(capture, presets_dir)
    before = published(capture)

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(publish.shutil, "copy2", full)
    with pytest.raises(DiskFull, match="publishing 2 file.*the previous output/ and every cached result were kept"):
        run_toy(capture, presets_dir, "double.factor=3")
    assert published(capture) == before and not list(capture.glob(".output.tmp-*"))


def test_a_full_disk_while_the_report_is_written_keeps_the_old_report(tmp_path, monkeypatch):
    (tmp_path / "output").mkdir()
    (tmp_path / "output" / "report.html").write_text("<p>the old report</p>")
    real_fdopen = os.fdopen

    def fdopen_that_fills(fd, *args, **kwargs):
        handle = real_fdopen(fd, *args, **kwargs)
        handle.write = lambda text: (_ for _ in ()).throw(OSError(errno.ENOSPC, "No space left on device"))
        return handle

    monkeypatch.setattr(fsutil.os, "fdopen", fdopen_that_fills)
    with pytest.raises(DiskFull, match="writing report.html: the previous report was kept"):
        html_report.write(tmp_path, [])
    assert (tmp_path / "output" / "report.html").read_text() == "<p>the old report</p>"
    assert [p.name for p in (tmp_path / "output").iterdir()] == ["report.html"]  # no partial file


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
    (entry_dir(capture, "double") / "stray.txt").write_text("a file put into the cache by hand")
    run_toy(capture, presets_dir)
    assert RUNS == ["double"] and "stray.txt was added" in caplog.text


@pytest.mark.parametrize(
    "spoil",
    [
        lambda status: status | {"contents": 5},
        lambda status: status | {"outputs": ["doubled.txt"]},
        lambda status: status | {"outputs": {"doubled": "../../../../etc/hostname"}},
        lambda status: status | {"contents": {"doubled.txt": "12"}},
        lambda status: status | {"seconds": "soon"},
        lambda status: status | {"components": None},
    ],
    ids=["contents", "outputs-list", "outputs-outside", "contents-entry", "seconds", "components"],
)
def test_a_status_json_of_valid_json_and_the_wrong_shape_is_recomputed(tmp_path, presets_dir, toy_cli, capsys, spoil):
    capture = make_capture(tmp_path)
    assert toy_cli(["--quiet", "run", str(capture)]) == 0  # the CLI's logging from the start, on this test's stderr
    status_file = entry_dir(capture, "double") / STATUS_FILE
    status_file.write_text(json.dumps(spoil(json.loads(status_file.read_text()))))
    RUNS.clear()
    for command in (["status"], ["report"], ["run", "--dry-run"], ["run"]):
        assert toy_cli(["--quiet", *command, str(capture)]) == 0
        err = capsys.readouterr().err
        assert "damaged status.json" in err and "Traceback" not in err
    assert RUNS == ["double"] and published(capture)[0] == "result 12.0\n"


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


def test_a_file_system_without_exchange_publishes_by_two_renames(tmp_path, presets_dir, monkeypatch):
    capture = make_capture(tmp_path)
    run_toy(capture, presets_dir)

    def unsupported(a, b):
        raise OSError(errno.EINVAL, "Invalid argument")

    monkeypatch.setattr(publish, "_exchange", unsupported)
    run_toy(capture, presets_dir, "double.factor=3")
    assert published(capture)[0] == "result 18.0\n" and not list(capture.glob(".output.tmp-*"))


@pytest.mark.parametrize(
    "manifest",
    [
        {"report.txt": {"stage": "report", "contents": {"../../victim/f.txt": [3, "0" * 64]}}},
        {"report.txt": {"stage": "report", "contents": {"/etc/hostname": [3, "0" * 64]}}},
        {"report.txt": {"stage": "report", "contents": {"report.txt": "12"}}},
        {"report.txt": ["not", "a", "record"]},
        ["a", "list"],
    ],
    ids=["leaves-output", "absolute", "wrong-entry", "wrong-record", "not-an-object"],
)
def test_a_damaged_manifest_is_ignored_and_nothing_is_written_outside_the_capture(
    tmp_path, presets_dir, caplog, manifest
):
    capture = make_capture(tmp_path)
    run_toy(capture, presets_dir)
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "f.txt").write_text("abc")
    (capture / "output" / "manifest.json").write_text(json.dumps(manifest))
    run_toy(capture, presets_dir, "double.factor=3")
    assert sorted(p.name for p in victim.iterdir()) == ["f.txt"]  # no f.edited.txt beside it
    assert published(capture)[0] == "result 18.0\n"
    assert "manifest.json is damaged" in caplog.text
    assert publish.current_manifest(capture) is not None  # the new one is whole


def test_published_files_are_as_readable_as_any_the_user_makes(tmp_path, presets_dir):
    """Not 0600, as tempfile.mkstemp makes them: what open() would under the umask."""
    capture = make_capture(tmp_path)
    run_toy(capture, presets_dir)
    for path in (capture / "output" / "manifest.json", capture / "output" / "report.txt"):
        assert path.stat().st_mode & 0o777 == 0o666 & ~fsutil.UMASK, path


def test_a_read_only_output_folder_is_replaced_and_leaves_nothing_behind(request, presets_dir):
    """As a user who is not root, whose chmod 0555 the permission checks honour."""
    user = nobody()
    shared = reachable_folder(request, "read-only-output-")
    presets_dir = Path(shutil.copytree(presets_dir, shared / "presets"))
    capture = make_capture(shared)
    run_toy(capture, presets_dir)
    give(capture, user)
    os.chmod(capture / "output", 0o555)
    for _ in range(2):  # the second run finds nothing the first left
        assert as_user(user, lambda: run_toy(capture, presets_dir, "double.factor=3")) == 0
    assert published(capture)[0] == "result 18.0\n"
    assert not list(capture.glob(".output.tmp-*"))
