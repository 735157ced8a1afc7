"""Poisson-disk subsampling (world space) and blue-noise thinning (image space) against brute force:
separation, coverage, confidence preference, and equality with the sequential greedy set."""

import numpy as np
import warp as wp
from scipy.spatial import cKDTree

from rgs_warp.seeding import CONFIDENCE_LEVELS, compact_mask, poisson_disk_subsample, thin_blue_noise


def priority(confidence, index, levels=CONFIDENCE_LEVELS):
    """kernels/poisson.py's dart priority in NumPy: confidence level, then lowbias32 of the index."""
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
