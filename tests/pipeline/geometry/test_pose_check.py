"""sfm's check of SfM's poses against the silhouettes (the whole stage runs in
test_geometry on the sample bird)."""

import numpy as np

from pipeline.camera.model import Pose
from pipeline.geometry.pose_check import silhouette_check
from tests.support.sphere_views import sphere_views

MIN_IOU, RESOLUTION, MIN_AGREEMENT = 0.2, 64, 0.5
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
        MIN_AGREEMENT,
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
        MIN_AGREEMENT,
    )
    assert off == [] and min(scores.values()) > 0.6, scores


def test_masks_that_agree_poorly_leave_every_pose_in():
    """Masks that each miss a different 30-50 % of the specimen (a white cube on a white
    table): right poses score low against the hull, and the check, as unreliable as its
    masks, drops none of them; trusting the masks would drop three."""
    views = sphere_views(10)
    names = [f"view_{i}" for i in range(len(views))]
    rng = np.random.default_rng(0)
    masks = {}
    for name, view in zip(names, views):
        v, u = np.nonzero(view.mask)
        direction = rng.normal(size=2)
        along = (u - u.mean()) * direction[0] + (v - v.mean()) * direction[1]
        cut = along > np.quantile(along, 1 - rng.uniform(0.3, 0.5))
        masks[name] = view.mask.copy()
        masks[name][v[cut], u[cut]] = False
    arguments = (
        {n: v.pose for n, v in zip(names, views)},
        {n: v.intrinsics for n, v in zip(names, views)},
        masks,
        MIN_IOU,
        RESOLUTION,
    )
    scores, off = silhouette_check(*arguments, MIN_AGREEMENT)
    assert off == []
    assert silhouette_check(*arguments, 0.0)[1], scores  # with the masks trusted, right poses go
