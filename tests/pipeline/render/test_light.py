"""pipeline.render.light: the estimated light's layout in Mitsuba, its scene files, its
lobe turned into a softbox and the irradiance it casts."""

import numpy as np
import pytest
import trimesh

from pipeline.camera.model import Intrinsics, Pose
from pipeline.fit.variables import MaterialVariables
from pipeline.formats.scene_folder import SPECIMEN_XML
from pipeline.render import capture_scene, light, scene_xml
from pipeline.render.parameters import FitParameter

K_SMALL = Intrinsics(24, 24, 30.0, 30.0, 11.5, 11.5)


def _scene_with_map(mi, folder, environment):
    mi.Bitmap(environment.astype(np.float32)).write(str(folder / light.ENVIRONMENT_FILE))
    root = scene_xml.new_scene()
    scene_xml.plugin(root, "emitter", {"type": "envmap", "id": "environment", "filename": light.ENVIRONMENT_FILE})
    return mi.load_file(str(scene_xml.write(root, folder / "scene.xml")))


def test_the_layout_spreads_the_texels_as_mitsuba_pads_them(mi, tmp_path):
    environment = np.random.default_rng(0).uniform(0.1, 2.0, (8, 16, 3)).astype(np.float32)
    data = np.array(mi.traverse(_scene_with_map(mi, tmp_path, environment))["environment.data"])
    layout = light.envmap_layout(8, 16)
    np.testing.assert_allclose(data.ravel()[list(layout.take)].reshape(layout.shape), environment, rtol=1e-6)
    np.testing.assert_allclose(environment.ravel()[list(layout.give)], data.ravel(), rtol=1e-6)


UP = light.Surface(np.array([[0.0, 0.0, 1.0]]), np.ones(1))
"""The board, where the scene stage measures a light's level when the photos show it."""


def test_the_light_keeps_its_level_on_the_measured_surface_and_its_padding_while_it_is_stepped(mi, tmp_path):
    """The scale and colour of an estimated light are fixed (they trade off against the
    albedo): its irradiance on the board stays the measured one, whatever the texels
    below the board do; the wrapped columns stay copies of the texels they repeat."""
    level = np.array([0.2, 0.5, 1.0])
    start = light.start("envmap", "world", level, 16)
    scene = _scene_with_map(mi, tmp_path, start.environment)
    (parameter,) = light.parameters(start, 0.0, UP)
    variables = MaterialVariables([parameter], {id(scene): mi.traverse(scene)}, [])
    variables.register(1.0)
    gradient = np.random.default_rng(1).normal(size=(8, 16, 3)).astype(np.float32)
    gradient[4:] = -5.0  # below the horizon: brighter and brighter
    import drjit as dr

    for _ in range(5):
        dr.set_grad(variables.optimizer[parameter.name], mi.TensorXf(gradient))
        variables.optimizer.step()
        variables.apply(id(scene))
    fitted = variables.snapshot()[parameter.name]
    assert np.ptp(fitted) > 0.01  # it moved
    assert np.all(fitted[5:] > 1.2 * level)  # the lower texels rose without lowering the rest
    measured = light.EstimatedLight("envmap", "world", fitted.astype(np.float32))
    on_board = [light.irradiance(lit, UP.normals, np.zeros(3)) for lit in (measured, start)]
    np.testing.assert_allclose(*on_board, rtol=1e-4)
    data = np.array(mi.traverse(scene)["environment.data"])
    np.testing.assert_allclose(data[:, 0], data[:, -2], rtol=1e-5)
    np.testing.assert_allclose(data[:, -1], data[:, 1], rtol=1e-5)
    np.testing.assert_allclose(data[:, 1:-1], fitted, rtol=1e-4)


def test_with_the_board_in_the_loss_the_light_level_is_the_fits(mi, tmp_path):
    """No surface to hold the level on (fit_material counts the board's print instead):
    a gradient that asks for more light everywhere raises the whole map."""
    level = np.array([0.2, 0.5, 1.0])
    start = light.start("envmap", "world", level, 16)
    scene = _scene_with_map(mi, tmp_path, start.environment)
    (parameter,) = light.parameters(start, 0.0, None)
    assert parameter.mean_weights is None
    variables = MaterialVariables([parameter], {id(scene): mi.traverse(scene)}, [])
    variables.register(1.0)
    import drjit as dr

    for _ in range(5):
        dr.set_grad(variables.optimizer[parameter.name], mi.TensorXf(np.full((8, 16, 3), -1.0, np.float32)))
        variables.optimizer.step()
        variables.apply(id(scene))
    fitted = light.EstimatedLight("envmap", "world", variables.snapshot()[parameter.name].astype(np.float32))
    raised = light.irradiance(fitted, UP.normals, np.zeros(3)) / light.irradiance(start, UP.normals, np.zeros(3))
    assert np.all(raised > 1.2)


@pytest.mark.parametrize("frame", ["world", "camera"])
def test_level_weights_are_each_texels_share_of_the_measured_surfaces_irradiance(frame):
    """Weighted, a map's mean is its irradiance on the surface over a uniform map's: on the board, only
    what comes from above counts; on a specimen seen from every side, the whole sphere."""
    rng = np.random.default_rng(3)
    environment = rng.uniform(0.1, 3.0, (16, 32, 3))
    lit = light.EstimatedLight("envmap", frame, environment.astype(np.float32))
    poses = {f"v{a}": Pose.look_at([np.cos(a), np.sin(a), 0.5], [0, 0, 0], up=[0, 0, 1]) for a in (0, 2, 4)}
    board = light.measured_surface("board", None, poses, frame)
    weights = light.level_weights(16, 32, frame, board)
    assert weights.sum() == pytest.approx(1.0)
    white = light.EstimatedLight("envmap", frame, np.ones_like(lit.environment))
    on_board = [light.irradiance(map_, board.normals, np.zeros(3)) for map_ in (lit, white)]
    expected = np.mean(on_board[0] / on_board[1], axis=0)
    np.testing.assert_allclose(weights.ravel() @ environment.reshape(-1, 3), expected, rtol=1e-6)
    if frame == "world":
        local, _ = light.directions(16, 32)
        below = (local @ light.map_to_frame("world").T)[..., 2] < -1e-6
        assert weights[below].sum() == 0 and weights[~below].min() >= 0
    # A sphere seen from three sides: its faces turned towards each camera, by their
    # projected area; a uniform map keeps its radiance as its weighted mean.
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    specimen = light.measured_surface("specimen (grey)", sphere, poses, frame, faces=500)
    assert len(specimen.normals) == len(specimen.weights) > 500
    weights = light.level_weights(16, 32, frame, specimen)
    assert weights.ravel() @ np.full(16 * 32, 0.7) == pytest.approx(0.7)
    local, _ = light.directions(16, 32)
    world_up = np.array([0, 0, 1.0]) if frame == "world" else poses["v0"].R @ [0, 0, 1.0]
    up = (local @ light.map_to_frame(frame).T) @ world_up
    assert weights[up > 0.5].sum() > 2 * weights[up < -0.5].sum() > 0  # seen from above, lit from all round


def test_a_uniform_map_and_a_constant_light_give_pi_times_their_radiance_on_any_surface():
    normals = np.array([[0, 0, 1.0], [1, 0, 0], [0, -1, 0], [0.6, 0, -0.8]])
    for model, width in (("constant", 1), ("envmap", 64)):
        uniform = light.start(model, "world", np.array([0.5, 1.0, 2.0]), width)
        np.testing.assert_allclose(
            light.irradiance(uniform, normals, np.zeros(3)), np.pi * np.array([[0.5, 1.0, 2.0]] * 4), rtol=0.01
        )


@pytest.mark.parametrize("frame", ["world", "camera"])
def test_the_brightest_lobe_becomes_a_softbox_in_its_direction(frame):
    start = light.start("envmap", frame, np.array([0.1, 0.1, 0.1]), 32)
    local, _ = light.directions(16, 32)
    towards = np.array([0.3, 0.4, 0.8]) / np.linalg.norm([0.3, 0.4, 0.8])  # in the light's frame
    in_map = light.map_to_frame(frame).T @ towards
    lobe = local @ in_map > np.cos(np.radians(12))
    environment = start.environment.copy()
    environment[lobe] = 5.0
    lit = light.with_area(light.EstimatedLight("envmap", frame, environment), np.array([0, 0, 0.1]), 2.0)
    position = np.array(lit.area.position) - [0, 0, 0.1]
    assert np.degrees(np.arccos(position @ towards / np.linalg.norm(position))) < 5
    assert np.linalg.norm(position) == pytest.approx(2.0)
    # The softbox subtends about the lobe's solid angle and carries its radiance.
    assert lit.area.size / 2.0 == pytest.approx(np.sqrt(2 * np.pi * (1 - np.cos(np.radians(12)))), rel=0.3)
    np.testing.assert_allclose(lit.area.radiance, [4.9] * 3, rtol=0.05)
    np.testing.assert_allclose(lit.environment, 0.1)
    # Its irradiance on a surface facing it is the lobe's, within the map's discretisation.
    facing = towards[None]
    np.testing.assert_allclose(
        light.irradiance(lit, facing, np.array([0, 0, 0.1])),
        light.irradiance(light.EstimatedLight("envmap", frame, environment), facing, np.zeros(3)),
        rtol=0.15,
    )


def test_written_lights_replace_the_old_ones_and_load(mi, tmp_path):
    pose = Pose.look_at([0.5, 0.0, 0.3], [0, 0, 0], up=[0, 0, 1])
    for name in ("scene.xml", "view-a.xml"):
        root = scene_xml.new_scene()
        scene_xml.plugin(root, "emitter", {"type": "constant", "id": "environment", "radiance": (0.5, 0.5, 0.5)})
        scene_xml.area_light(root, "softbox", [0.4, 0.4, 0.6], [0, 0, 0], [0, 0, 1], 0.3, (8.0, 8.0, 8.0))
        scene_xml.write(root, tmp_path / name)
    view_files = {"a.jpg": "view-a.xml"}
    envmap = light.start("envmap", "world", np.array([0.3, 0.3, 0.3]), 16)
    light.write(envmap, tmp_path, view_files, {"a.jpg": pose})
    for name in ("scene.xml", "view-a.xml"):
        keys = set(mi.traverse(mi.load_file(str(tmp_path / name))).keys())
        assert "environment.data" in keys and not any(k.startswith("softbox") for k in keys)
    lit = light.with_area(envmap, np.zeros(3), 1.0)
    light.write(lit, tmp_path, view_files, {"a.jpg": pose})
    keys = set(mi.traverse(mi.load_file(str(tmp_path / "view-a.xml"))).keys())
    assert {"environment.data", "softbox.emitter.radiance.value"} <= keys
    assert isinstance(light.parameters(lit, 0.01, UP)[1], FitParameter)


def test_texel_directions_are_mitsubas(mi, tmp_path):
    """Where Mitsuba's envmap, placed as the scene files place it, shows each texel."""
    from pipeline.render.capture_scene import environment_to_world

    environment = np.random.default_rng(2).uniform(0.1, 2.0, (8, 16, 3)).astype(np.float32)
    mi.Bitmap(environment).write(str(tmp_path / "map.exr"))
    to_world = environment_to_world("world", Pose(np.eye(3), np.zeros(3)))
    emitter = mi.load_dict(
        {"type": "envmap", "filename": str(tmp_path / "map.exr"), "to_world": mi.ScalarTransform4f(to_world)}
    )
    local, _ = light.directions(8, 16)
    world = local.reshape(-1, 3) @ light.map_to_frame("world").T
    interaction = mi.SurfaceInteraction3f()
    interaction.wi = mi.Vector3f(-world.T)
    seen = np.array(emitter.eval(interaction)).T.reshape(environment.shape)
    # Off the poles, where a row's texels all share one direction.
    np.testing.assert_allclose(seen[1:-1], environment[1:-1], rtol=1e-3)


def test_the_softbox_starts_round_the_specimens_box_centre_in_the_lights_frame():
    """with_area's sphere: the centre of the specimen's bounding box and area_distance
    radii; for a light riding with the camera, the centre in the first photo's camera
    coordinates (photos sorted by name)."""
    from pipeline.core.sections import LightSection

    vertices = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 4.0, 0.0], [2.0, 4.0, 2.0]])
    poses = {"b.jpg": Pose(np.eye(3), np.zeros(3)), "a.jpg": Pose(np.eye(3), np.array([0.0, 0.0, 5.0]))}
    centre, distance = light.specimen_sphere(vertices, LightSection(frame="world", area_distance=3.0), poses)
    np.testing.assert_allclose(centre, [1.0, 2.0, 1.0])
    assert distance == pytest.approx(3.0 * np.sqrt(6.0))
    centre, _ = light.specimen_sphere(vertices, LightSection(frame="camera", area_distance=3.0), poses)
    np.testing.assert_allclose(centre, [1.0, 2.0, 6.0])


def test_a_raised_level_in_the_files_renders_as_the_raised_scenes_and_keeps_the_tables_look(mi, tmp_path):
    """rescale_files writes what rescale_scenes does in memory: the map and the softbox
    times the factor, the table's albedo divided by it (the photos fix its product with
    the light), so the view renders the same from the files as from the scaled scene."""
    pose = Pose.look_at([0.5, 0.0, 0.3], [0, 0, 0], up=[0, 0, 1])
    specimen = scene_xml.new_scene()
    disk = scene_xml.plugin(specimen, "shape", {"type": "disk", "id": "ground"})
    scene_xml.plugin(disk, "bsdf", {"type": "diffuse", "id": capture_scene.GROUND_BSDF, "reflectance": (0.6, 0.5, 0.4)})
    scene_xml.write(specimen, tmp_path / SPECIMEN_XML)
    for name in ("scene.xml", "view-a.xml"):
        root = scene_xml.new_scene()
        scene_xml.include(root, SPECIMEN_XML)
        scene_xml.write(root, tmp_path / name)
    view_files = {"a.jpg": "view-a.xml"}
    lit = light.with_area(light.start("envmap", "world", np.array([0.3, 0.2, 0.1]), 16), np.zeros(3), 1.0)
    light.write(lit, tmp_path, view_files, {"a.jpg": pose})
    sensor = scene_xml.load_sensor(scene_xml.sensor_properties(K_SMALL, pose, 16, 0.01))
    scaled = mi.load_file(str(tmp_path / "view-a.xml"))
    light.rescale_scenes([scaled, scaled], 2.5)  # a scene listed twice is scaled once
    summary = light.rescale_files(tmp_path, lit.summary(), 2.5, view_files, {"a.jpg": pose})
    assert summary["area"]["radiance"] == pytest.approx([2.5 * v for v in lit.area.radiance])
    assert summary["environment_mean"] == pytest.approx([0.75, 0.5, 0.25], rel=1e-3)  # a half-float map
    written = mi.load_file(str(tmp_path / "view-a.xml"))
    assert np.allclose(np.ravel(mi.traverse(written)["ground.bsdf.reflectance.value"]), [0.24, 0.2, 0.16], rtol=1e-5)
    path = mi.load_dict({"type": "path", "max_depth": 3})
    in_memory = np.array(mi.render(scaled, sensor=sensor, integrator=path, spp=16, seed=1))
    from_files = np.array(mi.render(written, sensor=sensor, integrator=path, spp=16, seed=1))
    assert from_files.mean() > 0.05  # the table and the sky are in view
    assert np.abs(in_memory - from_files).max() < 1e-3 * from_files.max()  # the map is half floats


@pytest.mark.parametrize("value, message", [(-0.5, r"1 pixel\(s\) of .* are negative"), (np.nan, "NaN or infinite")])
def test_an_environment_map_that_is_no_radiance_is_refused(tmp_path, value, message):
    from pipeline.core.errors import PipelineError
    from pipeline.imaging.photo_io import write_image

    pixels = np.full((8, 16, 3), 0.5, np.float32)
    pixels[2, 3] = value
    path = write_image(tmp_path / "room.exr", pixels)
    with pytest.raises(PipelineError, match=message):
        light.check_environment_map(path, "light.environment_map = 'room.exr'")
    light.check_environment_map(write_image(tmp_path / "fine.exr", np.abs(np.nan_to_num(pixels))), "fine")
