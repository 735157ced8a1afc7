"""The keypoint odometry's bundle adjustment against exact synthetic geometry: the local BA, its
analytic Jacobian, and the rescaling of a solution to the start's baseline."""

import numpy as np
import pytest

from helpers_cameras import K, scene
from helpers_cameras import camera_centre as _centre
from rgs_warp.bundle_adjustment import Reprojection, bundle_adjust, project, rescaled_to_baseline, rodrigues


def _perturb(T, rng, deg, m):
    d = np.eye(4)
    d[:3, :3] = rodrigues(rng.normal(size=(1, 3)) * np.radians(deg) / np.sqrt(3))[0]
    d[:3, 3] = rng.normal(size=3) * m / np.sqrt(3)
    return d @ T


def test_local_ba_reduces_error_moves_free_poses_to_truth_and_holds_the_rest():
    """Six cameras, 150 points; the last two cameras held at the truth, the first four 0.2 deg / 1 cm off,
    the points 1 cm off, 0.1 px noise and 10 observations 25 px off.  The BA brings the free cameras
    within 3 mm (from 2-13 mm), the inliers' reprojection to the noise, and the residuals it returns
    are those of the held cameras where they were."""
    rng = np.random.default_rng(1)
    truth, points = scene(rng)
    n_free = 4
    start = truth.copy()
    for j in range(n_free):
        start[j] = _perturb(truth[j], rng, 0.2, 0.01)
    cam = np.repeat(np.arange(len(truth)), len(points))
    land = np.tile(np.arange(len(points)), len(truth))
    uv = np.concatenate([project(K, T, points)[0] for T in truth]) + rng.normal(0, 0.1, (len(cam), 2))
    outliers = rng.choice(len(cam), 10, replace=False)
    uv[outliers] += 25.0
    X0 = points + rng.normal(0, 0.01 / np.sqrt(3), points.shape)
    inlier = np.ones(len(cam), bool)
    inlier[outliers] = False

    def rms(cameras, X):
        r = np.concatenate([project(K, cameras[c], X[land[i : i + 1]])[0] for i, c in enumerate(cam)]) - uv
        return np.sqrt(np.mean(np.sum(r[inlier] ** 2, axis=1))), r

    before, _ = rms(start, X0)
    T_free, X, residual = bundle_adjust(start, n_free, X0, cam, land, uv, K, 1.0, 100)
    after_cameras = np.concatenate([T_free, start[n_free:]])
    after, recomputed = rms(after_cameras, X)
    assert before > 1.0 and after < 0.2, (before, after)  # 0.14 px: the noise
    np.testing.assert_allclose(residual, recomputed, atol=1e-6)  # held cameras were not moved
    e0 = np.array([np.linalg.norm(_centre(start[j]) - _centre(truth[j])) for j in range(n_free)])
    e1 = np.array([np.linalg.norm(_centre(T_free[j]) - _centre(truth[j])) for j in range(n_free)])
    assert e1.mean() < 0.3 * e0.mean() and e1.max() < 0.003, (e0, e1)
    assert np.median(np.linalg.norm(X - points, axis=1)) < 0.35 * np.median(np.linalg.norm(X0 - points, axis=1))
    assert np.all(np.linalg.norm(residual[outliers], axis=1) > 10.0)  # Huber: the outliers stay outliers


def test_ba_jacobian_matches_finite_differences():
    """The analytic Jacobian against central differences at rotation steps far from zero (where the
    left Jacobian of SO(3) matters), one camera held."""
    rng = np.random.default_rng(2)
    cameras, points = scene(rng, n_cameras=3, n_points=8)
    cam = np.repeat(np.arange(3), 8)
    land = np.tile(np.arange(8), 3)
    uv = np.concatenate([project(K, T, points)[0] for T in cameras])
    problem = Reprojection(cameras, 2, len(points), cam, land, uv, K)
    x = np.concatenate([rng.normal(0, 0.3, 12), (points + rng.normal(0, 0.05, points.shape)).ravel()])
    J = problem.jacobian(x).toarray()
    h = 1e-6
    J_fd = np.stack(
        [(problem.residuals(x + h * e) - problem.residuals(x - h * e)) / (2 * h) for e in np.eye(len(x))], axis=1
    )
    np.testing.assert_allclose(J, J_fd, rtol=1e-5, atol=1e-4 * np.abs(J_fd).max())
    assert problem.jacobian(x).nnz == 3 * 8 * 2 * 3 + 2 * 8 * 2 * 6  # the held camera has no columns


def test_the_start_refined_keeps_its_baseline_and_every_reprojection():
    """The similarity after a BA with one camera held: the free cameras and landmarks scaled about the
    held camera's centre, so that the start's second camera is as far from it as before; every
    projection stays where it was (to 1e-9 px), and a wrong scale would move them (the check can fail)."""
    rng = np.random.default_rng(3)
    cameras, points = scene(rng, n_cameras=4, n_points=40)
    held, free = cameras[0], cameras[1:].copy()
    for j in range(len(free)):  # what a BA with one camera held may return: the start at another scale
        c = _centre(free[j])
        free[j, :3, 3] = -free[j, :3, :3] @ (_centre(held) + 1.7 * (c - _centre(held)))
    X = _centre(held) + 1.7 * (points - _centre(held))
    out, X_out = rescaled_to_baseline(held, cameras[1], free, 0, X)
    assert np.linalg.norm(_centre(out[0]) - _centre(held)) == pytest.approx(
        np.linalg.norm(_centre(cameras[1]) - _centre(held)), rel=1e-12
    )
    for T_in, T_out in zip([held, *free], [held, *out], strict=True):
        before, _ = project(K, T_in, X)
        after, _ = project(K, T_out, X_out)
        np.testing.assert_allclose(after, before, atol=1e-9)
    np.testing.assert_allclose(X_out, points, atol=1e-9)  # here the scale it undoes is known
