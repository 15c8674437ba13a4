import json
import re

import pytest

from tests.support.toy_stages import RUNS, make_capture


def test_run_then_dry_run_explains_what_would_rerun(tmp_path, toy_cli, capsys):
    capture = make_capture(tmp_path)
    assert toy_cli(["run", str(capture)]) == 0
    capsys.readouterr()
    RUNS.clear()
    assert toy_cli(["run", str(capture), "--dry-run", "-s", "double.factor=5"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert RUNS == []
    by_stage = {line.split()[1]: line for line in lines}
    assert by_stage["ingest"].split()[0] == "cached"
    assert by_stage["double"].split()[0] == "run" and "double.factor: 2 -> 5" in by_stage["double"]
    assert "upstream double changed" in by_stage["report"]


def test_json_summary(tmp_path, toy_cli, capsys):
    capture = make_capture(tmp_path)
    assert toy_cli(["--quiet", "run", str(capture), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert [s["action"] for s in summary["stages"]] == ["run"] * 4
    assert summary["stages"][0]["metrics"] == {"files": 3}
    assert summary["outputs"] == {"report.txt": str(capture / "output" / "report.txt")}  # the result on top
    assert summary["stage_outputs"] == {"report": str(capture / "output" / "stages" / "report")}
    assert (capture / "output" / "stages" / "report" / "report.txt").read_text() == "result 12.0\n"
    assert summary["figures"] == {"ingest": {"files": 3}} and summary["seconds"] > 0
    assert toy_cli(["run", str(capture), "--dry-run", "--json"]) == 0
    dry = json.loads(capsys.readouterr().out)  # the JSON alone: it parses
    assert dry["dry_run"] and [s["action"] for s in dry["stages"]] == ["cached"] * 4


def test_version(toy_cli, capsys):
    from pipeline import __version__

    with pytest.raises(SystemExit) as done:
        toy_cli(["--version"])
    assert done.value.code == 0 and capsys.readouterr().out.strip() == f"pipeline {__version__}"


def test_run_and_report_write_a_page_of_every_stage_and_its_state(tmp_path, toy_cli, capsys):
    capture = make_capture(tmp_path)
    assert toy_cli(["--quiet", "run", str(capture)]) == 0
    page = capture / "output" / "report.html"

    def states() -> dict[str, str]:
        return dict(re.findall(r"<tr><td>(\w+)</td><td>([\w ]+)</td>", page.read_text()))

    assert states() == {"ingest": "ran", "double": "ran", "meta": "ran", "report": "ran"}
    page.unlink()
    assert toy_cli(["report", str(capture), "-s", "double.factor=5"]) == 0
    assert capsys.readouterr().out.strip() == str(page)
    assert states() == {"ingest": "cached", "double": "to run", "meta": "cached", "report": "to run"}


def test_config_error_exits_2_and_runs_nothing(tmp_path, toy_cli, capsys):
    capture = make_capture(tmp_path)
    assert toy_cli(["run", str(capture), "-s", "double.factor=0"]) == 2
    assert "double.factor = 0 is out of range: allowed [1, 100]" in capsys.readouterr().err
    assert RUNS == [] and not (capture / ".pipeline" / "cache").exists()


def test_user_error_in_a_stage_exits_1_with_one_message(tmp_path, toy_cli, capsys):
    capture = make_capture(tmp_path)
    assert toy_cli(["run", str(capture), "-s", "ingest.fail=user"]) == 1
    err = capsys.readouterr().err
    assert "000.txt: not a number; fix the file" in err and "Traceback" not in err


def test_missing_capture_exits_2(tmp_path, toy_cli, capsys):
    assert toy_cli(["run", str(tmp_path / "nope")]) == 2
    assert "capture folder" in capsys.readouterr().err
    assert toy_cli(["run", "sample_captures/nope"]) == 2
    assert "pipeline synth" in capsys.readouterr().err


def test_status_and_clean_keep_latest(tmp_path, toy_cli, capsys):
    capture = make_capture(tmp_path)
    toy_cli(["run", str(capture)])
    toy_cli(["run", str(capture), "-s", "double.factor=5"])
    capsys.readouterr()
    assert toy_cli(["status", str(capture), "--json"]) == 0
    rows = {r["stage"]: r for r in json.loads(capsys.readouterr().out)["stages"]}
    assert rows["double"]["entries"] == 2 and rows["double"]["state"] == "cached"
    assert rows["ingest"]["entries"] == 1
    assert toy_cli(["clean", str(capture), "--keep-latest"]) == 0
    toy_cli(["status", str(capture), "--json"])
    rows = {r["stage"]: r for r in json.loads(capsys.readouterr().out)["stages"]}
    assert rows["double"]["entries"] == 1
    assert rows["double"]["state"] == "to run"  # the factor=5 entry was the newest
    assert toy_cli(["clean", str(capture)]) == 0
    assert not (capture / ".pipeline" / "cache").exists()
    assert (capture / "output" / "report.txt").exists()  # results survive a clean


@pytest.mark.parametrize("command", [[], ["run"], ["report"], ["status"], ["clean"], ["config"]])
def test_help_on_every_command(toy_cli, command, capsys):
    with pytest.raises(SystemExit) as exit_info:
        toy_cli([*command, "--help"])
    assert exit_info.value.code == 0
    assert "usage: pipeline" in capsys.readouterr().out


def test_bad_usage_exits_2(toy_cli):
    with pytest.raises(SystemExit) as exit_info:
        toy_cli(["run"])
    assert exit_info.value.code == 2


def test_config_lists_every_key_with_its_doc(toy_cli, capsys):
    assert toy_cli(["config", "-s", "double.factor=9"]) == 0
    out = capsys.readouterr().out
    assert "factor = 9    (int in [1, 100])" in out and "Integer factor." in out
    assert "[board]" in out and "square_mm" in out


def test_a_mitsuba_variant_that_cannot_render_here_is_refused_before_any_stage(
    tiny_capture, tmp_path, monkeypatch, capsys
):
    """The first stage that renders would have found out after the others ran."""
    import shutil

    from pipeline.cli import main as cli_main
    from pipeline.render import mitsuba_variant

    capture = shutil.copytree(tiny_capture, tmp_path / "capture")
    monkeypatch.setattr(mitsuba_variant, "probe", lambda variant: (False, "no CUDA driver (libcuda) on this machine"))
    mitsuba_variant.choose.cache_clear()
    try:
        assert cli_main(["run", str(capture), "--until", "scene", "-s", "mitsuba.variant='cuda_ad_rgb'"]) == 2
    finally:
        mitsuba_variant.choose.cache_clear()
    err = capsys.readouterr().err
    assert "mitsuba.variant = 'cuda_ad_rgb'" in err and "no CUDA driver" in err and "stage uv renders" in err
    assert not (capture / ".pipeline" / "cache").exists()
