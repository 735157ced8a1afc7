"""Batched float64 DLT against numpy.linalg.svd of the same construction, and the Triangulator on
synthetic correspondences (known points projected into known cameras, noise and outliers)."""

import numpy as np
import pytest
import warp as wp

from rgs_warp.config import TriangulationConfig
from rgs_warp.kernels.dlt import mat34d
from rgs_warp.triangulation import Triangulator, baseline_angle_deg, projection_matrices, triangulate_dlt

K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])


def look_at(eye, target):
    """Camera-to-world pose (OpenCV axes) at ``eye`` looking at ``target``."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross([0.0, -1.0, 0.0], z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    T[:3, 3] = eye
    return T


def rig(rng, views, baseline, distance, origin):
    """Projection matrices of cameras scattered by ``baseline`` around ``origin``, all looking at a
    target ``distance`` ahead; returns (P, target)."""
    target = origin + np.array([0.0, 0.0, distance])
    eyes = origin + rng.normal(size=(views, 3)) * baseline
    return projection_matrices(K, np.stack([look_at(e, target) for e in eyes])), target


def project(P, X):
    y = np.einsum("vij,nj->nvi", P, np.concatenate([X, np.ones((len(X), 1))], 1))
    return y[..., :2] / y[..., 2:]


def centres(P):
    return np.stack([-np.linalg.solve(p[:, :3], p[:, 3]) for p in P])


def reference_dlt(P, x, valid):
    """The construction of kernels/dlt.py in NumPy: world normalised by the centres of the views
    used, unit-norm rows, smallest right singular vector by numpy.linalg.svd."""
    C = centres(P)
    out = np.full((len(x), 3), np.nan)
    for i in range(len(x)):
        vs = np.flatnonzero(valid[i])
        if len(vs) < 2:
            continue
        c = C[vs].mean(0)
        s = np.sqrt(np.mean(np.sum((C[vs] - c) ** 2, 1))) or 1.0
        rows = []
        for v in vs:
            for k in range(2):
                r = x[i, v, k] * P[v, 2] - P[v, k]
                r = np.concatenate([s * r[:3], [r[:3] @ c + r[3]]])
                rows.append(r / np.linalg.norm(r))
        h = np.linalg.svd(np.array(rows))[2][-1]
        out[i] = s * h[:3] / h[3] + c
    return out


CASES = {
    # name: (views, camera spread m, distance m, noise px, world origin offset m)
    "2 views": (2, 0.3, 3.0, 0.5, 0.0),
    "3 views": (3, 0.3, 3.0, 0.5, 5.0),
    "8 views": (8, 0.5, 4.0, 1.0, 0.0),
    "nearly parallel rays": (3, 0.002, 3.0, 0.3, 10.0),
    "far points": (3, 0.3, 300.0, 0.3, 100.0),
}


@pytest.mark.parametrize("case", list(CASES))
def test_dlt_matches_numpy_svd(case, device):
    views, spread, distance, noise, offset = CASES[case]
    rng = np.random.default_rng(len(case))
    P, target = rig(rng, views, spread, distance, origin=np.array([offset, -offset, 0.5 * offset]))
    n = 300
    X_true = target + rng.normal(size=(n, 3)) * 0.2 * distance
    x = project(P, X_true) + rng.normal(size=(n, views, 2)) * noise
    valid = np.ones((n, views), bool)
    if views > 2:
        valid[rng.random((n, views)) < 0.25] = False
    X, residual = triangulate_dlt(P, x, valid, device=device)
    X, residual = X.numpy(), residual.numpy()
    ref = reference_dlt(P, x, valid)
    solved = np.isfinite(residual)
    assert solved.sum() > n // 2, "most points must triangulate"
    rel = np.linalg.norm(X[solved] - ref[solved], axis=1) / np.linalg.norm(ref[solved], axis=1)
    assert rel.max() < 1e-9
    # the residual is the RMS pixel error over the valid views
    err = np.linalg.norm(project(P, X[solved]) - x[solved], axis=2)
    rms = np.sqrt(np.sum(err**2 * valid[solved], 1) / valid[solved].sum(1))
    np.testing.assert_allclose(residual[solved], rms, rtol=1e-9)
    # unsolved points are those with fewer than two views, or degenerate (behind a camera)
    few = valid.sum(1) < 2
    assert np.all(~solved[few]) and np.all(np.isnan(X[few]))


def test_dlt_noise_free_is_exact(device):
    rng = np.random.default_rng(3)
    P, target = rig(rng, 4, 0.3, 3.0, origin=np.zeros(3))
    X_true = target + rng.normal(size=(200, 3)) * 0.5
    X, residual = triangulate_dlt(P, project(P, X_true), np.ones((200, 4), bool), device=device)
    np.testing.assert_allclose(X.numpy(), X_true, rtol=1e-9, atol=1e-9)
    assert residual.numpy().max() < 1e-7


def test_dlt_flags_degenerate_points(device):
    # Two cameras, same orientation, 0.2 m apart along x.
    T0, T1 = np.eye(4), np.eye(4)
    T1[0, 3] = 0.2
    P = projection_matrices(K, np.stack([T0, T1]))
    X_front = np.array([[0.1, 0.0, 2.0]])
    x_front = project(P, X_front)[0]
    x = np.stack(
        [
            x_front,
            project(P, np.array([[0.1, 0.0, -2.0]]))[0],  # behind both cameras
            np.array([[319.5, 239.5], [319.5, 239.5]]),  # parallel rays: point at infinity
            x_front,  # only one valid view
        ]
    )
    valid = np.array([[1, 1], [1, 1], [1, 1], [1, 0]], bool)
    X, residual = triangulate_dlt(P, x, valid, device=device)
    X, residual = X.numpy(), residual.numpy()
    np.testing.assert_allclose(X[0], X_front[0], rtol=1e-12)
    assert np.isfinite(residual[0]) and np.all(np.isinf(residual[1:]))
    assert np.all(np.isfinite(X[1])) and np.all(np.isnan(X[2:]))


def test_dlt_accepts_warp_arrays(device):
    rng = np.random.default_rng(4)
    P, target = rig(rng, 3, 0.3, 3.0, origin=np.zeros(3))
    X_true = target + rng.normal(size=(50, 3)) * 0.5
    x = project(P, X_true)
    X, _ = triangulate_dlt(
        wp.array(P, dtype=mat34d, device=device),
        wp.array(x, dtype=wp.vec2d, device=device),
        wp.array(np.ones((50, 3), bool), dtype=wp.bool, device=device),
        device=device,
    )
    np.testing.assert_allclose(X.numpy(), X_true, rtol=1e-9)
    with pytest.raises(TypeError):
        triangulate_dlt(wp.array(x, dtype=wp.vec2d, device=device), x, np.ones((50, 3)), device=device)


def test_baseline_angle(device):
    rng = np.random.default_rng(5)
    P, target = rig(rng, 4, 0.3, 3.0, origin=np.zeros(3))
    X = target + rng.normal(size=(100, 3)) * 0.5
    valid = rng.random((100, 4)) < 0.7
    got = baseline_angle_deg(P, X, valid, device=device).numpy()
    C = centres(P)
    expected = np.zeros(100)
    for i in range(100):
        vs = np.flatnonzero(valid[i])
        for a in vs:
            for b in vs[vs > a]:
                ra, rb = X[i] - C[a], X[i] - C[b]
                cos = ra @ rb / np.linalg.norm(ra) / np.linalg.norm(rb)
                expected[i] = max(expected[i], np.degrees(np.arccos(np.clip(cos, -1, 1))))
    np.testing.assert_allclose(got, expected, atol=1e-6)
    assert np.all(got[valid.sum(1) < 2] == 0.0)


def _scene(rng, n, neighbour_offsets):
    """A reference camera and neighbours displaced by ``neighbour_offsets`` (m), looking at a
    point cloud 3 m ahead; returns (P (1 + M, 3, 4), X_true (n, 3), ref_uv (n, 2), match_uv (n, M, 2))."""
    target = np.array([0.0, 0.0, 3.0])
    eyes = [np.zeros(3)] + [np.asarray(o, float) for o in neighbour_offsets]
    P = projection_matrices(K, np.stack([look_at(e, target) for e in eyes]))
    X_true = target + rng.normal(size=(n, 3)) * 0.4
    uv = project(P, X_true)
    return P, X_true, uv[:, 0], uv[:, 1:]


def _run(tri, P, ref_uv, match_uv, confidence, device):
    out = tri.triangulate(
        wp.array(P, dtype=mat34d, device=device),
        wp.array(ref_uv, dtype=wp.vec2d, device=device),
        wp.array(match_uv, dtype=wp.vec2d, device=device),
        wp.array(confidence.astype(np.float32), device=device),
    )
    return {k: getattr(out, k).numpy() for k in ("X", "residual_px", "parallax_deg", "support", "valid")}


def test_triangulator_recovers_points_and_rejects_outliers(device):
    rng = np.random.default_rng(6)
    n = 400
    P, X_true, ref_uv, match_uv = _scene(rng, n, [(0.3, 0, 0), (-0.3, 0.1, 0), (0, 0.3, 0.1), (0.2, -0.2, 0)])
    noisy = match_uv + rng.normal(size=match_uv.shape) * 0.3
    # 20% of the pixels: every match is garbage -> no hypothesis survives;
    # another 20%: one neighbour's match is wrong -> outvoted, excluded from the joint solve.
    garbage = rng.random(n) < 0.2
    noisy[garbage] = rng.random((garbage.sum(), 4, 2)) * [640, 480]
    one_bad = ~garbage & (rng.random(n) < 0.25)
    bad_view = rng.integers(0, 4, n)
    noisy[one_bad, bad_view[one_bad]] += rng.choice([-1, 1], size=(one_bad.sum(), 2)) * 25.0
    confidence = np.ones((n, 4))
    confidence[rng.random((n, 4)) < 0.1] = 0.0  # unmatched
    tri = Triangulator(TriangulationConfig(min_parallax_deg=1.0, max_reproj_px=2.0), device=device)
    r = _run(tri, P, ref_uv, noisy, confidence, device)
    valid = r["valid"] == 1
    assert valid[~garbage].mean() > 0.95
    assert valid[garbage].mean() < 0.05
    good = valid & ~garbage
    err = np.linalg.norm(r["X"][good] - X_true[good], axis=1)
    # two-view depth error at 3 m with 0.3 m baselines and 0.3 px noise is ~2 cm (Z^2 sigma / f b);
    # the joint solution over up to 5 views must do clearly better
    assert np.median(err) < 1e-2 and np.percentile(err, 99) < 5e-2
    assert np.all(r["residual_px"][good] <= 2.0) and np.all(r["parallax_deg"][good] >= 1.0)
    # wrong matches are never among the views used; pixels with 3+ agreeing neighbours use them all
    bits = 1 << (bad_view + 1)
    assert not np.any(r["support"][one_bad & valid] & bits[one_bad & valid])
    clean = good & ~one_bad & (confidence.sum(1) == 4)
    assert np.mean(r["support"][clean] == 0b11111) > 0.95


def test_triangulator_rejects_small_parallax(device):
    rng = np.random.default_rng(7)
    P, X_true, ref_uv, match_uv = _scene(rng, 200, [(0.02, 0, 0), (0, 0.3, 0)])  # 0.4 deg vs 6 deg
    confidence = np.ones((200, 2))
    tri = Triangulator(TriangulationConfig(min_parallax_deg=1.0, max_reproj_px=2.0), device=device)
    r = _run(tri, P, ref_uv, match_uv, confidence, device)
    assert np.all(r["valid"] == 1) and np.all(r["parallax_deg"] > 3.0)
    confidence[:, 1] = 0.0  # only the short baseline left
    r = _run(tri, P, ref_uv, match_uv, confidence, device)
    assert np.all(r["valid"] == 0)


def test_triangulator_keeps_best_hypothesis(device):
    rng = np.random.default_rng(8)
    n = 200
    P, X_true, ref_uv, match_uv = _scene(rng, n, [(0.3, 0, 0), (0.3, 0.05, 0)])
    tri = Triangulator(TriangulationConfig(min_parallax_deg=1.0, max_reproj_px=1.0), device=device)
    for noisy_neighbour in (0, 1):
        # One neighbour 1.6 px off vertically (two-view residual ~0.8 px, passes), the other exact;
        # they disagree by more than the 1 px threshold: the exact one must win, in either order.
        noisy = match_uv.copy()
        noisy[:, noisy_neighbour, 1] += 1.6
        r = _run(tri, P, ref_uv, noisy, np.ones((n, 2)), device)
        assert np.all(r["valid"] == 1)
        assert np.all(r["support"] == 1 | 1 << (2 - noisy_neighbour))
        np.testing.assert_allclose(r["X"], X_true, atol=1e-6)
    # Along the epipolar line instead: the wrong match triangulates with zero residual but the
    # third neighbour votes for the right point.
    P, X_true, ref_uv, match_uv = _scene(rng, n, [(0.3, 0, 0), (0.0, 0.3, 0), (-0.3, 0, 0)])
    slid = match_uv.copy()
    slid[:, 0] = project(P[1:2], 1.15 * X_true)[:, 0]  # the reference ray, 15% deeper (ref centre at 0)
    tri = Triangulator(TriangulationConfig(min_parallax_deg=1.0, max_reproj_px=1.0), device=device)
    r = _run(tri, P, ref_uv, slid, np.ones((n, 3)), device)
    assert np.mean(r["support"] == 0b1101) > 0.95
    np.testing.assert_allclose(r["X"][r["support"] == 0b1101], X_true[r["support"] == 0b1101], atol=1e-6)


def test_triangulator_grows_buffers(device):
    rng = np.random.default_rng(9)
    tri = Triangulator(TriangulationConfig(), device=device)
    for n in (10, 3000):
        P, X_true, ref_uv, match_uv = _scene(rng, n, [(0.3, 0, 0)])
        r = _run(tri, P, ref_uv, match_uv, np.ones((n, 1)), device)
        assert r["X"].shape == (n, 3)
        np.testing.assert_allclose(r["X"], X_true, atol=1e-6)
