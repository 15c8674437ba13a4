"""What the benchmarks share: running the real stages, and writing results into
docs/benchmarks.md, one marked section per benchmark."""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "docs" / "benchmarks.md"


def machine() -> str:
    """The machine a section was measured on, in words: cores, memory, GPU."""
    memory = next(
        int(line.split()[1]) / 2**20
        for line in Path("/proc/meminfo").read_text().splitlines()
        if line.startswith("MemTotal")
    )
    gpu = (
        shutil.which("nvidia-smi")
        and subprocess.run(
            ["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True, text=True
        ).stdout.strip()
    )
    return f"Machine: {os.cpu_count()} cores, {memory:.0f} GiB, {gpu or 'no GPU'}."


def code_version(*paths: str, label: str | None = None) -> str:
    """The code a benchmark runs: HEAD's short commit and the git tree of ``paths`` in it
    (a later commit that changes nothing there keeps the tree), with "+changes" when
    the work tree differs from HEAD there, a new file included; ``label`` names the
    paths in the text (default: the paths joined by slashes)."""

    def git(*arguments: str) -> str:
        return subprocess.run(["git", *arguments], cwd=ROOT, capture_output=True, text=True, check=True).stdout

    trees = git("rev-parse", *(f"HEAD:{path}" for path in paths)).split()
    changed = bool(git("status", "--porcelain", "--", *paths).strip())  # untracked files too
    tree = hashlib.sha1(" ".join(trees).encode()).hexdigest()[:12]
    return f"commit {git('rev-parse', '--short', 'HEAD').strip()}, {label or '/'.join(paths)} tree {tree}" + (
        " +changes" if changed else ""
    )


def run_stages(
    capture: Path, until: str, *overrides: str, force: tuple[str, ...] = (), preset: str = "standard"
) -> tuple[dict, dict]:
    """The stage DAG on ``capture`` up to ``until``: (outputs, seconds) per stage; a
    cached stage's seconds are those of the run that computed it."""
    from pipeline.core.config import load_config
    from pipeline.core.runner import Runner, Selection
    from pipeline.core.sections import schema
    from stages import STAGES

    config = load_config(schema(STAGES), capture, preset, list(overrides))
    plan = Runner(capture, STAGES, config).run(Selection(until=until, force=force))
    return {i.stage.name: i.entry.outputs for i in plan}, {i.stage.name: i.seconds for i in plan}


def truth_in_reconstruction(capture: Path, outputs: dict):
    """The camera alignment (reconstruction to truth) and the true mesh, geometry only,
    moved into the reconstruction's frame by its inverse."""
    import numpy as np
    import trimesh

    from pipeline.formats.cameras import read_cameras, read_views
    from pipeline.synthetic.score import score_cameras

    _, true_poses = read_cameras(capture / "ground_truth" / "cameras.json")
    _, similarity = score_cameras({n: p for n, (_, p) in read_views(outputs["sfm"]["cameras"]).items()}, true_poses)
    truth = trimesh.load(capture / "ground_truth" / "mesh.ply", force="mesh", process=False)
    bare = trimesh.Trimesh(truth.vertices, truth.faces, process=False)
    bare.apply_transform(np.linalg.inv(similarity.matrix()))
    return similarity, bare


CLI = "import sys; from pipeline.cli import main; sys.exit(main(sys.argv[1:]))"
"""The real CLI in a process of its own: ``[sys.executable, "-c", CLI, *argv]``."""


def synthetic_capture(folder: Path, views: int, size: tuple[int, int], spp: int, shots: int, *run: str) -> Path:
    """``pipeline synth`` into ``folder`` (seed 3), then ``pipeline run`` with ``run``'s
    options when given; a folder that already holds a published run is kept as it is."""
    if (folder / "output" / "manifest.json").is_file():
        return folder
    shutil.rmtree(folder, ignore_errors=True)
    synth = ["synth", str(folder), "--views", str(views), "--width", str(size[0]), "--height", str(size[1])]
    synth += ["--spp", str(spp), "--calibration-shots", str(shots), "--seed", "3"]
    subprocess.run([sys.executable, "-c", CLI, "-q", *synth], check=True, cwd=ROOT)
    if run:
        subprocess.run([sys.executable, "-c", CLI, "-q", "run", str(folder), *run], check=True, cwd=ROOT)
    return folder


def finish(process: subprocess.Popen, timeout: float) -> tuple[str, str, bool]:
    """``process``'s standard output and error, and whether it outlived ``timeout``
    seconds (then it is killed: a watchdog, so that no case hangs the benchmark)."""
    try:
        out, err = process.communicate(timeout=timeout)
        return out, err, False
    except subprocess.TimeoutExpired:
        process.kill()
        out, err = process.communicate()
        return out, err, True


def write_section(name: str, lines: list[str]) -> str:
    """Replace the section between ``<!-- NAME:begin -->`` and ``<!-- NAME:end -->``
    (a new section goes at the end); returns the section's text."""
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    section = "\n".join([begin, *lines, end])
    text = BENCHMARKS.read_text()
    if begin in text:
        text = text[: text.index(begin)] + section + text[text.index(end) + len(end) :]
    else:
        text = text.rstrip("\n") + f"\n\n{section}\n"
    BENCHMARKS.write_text(text)
    return section
