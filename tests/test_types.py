"""``rgs_warp.types.Camera`` refuses intrinsics that cannot be a pinhole camera of its image."""

import pytest

from rgs_warp.types import Camera

W, H = 64, 48


@pytest.mark.parametrize(
    "values, message",
    [
        (dict(fx=-60.0), "fx = -60.0: a focal length must be a positive"),
        (dict(fy=0.0), "fy = 0.0: a focal length"),
        (dict(fx=float("nan")), "fx = nan"),
        (dict(cx=64.0), r"cx = 64.0: the principal point must lie inside the 64x48 image \(-0.5 .. 63.5"),
        (dict(cy=-3.0), "cy = -3.0: the principal point"),
        (dict(width=0), "width = 0: the image size"),
    ],
)
def test_camera_refuses_bad_intrinsics(values, message):
    args = dict(fx=60.0, fy=60.0, cx=31.5, cy=23.5, width=W, height=H) | values
    with pytest.raises(ValueError, match=message):
        Camera(**args)
