"""pipeline.fit.passes: what the photometric geometry pass compares."""

import cv2
import numpy as np
import pytest

from pipeline.camera.model import Intrinsics, Pose
from pipeline.fit.loop import FitView
from pipeline.fit.passes import backdrop_views
from pipeline.fit.views import Window
from pipeline.formats.scene_description import Ground
from pipeline.render import scene_xml
from tests.support.scene_descriptions import scene_description

K = Intrinsics(32, 32, 40.0, 40.0, 15.5, 15.5)


@pytest.mark.slow
@pytest.mark.parametrize("gain, table", [(None, False), (2.0, False), (None, True)])
def test_outside_its_mask_and_off_the_table_a_photo_is_the_scenes_own_backdrop(mi, tmp_path, gain, table):
    # A black square filling the view under a sky of 0.4; the photo (0.9 everywhere, a
    # bright cloth behind the specimen) masks only the left half as specimen. With a
    # table under it (as the scene stage puts one) every ray meets the table first.
    scene = mi.load_dict(
        {
            "type": "scene",
            "environment": {"type": "constant", "id": "environment", "radiance": {"type": "rgb", "value": 0.4}},
            "specimen": {
                "type": "rectangle",
                "id": "specimen",
                "bsdf": {"type": "diffuse", "id": "specimen_bsdf", "reflectance": {"type": "rgb", "value": 0.0}},
            },
        }
    )
    pose = Pose.look_at([0.0, 0.0, 3.0], [0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0])
    sensor = scene_xml.load_sensor(scene_xml.sensor_properties(K, pose, 4, 0.01))
    mask = np.zeros((K.height, K.width), np.uint8)
    mask[:, :16] = 255
    cv2.imwrite(str(tmp_path / "mask.png"), mask)
    photo = np.full((K.height, K.width, 3), 0.9, np.float32)
    measured = None if gain is None else np.full(3, gain, np.float32)
    view = FitView("photo", scene, sensor, photo, np.zeros((K.height, K.width), np.float32), gain=measured)
    window = Window(1.0, 0, 0, K.width, K.height, (K.height, K.width))

    description = scene_description(ground=Ground(radius=10.0, albedo=[0.5] * 3) if table else None)
    (compared,) = backdrop_views(
        [(view, window)], {"photo": tmp_path / "mask.png"}, {"photo": (K, pose)}, description, 4
    )
    np.testing.assert_allclose(compared.reference[:, :16], 0.9)
    # the specimen covers the right half too, but the backdrop is the sky behind it
    np.testing.assert_allclose(compared.reference[:, 16:], 0.9 if table else 0.4 * (gain or 1.0), rtol=1e-5)
    np.testing.assert_array_equal(compared.weight, 1.0)
