"""Poisson-disk subsampling (world space) and blue-noise thinning (image space) against brute force:
separation, coverage, confidence preference, and equality with the sequential greedy set.  The
PointSeeder's per-seed initialisation (plane frame, Eq. 13 scales, median colour, Eq. 14 opacity) against
NumPy, and end to end on a synthetic scene (depth error, PSNR of the seeded map)."""

import numpy as np
import pytest
import warp as wp
from scipy.spatial import cKDTree

from rgs_warp.config import SeedingConfig, TriangulationConfig
from rgs_warp.datasets.synthetic import SyntheticDataset
from rgs_warp.eval.photometric import psnr
from rgs_warp.geometry import invert_pose, quat_to_matrix, se3_exp
from rgs_warp.kernels import seeding as ks
from rgs_warp.kernels.dlt import mat34d
from rgs_warp.keyframes import KeyframeBuffer
from rgs_warp.render import Renderer
from rgs_warp.sampling import CONFIDENCE_LEVELS, compact_mask, poisson_disk_subsample, thin_blue_noise
from rgs_warp.seeding import PointSeeder, Seeder
from rgs_warp.triangulation import TriangulatedPoints, Triangulator, projection_matrices
from rgs_warp.types import Camera, GaussianMap


def priority(confidence, index, levels=CONFIDENCE_LEVELS):
    """kernels/sampling.py's dart priority in NumPy: confidence level, then lowbias32 of the index."""
    x = np.asarray(index).astype(np.uint64)
    m = np.uint64(0xFFFFFFFF)
    x ^= x >> np.uint64(16)
    x = (x * np.uint64(0x7FEB352D)) & m
    x ^= x >> np.uint64(15)
    x = (x * np.uint64(0x846CA68B)) & m
    x ^= x >> np.uint64(16)
    level = (np.clip(confidence, 0, 1).astype(np.float32) * np.float32(levels)).astype(np.int64)
    return level * (1 << 32) + x.astype(np.int64)


def greedy(points, radius, prio):
    """Sequential greedy in priority order: keep a point unless a kept one conflicts with it."""
    tree = cKDTree(points)
    keep = np.zeros(len(points), bool)
    for i in np.argsort(-prio, kind="stable"):
        near = np.asarray(tree.query_ball_point(points[i], radius.max()), int)
        d = np.linalg.norm(points[near] - points[i], axis=1)
        if not np.any(keep[near] & (d < np.maximum(radius[i], radius[near]))):
            keep[i] = True
    return keep


def _poisson(points, radius, confidence, device, candidate=None):
    counters = wp.zeros(2, dtype=wp.int32, device=device)
    keep = poisson_disk_subsample(
        wp.array(points.astype(np.float32), dtype=wp.vec3, device=device),
        wp.array(radius.astype(np.float32), device=device),
        wp.array(confidence.astype(np.float32), device=device),
        candidate=None if candidate is None else wp.array(candidate.astype(np.int32), device=device),
        counters=counters,
    )
    return keep.numpy(), int(counters.numpy()[1])


def test_poisson_separation_coverage_and_greedy_order(device):
    rng = np.random.default_rng(0)
    n = 3000
    points = (rng.random((n, 3)) * [2.0, 2.0, 0.1]).astype(np.float32)  # a thick wall
    radius = np.full(n, 0.08, np.float32)
    confidence = rng.random(n).astype(np.float32)
    keep, rounds = _poisson(points, radius, confidence, device)
    assert set(np.unique(keep)) == {0, 1}
    kept = points[keep == 1]
    d, _ = cKDTree(kept).query(kept, 2)
    assert d[:, 1].min() >= 0.08 * (1 - 1e-6)
    d, _ = cKDTree(kept).query(points)
    assert d.max() <= 2 * 0.08  # the spec's coverage bound (the scheme guarantees r)
    np.testing.assert_array_equal(keep == 1, greedy(points, radius, priority(confidence, np.arange(n))))
    assert rounds <= 20
    # higher confidence preferred, and deterministic
    assert confidence[keep == 1].mean() > confidence.mean() + 0.1
    # every rejected point lost to a kept neighbour of at least its confidence level
    level = np.floor(confidence * CONFIDENCE_LEVELS)
    tree = cKDTree(points[keep == 1])
    for i in np.flatnonzero(keep == 0):
        near = np.flatnonzero(keep == 1)[tree.query_ball_point(points[i], 0.08)]
        assert level[near].max() >= level[i]
    np.testing.assert_array_equal(keep, _poisson(points, radius, confidence, device)[0])


def test_poisson_variable_radius_and_candidates(device):
    rng = np.random.default_rng(1)
    n = 2000
    points = (rng.random((n, 3)) * [2.0, 2.0, 2.0]).astype(np.float32)
    radius = (0.05 + 0.15 * points[:, 2] / 2.0).astype(np.float32)  # pixel footprint grows with depth
    confidence = rng.random(n).astype(np.float32)
    candidate = rng.random(n) < 0.8
    keep, _ = _poisson(points, radius, confidence, device, candidate)
    assert not np.any(keep[~candidate])
    k = np.flatnonzero(keep)
    d = np.linalg.norm(points[k, None] - points[None, k], axis=2)
    np.fill_diagonal(d, np.inf)
    assert np.all(d >= np.maximum(radius[k, None], radius[None, k]) * (1 - 1e-6))
    c = np.flatnonzero(candidate)
    d = np.linalg.norm(points[c, None] - points[None, k], axis=2)
    assert np.all(np.any(d <= np.maximum(radius[c, None], radius[None, k]), axis=1))
    ref = np.zeros(n, bool)
    ref[c] = greedy(points[c], radius[c], priority(confidence[c], c))
    np.testing.assert_array_equal(keep == 1, ref)


def test_poisson_confidence_wins_conflicts(device):
    # pairs of points 1 cm apart (r = 5 cm), pairs 1 m apart: exactly the more confident of each pair
    rng = np.random.default_rng(2)
    base = np.stack(np.meshgrid(np.arange(10.0), np.arange(10.0), [0.0]), -1).reshape(-1, 3)
    points = np.concatenate([base, base + [0.01, 0, 0]]).astype(np.float32)
    # distinct confidence levels within each pair (within a level the hashed index decides)
    level_a = rng.integers(0, CONFIDENCE_LEVELS, 100)
    level_b = (level_a + rng.integers(1, CONFIDENCE_LEVELS, 100)) % CONFIDENCE_LEVELS
    confidence = (np.concatenate([level_a, level_b]) + 0.5) / CONFIDENCE_LEVELS
    keep, _ = _poisson(points, np.full(len(points), 0.05), confidence, device)
    first_wins = level_a > level_b
    np.testing.assert_array_equal(keep[:100] == 1, first_wins)
    np.testing.assert_array_equal(keep[100:] == 1, ~first_wins)


def _thin(confidence, spacing, device):
    counters = wp.zeros(2, dtype=wp.int32, device=device)
    keep = thin_blue_noise(wp.array(confidence.astype(np.float32), device=device), spacing, counters=counters)
    return keep.numpy(), int(counters.numpy()[1])


def test_thinning_blue_noise(device):
    rng = np.random.default_rng(3)
    h, w, spacing = 48, 64, 3.0
    confidence = np.full((h, w), 0.6, np.float32)  # left half: homogeneous
    confidence[:, 32:] = rng.random((h, 32))  # right half: varied
    confidence[:4] = 0.0  # unmatched rows
    keep, rounds = _thin(confidence, spacing, device)
    yx = np.argwhere(keep == 1).astype(float)
    d, _ = cKDTree(yx).query(yx, 2)
    assert d[:, 1].min() >= spacing  # no clumps
    d, _ = cKDTree(yx).query(np.argwhere(confidence > 0).astype(float))
    assert d.max() < spacing  # maximal: every matched pixel has a kept one nearby
    assert not keep[:4].any()
    # the homogeneous half is not emptied: a maximal 3-px Poisson set covers ~1 pixel in 8-12
    density = keep[4:, :29].mean()
    assert 1 / 14 < density < 1 / 6
    # confident pixels preferred, exactly the greedy set in confidence order
    right = confidence[:, 32:]
    assert right[keep[:, 32:] == 1].mean() > right[4:].mean() + 0.15
    idx = np.argwhere(confidence > 0)
    ref = greedy(
        idx.astype(float), np.full(len(idx), spacing), priority(confidence[confidence > 0], idx[:, 0] * w + idx[:, 1])
    )
    np.testing.assert_array_equal(keep[confidence > 0] == 1, ref)
    assert rounds <= 20


def test_compact_mask(device):
    rng = np.random.default_rng(4)
    mask = (rng.random((30, 40)) < 0.3).astype(np.int32)
    idx, count = compact_mask(wp.array(mask, device=device))
    c = int(count.numpy()[0])
    assert c == mask.sum()
    np.testing.assert_array_equal(idx.numpy()[:c], np.flatnonzero(mask))


# ---- PointSeeder ------------------------------------------------------------------------------------


def synthetic_seeding(
    device, cfg=None, width=160, height=90, noise_px=0.3, seed=0, ids=(10, 9, 11), n_frames=12, **options
):
    """Seed room0's keyframe 10 (of 12) from ground-truth correspondences with keyframes 9 and 11.

    Correspondences: every reference pixel with depth, back-projected with the true depth and pose,
    projected into each neighbour (+ ``noise_px`` Gaussian noise per coordinate), confident where
    the neighbour sees it unoccluded (its depth within 2 %).  Triangulated with the Triangulator,
    seeded into an empty map.  Returns a dict of everything the checks need."""
    ds = SyntheticDataset(
        "room0",
        width=width,
        height=height,
        n_frames=n_frames,
        exposure_drift=True,
        device=device,
        prefetch=0,
        progress=False,
        **options,
    )
    cam = ds.camera
    frames = [ds[i] for i in ids]
    exposure = np.loadtxt(ds.root / "exposure.txt")[list(ids)]
    rng = np.random.default_rng(seed)
    ref = frames[0]
    v, u = np.nonzero(ref.depth > 0)
    z = ref.depth[v, u].astype(np.float64)
    x_cam = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], 1)
    X_true = x_cam @ ref.pose_gt[:3, :3].T + ref.pose_gt[:3, 3]
    P = projection_matrices(cam.K, np.stack([f.pose_gt for f in frames]))
    match_uv, conf = [], []
    for f, Pn in zip(frames[1:], P[1:], strict=True):
        y = X_true @ Pn[:, :3].T + Pn[:, 3]
        uv = y[:, :2] / y[:, 2:]
        iu, iv = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
        inside = (y[:, 2] > 0) & (iu >= 0) & (iu < cam.width) & (iv >= 0) & (iv < cam.height)
        d = np.where(inside, f.depth[np.clip(iv, 0, cam.height - 1), np.clip(iu, 0, cam.width - 1)], 0.0)
        visible = inside & (np.abs(d - y[:, 2]) < 0.02 * y[:, 2])
        match_uv.append(uv + rng.normal(size=uv.shape) * noise_px)
        conf.append(visible.astype(np.float32))
    match_uv, conf = np.stack(match_uv, 1), np.stack(conf, 1)
    tri = Triangulator(TriangulationConfig(), device)
    points = tri.triangulate(
        wp.array(P, dtype=mat34d, device=device),
        wp.array(np.stack([u, v], 1).astype(np.float64), dtype=wp.vec2d, device=device),
        wp.array(match_uv, dtype=wp.vec2d, device=device),
        wp.array(conf, device=device),
    )
    aggregated = (0.6 + 0.4 * rng.random(len(u))).astype(np.float32)
    keyframes = KeyframeBuffer(4, cam.width, cam.height, device)
    views = zip(ids, frames, exposure, strict=True)
    slots = [keyframes.add(i, f.pose_gt, f.rgb, f.depth, exposure=e) for i, f, e in views]
    seeder = PointSeeder(cfg or SeedingConfig(), cam, device)
    gmap = GaussianMap(1024, sh_degree=2, device=device)
    added = seeder.seed(points, wp.array(aggregated, device=device), keyframes, slots, gmap)
    return {
        "camera": cam,
        "frames": frames,
        "exposure": exposure,
        "uv": np.stack([u, v], 1),
        "X_true": X_true,
        "valid": points.valid.numpy().astype(bool),
        "X": points.X.numpy(),
        "seed_index": seeder.seed_index.numpy()[:added].copy(),
        "gmap": gmap,
        "added": added,
    }


def render_reference(case, device):
    """The reference keyframe rendered from the seeded map, with its exposure applied (Eq. 3)."""
    cam, ref = case["camera"], case["frames"][0]
    g, b = case["exposure"][0]
    out = Renderer(device).forward(case["gmap"], cam, ref.pose_gt)
    return np.clip(g * out.color.numpy() + b, 0.0, 1.0), out.alpha.numpy().copy()


def look_at(eye, target):
    """Camera-to-world pose (OpenCV axes) at ``eye`` looking at ``target``."""
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross([0.0, -1.0, 0.0], z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    T[:3, 3] = eye
    return T


CAM = Camera(fx=100.0, fy=90.0, cx=31.5, cy=23.5, width=64, height=48)


def points_of(X, residual_px, parallax_deg, support, valid, device):
    """TriangulatedPoints made by hand."""
    n = len(X)

    def full(value, dtype):
        return wp.array(np.broadcast_to(np.asarray(value), (n,)).copy(), dtype=dtype, device=device)

    return TriangulatedPoints(
        wp.array(np.asarray(X, np.float64), dtype=wp.vec3d, device=device),
        full(residual_px, wp.float64),
        full(parallax_deg, wp.float64),
        full(support, wp.int32),
        full(valid, wp.int32),
    )


def seed_points(points, confidence, poses, device, cfg=None, images=None, exposure=None):
    """Seed into a fresh map whose SH rows hold garbage (the Seeder must zero higher bands)."""
    keyframes = KeyframeBuffer(max(len(poses), 2), CAM.width, CAM.height, device)
    for v, T in enumerate(poses):
        rgb = np.zeros((CAM.height, CAM.width, 3), np.float32) if images is None else images[v]
        keyframes.add(v, T, rgb, exposure=(1.0, 0.0) if exposure is None else exposure[v])
    seeder = PointSeeder(cfg or SeedingConfig(), CAM, device)
    gmap = GaussianMap(16, sh_degree=2, device=device)
    gmap.sh.fill_(wp.vec3(7.0, 7.0, 7.0))
    added = seeder.seed(
        points, wp.array(np.asarray(confidence, np.float32), device=device), keyframes, list(range(len(poses))), gmap
    )
    out = gmap.to_numpy()
    return out, seeder.seed_index.numpy()[:added].copy()


@pytest.mark.parametrize("normal_true", [(0.3, -0.2, -1.0), (0.8, 0.2, -0.6), (0.1, 0.7, -0.5)])
def test_seeder_plane_frame_matches_numpy_pca(normal_true, device):
    rng = np.random.default_rng(5)
    T_ref = look_at(np.array([0.3, -0.2, -0.5]), np.array([0.0, 0.0, 2.0]))
    normal_true = np.array(normal_true) / np.linalg.norm(normal_true)
    # every reference pixel's ray meets the plane n . X = n . (0, 0, 2): a slanted wall seen at ~2 m
    u, v = np.meshgrid(np.arange(CAM.width), np.arange(CAM.height))
    rays = np.stack([(u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy, np.ones_like(u, float)], -1).reshape(-1, 3)
    rays = rays @ T_ref[:3, :3].T
    C = T_ref[:3, 3]
    t = (normal_true @ [0.0, 0.0, 2.0] - normal_true @ C) / (rays @ normal_true)
    X = C + t[:, None] * rays + rng.normal(size=(len(t), 1)) * 0.002 * normal_true  # 2 mm off the plane
    isolated = C + np.array([[0.0, 0.0, 1.0], [0.3, 0.1, 1.2]]) @ T_ref[:3, :3].T  # nothing near them
    X = np.concatenate([X, isolated])
    valid = np.ones(len(X), np.int32)
    valid[rng.random(len(X)) < 0.1] = 0
    valid[-2:] = 1
    cfg = SeedingConfig(poisson_radius_px=2.0)
    out, index = seed_points(points_of(X, 0.3, 10.0, 3, valid, device), rng.random(len(X)), [T_ref], device, cfg)
    assert len(index) > 100 and np.all(valid[index] == 1)
    np.testing.assert_allclose(out["means"], X[index], atol=1e-6)
    R = quat_to_matrix(out["rotations"])
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-5)
    normal = R[:, :, 2]  # the rotation maps the local z axis to the normal
    # NumPy: covariance of the valid points within plane_radius_px footprints, smallest eigenvector
    z = (X - C) @ T_ref[:3, 2]
    footprint = z / np.sqrt(CAM.fx * CAM.fy)
    tree = cKDTree(X[valid == 1])
    ref_normals = []
    for k in index:
        nb = X[valid == 1][tree.query_ball_point(X[k], cfg.plane_radius_px * footprint[k])]
        to_cam = (C - X[k]) / np.linalg.norm(C - X[k])
        if len(nb) < cfg.plane_min_neighbours:
            ref_normals.append(to_cam)
            continue
        n = np.linalg.eigh(np.cov(nb.T, bias=True))[1][:, 0]
        ref_normals.append(n if n @ to_cam >= 0 else -n)
    ref_normals = np.array(ref_normals)
    dots = np.sum(normal * ref_normals, 1)
    assert np.all(dots > 1 - 1e-4), np.sort(dots)[:5]
    # the fit finds the wall (2 mm noise over a ~10 cm patch: within a few degrees), facing the camera
    on_wall = index < len(X) - 2
    assert np.median(np.abs(normal[on_wall] @ normal_true)) > np.cos(np.radians(3))
    # isolated seeds fall back to the viewing direction
    for k in (len(X) - 2, len(X) - 1):
        np.testing.assert_allclose(normal[index == k][0], (C - X[k]) / np.linalg.norm(C - X[k]), atol=1e-5)


def test_seeder_scales_eq13_and_opacity_eq14(device):
    # six points, fewer than plane_min_neighbours: normal = viewing direction, cos(incidence) = 1
    T_ref = np.eye(4)
    cfg = SeedingConfig(poisson_radius_px=6.0, tangential_scale=0.8, min_residual_px=0.25, plane_min_neighbours=7)
    depth = np.array([1.0, 2.0, 3.0, 4.0, 2.5, 1.5])
    X = np.stack([np.linspace(-0.4, 0.4, 6) * depth, np.zeros(6), depth], 1)
    residual = np.array([0.4, 0.05, 1.5, 0.3, 0.6, 0.0])
    parallax = np.array([5.0, 40.0, 1.0, 12.0, 3.0, 20.0])
    support = np.array([3, 3, 7, 15, 7, 3])  # 2, 2, 3, 4, 3, 2 views
    confidence = np.array([0.0, 1.0, 0.5, 0.25, 2.0, -1.0])  # outside [0, 1] clips
    poses = [T_ref] + [np.eye(4) + np.pad(np.eye(3)[k : k + 1].T * 0.2, ((0, 1), (3, 0))) for k in range(3)]
    out, index = seed_points(points_of(X, residual, parallax, support, 1, device), confidence, poses, device, cfg)
    np.testing.assert_array_equal(np.sort(index), np.arange(6))
    order = np.argsort(index)
    scales = np.exp(out["log_scales"][order])
    # by hand: s_perp = tangential_scale * poisson_radius_px * z / sqrt(fx fy)
    f = np.sqrt(100.0 * 90.0)
    s_perp = 0.8 * 6.0 * depth / f
    views = np.array([2, 2, 3, 4, 3, 2])
    sigma_px = np.maximum(residual * np.sqrt(2 * views / (2 * views - 3)), 0.25)
    s_par = np.clip(depth * sigma_px / (f * np.tan(np.radians(parallax))), 0.1 * s_perp, 1.0 * s_perp)
    np.testing.assert_allclose(scales[:, 0], s_perp, rtol=1e-5)
    np.testing.assert_allclose(scales[:, 1], s_perp, rtol=1e-5)
    np.testing.assert_allclose(scales[:, 2], s_par, rtol=1e-4)
    # the cases cover both clips and the unclipped middle
    raw = depth * sigma_px / (f * np.tan(np.radians(parallax)))
    assert np.any(raw < 0.1 * s_perp) and np.any(raw > s_perp) and np.any((raw > 0.1 * s_perp) & (raw < s_perp))
    alpha = 1 / (1 + np.exp(-out["opacity_logits"][order]))
    np.testing.assert_allclose(alpha, 0.1 + 0.8 * np.clip(confidence, 0, 1), atol=1e-5)


def test_seeder_without_valid_points_adds_nothing(device):
    X = np.array([[0.0, 0.0, 2.0], [np.nan, np.nan, np.nan], [0.0, 0.0, -1.0]])
    out, index = seed_points(points_of(X, 0.3, 10.0, 3, [0, 1, 1], device), np.ones(3), [np.eye(4)], device)
    assert len(index) == 0 and len(out["means"]) == 0


def bilinear(image, u, v):
    u0 = np.minimum(np.floor(u).astype(int), image.shape[1] - 2)
    v0 = np.minimum(np.floor(v).astype(int), image.shape[0] - 2)
    a, b = (u - u0)[:, None], (v - v0)[:, None]
    top = (1 - a) * image[v0, u0] + a * image[v0, u0 + 1]
    return (1 - b) * top + b * ((1 - a) * image[v0 + 1, u0] + a * image[v0 + 1, u0 + 1])


def test_seeder_colour_is_exposure_corrected_median(device):
    # a textured wall z = 3 seen by 5 cameras with different exposures (Eq. 3: I = g C + b); view 3 is
    # blocked by a white occluder, which the median must ignore
    rng = np.random.default_rng(6)

    def texture(P):
        return np.clip(
            0.5 + 0.3 * np.stack([np.sin(3 * P[:, 0]), np.cos(4 * P[:, 1]), np.sin(2 * P[:, 0] + 3 * P[:, 1])], 1), 0, 1
        )

    eyes = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [-0.3, 0.1, 0.0], [0.0, 0.3, 0.1], [0.1, -0.3, 0.0]])
    poses = [look_at(e, np.array([0.0, 0.0, 3.0])) for e in eyes]
    exposure = np.array([[1.0, 0.0], [1.2, -0.05], [0.8, 0.05], [1.0, 0.0], [0.9, 0.02]])
    u, v = np.meshgrid(np.arange(CAM.width), np.arange(CAM.height))
    images = []
    for T, (g, b) in zip(poses, exposure, strict=True):
        rays = np.stack([(u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy, np.ones_like(u, float)], -1).reshape(-1, 3)
        rays = rays @ T[:3, :3].T
        P = T[:3, 3] + ((3.0 - T[2, 3]) / rays[:, 2])[:, None] * rays
        images.append((g * texture(P) + b).reshape(CAM.height, CAM.width, 3).astype(np.float32))
    images[3][:] = 1.0
    n = 300
    X = np.stack([rng.uniform(-0.6, 0.6, n), rng.uniform(-0.4, 0.4, n), np.full(n, 3.0)], 1)
    support = rng.integers(0, 32, n) | 1  # the reference always supports
    support[:100] = 31  # all five views: one outlier among five
    cfg = SeedingConfig(poisson_radius_px=0.01)  # keep every point
    out, index = seed_points(
        points_of(X, 0.3, 10.0, support, 1, device), np.ones(n), poses, device, cfg, images, exposure
    )
    assert len(index) == n
    colour = out["sh"][:, 0] * 0.28209479177387814 + 0.5
    assert np.all(out["sh"][:, 1:] == 0.0)  # higher bands start at zero
    # NumPy reference: per-channel median of (I - b) / g over supporting views where X projects inside
    ref = np.empty((n, 3))
    for i, k in enumerate(index):
        samples = []
        for view, (T, (g, b)) in enumerate(zip(poses, exposure, strict=True)):
            y = (X[k] - T[:3, 3]) @ T[:3, :3]
            pu, pv = CAM.fx * y[0] / y[2] + CAM.cx, CAM.fy * y[1] / y[2] + CAM.cy
            if (support[k] >> view) & 1 and 0 <= pu <= CAM.width - 1 and 0 <= pv <= CAM.height - 1:
                samples.append((bilinear(images[view], np.array([pu]), np.array([pv]))[0] - b) / g)
        ref[i] = np.median(samples, axis=0)
    np.testing.assert_allclose(colour, ref, atol=2e-5)
    # with all five views the occluded one does not spoil the colour: it stays the wall's texture
    five = index < 100
    np.testing.assert_allclose(colour[five], texture(X[index[five]]), atol=0.03)


def surface_normals(depth, cam, T_WC):
    """World normals (facing the camera) of the depth map by central differences; NaN at depth edges."""
    v, u = np.mgrid[0 : cam.height, 0 : cam.width]
    X = np.stack([(u - cam.cx) / cam.fx * depth, (v - cam.cy) / cam.fy * depth, depth], -1)
    du, dv = np.zeros_like(X), np.zeros_like(X)
    du[:, 1:-1], dv[1:-1] = X[:, 2:] - X[:, :-2], X[2:] - X[:-2]
    n = np.cross(du, dv)
    n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-12
    n = np.where(np.sum(n * X, -1, keepdims=True) > 0, -n, n)
    # both differences on one surface (no depth edge): second differences below 1 % of the depth
    c = depth[1:-1, 1:-1]
    smooth = np.zeros(depth.shape, bool)
    smooth[1:-1, 1:-1] = (np.abs(depth[1:-1, 2:] + depth[1:-1, :-2] - 2 * c) < 0.01 * c) & (
        np.abs(depth[2:, 1:-1] + depth[:-2, 1:-1] - 2 * c) < 0.01 * c
    )
    return np.where(smooth[..., None] & (depth[..., None] > 0), n @ T_WC[:3, :3].T, np.nan)


def test_seeder_end_to_end_on_synthetic_room(device):
    """room0 keyframe 15 of 30 with keyframes 13 and 18 (0.3 px match noise, exposure drift): the
    pair of neighbours with the most overlap whose median triangulated depth error is below 1 %
    (room0's path mostly turns, and moves along the optical axis where it does not)."""
    case = synthetic_seeding(device, ids=(15, 13, 18), n_frames=30)
    cam, ref, gmap = case["camera"], case["frames"][0], case["gmap"]
    valid, index = case["valid"], case["seed_index"]
    T = ref.pose_gt

    def depth(P):
        return (P - T[:3, 3]) @ T[:3, 2]

    error = np.abs(depth(case["X"]) - depth(case["X_true"])) / depth(case["X_true"])
    assert valid.mean() > 0.6 and np.median(error[valid]) < 0.01, (valid.mean(), np.median(error[valid]))
    # Poisson-disk subset of the valid points: no two seeds closer than the radius (1 footprint)
    assert len(gmap) == case["added"] == len(index) and np.all(valid[index]) and 0.5 * valid.sum() < len(index)
    means = gmap.to_numpy()["means"]
    d, j = cKDTree(means).query(means, 2)
    assert np.all(d[:, 1] >= np.maximum(depth(means), depth(means[j[:, 1]])) / np.sqrt(cam.fx * cam.fy) * (1 - 1e-4))
    # orientation: the fitted normals follow the true surface
    uv = case["uv"][index]
    n_true = surface_normals(ref.depth, cam, T)[uv[:, 1], uv[:, 0]]
    n_seed = quat_to_matrix(gmap.to_numpy()["rotations"])[:, :, 2]
    ok = np.isfinite(n_true[:, 0])
    angle = np.degrees(np.arccos(np.clip(np.sum(n_true[ok] * n_seed[ok], 1), -1, 1)))
    assert np.median(angle) < 5.0, np.median(angle)
    # photometric: the seeded map (no optimisation) renders the reference keyframe where it was seeded
    image, alpha = render_reference(case, device)
    seeded = np.zeros(ref.depth.shape, bool)
    seeded[case["uv"][valid, 1], case["uv"][valid, 0]] = True
    psnr_seeded = psnr(image[seeded], ref.rgb[seeded])
    print(f"median depth error {np.median(error[valid]):.4f}, seeds {len(index)}, normal {np.median(angle):.1f} deg")
    print(f"PSNR seeded pixels {psnr_seeded:.2f} dB, whole image {psnr(image, ref.rgb):.2f} dB")
    assert alpha[seeded].mean() > 0.95
    assert psnr_seeded > 32.0


# ---- seeds ------------------------------------------------------------------------------------------
def test_depth_points_backprojects_the_cell_centres(device):
    rng = np.random.default_rng(17)
    H, W, stride = 22, 26, 4
    fx, fy, cx, cy = 20.0, 21.0, 12.5, 10.5
    v, u = np.mgrid[0:H, 0:W]
    depth = 2.0 + 0.01 * u + 0.02 * v + 0.0005 * u**2  # smooth: second differences ~0.016 m
    depth[:, 13:] += 1.0  # a step edge between the cells at u = 10 and u = 14
    depth[6, 18] = 0.0  # an invalid cell centre
    depth[10, 22] = 0.0  # a border cell without depth, the right neighbour of the cell (10, 18)
    depth = depth.astype(np.float32)
    alpha = rng.uniform(0, 0.3, (H, W)).astype(np.float32)
    alpha[14, 6] = 0.9  # covered by the map already
    T_WC = se3_exp(np.array([0.3, -0.2, 0.1, 0.2, -0.1, 0.3]))
    hg, wg = H // stride, W // stride
    out = [wp.zeros(hg * wg, dtype=t, device=device) for t in (wp.vec3d, wp.float64, wp.float64, wp.int32, wp.int32)]
    max_rel_jump, max_alpha = 0.05, 0.5
    wp.launch(
        ks.depth_points,
        dim=(hg, wg),
        inputs=[wp.array(depth, device=device), fx, fy, cx, cy, wp.mat44d(T_WC), stride, max_rel_jump, 0.7, 90.0]
        + [wp.array(alpha, device=device), max_alpha],
        outputs=out,
        device=device,
    )
    X, residual, parallax, support, valid = (a.numpy() for a in out)

    gy, gx = np.mgrid[0:hg, 0:wg]
    uc, vc = (gx * stride + stride // 2).ravel(), (gy * stride + stride // 2).ravel()
    z = depth[vc, uc].astype(np.float64)
    ok = (z > 0) & (alpha[vc, uc] < max_alpha)
    inner = (uc >= stride) & (uc + stride < W) & (vc >= stride) & (vc + stride < H)
    for i in np.flatnonzero(ok & inner):
        nb = [depth[vc[i], uc[i] - stride], depth[vc[i], uc[i] + stride]]
        nb += [depth[vc[i] - stride, uc[i]], depth[vc[i] + stride, uc[i]]]
        ok[i] = min(nb) > 0 and max(abs(nb[0] + nb[1] - 2 * z[i]), abs(nb[2] + nb[3] - 2 * z[i])) < max_rel_jump * z[i]
    P = np.stack([(uc - cx) / fx * z, (vc - cy) / fy * z, z], axis=1)
    np.testing.assert_allclose(X, P @ T_WC[:3, :3].T + T_WC[:3, 3], atol=1e-6)
    np.testing.assert_array_equal(valid, ok.astype(np.int32))
    cell = {(int(a), int(b)): bool(o) for a, b, o in zip(vc, uc, ok, strict=True)}
    assert not cell[(6, 10)] and not cell[(6, 14)] and cell[(6, 6)]  # the step edge; a smooth interior cell
    assert not cell[(6, 18)] and not cell[(10, 22)] and not cell[(14, 6)]  # no depth; covered
    assert not cell[(10, 18)] and cell[(14, 18)]  # a neighbour without depth
    assert cell[(2, 2)] and cell[(18, 22)]  # border cells skip the discontinuity test
    assert np.all(residual == np.float32(0.7)) and np.all(parallax == 90.0) and np.all(support == 1)


def test_mask_covered_points(device):
    rng = np.random.default_rng(18)
    H, W, n = 12, 16, 300
    fx, fy, cx, cy = 15.0, 15.0, 7.5, 5.5
    T_WC = se3_exp(np.array([0.2, 0.1, -0.3, 0.1, 0.2, -0.1]))
    uv = np.stack([rng.uniform(-2, W + 1, n), rng.uniform(-2, H + 1, n)], axis=1)  # some off the image
    z = rng.uniform(1.0, 3.0, n)
    P = np.stack([(uv[:, 0] - cx) / fx * z, (uv[:, 1] - cy) / fy * z, z], axis=1)
    X = P @ T_WC[:3, :3].T + T_WC[:3, 3]
    alpha = rng.uniform(0.3, 1.0, (H, W)).astype(np.float32)
    d_map = rng.uniform(1.0, 3.0, (H, W))
    valid0 = (rng.uniform(size=n) < 0.8).astype(np.int32)
    # pixel of each point as the kernel takes it: rounded, clamped into the image
    pu = np.clip(np.round(uv[:, 0]).astype(int), 0, W - 1)
    pv = np.clip(np.round(uv[:, 1]).astype(int), 0, H - 1)
    near = rng.uniform(size=n) < 0.5
    d_map[pv[near], pu[near]] = z[near] * (1 + rng.uniform(-0.03, 0.03, near.sum()))  # the map agrees
    rendered_depth = (alpha * d_map).astype(np.float32)
    max_alpha, tol = 0.6, 0.05
    valid = wp.array(valid0, dtype=wp.int32, device=device)
    wp.launch(
        ks.mask_covered_points,
        dim=n,
        inputs=[wp.array(uv, dtype=wp.vec2d, device=device), wp.array(alpha, device=device)]
        + [wp.array(rendered_depth, device=device), wp.array(X, dtype=wp.vec3d, device=device)]
        + [wp.mat44d(invert_pose(T_WC)), max_alpha, tol],
        outputs=[valid],
        device=device,
    )
    a = alpha[pv, pu].astype(np.float64)
    covered = (a >= max_alpha) & (np.abs(rendered_depth[pv, pu] / a - z) <= tol * z)
    ref = np.where(covered, 0, valid0)
    assert (valid0 & covered).sum() > 20 and (valid0 & ~covered).sum() > 20
    np.testing.assert_array_equal(valid.numpy(), ref)


def test_reject_depth_inconsistent_points(device):
    rng = np.random.default_rng(19)
    H, W, n = 12, 16, 300
    fx, fy, cx, cy = 15.0, 15.0, 7.5, 5.5
    T_WC = se3_exp(np.array([-0.1, 0.2, 0.3, -0.2, 0.1, 0.1]))
    uv = np.stack([rng.uniform(-2, W + 1, n), rng.uniform(-2, H + 1, n)], axis=1)  # some off the image
    z = rng.uniform(1.0, 3.0, n)
    P = np.stack([(uv[:, 0] - cx) / fx * z, (uv[:, 1] - cy) / fy * z, z], axis=1)
    X = P @ T_WC[:3, :3].T + T_WC[:3, 3]
    measured = rng.uniform(1.0, 3.0, (H, W)).astype(np.float32)
    measured[rng.uniform(size=(H, W)) < 0.15] = 0.0  # no measurement there
    pu = np.clip(np.round(uv[:, 0]).astype(int), 0, W - 1)
    pv = np.clip(np.round(uv[:, 1]).astype(int), 0, H - 1)
    agree = rng.uniform(size=n) < 0.5
    has = measured[pv, pu] > 0
    measured[pv[agree & has], pu[agree & has]] = (z * (1 + rng.uniform(-0.03, 0.03, n)))[agree & has]
    valid0 = (rng.uniform(size=n) < 0.8).astype(np.int32)
    tol = 0.05
    valid = wp.array(valid0, dtype=wp.int32, device=device)
    wp.launch(
        ks.reject_depth_inconsistent_points,
        dim=n,
        inputs=[wp.array(uv, dtype=wp.vec2d, device=device), wp.array(measured, device=device)]
        + [wp.array(X, dtype=wp.vec3d, device=device), wp.mat44d(invert_pose(T_WC)), tol],
        outputs=[valid],
        device=device,
    )
    d = measured[pv, pu].astype(np.float64)
    inconsistent = (d > 0) & (np.abs(z - d) > tol * d)
    ref = np.where(inconsistent, 0, valid0)
    assert (valid0 & inconsistent).sum() > 20 and (valid0 & ~inconsistent & (d > 0)).sum() > 20
    assert (valid0 & (d == 0)).sum() > 5  # points without a measurement are kept
    np.testing.assert_array_equal(valid.numpy(), ref)


def test_union_alpha(device):
    rng = np.random.default_rng(23)
    a, b = rng.uniform(0, 1, (2, 7, 9)).astype(np.float32)
    out = wp.zeros((7, 9), dtype=wp.float32, device=device)
    aw, bw = wp.array(a, device=device), wp.array(b, device=device)
    wp.launch(ks.union_alpha, dim=(7, 9), inputs=[aw, bw], outputs=[out], device=device)
    # compositing the two layers in either order leaves transmittance (1 - a)(1 - b)
    np.testing.assert_allclose(out.numpy(), 1.0 - (1.0 - a) * (1.0 - b), atol=1e-6)
    wp.launch(ks.union_alpha, dim=(7, 9), inputs=[aw, bw], outputs=[aw], device=device)  # in place
    np.testing.assert_allclose(aw.numpy(), out.numpy(), atol=0)


def test_extrapolate_depth_step_matches_numpy(device):
    # one step against a reference written another way: the largest of the 3x3 window's values (holes
    # are 0, so they never win), kept where the pixel was measured; then n steps reach n pixels
    rng = np.random.default_rng(31)
    depth = rng.uniform(0.5, 4.0, (11, 14)).astype(np.float32)
    depth[rng.uniform(size=depth.shape) < 0.45] = 0.0
    depth[:, :5] = 0.0  # a border band 5 px wide
    src = wp.array(depth, device=device)
    out = wp.zeros_like(src)
    wp.launch(ks.extrapolate_depth_step, dim=depth.shape, inputs=[src], outputs=[out], device=device)
    padded = np.pad(depth, 1)
    windows = np.stack([padded[dy : dy + 11, dx : dx + 14] for dy in range(3) for dx in range(3)])
    ref = np.where(depth > 0, depth, windows.max(axis=0))
    np.testing.assert_array_equal(out.numpy(), ref)
    assert (ref[:, 4] > 0).sum() > 5 and (ref[:, :4] == 0).all()  # one step: one more column of the band
    for _ in range(4):
        wp.launch(ks.extrapolate_depth_step, dim=depth.shape, inputs=[out], outputs=[src], device=device)
        out, src = src, out
    assert (out.numpy() > 0).all()


# ---- the Seeder stage --------------------------------------------------------------------------------
def _wall_keyframe(device, hole=None):
    """One keyframe looking at a textured wall at 2 m (identity pose); ``hole``: (rows, cols) slices
    without measured depth."""
    rng = np.random.default_rng(8)
    rgb = rng.uniform(0.2, 0.8, (CAM.height, CAM.width, 3)).astype(np.float32)
    depth = np.full((CAM.height, CAM.width), 2.0, np.float32)
    if hole is not None:
        depth[hole] = 0.0
    keyframes = KeyframeBuffer(2, CAM.width, CAM.height, device)
    return keyframes, keyframes.add(0, np.eye(4), rgb, depth)


def test_seeder_depth_seeds(device):
    # the first keyframe of an empty map gets measured-depth seeds; the pixels without depth get none
    hole = (slice(10, 30), slice(20, 44))
    keyframes, slot = _wall_keyframe(device, hole)
    cfg = SeedingConfig(depth_extrapolate_px=0)  # measured depth only
    renderer = Renderer(device)
    seeder = Seeder(cfg, CAM, device, mode="rgbd", renderer=renderer)
    gmap = GaussianMap(16, sh_degree=2, device=device)
    added = seeder.seed_depth(gmap, keyframes, slot)
    assert added == len(gmap) > 50
    z = gmap.to_numpy()["means"][:, 2]
    assert np.isclose(z, 2.0, atol=1e-4).all()
    alpha = renderer.forward(gmap, CAM, np.eye(4)).alpha.numpy()
    inside = alpha[12:28, 22:42]  # the hole, away from its border (the seeds need valid neighbours)
    assert inside.max() < 0.1, inside.max()
    # a second keyframe at the same place: covered, nothing new
    slot2 = keyframes.add(1, np.eye(4), keyframes.rgb[slot].numpy(), keyframes.depth[slot].numpy())
    assert seeder.seed_depth(gmap, keyframes, slot2) < 0.05 * added


@pytest.mark.parametrize("extrapolate_px", [0, 12])
def test_seeder_extrapolates_depth_into_the_border_without_it(device, extrapolate_px):
    # a registered depth camera sees less than the colour camera: a band along the left edge has no
    # depth.  With depth_extrapolate_px the band gets seeds at the nearby measured depth (a wall at 2 m)
    # and the map covers it; without, it stays uncovered.  Measured pixels are seeded as before.
    band = (slice(None), slice(0, 10))
    keyframes, slot = _wall_keyframe(device, band)
    renderer = Renderer(device)
    seeder = Seeder(SeedingConfig(depth_extrapolate_px=extrapolate_px), CAM, device, mode="rgbd", renderer=renderer)
    gmap = GaussianMap(16, sh_degree=2, device=device)
    added = seeder.seed_depth(gmap, keyframes, slot)
    means = gmap.to_numpy()["means"]
    np.testing.assert_allclose(means[:, 2], 2.0, atol=1e-4)  # every seed on the wall, none floating
    u = CAM.fx * means[:, 0] / means[:, 2] + CAM.cx
    assert ((u < 9.5).sum() > 20) == (extrapolate_px > 0), (u < 9.5).sum()
    alpha = renderer.forward(gmap, CAM, np.eye(4)).alpha.numpy()
    border, measured = alpha[4:-4, 1:8], alpha[4:-4, 20:50]
    if extrapolate_px:
        assert border.mean() > 0.8 * measured.mean() and border.min() > 0.25, (border.mean(), measured.mean())
    else:
        assert border[:, :6].max() < 0.1, border.max()
    assert added > 50


def test_frame_fill_with_the_callers_alpha_seeds_as_its_own_render(device):
    # half of a wall mapped; a fill given the map's opacity (as the SLAM passes tracking's last render)
    # adds the same seeds as one that renders it, and leaves that opacity as it was
    keyframes, slot = _wall_keyframe(device)
    depth = keyframes.depth[slot].numpy().copy()
    depth[:, CAM.width // 2 :] = 0.0
    half = keyframes.add(1, np.eye(4), keyframes.rgb[slot].numpy(), depth)
    cfg = SeedingConfig(depth_extrapolate_px=0, frame_fill_min_uncovered=0.0)
    rgb, full = keyframes.rgb[slot], keyframes.depth[slot]
    runs = []
    for given in (False, True):
        renderer = Renderer(device)
        seeder = Seeder(cfg, CAM, device, mode="rgbd", renderer=renderer)
        gmap = GaussianMap(16, sh_degree=1, device=device)
        seeder.seed_depth(gmap, keyframes, half)
        alpha = wp.clone(Renderer(device).forward(gmap, CAM, np.eye(4)).alpha) if given else None
        before = None if alpha is None else alpha.numpy().copy()
        added = seeder.fill_frame(gmap, 2, rgb, full, np.eye(4), (1.0, 0.0), alpha)
        if given:
            np.testing.assert_array_equal(alpha.numpy(), before)
        runs.append((added, seeder.pending.to_numpy()["means"]))
    assert runs[0][0] == runs[1][0] > 20
    np.testing.assert_array_equal(runs[0][1], runs[1][1])
    wrong = wp.zeros((CAM.height // 2, CAM.width // 2), dtype=wp.float32, device=device)
    with pytest.raises(ValueError, match="alpha is"):
        seeder.fill_frame(gmap, 3, rgb, full, np.eye(4), (1.0, 0.0), wrong)


def test_keep_detail_points_matches_numpy(device):
    rng = np.random.default_rng(21)
    H, W, stride, coarse, min_gradient = 13, 19, 1, 4, 0.05
    rgb = np.full((H, W, 3), 0.5, np.float32)
    rgb[:, 10:] = rng.uniform(0.0, 1.0, (H, W - 10, 3))  # detail on the right, plain on the left
    rgb[4, 3] = 0.9  # one bright pixel: detail at its four neighbours
    hg, wg = H // stride, W // stride
    valid0 = (rng.uniform(size=hg * wg) < 0.9).astype(np.int32)
    valid = wp.array(valid0, dtype=wp.int32, device=device)
    wp.launch(
        ks.keep_detail_points,
        dim=(hg, wg),
        inputs=[wp.array(rgb, dtype=wp.vec3, device=device), stride, coarse, min_gradient],
        outputs=[valid],
        device=device,
    )
    grey = rgb.mean(axis=2)
    padded = np.pad(grey, 1, mode="edge")
    du = 0.5 * (padded[1:-1, 2:] - padded[1:-1, :-2])
    dv = 0.5 * (padded[2:, 1:-1] - padded[:-2, 1:-1])
    gy, gx = np.mgrid[0:hg, 0:wg]
    u, v = (gx * stride + stride // 2).ravel(), (gy * stride + stride // 2).ravel()
    on_coarse = (u < W // coarse * coarse) & (v < H // coarse * coarse) & (u % coarse == 2) & (v % coarse == 2)
    detail = np.hypot(du, dv)[v, u] >= min_gradient
    np.testing.assert_array_equal(valid.numpy(), valid0 * (detail & ~on_coarse))
    assert detail[(v == 4) & (u == 2)].all() and not detail[(v == 4) & (u == 3)].any()  # neighbours, not the pixel
    assert valid.numpy()[(u < 9) & (v > 6)].sum() == 0  # plain image far from the bright pixel


def test_detail_seeds_go_where_the_image_has_detail(device):
    """seeding.detail_stride=1 beside depth_stride=2: a wall textured on its left half, plain on its
    right, gets about 5x the seeds on the textured half (measured: 816 against 157; the coarse grid plus
    every pixel) and the same seeds on the plain half."""
    rng = np.random.default_rng(9)
    rgb = np.full((CAM.height, CAM.width, 3), 0.5, np.float32)
    rgb[:, :32] = rng.uniform(0.2, 0.8, (CAM.height, 32, 3))
    depth = np.full((CAM.height, CAM.width), 2.0, np.float32)
    counts = {}
    for detail in (0, 1):
        keyframes = KeyframeBuffer(1, CAM.width, CAM.height, device)
        slot = keyframes.add(0, np.eye(4), rgb, depth)
        seeder = Seeder(SeedingConfig(detail_stride=detail), CAM, device, mode="rgbd")
        gmap = GaussianMap(16, sh_degree=2, device=device)
        assert seeder.seed_depth(gmap, keyframes, slot) == len(gmap)
        means = gmap.to_numpy()["means"]
        u = means[:, 0] / means[:, 2] * CAM.fx + CAM.cx
        counts[detail] = ((u < 30.5).sum(), (u > 33.5).sum())  # textured, plain (off the seam)
    (tex0, plain0), (tex1, plain1) = counts[0], counts[1]
    assert abs(tex0 - plain0) <= 0.1 * plain0, counts
    assert tex1 > 3.0 * tex0 and plain1 == plain0, counts


def test_dropped_points_park_behind_the_camera_spread_over_the_hash_grid(device):
    """Points the seeding drops (invalid, or behind the view) stay in its hash grid: they must lie
    where no seed can (behind the reference camera) and must not fill one cell, which a query
    reaching it would walk whole.  Cells counted as ``wp.HashGrid`` wraps them (128^3) at a 1 cm cell,
    about a plane-fit radius at a metre."""
    n = 20000
    T_WC = np.eye(4)
    T_WC[:3, :3] = quat_to_matrix(np.array([0.1, -0.2, 0.05, 0.97]) / np.linalg.norm([0.1, -0.2, 0.05, 0.97]))
    T_WC[:3, 3] = [0.4, -0.3, 1.2]
    T_CW = invert_pose(T_WC)
    prm = PointSeeder(SeedingConfig(), CAM, device)._params
    X = wp.array(np.random.default_rng(0).normal(size=(n, 3)), dtype=wp.vec3d, device=device)
    valid = wp.zeros(n, dtype=wp.int32, device=device)
    points = wp.zeros(n, dtype=wp.vec3, device=device)
    footprint, radius = wp.zeros(n, dtype=wp.float32, device=device), wp.zeros(n, dtype=wp.float32, device=device)
    stats = wp.zeros(2, dtype=wp.float32, device=device)
    view = wp.array([T_CW.astype(np.float32)], dtype=wp.mat44, device=device)
    wp.launch(ks.seed_footprint, dim=n, inputs=[X, valid, view, prm], outputs=[points, footprint, radius, stats])
    assert not footprint.numpy().any() and not stats.numpy().any()
    P = points.numpy().astype(np.float64)
    z = (P @ T_CW[:3, :3].T + T_CW[:3, 3])[:, 2]
    assert z.max() < -0.5  # behind the camera
    _, per_cell = np.unique(np.floor(P / 0.01).astype(np.int64) % 128, axis=0, return_counts=True)
    assert per_cell.max() <= 4
