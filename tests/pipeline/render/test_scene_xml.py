import numpy as np
import pytest

from pipeline.camera.model import Intrinsics, Pose
from pipeline.render import scene_xml

AWKWARD_NAMES = ["$HOME", "view--03", "a$b.c", "<&'\">", "photo - -", "-"]


@pytest.mark.slow
def test_names_users_choose_make_scene_files_mitsuba_loads(mi, tmp_path):
    root = scene_xml.new_scene()
    camera, pose = Intrinsics(32, 24, 30.0, 30.0, 15.5, 11.5), Pose(np.eye(3), np.array([0.0, 0.0, 2.0]))
    for name in AWKWARD_NAMES:
        scene_xml.sensor(root, name, scene_xml.sensor_properties(camera, pose, 4, 0.01))
    scene_xml.plugin(root, "shape", {"type": "sphere", "id": "specimen"})
    path = scene_xml.write(root, tmp_path / "scene.xml", "photos " + " ".join(AWKWARD_NAMES))
    scene = mi.load_file(str(path))
    ids = [sensor.id() for sensor in scene.sensors()]
    assert len(ids) == len(AWKWARD_NAMES)
    assert all("$" not in i and "." not in i for i in ids)


@pytest.mark.slow
def test_sensor_pixels_average_their_own_square(mi, tmp_path):
    # An emitter's edge on the boundary between columns 15 and 16: averaged down, a photo
    # keeps it there, so a pixel on either side must not take any of the other side's
    # light (Mitsuba's default Gaussian filter gives both columns a share).
    root = scene_xml.new_scene()
    camera, pose = Intrinsics(32, 24, 30.0, 30.0, 15.5, 11.5), Pose(np.eye(3), np.array([0.0, 0.0, 2.0]))
    scene_xml.sensor(root, "photo", scene_xml.sensor_properties(camera, pose, 16, 0.01))
    scene_xml.plugin(root, "integrator", {"type": "direct"})
    half_plane = {
        "type": "rectangle",
        "id": "edge",
        "flip_normals": True,
        "emitter": {"type": "area", "radiance": [1.0] * 3},
    }
    left_of_origin = np.array([[1.0, 0, 0, -1], [0, 5, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    scene_xml.transform_matrix(scene_xml.plugin(root, "shape", half_plane), left_of_origin)
    image = np.asarray(mi.render(mi.load_file(str(scene_xml.write(root, tmp_path / "edge.xml")))))[..., 0]
    assert image[:, :16].min() == pytest.approx(1.0, abs=1e-6) or image[:, 16:].min() == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(np.sort(np.unique(image.round(6))), [0.0, 1.0])
