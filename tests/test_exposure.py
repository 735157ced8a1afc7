"""KeyframeExposure (exposure.py): moments against a float64 NumPy reference; exposure recovered."""

import numpy as np
import pytest
import warp as wp

from rgs_warp.datasets.synthetic.dataset import SyntheticDataset
from rgs_warp.exposure import MAX_REL_DEPTH, KeyframeExposure, rma_exposure
from rgs_warp.geometry import invert_pose
from rgs_warp.kernels import exposure as ke
from rgs_warp.keyframes import KeyframeBuffer


def _moments_reference(rgb, depth, T_WC, cam, refs):
    """The kernel's sums in float64 NumPy: refs are (rgb, depth, T_WC, (g, b)) of the keyframes."""
    H, W = depth.shape
    v, u = np.mgrid[0:H, 0:W]
    lo, hi = 1 / 255, 254 / 255
    ok = (depth > 0) & (rgb.min(-1) > lo) & (rgb.max(-1) < hi)
    z = depth[ok].astype(np.float64)
    X_W = T_WC @ np.stack([(u[ok] - cam.cx) * z / cam.fx, (v[ok] - cam.cy) * z / cam.fy, z, np.ones_like(z)])
    Y = rgb[ok].astype(np.float64)
    m = np.zeros(ke.M_COLUMNS)
    for rgb_r, depth_r, T_r, (g, b) in refs:
        X = invert_pose(T_r) @ X_W
        zr = X[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            ur, vr = cam.fx * X[0] / zr + cam.cx, cam.fy * X[1] / zr + cam.cy
        keep = (zr > 0) & (ur >= 0) & (ur <= W - 1) & (vr >= 0) & (vr <= H - 1)
        ur, vr, zr, y = ur[keep], vr[keep], zr[keep], Y[keep]
        rx, ry = (ur + 0.5).astype(int), (vr + 0.5).astype(int)
        d = depth_r[ry, rx]
        keep = (d > 0) & (np.abs(d - zr) < MAX_REL_DEPTH * zr)
        x, y = rgb_r[ry[keep], rx[keep]].astype(np.float64), y[keep]
        keep = (x.min(-1) > lo) & (x.max(-1) < hi)
        x, y = ((x[keep] - b) / g).ravel(), y[keep].ravel()
        m += [x.size, x.sum(), y.sum(), (x * x).sum(), (y * y).sum(), (x * y).sum()]
    return m


@pytest.mark.parametrize("frame", [6, 12])
def test_keyframe_exposure_against_numpy_and_truth(device, frame):
    """Frame ``frame`` of a sequence with a strong exposure drift, against keyframes 0 and 3 at their
    true exposures (relative to frame 0's): the kernel's moments match NumPy's, and the reduced major
    axis recovers the frame's true relative exposure."""
    ds = SyntheticDataset(
        "room0", width=160, height=90, n_frames=120, max_frames=20, exposure_drift=0.3, device=device, progress=False
    )
    exp = np.loadtxt(ds.mesh_path.parent / "exposure.txt")
    g0, b0 = exp[0]

    def truth(i):
        return exp[i, 0] / g0, exp[i, 1] - exp[i, 0] / g0 * b0

    kf = KeyframeBuffer(4, ds.camera.width, ds.camera.height, device)
    for i in (0, 3):
        kf.add(i, ds[i].pose_gt, ds[i].rgb, ds[i].depth, truth(i))
    f = ds[frame]
    est = KeyframeExposure(ds.camera, 4, device)
    rgb = wp.array(f.rgb, dtype=wp.vec3, device=device)
    depth = wp.array(f.depth, dtype=wp.float32, device=device)
    g, b = est.estimate(kf, rgb, depth, f.pose_gt, fallback=(1.0, 0.0))
    refs = [(ds[i].rgb, ds[i].depth, ds[i].pose_gt, truth(i)) for i in (0, 3)]
    m_ref = _moments_reference(f.rgb, f.depth, f.pose_gt, ds.camera, refs)
    m = est._moments_host.numpy()
    # float32 projection in the kernel: a few samples round to the neighbouring pixel
    assert m[ke.M_N] == pytest.approx(m_ref[ke.M_N], rel=5e-3)
    np.testing.assert_allclose(m / m[ke.M_N], m_ref / m_ref[ke.M_N], rtol=2e-3, atol=1e-5)
    assert (g, b) == pytest.approx(rma_exposure(m_ref, (1.0, 0.0)), rel=2e-3, abs=1e-3)
    g_true, b_true = truth(frame)
    assert abs(g / g_true - 1) < 0.03 and abs(b - b_true) < 0.01, ((g, b), truth(frame))
    # no references or no depth: the fallback
    assert est.estimate(kf, rgb, None, f.pose_gt, fallback=(0.5, 0.1)) == (0.5, 0.1)
    assert est.estimate(
        KeyframeBuffer(2, ds.camera.width, ds.camera.height, device), rgb, depth, f.pose_gt, (0.5, 0.1)
    ) == (0.5, 0.1)


def test_rma_exposure_from_sums():
    rng = np.random.default_rng(0)
    x = rng.uniform(0.1, 0.9, 5000)
    y = 1.3 * x - 0.05
    m = np.array([x.size, x.sum(), y.sum(), (x * x).sum(), (y * y).sum(), (x * y).sum()])
    assert rma_exposure(m, (1.0, 0.0)) == pytest.approx((1.3, -0.05))
    assert rma_exposure(m[:1].tolist() + [0] * 5, (1.0, 0.0)) == (1.0, 0.0)
    assert rma_exposure(np.r_[10.0, m[1:]], (0.9, 0.0)) == (0.9, 0.0)  # too few samples
