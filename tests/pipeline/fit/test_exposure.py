"""pipeline.fit.exposure: a held-out photo's exposure read off the table it shares with
the training photos, whatever the fitted scene makes of the table."""

import cv2
import numpy as np
import pytest

from pipeline.fit.exposure import table_gains
from pipeline.fit.views import CapturePhotos
from pipeline.formats.scene_description import Ground
from pipeline.render import scene_xml
from tests.support.scene_descriptions import scene_description
from tests.support.sphere_views import RADIUS, K, ring_poses, sphere_mask

WHITE_BALANCE = np.array([1.0, 0.9, 1.1])
"""Every photo's channels scaled so: the gains are RGB."""


def _table_photos(folder, exposures: dict[str, float]):
    """A grey sphere on a table disk with a checker of reflectance 0.2 and 0.8 under a sky
    and a sun (the sphere shades and shadows the table), seen by ring cameras; each photo
    the render times its exposure and WHITE_BALANCE. Returns the description's ground and
    (CapturePhotos)."""
    import mitsuba as mi

    from pipeline.imaging.photo_io import write_image

    checker = {
        "type": "checkerboard",
        "color0": {"type": "rgb", "value": 0.2},
        "color1": {"type": "rgb", "value": 0.8},
        "to_uv": mi.ScalarTransform4f().scale([8, 8, 1]),
    }
    truth = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": 3},
            "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.3, 0.28, 0.25]}},
            "sun": {"type": "directional", "direction": [-0.3, -0.2, -1.0], "irradiance": 1.2},
            "specimen": {"type": "sphere", "radius": RADIUS, "bsdf": {"type": "diffuse"}},
            "ground": {
                "type": "disk",
                "to_world": mi.ScalarTransform4f().scale([0.5, 0.5, 1.0]),
                "bsdf": {"type": "diffuse", "reflectance": checker},
            },
        }
    )
    cameras, linear, masks = {}, {}, {}
    for (name, exposure), pose in zip(sorted(exposures.items()), ring_poses(len(exposures), 0.3, 30.0, 45.0)):
        sensor = scene_xml.load_sensor(scene_xml.sensor_properties(K, pose, 64, 0.01))
        photo = exposure * WHITE_BALANCE * np.asarray(mi.render(truth, sensor=sensor, spp=64, seed=3), np.float32)
        cameras[name], linear[name] = (K, pose), write_image(folder / f"{name}.exr", photo)
        masks[name] = folder / f"{name}.png"
        cv2.imwrite(str(masks[name]), sphere_mask(pose).astype(np.uint8) * 255)
    return scene_description(ground=Ground(radius=0.5, albedo=[0.5] * 3)), CapturePhotos(cameras, linear, masks)


@pytest.mark.slow
def test_a_held_out_photos_exposure_is_read_off_the_table_it_shares(mi, tmp_path):
    """Eight photos round a sphere at exposures from 0.5 to 1.4, one held out at 0.45: the
    table's pixels, compared point by point with the nearest training photos' (the sphere
    hides different table in each), give its RGB gain, or one gain, within 3 %, and each
    training photo's from the others as well. Nothing is rendered: the checker, the shadow
    and the sphere's light on the table cancel, which a render of a plain table would not."""
    exposures = {"a": 1.0, "b": 1.25, "c": 0.8, "d": 1.4, "e": 0.5, "f": 1.1, "g": 0.7, "held": 0.45}
    description, photos = _table_photos(tmp_path, exposures)
    fitted = {n: list(e * WHITE_BALANCE) for n, e in exposures.items() if n != "held"}
    measured = table_gains(description, photos, fitted, ["held"], 3)
    np.testing.assert_allclose(measured["gains"]["held"], 0.45 * WHITE_BALANCE, rtol=0.03)
    error = measured["training_error"]
    assert error["photos"] == 7 and error["median"] <= error["p90"] <= error["max"] < 0.03
    single = table_gains(description, photos, {n: [np.mean(g)] * 3 for n, g in fitted.items()}, ["held"], 1)
    assert single["gains"]["held"] == pytest.approx([0.45] * 3, rel=0.03)
    # a photo that shows no table (its mask covers the frame) gets no gain; no table in the
    # scene, or no fitted gains: nothing measured
    cv2.imwrite(str(photos.masks["held"]), np.full((K.height, K.width), 255, np.uint8))
    assert "held" not in table_gains(description, photos, fitted, ["held"], 3)["gains"]
    assert table_gains(scene_description(), photos, fitted, ["held"], 3) == {}
    assert table_gains(description, photos, {}, ["held"], 3) == {}
