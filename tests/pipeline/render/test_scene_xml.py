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
