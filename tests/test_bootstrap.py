"""Monocular two-view bootstrap: the window search against brute force, the relative pose (OpenCV's
essential matrix) on synthetic correspondences against their true pose (exact without noise, robust
to 30 and 50 % outliers, deterministic), the whole bootstrap on rendered office pairs against their
ground-truth pose and depth, rejection of pairs without parallax, and the hand-over to the PointSeeder."""

import cv2
import numpy as np
import pytest
import warp as wp

from rgs_warp.bootstrap import (
    BandedWindowSearch,
    BootstrapConfig,
    MonoBootstrap,
    epipolar_distance_px,
    relative_pose,
    to_triangulated_points,
)
from rgs_warp.config import MatchingConfig, SeedingConfig
from rgs_warp.datasets.sevenscenes import SevenScenesDataset
from rgs_warp.datasets.synthetic import SequenceRenderer, SyntheticConfig
from rgs_warp.geometry import invert_pose, rotation_angle_deg, skew, so3_exp
from rgs_warp.kernels.bootstrap import select_matches, window_search
from rgs_warp.kernels.math import NO_MATCH
from rgs_warp.keyframes import KeyframeBuffer
from rgs_warp.seeding import PointSeeder
from rgs_warp.types import GaussianMap

# ---- window search ------------------------------------------------------------------------------


def parabola(left, centre, right):
    curvature = left - 2 * centre + right
    return 0.0 if curvature >= 0 else float(np.clip(0.5 * (left - right) / curvature, -0.5, 0.5))


def brute_force_window(query, uv, target, stride, offset, radius, exclusion):
    """kernels/matching.py: window_search without ZNCC refinement, one query at a time in NumPy."""
    hf, wf, _ = target.shape
    out = []
    for q, (u, v) in zip(query, uv, strict=True):
        if q @ q < 0.25:
            out.append(((u, v), NO_MATCH, NO_MATCH))
            continue
        grid = (np.array([u, v]) - 0.5 * (stride - 1)) / stride + offset
        cx, cy = np.clip(np.floor(grid + 0.5).astype(int), 0, [wf - 1, hf - 1])
        x0, x1, y0, y1 = max(cx - radius, 0), min(cx + radius, wf - 1), max(cy - radius, 0), min(cy + radius, hf - 1)
        sims = target[y0 : y1 + 1, x0 : x1 + 1] @ q
        by, bx = np.unravel_index(np.argmax(sims), sims.shape)
        best = sims[by, bx]
        by, bx = by + y0, bx + x0
        yy, xx = np.mgrid[y0 : y1 + 1, x0 : x1 + 1]
        far = np.maximum(abs(xx - bx), abs(yy - by)) > exclusion
        second = sims[far].max() if exclusion >= 0 and far.any() else NO_MATCH
        dx = parabola(target[by, bx - 1] @ q, best, target[by, bx + 1] @ q) if 0 < bx < wf - 1 else 0.0
        dy = parabola(target[by - 1, bx] @ q, best, target[by + 1, bx] @ q) if 0 < by < hf - 1 else 0.0
        out.append(((stride * (bx + dx) + 0.5 * (stride - 1), stride * (by + dy) + 0.5 * (stride - 1)), best, second))
    match, best, second = zip(*out, strict=True)
    return np.array(match), np.array(best), np.array(second)


def unit_rows(a):
    return (a / np.linalg.norm(a, axis=-1, keepdims=True)).astype(np.float32)


@pytest.mark.parametrize("offset, exclusion", [((0.0, 0.0), 2), ((3.3, -1.6), 1), ((-2.2, 0.4), -1)])
@pytest.mark.parametrize("bands", [0, 4, 20])  # 0: window_search; else BandedWindowSearch (20 > rows)
@pytest.mark.parametrize("radius", [3, 13])  # 13: the whole grid, as the bootstrap's coarse pass
def test_window_search_matches_brute_force(device, offset, exclusion, bands, radius):
    rng = np.random.default_rng(0)
    hf, wf, dim, stride = 9, 13, 16, 4
    # smooth descriptor fields (random fields blurred along both axes), so the parabola fits have peaks
    target = rng.normal(size=(hf + 2, wf + 2, dim))
    target = unit_rows(target[:-2, :-2] + target[1:-1, 1:-1] + target[2:, 2:] + target[1:-1, :-2] + target[:-2, 1:-1])
    n = 200
    uv = rng.uniform([-3, -3], [stride * wf + 2, stride * hf + 2], size=(n, 2)).astype(np.float32)
    query = unit_rows(rng.normal(size=(n, dim)))
    # the first 100 queries are noisy copies of a target cell inside their window
    cell = np.floor((uv[:100] - 0.5 * (stride - 1)) / stride + offset + 0.5).astype(int)
    cell = np.clip(cell + rng.integers(-radius, radius + 1, (100, 2)), 0, [wf - 1, hf - 1])
    query[:100] = unit_rows(target[cell[:, 1], cell[:, 0]] + 0.3 * query[:100])
    query[150] = 0.0  # textureless
    kw = {"device": device}
    outs = [wp.zeros(n, dtype=wp.vec2, **kw), wp.zeros(n, dtype=wp.float32, **kw), wp.zeros(n, dtype=wp.float32, **kw)]
    grey = wp.zeros((2, 2), dtype=wp.float32, **kw)  # unused without ZNCC refinement
    args = [wp.array(query, **kw), wp.array(uv, dtype=wp.vec2, **kw), grey, wp.array(target, **kw), grey, stride]
    if bands:
        BandedWindowSearch(n, bands, device)(*args, wp.vec2(*offset), radius, exclusion, [0, 0], outs)
    else:
        wp.launch(
            window_search, dim=n, inputs=[*args, wp.vec2(*offset), radius, exclusion, 0, 0], outputs=outs, device=device
        )
    match, best, second = brute_force_window(query, uv, target, stride, np.array(offset), radius, exclusion)
    np.testing.assert_allclose(outs[1].numpy(), best, atol=1e-5)
    np.testing.assert_allclose(outs[2].numpy(), second, atol=1e-5)
    np.testing.assert_allclose(outs[0].numpy(), match, atol=1e-3)
    assert best[150] == NO_MATCH and np.all(best[:100] > 0.9)  # the planted matches are found


def test_select_matches_ratio_similarity_and_mutual(device):
    # rows: good; too dissimilar; ambiguous (second best nearly as good); not mutual; no second best
    sim = np.array([0.9, 0.4, 0.9, 0.9, 0.9], np.float32)
    second = np.array([0.5, 0.0, 0.89, 0.5, NO_MATCH], np.float32)
    ref = np.zeros((5, 2), np.float32)
    bwd = np.array([[0.3, 0.4], [0, 0], [0, 0], [1.5, 0.0], [0, 0]], np.float32)
    kw = {"device": device}
    fb, valid = wp.zeros(5, dtype=wp.float32, **kw), wp.zeros(5, dtype=wp.int32, **kw)
    vec2 = lambda a: wp.array(a, dtype=wp.vec2, **kw)  # noqa: E731
    wp.launch(
        select_matches,
        dim=5,
        inputs=[vec2(ref), vec2(ref), wp.array(sim, **kw), wp.array(second, **kw), vec2(bwd), 0.5, 0.9, 1.0],
        outputs=[fb, valid],
        device=device,
    )
    np.testing.assert_array_equal(valid.numpy(), [1, 0, 0, 0, 1])
    np.testing.assert_allclose(fb.numpy(), [0.5, 0, 0, 1.5, 0], atol=1e-6)


# ---- relative pose (OpenCV) ---------------------------------------------------------------------

K = np.array([[320.0, 0.0, 319.5], [0.0, 320.0, 179.5], [0.0, 0.0, 1.0]])


def normalised(uv, K):
    return (uv - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])


def two_view_scene(rng, n, noise_px=0.0, outlier_ratio=0.0, R=None, t=None):
    """Points 1-6 m in front of camera 0 seen from camera k (default: moved by 20 cm, turned by
    ~6 deg); pixels in both (uniform random pixels in k for the outliers; points that leave image k
    are kept, a wider camera).  Returns uv0, uvk, R, t (X_k = R X_0 + t), outlier."""
    R = so3_exp(np.radians([2.0, -5.0, 1.5])) if R is None else R
    t = np.array([0.15, -0.03, 0.12]) if t is None else t
    z = rng.uniform(1.0, 6.0, n)
    uv0 = rng.uniform([0, 0], [639, 359], (n, 2))
    X0 = np.concatenate([normalised(uv0, K) * z[:, None], z[:, None]], 1)
    Xk = X0 @ R.T + t
    uvk = Xk[:, :2] / Xk[:, 2:] * K[0, 0] + K[:2, 2]
    uvk = uvk + rng.normal(0, noise_px, uvk.shape)
    outlier = rng.random(n) < outlier_ratio
    uvk[outlier] = rng.uniform([0, 0], [639, 359], (outlier.sum(), 2))
    return uv0, uvk, R, t, outlier


def pose_errors_deg(R_est, t_est, R, t):
    """Rotation error and angle between the translation directions, degrees."""
    cos = t_est @ t / (np.linalg.norm(t_est) * np.linalg.norm(t))
    return rotation_angle_deg(R_est.T @ R), float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def test_relative_pose_noise_free_is_exact():
    rng = np.random.default_rng(1)
    # sideways, forward, backward and diagonal motions with turns of up to 10 deg: together they
    # need more than one of the four (R, t) of the essential matrix
    for motion in range(6):
        R = so3_exp(rng.normal(0, np.radians(5), 3))
        t = rng.normal(0, 0.1, 3) if motion else np.array([0.0, 0.0, -0.2])
        uv0, uvk, R, t, _ = two_view_scene(rng, 200, R=R, t=t)
        R_est, t_est, inliers, in_front = relative_pose(uv0, uvk, K, threshold_px=0.5)
        assert inliers.all() and in_front.all()
        rot, tdir = pose_errors_deg(R_est, t_est, R, t)
        assert rot < 1e-3 and tdir < 0.02, (motion, rot, tdir)  # OpenCV fits in float32
        assert np.linalg.norm(t_est) == pytest.approx(1.0)


@pytest.mark.parametrize(
    "outlier_ratio, max_rot_deg, max_tdir_deg",
    # 50 % outliers: the 8-point MSAC with 512 samples this replaced was 15 deg off (median of 20
    # scenes) in translation direction; OpenCV's 5-point USAC is within 5 deg
    [(0.3, 0.05, 1.0), (0.5, 0.2, 3.0)],
)
def test_relative_pose_with_outliers(outlier_ratio, max_rot_deg, max_tdir_deg):
    rng = np.random.default_rng(2)
    uv0, uvk, R, t, outlier = two_view_scene(rng, 600, noise_px=0.3, outlier_ratio=outlier_ratio)
    assert abs(outlier.mean() - outlier_ratio) < 0.05
    R_est, t_est, inliers, in_front = relative_pose(uv0, uvk, K, threshold_px=1.0)
    rot, tdir = pose_errors_deg(R_est, t_est, R, t)
    assert rot < max_rot_deg and tdir < max_tdir_deg, (rot, tdir)
    assert inliers[~outlier].mean() > 0.95  # 1 px Sampson keeps the 0.3 px noise
    assert inliers[outlier].mean() < 0.05  # random pixels near their epipolar line by chance
    assert in_front.mean() > 0.98


def test_relative_pose_is_deterministic():
    """The same correspondences give the same pose, whatever OpenCV's global RNG did in between."""
    rng = np.random.default_rng(3)
    uv0, uvk, *_ = two_view_scene(rng, 400, noise_px=0.5, outlier_ratio=0.3)
    first = relative_pose(uv0, uvk, K)
    cv2.setRNGSeed(12345)
    cv2.findEssentialMat(uv0, uvk, K, method=cv2.RANSAC)  # draws from the global RNG
    again = relative_pose(uv0, uvk, K)
    for a, b in zip(first, again, strict=True):
        np.testing.assert_array_equal(a, b)


def test_epipolar_distance_px():
    rng = np.random.default_rng(4)
    uv0, uvk, R, t, _ = two_view_scene(rng, 50)
    E = skew(t) @ R
    np.testing.assert_allclose(epipolar_distance_px(E, uv0, uvk, K), 0.0, atol=1e-8)
    # move each match 1.5 px along the normal of its epipolar line in image k
    Kinv = np.linalg.inv(K)
    line = np.concatenate([uv0, np.ones((50, 1))], 1) @ (Kinv.T @ E @ Kinv).T
    normal = line[:, :2] / np.linalg.norm(line[:, :2], axis=1, keepdims=True)
    np.testing.assert_allclose(epipolar_distance_px(E, uv0, uvk + 1.5 * normal, K), 1.5, rtol=1e-6)


# ---- rendered pairs -----------------------------------------------------------------------------


def bilinear_depth(depth, uv):
    """Depth at sub-pixel points (0 across depth edges: there the truth is undefined)."""
    x0 = np.clip(np.floor(uv[:, 0]).astype(int), 0, depth.shape[1] - 2)
    y0 = np.clip(np.floor(uv[:, 1]).astype(int), 0, depth.shape[0] - 2)
    fx, fy = uv[:, 0] - x0, uv[:, 1] - y0
    d = np.stack([depth[y0, x0], depth[y0, x0 + 1], depth[y0 + 1, x0], depth[y0 + 1, x0 + 1]], 1)
    value = (1 - fy) * ((1 - fx) * d[:, 0] + fx * d[:, 1]) + fy * ((1 - fx) * d[:, 2] + fx * d[:, 3])
    edge = (d.min(1) <= 0) | (d.max(1) - d.min(1) > 0.05 * d.mean(1))
    return np.where(edge, 0.0, value)


@pytest.fixture(scope="module")
def office_pair(device):
    """office0 at 320x180, frames 0 and 8 (20 cm, 13 deg apart: 3.4 deg median parallax), bootstrapped."""
    seq = SequenceRenderer(SyntheticConfig(scene="office0", width=320, height=180, n_frames=100), device)
    (rgb0, depth0), (rgbk, _) = seq.render(0), seq.render(8)
    cam = seq.cfg.camera
    boot = MonoBootstrap(BootstrapConfig(), cam, device)
    result = boot.try_init(rgb0, rgbk)
    assert result is not None, boot.last_rejection
    T_0k = invert_pose(seq.poses[0]) @ seq.poses[8]
    return {"camera": cam, "rgb": (rgb0, rgbk), "depth0": depth0, "T_0k": T_0k}, result


@pytest.mark.slow  # the office pair takes 5 s to build
def test_bootstrap_recovers_pose_and_depth(office_pair):
    truth, r = office_pair
    T = truth["T_0k"]
    assert rotation_angle_deg(T[:3, :3].T @ r.T_0k[:3, :3]) < 0.5
    cos = T[:3, 3] @ r.T_0k[:3, 3] / (np.linalg.norm(T[:3, 3]) * np.linalg.norm(r.T_0k[:3, 3]))
    assert np.degrees(np.arccos(min(cos, 1.0))) < 5.0
    assert len(r.points) > 1000 and r.inlier_ratio > 0.9 and r.median_parallax_deg > 2.0
    # gauge: median depth in frame 0 is scene_depth_m; T_0k carries the same scale (the points
    # reproject onto their matches in frame k)
    assert np.median(r.points[:, 2]) == pytest.approx(MatchingConfig().scene_depth_m)
    cam = truth["camera"]
    Xk = r.points @ r.T_0k[:3, :3] - r.T_0k[:3, :3].T @ r.T_0k[:3, 3]  # R^T (X - t)
    uvk = Xk[:, :2] / Xk[:, 2:] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    assert np.median(np.linalg.norm(uvk - r.match_uv, axis=1)) < 0.5
    # depths against the rendered ground truth after aligning the scale
    d = bilinear_depth(truth["depth0"], r.ref_uv)
    ok = d > 0
    assert ok.mean() > 0.8
    z = r.points[ok, 2] * np.median(d[ok] / r.points[ok, 2])
    rel = np.abs(z - d[ok]) / d[ok]
    assert np.median(rel) < 0.03 and np.mean(rel < 0.10) > 0.85, (np.median(rel), np.mean(rel < 0.10))
    assert np.all(r.residual_px <= 1.0) and np.all(r.parallax_deg >= 0.5)
    assert np.all((r.confidence >= 0) & (r.confidence <= 1)) and r.confidence.mean() > 0.5


@pytest.mark.slow
def test_bootstrap_pose_at_160x90(device):
    """office0 at 160x90, frames 0 and 7 (14 cm, 10 deg apart: 2.7 deg median parallax), the first
    pairs a caller reaches.  Measured: rotation 0.10 deg and translation direction 2.2 deg off (as
    the hand-written 8-point MSAC with Sampson refinement that OpenCV replaced), hence bounds
    tighter than 0.5 / 5 deg.  Depths are noisier than at 320x180 (4 % median, not checked here)."""
    seq = SequenceRenderer(SyntheticConfig(scene="office0", width=160, height=90, n_frames=100), device)
    boot = MonoBootstrap(BootstrapConfig(), seq.cfg.camera, device)
    r = boot.try_init(seq.render(0)[0], seq.render(7)[0])
    assert r is not None, boot.last_rejection
    T = invert_pose(seq.poses[0]) @ seq.poses[7]
    assert rotation_angle_deg(T[:3, :3].T @ r.T_0k[:3, :3]) < 0.25
    cos = T[:3, 3] @ r.T_0k[:3, 3] / (np.linalg.norm(T[:3, 3]) * np.linalg.norm(r.T_0k[:3, 3]))
    assert np.degrees(np.arccos(min(cos, 1.0))) < 3.0
    assert len(r.points) > 300


@pytest.mark.slow
def test_bootstrap_rejects_pairs_without_parallax(device):
    seq = SequenceRenderer(SyntheticConfig(scene="office0", width=160, height=90, n_frames=100), device)
    rgb0, _ = seq.render(0)
    boot = MonoBootstrap(BootstrapConfig(), seq.cfg.camera, device)
    # frame 2: 1.2 cm from frame 0 (0.3 deg of parallax at 2 m), turned by 1 deg
    assert boot.try_init(rgb0, seq.render(2)[0]) is None
    assert boot.last_rejection
    # pure rotation: frame 0's camera turned by 6 deg (the pose is well defined, the depth is not)
    seq.poses[1] = seq.poses[0].copy()
    seq.poses[1][:3, :3] = seq.poses[0][:3, :3] @ so3_exp(np.radians([1.0, 6.0, 0.5]))
    assert boot.try_init(rgb0, seq.render(1)[0]) is None
    assert boot.last_rejection
    # the same search finds most of the rotated image: the rejection is the geometry's, not the matcher's
    _, match_uv, valid = boot.match(rgb0, seq.render(1)[0])
    assert valid.mean() > 0.5


@pytest.mark.slow  # the office pair takes 5 s to build
def test_to_triangulated_points_seeds_both_keyframes(office_pair, device):
    truth, r = office_pair
    cam = truth["camera"]
    T_W0 = np.eye(4)
    T_W0[:3, :3] = so3_exp(np.array([0.1, -0.2, 0.3]))
    T_W0[:3, 3] = [1.0, -2.0, 0.5]
    points = to_triangulated_points(r, T_W0, device)
    X_world = r.points @ T_W0[:3, :3].T + T_W0[:3, 3]
    np.testing.assert_allclose(points.X.numpy(), X_world, atol=1e-9)
    assert np.all(points.support.numpy() == 0b11) and np.all(points.valid.numpy() == 1)
    keyframes = KeyframeBuffer(2, cam.width, cam.height, device)
    slots = [keyframes.add(0, T_W0, truth["rgb"][0]), keyframes.add(8, T_W0 @ r.T_0k, truth["rgb"][1])]
    seeder = PointSeeder(SeedingConfig(), cam, device)
    gmap = GaussianMap(1024, sh_degree=2, device=device)
    added = seeder.seed(points, wp.array(r.confidence, device=device), keyframes, slots, gmap)
    assert 0.3 * len(X_world) < added <= len(X_world)
    index = seeder.seed_index.numpy()[:added]
    np.testing.assert_allclose(gmap.means.numpy()[:added], X_world[index], atol=1e-5)


@pytest.mark.slow  # two pairs at 320x240: about 10 s
def test_sevenscenes_bootstraps_within_the_default_wait(shared_data, device):
    """The shared 7-Scenes frames start slowly: frame 0 against frame 32 has too little parallax
    (1.3 deg), frame 40 bootstraps, with the rotation and the translation direction close to the
    ground truth's.  ``bootstrap.max_wait_frames`` must reach it (it was 30: the run fell back to a
    plane and lost 470 of its 500 frames on the H100)."""
    cfg = BootstrapConfig()
    ds = SevenScenesDataset(shared_data / "7scenes-redkitchen", downscale=2, max_frames=41)
    boot = MonoBootstrap(cfg, ds.camera, device)
    f0 = ds[0]
    assert boot.try_init(f0.rgb, ds[32].rgb) is None and "parallax" in boot.last_rejection
    k = 40
    assert k < cfg.max_wait_frames
    result = boot.try_init(f0.rgb, ds[k].rgb)
    assert result is not None, boot.last_rejection
    T_0k = invert_pose(f0.pose_gt) @ ds[k].pose_gt
    assert rotation_angle_deg(result.T_0k[:3, :3].T @ T_0k[:3, :3]) < 1.5
    t_est, t_gt = result.T_0k[:3, 3], T_0k[:3, 3]
    cos = t_est @ t_gt / np.linalg.norm(t_est) / np.linalg.norm(t_gt)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))) < 20.0
