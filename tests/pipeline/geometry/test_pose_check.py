"""sfm's check of SfM's poses against the silhouettes (the whole stage runs in
test_geometry on the sample bird)."""

from pipeline.camera.model import Pose
from pipeline.geometry.pose_check import silhouette_check
from tests.support.sphere_views import sphere_views

MIN_IOU, RESOLUTION = 0.2, 64
"""The sfm stage's defaults."""


def test_several_wrong_poses_are_all_found():
    """Two photos posed looking past the specimen (SfM once posed two of
    bird_volumetric's 164 and 42 degrees off) carve the hull that lets one photo
    disagree down to a sliver no photo matches, so every photo would fail against
    it; the consensus hull finds just those two."""
    views = sphere_views(10)
    names = [f"view_{i}" for i in range(len(views))]
    poses = {n: v.pose for n, v in zip(names, views)}
    poses["view_2"] = Pose.look_at(poses["view_2"].center, [0.0, 0.0, 0.25])
    poses["view_7"] = Pose.look_at(poses["view_7"].center, [0.0, 0.0, -0.25])
    scores, off = silhouette_check(
        poses,
        {n: v.intrinsics for n, v in zip(names, views)},
        {n: v.mask for n, v in zip(names, views)},
        MIN_IOU,
        RESOLUTION,
    )
    assert off == ["view_2", "view_7"], scores
    assert min(scores[n] for n in names if n not in off) > 0.6, scores


def test_right_poses_all_pass():
    views = sphere_views(10)
    names = [f"view_{i}" for i in range(len(views))]
    scores, off = silhouette_check(
        {n: v.pose for n, v in zip(names, views)},
        {n: v.intrinsics for n, v in zip(names, views)},
        {n: v.mask for n, v in zip(names, views)},
        MIN_IOU,
        RESOLUTION,
    )
    assert off == [] and min(scores.values()) > 0.6, scores
