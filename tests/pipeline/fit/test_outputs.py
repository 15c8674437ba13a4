"""Texture files of the fit stages (pipeline.fit.outputs)."""

import subprocess
import sys

import numpy as np

from pipeline.fit.outputs import write_volume_grid


def test_volume_grid_file_is_the_one_mitsuba_writes_and_reads(tmp_path, mi):
    grid = np.random.default_rng(0).random((3, 4, 5, 3), dtype=np.float32)
    write_volume_grid(tmp_path / "ours.vol", grid)
    mi.VolumeGrid(grid).write(str(tmp_path / "mitsuba.vol"))
    assert (tmp_path / "ours.vol").read_bytes() == (tmp_path / "mitsuba.vol").read_bytes()
    np.testing.assert_array_equal(np.array(mi.VolumeGrid(str(tmp_path / "ours.vol"))), grid)


def test_a_grid_texture_is_written_before_any_mitsuba_variant_is_set(tmp_path):
    """fit_texture writes its starting texture before it chooses a variant; with
    fit_material cached nothing else in the process has set one (a volumetric
    capture's fit_texture failed that way)."""
    script = (
        "import sys, numpy as np; from pathlib import Path;"
        "from pipeline.fit.outputs import write_texture_files;"
        "from pipeline.render.materials import TEXTURE_SLOTS;"
        "write_texture_files(Path(sys.argv[1]), TEXTURE_SLOTS['volumetric'], np.full((2, 3, 4, 3), 0.5, np.float32));"
        "import mitsuba; assert mitsuba.variant() is None"
    )
    subprocess.run([sys.executable, "-c", script, str(tmp_path)], check=True)
    assert {p.name for p in tmp_path.iterdir()} == {"albedo.vol", "albedo.png"}
