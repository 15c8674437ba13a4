"""The studies' kits of bench/fit_kits.py, each in a folder with its references (kept
apart from bench/fit_kits.py, whose code keys the original loop's stored outcomes)."""

from __future__ import annotations

import tempfile
from pathlib import Path

from bench.fit_kits import draw_kit, references


def kits_with_references(material: str, seeds: str, work: Path | None, mi):
    """Each kit of ``seeds`` (comma-separated) and its folder in ``work``
    (``material``-``seed``; a new temporary folder for None), its references rendered
    there (bench/fit_kits.py, ``references``), in turn."""
    work = work or Path(tempfile.mkdtemp(prefix="kits-"))
    for seed in (int(s) for s in seeds.split(",")):
        kit = draw_kit(seed, material)
        folder = work / f"{material}-{seed}"
        folder.mkdir(parents=True, exist_ok=True)
        references(kit, folder, mi)
        yield kit, folder
