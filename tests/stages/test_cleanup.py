"""Stage cleanup on meshes with the faults a hull or Poisson surface brings: a hole, a
floating speck, too many faces."""

import json
import logging

import numpy as np
import pytest
import trimesh

from pipeline.core.stage import StageInputs
from stages.cleanup import Config, main


def _run(mesh: trimesh.Trimesh, tmp_path, conf: Config) -> tuple[trimesh.Trimesh, dict]:
    source = tmp_path / "in.ply"
    mesh.export(source)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    inputs = StageInputs(capture_dir=tmp_path, files=(), upstream={"mesh": {"mesh": source}}, shared={})
    result = main(conf, inputs, out_dir)
    assert set(result.outputs) == {"mesh", "report"}
    return trimesh.load(result.outputs["mesh"], force="mesh"), json.loads(result.outputs["report"].read_text())


def test_a_holed_sphere_with_a_speck_comes_out_closed_in_one_piece(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    keep = np.ones(len(sphere.faces), bool)
    keep[np.argsort(sphere.triangles_center[:, 2])[-6:]] = False  # a small hole at the top
    holed = trimesh.Trimesh(sphere.vertices, sphere.faces[keep], process=False)
    speck = trimesh.creation.icosphere(subdivisions=1, radius=0.001)
    speck.apply_translation([0.2, 0, 0])
    mesh, report = _run(trimesh.util.concatenate([holed, speck]), tmp_path, Config())
    assert not report["before"]["watertight"] and report["before"]["components"] == 2
    assert report["after"]["watertight"] and report["after"]["components"] == 1 and report["after"]["genus"] == 0
    assert mesh.is_watertight
    assert mesh.bounds[1][0] < 0.06  # the speck is gone
    np.testing.assert_allclose(mesh.volume, sphere.volume, rtol=0.05)


@pytest.mark.parametrize("fraction", [1.0, 0.9])
def test_the_largest_component_is_kept_whatever_the_fraction(tmp_path, fraction):
    """Two spheres apart: neither's box spans the whole mesh's, so the filter alone would
    remove both and leave nothing to clean."""
    big = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    small = trimesh.creation.icosphere(subdivisions=3, radius=0.03)
    small.apply_translation([0.2, 0, 0])
    conf = Config(min_component_fraction=fraction, remesh_edge_fraction=0.0, smoothing_steps=0)
    mesh, report = _run(trimesh.util.concatenate([big, small]), tmp_path, conf)
    assert report["after"]["components"] == 1 and mesh.bounds[1][0] < 0.06
    np.testing.assert_allclose(mesh.volume, big.volume, rtol=0.02)


def test_a_hole_larger_than_allowed_stays_open_and_is_reported(tmp_path, caplog):
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    keep = sphere.triangles_center[:, 2] < 0.03  # the whole cap cut off
    pipeline_logger = logging.getLogger("pipeline")  # the CLI's tests stop it propagating
    pipeline_logger.addHandler(caplog.handler)
    try:
        mesh, report = _run(
            trimesh.Trimesh(sphere.vertices, sphere.faces[keep], process=False), tmp_path, Config(max_hole_edges=10)
        )
    finally:
        pipeline_logger.removeHandler(caplog.handler)
    assert not report["after"]["watertight"] and report["after"]["boundary_edges"] > 10
    assert "cleanup.max_hole_edges" in caplog.text


@pytest.mark.parametrize("target", [500, 3000])
def test_decimation_reaches_the_target_face_count(tmp_path, target):
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.05)  # 20480 faces
    mesh, report = _run(sphere, tmp_path, Config(target_faces=target))
    assert report["before"]["faces"] == 20480
    assert 0.8 * target <= report["after"]["faces"] <= target
