"""The scorer is proven on outputs built from the ground truth itself."""

import json
import shutil

import numpy as np
import OpenImageIO as oiio
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from pipeline import cli
from pipeline.camera.model import Intrinsics, Pose
from pipeline.formats.cameras import read_cameras, write_cameras
from pipeline.synthetic.score import score_cameras, score_capture, score_mesh, score_texture, true_surface

SIMILARITY = (2.3, Rotation.from_euler("xyz", [20, -35, 60], degrees=True).as_matrix(), np.array([1.0, -2.0, 0.5]))


@pytest.fixture
def capture(tiny_capture, tmp_path):
    """A private copy of the tiny synthetic capture, with an empty output/stages/."""
    copy = tmp_path / "capture"
    shutil.copytree(tiny_capture, copy)
    (copy / "output" / "stages").mkdir(parents=True)
    return copy


def write_exr(path, pixels):
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(pixels.shape[1], pixels.shape[0], 3, oiio.FLOAT))
    out.write_image(pixels.astype(np.float32))
    out.close()


def perfect_outputs(capture, transform=None):
    """Write output/stages/ as a perfect pipeline would, optionally in a similarity-transformed frame."""
    truth, out = capture / "ground_truth", capture / "output" / "stages"
    for stage in ("calibrate", "sfm", "uv", "fit_material", "fit_texture", "fit_geometry"):
        (out / stage).mkdir()
    intrinsics, poses = read_cameras(truth / "cameras.json")
    mesh = trimesh.load(truth / "mesh.ply")
    if transform is not None:
        s, R, t = transform
        # x_new = s R x + t: camera rotation R_cam R^T, centre s R c + t
        poses = {n: Pose(p.R @ R.T, -(p.R @ R.T) @ (s * R @ p.center + t)) for n, p in poses.items()}
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = s * R, t
        mesh.apply_transform(M)
    write_cameras(out / "sfm" / "cameras.json", intrinsics, poses)
    (out / "calibrate" / "intrinsics.json").write_text(json.dumps(intrinsics.to_json()))
    mesh.export(out / "uv" / "mesh.ply")
    material = json.loads((truth / "material.json").read_text())
    params = {k: material[k] for k in ("base_color_mean", "roughness", "spec_trans", "eta")}
    params["base_color"] = params.pop("base_color_mean")
    (out / "fit_material" / "params.json").write_text(json.dumps({"model": material["model"], "params": params}))
    image = np.random.default_rng(0).uniform(0, 1, (8, 8, 3))
    for stage in ("fit_material", "fit_texture", "fit_geometry"):
        (out / stage / "heldout").mkdir()
        write_exr(out / stage / "heldout" / "view_005.render.exr", image)
        write_exr(out / stage / "heldout" / "view_005.reference.exr", image)
    (out / "fit_geometry" / "params.json").write_text(json.dumps({"model": material["model"], "params": params}))


def test_perfect_outputs_score_zero_error(capture):
    perfect_outputs(capture)
    report = score_capture(capture)
    assert report["missing"] == []
    assert report["intrinsics"] == {"focal_error_pct": 0, "principal_point_error_px": 0, "distortion_max_abs_error": 0}
    assert report["cameras"]["registered_fraction"] == 1.0
    assert report["cameras"]["rotation_error_deg_max"] < 1e-4
    assert report["cameras"]["centre_error_pct_max"] < 1e-6
    assert report["mesh"]["chamfer_pct_of_diagonal"] < 1e-6
    assert report["mesh"]["normal_consistency"] > 0.999999
    assert report["mesh"]["shading_normal_error_deg"] < 1e-3
    for part in ("material", "material_fit_geometry"):
        assert all(v == 0 for k, v in report[part].items() if k.endswith("_error")), part
    assert report["heldout"]["psnr_db_mean"] == report["heldout_geometry"]["psnr_db_mean"] == float("inf")


def test_score_is_invariant_to_a_similarity_of_the_whole_reconstruction(capture):
    perfect_outputs(capture, transform=SIMILARITY)
    report = score_capture(capture)
    assert report["cameras"]["rotation_error_deg_max"] < 1e-4
    assert report["cameras"]["centre_error_pct_max"] < 1e-6
    assert report["mesh"]["chamfer_pct_of_diagonal"] < 1e-3  # float32 PLY round-off at ~2 m offsets


def ring_of_poses(count=30):
    return {
        f"v{i:02d}": Pose.look_at([np.cos(a) * 0.4, np.sin(a) * 0.4, 0.2], [0, 0, 0.05])
        for i, a in enumerate(np.linspace(0, 2 * np.pi, count, endpoint=False))
    }


def test_rotated_camera_gives_its_rotation_error():
    truth = ring_of_poses()
    estimate = dict(truth)
    tilt = Rotation.from_rotvec(np.radians(2.0) * np.array([0.6, 0.0, 0.8])).as_matrix()
    # rotate camera v07 about its own centre: the centre stays, only R changes
    pose = truth["v07"]
    estimate["v07"] = Pose(tilt @ pose.R, -(tilt @ pose.R) @ pose.center)
    metrics, _ = score_cameras(estimate, truth)
    assert metrics["per_image"]["v07"]["rotation_deg"] == pytest.approx(2.0, abs=1e-6)
    assert metrics["per_image"]["v03"]["rotation_deg"] < 1e-6
    assert metrics["centre_error_pct_max"] < 1e-6


def test_moved_camera_centre_gives_its_centre_error():
    truth = ring_of_poses()
    estimate = dict(truth)
    scene_size = np.linalg.norm(np.ptp(np.array([p.center for p in truth.values()]), axis=0))
    moved = truth["v10"].center + np.array([0.0, 0.0, 0.02 * scene_size])
    estimate["v10"] = Pose(truth["v10"].R, -truth["v10"].R @ moved)
    metrics, _ = score_cameras(estimate, truth)
    # A 7-parameter similarity fit to 30 centres absorbs at most ~7/30 of one outlier.
    moved_error = metrics["per_image"]["v10"]["centre_pct"]
    assert 2.0 * (1 - 7 / 30) <= moved_error <= 2.0
    others = [m["centre_pct"] for n, m in metrics["per_image"].items() if n != "v10"]
    assert max(others) < moved_error / 5


def test_missing_cameras_are_counted():
    truth = ring_of_poses()
    estimate = {n: p for n, p in truth.items() if n not in ("v00", "v01")}
    metrics, _ = score_cameras(estimate, truth)
    assert metrics["registered_fraction"] == pytest.approx(28 / 30)
    assert metrics["unregistered"] == ["v00", "v01"]


def test_scaled_mesh_gives_the_expected_chamfer_distance():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    bigger = sphere.copy()
    bigger.apply_scale(1.05)
    metrics = score_mesh(bigger, sphere)
    diagonal = np.linalg.norm(sphere.bounds[1] - sphere.bounds[0])
    assert metrics["chamfer_pct_of_diagonal"] == pytest.approx(100 * 0.05 / diagonal, rel=0.03)
    assert metrics["normal_consistency"] > 0.999
    assert metrics["shading_normal_error_deg"] < 0.5


def test_shading_normal_error_is_the_tilt_of_the_vertex_normals():
    """A mesh whose vertex normals are all tilted by 10 degrees (positions exact) scores
    10 degrees, and its Chamfer distance stays zero: the error a fitted material sees."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    tilt = trimesh.transformations.rotation_matrix(np.radians(10.0), [0, 0, 1])[:3, :3]
    tilted = trimesh.Trimesh(
        sphere.vertices, sphere.faces, vertex_normals=sphere.vertex_normals @ tilt.T, process=False
    )
    metrics = score_mesh(tilted, sphere)
    assert metrics["chamfer_pct_of_diagonal"] < 1e-6
    # rotating about z tilts a normal by 10 degrees times its distance from the z axis
    horizontal = np.linalg.norm(sphere.vertex_normals[:, :2], axis=1)
    expected = np.degrees(np.arccos(np.cos(np.radians(10.0)) * horizontal**2 + (1 - horizontal**2)))
    assert metrics["shading_normal_error_deg"] == pytest.approx(expected.mean(), rel=0.05)
    assert metrics["shading_normal_error_deg"] > 5


def test_offset_parameters_give_their_errors(capture):
    perfect_outputs(capture)
    params_file = capture / "output" / "stages" / "fit_material" / "params.json"
    params = json.loads(params_file.read_text())
    params["params"]["roughness"] += 0.1
    params["params"]["base_color"][1] -= 0.04
    params_file.write_text(json.dumps(params))
    report = score_capture(capture)["material"]
    assert report["roughness_abs_error"] == pytest.approx(0.1)
    assert report["base_color_abs_error"] == pytest.approx(0.04)
    assert report["eta_abs_error"] == 0


def test_sigma_t_error_is_relative():
    from pipeline.synthetic.score import score_material

    truth = {"model": "volumetric", "sigma_t": 180.0, "alpha": 0.12}
    errors = score_material({"model": "volumetric", "params": {"sigma_t": 216.0, "alpha": 0.1}}, truth)
    assert errors["sigma_t_rel_error"] == pytest.approx(0.2)
    assert errors["alpha_abs_error"] == pytest.approx(0.02)


def test_heldout_psnr_of_a_known_error(capture):
    perfect_outputs(capture)
    folder = capture / "output" / "stages" / "fit_material" / "heldout"
    reference = np.full((8, 8, 3), 0.5)
    write_exr(folder / "view_005.reference.exr", reference)
    write_exr(folder / "view_005.render.exr", reference + 0.01)  # MSE 1e-4 -> 40 dB
    assert score_capture(capture)["heldout"]["psnr_db_mean"] == pytest.approx(40.0, abs=1e-3)


def test_cli_scores_what_exists_and_lists_what_is_missing(capture, capsys):
    intrinsics, _ = read_cameras(capture / "ground_truth" / "cameras.json")
    wrong = Intrinsics(**{**intrinsics.to_json(), "fx": intrinsics.fx * 1.02, "fy": intrinsics.fy * 1.02})
    (capture / "output" / "stages" / "calibrate").mkdir()
    (capture / "output" / "stages" / "calibrate" / "intrinsics.json").write_text(json.dumps(wrong.to_json()))
    assert cli.main(["score", str(capture)]) == 0
    err = capsys.readouterr().err
    assert "not scored: sfm/cameras.json (sfm has not run)" in err
    report = json.loads((capture / "output" / "score.json").read_text())
    assert report["intrinsics"]["focal_error_pct"] == pytest.approx(2.0)
    assert len(report["missing"]) == 6  # cameras, mesh, params and three heldout folders


def test_cli_refuses_a_capture_without_ground_truth(tmp_path, capsys):
    (tmp_path / "real").mkdir()
    assert cli.main(["score", str(tmp_path / "real")]) == 1
    assert "only synthetic captures" in capsys.readouterr().err


def side_view_uv(sphere: trimesh.Trimesh) -> np.ndarray:
    """UVs of the unit sphere seen from the side: u from x, v from z (0 at the north
    pole); front and back share texels, which suits colours that vary with z only."""
    return np.c_[0.5 + 0.45 * sphere.vertices[:, 0], (1 - sphere.vertices[:, 2]) / 2]


def test_texture_score_reads_rows_from_v_zero_at_the_top():
    from pipeline.imaging.photo_io import srgb_decode, to_uint8

    sphere = trimesh.creation.icosphere(subdivisions=4)
    red, blue = np.array([0.8, 0.1, 0.1]), np.array([0.1, 0.1, 0.8])
    truth = sphere.copy()
    upper = (truth.vertices[:, 2] > 0)[:, None]
    truth.visual.vertex_colors = np.c_[to_uint8(np.where(upper, red, blue)), np.full(len(upper), 255, np.uint8)]
    textured = sphere.copy()
    # v grows downwards from the north pole: the texture's top rows are the upper half
    textured.visual = trimesh.visual.TextureVisuals(uv=side_view_uv(sphere))
    texture = np.zeros((64, 64, 3))
    texture[:32], texture[32:] = red, blue
    texture = srgb_decode(to_uint8(texture) / 255)  # the same 8-bit rounding as the truth
    report = score_texture(textured, texture, np.array([0.45, 0.1, 0.45]), true_surface(truth))
    # only points next to the equator (blended vertex colours) differ
    assert max(report["mean_abs_error"]) < 0.05 < min(report["constant_mean_abs_error"][0::2])
    # the truth baked into the same atlas scores as well as the right texture
    np.testing.assert_allclose(report["bake_mean_abs_error"], report["mean_abs_error"], atol=0.01)
    assert "seen_fraction" not in report  # no views given


def test_texture_score_splits_off_what_no_view_sees(mi):
    """A camera above the north pole sees only the upper half: the texture's wrong
    lower half counts in the whole surface's error, not in the seen surface's."""
    from pipeline.imaging.photo_io import srgb_decode, to_uint8

    sphere = trimesh.creation.icosphere(subdivisions=4)
    truth = sphere.copy()
    truth.visual.vertex_colors = np.c_[
        to_uint8(np.full((len(sphere.vertices), 3), 0.8)), np.full(len(sphere.vertices), 255, np.uint8)
    ]
    textured = sphere.copy()
    textured.visual = trimesh.visual.TextureVisuals(uv=side_view_uv(sphere))
    texture = np.full((64, 64, 3), srgb_decode(np.array([to_uint8(np.array([0.8]))[0] / 255]))[0])
    texture[40:] = 0.0  # wrong below z = -0.25
    looking_down = Pose(R=np.diag([1.0, -1.0, -1.0]), t=np.array([0.0, 0.0, 5.0]))
    camera = Intrinsics(width=200, height=200, fx=300, fy=300, cx=100, cy=100)
    report = score_texture(textured, texture, np.array([0.5, 0.5, 0.5]), true_surface(truth, [(camera, looking_down)]))
    assert 0.4 < report["seen_fraction"] < 0.55  # the upper half, less its grazing rim
    assert max(report["seen_mean_abs_error"]) < 0.01 < min(report["mean_abs_error"])
    # Two more views from above and one from below: the lower half is seen, by one
    # view of four, and counts in the seen error but not in the well-seen one (a third).
    looking_up = Pose(R=np.diag([1.0, 1.0, 1.0]), t=np.array([0.0, 0.0, 5.0]))
    above = [(camera, Pose(R=looking_down.R, t=looking_down.t + [dx, 0.0, 0.0])) for dx in (-0.2, 0.0, 0.2)]
    report = score_texture(
        textured, texture, np.array([0.5, 0.5, 0.5]), true_surface(truth, [*above, (camera, looking_up)])
    )
    assert report["well_seen_views"] == 2 and report["seen_fraction"] > 0.75  # both halves, less their rims
    assert 0.4 < report["well_seen_fraction"] < 0.55
    assert max(report["well_seen_mean_abs_error"]) < 0.01 < min(report["seen_mean_abs_error"])


def test_an_estimated_light_in_another_frame_scores_its_irradiance_error(tmp_path):
    """The true rig (a room map wider than the scorer filters to, and a softbox) written
    as the scorer reads it; the estimate is the same light in a frame turned 90 degrees
    about the vertical, scaled and moved: exact, it scores 0; 10 % too bright, 10 %."""
    from dataclasses import asdict

    from pipeline.camera.model import Similarity
    from pipeline.core.sections import LightSection
    from pipeline.render import light
    from pipeline.synthetic.score import TRUE_MAP_WIDTH, score_light

    truth = tmp_path / "capture" / "ground_truth"
    truth.mkdir(parents=True)
    trimesh.creation.icosphere(subdivisions=3, radius=0.05).export(truth / "mesh.ply")
    room = np.full((256, 512, 3), (0.2, 0.25, 0.3), np.float32)
    room[40:90, 100:180] = (4.0, 3.5, 3.0)  # a window above the horizon, off to one side
    write_exr(truth / "room.exr", room)
    section = LightSection(
        model="given",
        environment_map="ground_truth/room.exr",
        area_position=(0.3, 0.2, 0.4),
        area_target=(0.0, 0.0, 0.0),
        area_size=0.2,
        area_radiance=(5.0, 4.0, 3.0),
    )
    (truth / "light.json").write_text(json.dumps(asdict(section)))

    # x_truth = s R x_est + t; turning about the vertical (the map's y) shifts columns.
    scale, rotation, shift = 2.0, Rotation.from_euler("z", 90, degrees=True).as_matrix(), np.array([0.1, -0.2, 0.0])
    filtered = room.reshape(64, 4, TRUE_MAP_WIDTH, 4, 3).mean(axis=(1, 3))
    local, _ = light.directions(64, TRUE_MAP_WIDTH)
    seen = (local @ light.map_to_frame("world").T) @ rotation.T @ light.map_to_frame("world")  # truth's map frame
    columns = np.round((np.arctan2(seen[..., 0], -seen[..., 2]) / (2 * np.pi)) % 1 * TRUE_MAP_WIDTH - 0.5)
    estimate_map = filtered[np.arange(64)[:, None], columns.astype(int) % TRUE_MAP_WIDTH]

    def in_estimate_frame(point):
        return tuple(rotation.T @ (np.asarray(point) - shift) / scale)

    similarity = Similarity(scale, rotation, shift)
    for brightness in (1.0, 1.1):
        fitted = tmp_path / f"fitted-{brightness}"
        fitted.mkdir()
        estimate = light.EstimatedLight(
            "envmap+area",
            "world",
            estimate_map * brightness,
            light.AreaLight(
                in_estimate_frame(section.area_position),
                in_estimate_frame(section.area_target),
                section.area_size / scale,
                tuple(brightness * np.array(section.area_radiance)),
            ),
        )
        write_exr(fitted / light.ENVIRONMENT_FILE, estimate.environment)
        scored = score_light(tmp_path / "capture", estimate.summary(), fitted, similarity)
        assert scored["irradiance_rel_error"] == pytest.approx(brightness - 1, abs=0.01), scored
        np.testing.assert_allclose(scored["irradiance_ratio"], brightness, rtol=0.01)


def test_a_held_out_photo_exposed_darker_loses_its_gain_in_the_gain_matched_psnr(tmp_path):
    from pipeline.formats.scene_folder import heldout_files
    from pipeline.imaging.photo_io import write_image
    from pipeline.synthetic.score import score_heldout

    rng = np.random.default_rng(0)
    reference = rng.uniform(0.2, 0.8, (32, 32, 3)).astype(np.float32)
    render_path, reference_path, _ = heldout_files(tmp_path, "photo.jpg")
    noise = rng.normal(0, 0.01, reference.shape).astype(np.float32)
    write_image(render_path, reference / np.array([0.6, 0.6, 0.55], np.float32) + noise)  # the photo 40 % darker
    write_image(reference_path, reference)
    scores = score_heldout(tmp_path)
    assert scores["psnr_db_mean"] < 12 and scores["psnr_gain_db_mean"] > 38
