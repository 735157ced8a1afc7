"""``rgs_warp.seeding`` under ``mapping.max_gaussians``: a seeding over the cap keeps seeds spread over
the image."""

import numpy as np

from rgs_warp.config import SeedingConfig
from rgs_warp.types import Camera, GaussianMap

CAMERA = Camera(80.0, 80.0, 79.5, 44.5, 160, 90)


def test_a_seeding_over_the_cap_keeps_seeds_spread_over_the_image(device):
    from rgs_warp.keyframes import KeyframeBuffer
    from rgs_warp.seeding import Seeder

    buffer = KeyframeBuffer(2, CAMERA.width, CAMERA.height, device)
    buffer.add(0, np.eye(4), np.full((90, 160, 3), 0.5), np.full((90, 160), 2.0))
    counts, spans = [], []
    for cap in (0, 500):
        gmap = GaussianMap(16, device=device)
        Seeder(SeedingConfig(), CAMERA, device, max_gaussians=cap).seed_depth(gmap, buffer, 0)
        means = gmap.to_numpy()["means"]
        counts.append(len(gmap))
        spans.append(np.ptp(means[:, :2], axis=0))
    assert counts[0] > 1000 and counts[1] == 500
    np.testing.assert_allclose(spans[1], spans[0], rtol=0.05)  # the kept seeds still span the view
