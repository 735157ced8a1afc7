"""Issue 18's exposure gauge on the CPU: on a synthetic sequence whose exposure drifts, the map's
colour stays in the first frame's exposure.  Imports only what 8dc16f7 had too, so the same file runs
against it (and fails there: the numbers are in the test's docstring)."""

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from rgs_warp.config import load_config
from rgs_warp.datasets.synthetic.dataset import SyntheticDataset
from rgs_warp.slam import SLAM

# The slower 40-frame path (the first 40 of 120 frames): tracking holds on it at 160x90 (the 40-frame
# sequence loses it at frames 18-20, experiments/results/fidelity.md); log-gain drift of std 0.3
# (three times dataset.exposure_drift=true's), biases of std 0.06.
SEQUENCE = dict(width=160, height=90, n_frames=120, max_frames=40, exposure_drift=0.3)
# exposure_from=keyframes: the gauge fix under test (an option: by default it broke 7-Scenes tracking
# on the GPU, fidelity.md); views_per_iter=0: the mapping of the runs measured below (every window
# view each iteration). Neither key exists at 8dc16f7, where the same runs were made without them.
OVERRIDES = [
    "tracking.exposure_from=keyframes",
    "mapping.init_iters=60",
    "mapping.iters=15",
    "mapping.views_per_iter=0",
    "mapping.window=3",
]


def colour_gauge(render: np.ndarray, alpha: np.ndarray, frame: np.ndarray, exposure, first_exposure, sigma=2.0):
    """The map's mean colour against the frame's brought back to the first frame's exposure with the
    true exposures (rgb = g * colour + b): ratios - 1 of the means over the covered, unclipped pixels,
    all of them and their dark and bright halves (split at the median grey level of the frame's).
    Both images are local means first (Gaussian of ``sigma`` pixels over those pixels), so that the
    halves compare the colours of regions, not the sharpness of their edges (the map is blurrier than
    the frames).  A gain-only exposure that folds a bias into the gain keeps the mean and moves the
    halves apart: dark regions too bright for a positive bias."""
    (g, b), (g0, b0) = exposure, first_exposure
    truth = (frame.astype(np.float64) - b) / g * g0 + b0
    covered = (alpha > 0.5) & np.all((frame > 0.0) & (frame < 1.0), axis=-1)
    weight = np.maximum(gaussian_filter(covered.astype(np.float64), sigma), 1e-6)

    def local_mean(image):
        return np.stack([gaussian_filter(image[..., c] * covered, sigma) for c in range(3)], -1) / weight[..., None]

    r, t = local_mean(np.clip(render, 0.0, 1.0).astype(np.float64))[covered], local_mean(truth)[covered]
    bright = t.mean(1) > np.median(t.mean(1))
    return tuple(r[m].mean() / t[m].mean() - 1.0 for m in (np.ones_like(bright), ~bright, bright))


@pytest.mark.slow
def test_map_colour_stays_in_the_first_frames_exposure(device):
    """Every 5th frame of the drifting sequence, rendered from its tracked pose, against the frame in
    the first frame's exposure (``colour_gauge``); mean over the frames, in %:

    | code | exposure drift | all | dark half | bright half |
    |---|---|---|---|---|
    | 8dc16f7 (exposure: the gain against the map; 140cbbd the same) | 0.3 | -1.34 | **+5.10 (fails)** | -4.46 |
    | 140cbbd | off | -2.19 | +0.06 | -3.36 |
    | tracking.exposure_from=keyframes | 0.3 | -2.42 | -0.04 | -3.58 |
    | the same | off | -2.57 | -0.45 | -3.67 |
    | the true exposures given to seeding and mapping | 0.3 | -2.29 | +0.45 | -3.63 |

    The map renders about 2 % darker than the frames without any drift (its L1 fit at this size),
    most of it in the bright half; the dark half reads the gauge without that floor.  2 min 20 s on
    one CPU core.
    """
    ds = SyntheticDataset("room0", device=device, progress=False, **SEQUENCE)
    exposure = np.loadtxt(ds.mesh_path.parent / "exposure.txt")
    cfg = load_config(["dataset=synthetic/room0", f"device={device}", *OVERRIDES])
    slam = SLAM(cfg, ds.camera, device=device, T_first_WC=ds[0].pose_gt)
    for f in ds:
        slam.process(f.rgb, f.depth, f.timestamp)
    slam.finish()
    _, poses = slam.trajectory()
    errors = []
    for i in range(0, len(ds), 5):
        res = slam.render(poses[i])
        errors.append(colour_gauge(res.color.numpy(), res.alpha.numpy(), ds[i].rgb, exposure[i], exposure[0]))
    mean, dark, bright = 100 * np.mean(errors, axis=0)
    print(
        f"map colour against the first frame's exposure: all {mean:+.2f} %, dark {dark:+.2f} %, bright {bright:+.2f} %"
    )
    assert abs(mean) < 3.5, (mean, dark, bright)
    assert abs(dark) < 3.0, (mean, dark, bright)
    assert abs(bright) < 5.0, (mean, dark, bright)
