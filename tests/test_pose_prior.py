"""The keypoint pose prior (issue 22): landmarks lifted with the map's depth, and PnP against them
recovering a fast turn that a stale prediction misses."""

import numpy as np
import pytest

from rgs_warp.datasets.synthetic import SequenceRenderer, SyntheticConfig
from rgs_warp.datasets.synthetic.textures import linear_to_srgb
from rgs_warp.pose_prior import PosePrior
from rgs_warp.tracking import pose_error


@pytest.mark.slow
def test_pnp_recovers_a_fast_turn_from_a_stale_prediction(device):
    """Landmarks of room0's frame 63 (its true depth as the map's, full opacity) at 640x360; frame 65
    is 5.4 cm and 15.6 deg away, mid-turn.  From frame 63's pose as the prediction, PnP finds frame
    65's pose to a centimetre and a third of a degree.  An image without the landmarks' texture gives
    no pose and says why."""
    cfg = SyntheticConfig(scene="room0", width=640, height=360, n_frames=100)
    seq = SequenceRenderer(cfg, device=device)

    def frame(i):
        rgb, depth = seq.render(i)
        return np.clip(linear_to_srgb(rgb), 0, 1).astype(np.float32), depth.astype(np.float32)

    poses = seq.poses
    prior = PosePrior(cfg.camera)
    rgb65 = frame(65)[0]
    assert prior.pose(rgb65, poses[63]).T_WC is None  # no landmarks yet
    rgb63, depth63 = frame(63)
    assert prior.add_keyframe(rgb63, depth63, np.ones_like(depth63), poses[63]) > 300
    gap = pose_error(poses[65], poses[63])
    assert gap[0] > 0.05 and gap[1] > 15.0, gap
    result = prior.pose(rgb65, poses[63])
    assert result.T_WC is not None, result.reason
    dt, dr = pose_error(result.T_WC, poses[65])
    assert dt < 0.015 and dr < 0.35, (dt, dr, result.inliers, result.matches)
    noise = np.random.default_rng(0).uniform(0, 1, rgb65.shape).astype(np.float32)
    none = prior.pose(noise, poses[63])
    assert none.T_WC is None and none.reason


def test_lifting_uses_the_rendered_depth_and_opacity():
    """A keyframe's landmarks are its keypoints back-projected with expected depth / opacity where the
    opacity reaches 0.5, moved to the world by its pose; none where the map is transparent."""
    from rgs_warp.types import Camera

    cam = Camera(fx=100.0, fy=100.0, cx=79.5, cy=59.5, width=160, height=120)
    rng = np.random.default_rng(1)
    rgb = np.kron(rng.uniform(0, 1, (12, 16, 3)), np.ones((10, 10, 1))).astype(np.float32)  # a checker of blocks
    alpha = np.full((120, 160), 0.8, np.float32)
    alpha[:, :80] = 0.2  # the left half: no map there
    depth = 2.0 * alpha  # expected depth of a surface at 2 m
    T = np.eye(4)
    T[:3, 3] = [1.0, -2.0, 0.5]
    prior = PosePrior(cam, min_inliers=6)
    n = prior.add_keyframe(rgb, depth, alpha, T)
    uv, _ = prior.keypoints(rgb)
    assert 0 < n == int(np.sum(np.rint(uv[:, 0]) >= 80)) < len(uv)
    _, points = prior._landmarks[0]
    np.testing.assert_allclose(points[:, 2], 2.5, atol=1e-5)  # z = 2 m in the camera, + 0.5 m
    assert np.all(points[:, 0] >= 1.0 - 1e-6)  # the right half of the image: x >= 0 in the camera


def test_settings_are_checked():
    from rgs_warp.types import Camera

    with pytest.raises(ValueError, match="keypoint_min_inliers"):
        PosePrior(Camera(fx=1.0, fy=1.0, cx=0.5, cy=0.5, width=2, height=2), min_inliers=3)
