"""pipeline.report on a small synthetic bird through export (tiny fits): the page is
self-contained and a headless Chromium (Debian's chromium package, which bin/test
installs) renders it with every image decoded."""

import re
import shutil

import pytest

from pipeline.cli import main as cli_main
from tests.support.gltf_viewers import headless_chromium
from tests.support.tiny_fits import TINY_FIT, TINY_TEXTURE

pytestmark = pytest.mark.slow
OVERRIDES = (*TINY_FIT, *TINY_TEXTURE, "fit_geometry.enabled=false")  # as tests/stages/test_export.py


def test_the_report_opens_offline_in_chromium_with_every_image_loaded(run_stages, small_bird, tmp_path):
    run_stages(small_bird, "export", *OVERRIDES)
    assert cli_main(["--quiet", "report", str(small_bird), *(a for o in OVERRIDES for a in ("-s", o))]) == 0
    text = (small_bird / "output" / "report.html").read_text()
    for heading in ("Summary", "3D view", "Stages", "Cameras and mesh", "Choices", "Parameters (fit_geometry)"):
        assert f"<h2>{heading}</h2>" in text, heading
    assert "<h2>Held-out photos</h2>" in text and "<h2>Trajectories</h2>" in text and "<h2>Warnings</h2>" in text
    assert "Preset standard; settings given: fit_material.iterations=8" in text and "<td>mitsuba</td>" in text
    # Held-out reference, render and difference of 2 photos after each of the three fit
    # stages, the difference's scale; the cameras; the trajectories of fit_material and
    # fit_texture; the texture map when one was kept.
    images = text.count("<img ")
    textured = "base colour texture (UV atlas)" in text
    assert images == 3 * 2 * 3 + 1 + 1 + 2 + textured
    # Nothing fetched: every image embedded; links only to the final files beside the page.
    assert not re.search(r"""src=['"](?!data:)""", text)
    links = re.findall(r"""href=['"]([^'"]+)""", text)
    assert set(links) == {"scene.xml", "params.json", "specimen.glb", "heldout", "README.txt"}
    alone = tmp_path / "report.html"  # a copy alone in a folder: opens offline
    shutil.copy2(small_bird / "output" / "report.html", alone)
    dom = headless_chromium(
        ["--virtual-time-budget=10000", "--dump-dom", alone.as_uri()],
        lambda page: re.search(r'id="specimen-view"[^>]*data-(rendered|error)=', page) is not None,
    )
    counted = re.search(r'data-images="(\d+)" data-images-loaded="(\d+)"', dom)
    assert counted is not None, dom[:500]
    assert int(counted.group(1)) == images and int(counted.group(2)) == images
    # The 3D view drew the glb (WebGL in software), offline.
    assert re.search(r'id="specimen-view"[^>]*data-rendered="1"', dom), re.findall(
        r'<div id="specimen-view"[^>]*>', dom
    )
