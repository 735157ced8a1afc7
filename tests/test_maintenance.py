"""Maintenance pass (supplement §4.5): pruning reasons and duplicate merging, each checked against an
independent NumPy reference, and the Maintainer stage that removes both from the map."""

import numpy as np
import warp as wp

from helpers_maps import flat_map
from rgs_warp.config import MappingConfig
from rgs_warp.geometry import invert_pose, matrix_to_quat
from rgs_warp.maintenance import Maintainer, MergeScratch, PruneStats, merge_duplicates, prune_mask
from rgs_warp.types import Camera, GaussianMap

SH_C0 = 0.28209479177387814
NUM_SH = 4
CAM = Camera(500.0, 500.0, 319.5, 239.5, 640, 480)


def _rot(axis: int, deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _pose() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = _rot(0, 10.0) @ _rot(1, -20.0)
    T[:3, 3] = [0.3, -0.2, 1.0]
    return T


T_WC = _pose()


def _logit(p):
    p = np.asarray(p, dtype=np.float64)
    return np.log(p / (1.0 - p))


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-np.asarray(x, dtype=np.float64)))


# ---- pruning ---------------------------------------------------------------------------------------


def _good_rows(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Gaussians that violate no bound: small, opaque enough, finite."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return {
        "means": rng.uniform(-1.0, 1.0, size=(n, 3)),
        "quats_xyzw": q / np.linalg.norm(q, axis=1, keepdims=True),
        "log_scales": np.log(rng.uniform(0.005, 0.05, size=(n, 3))),
        "opacity_logits": _logit(rng.uniform(0.2, 0.99, size=n)),
        "sh": rng.normal(scale=0.2, size=(n, NUM_SH, 3)),
    }


def _map(rows, device):
    return GaussianMap.from_numpy(**{k: np.asarray(v, np.float32) for k, v in rows.items()}, device=device)


def _prune(rows, device, obs=None, vis=None, **kw):
    gmap = _map(rows, device)
    obs_wp = None if obs is None else wp.array(np.asarray(obs, np.int32), dtype=wp.int32, device=device)
    vis_wp = None if vis is None else wp.array(np.asarray(vis, np.float32), dtype=wp.float32, device=device)
    mask, stats = prune_mask(gmap, obs_wp, vis_wp, **kw)
    return mask.numpy().astype(bool), PruneStats.read(stats)


def _flags(n, idx):
    m = np.zeros(n, dtype=bool)
    m[list(idx)] = True
    return m


def test_prune_opacity(device):
    rows = _good_rows(20)
    rows["opacity_logits"][[3, 7]] = _logit([0.049, 0.001])
    rows["opacity_logits"][5] = _logit(0.051)
    mask, stats = _prune(rows, device)
    np.testing.assert_array_equal(mask, _flags(20, [3, 7]))
    assert stats == PruneStats(total=2, invalid=0, opacity=2, scale=0, hidden=0)


def test_prune_scale_absolute_and_relative(device):
    rows = _good_rows(20)
    rows["log_scales"][2] = np.log([0.3, 0.3, 0.3])  # sqrt(tr Sigma) = 0.52 m
    rows["log_scales"][4] = np.log([0.45, 0.01, 0.01])  # 0.4502 m: largest axis below 0.5 m, kept
    rows["log_scales"][9] = np.log([0.15, 0.15, 0.05])  # 0.218 m
    mask, stats = _prune(rows, device, max_scale_m=0.5)
    np.testing.assert_array_equal(mask, _flags(20, [2]))
    assert stats.scale == 1 and stats.total == 1
    # a 2 m scene allows 0.1 x 2 = 0.2 m
    mask, stats = _prune(rows, device, max_scale_m=0.5, max_scale_rel=0.1, scene_extent_m=2.0)
    np.testing.assert_array_equal(mask, _flags(20, [2, 4, 9]))
    assert stats.scale == 3


def test_prune_non_finite(device):
    rows = _good_rows(20)
    rows["means"][1, 2] = np.nan
    rows["log_scales"][6, 0] = np.inf
    rows["sh"][8, 3, 1] = np.nan  # a higher band
    rows["quats_xyzw"][11] = 0.0
    rows["opacity_logits"][13] = np.nan
    mask, stats = _prune(rows, device)
    np.testing.assert_array_equal(mask, _flags(20, [1, 6, 8, 11, 13]))
    assert stats == PruneStats(total=5, invalid=5, opacity=0, scale=0, hidden=0)


def test_prune_hidden(device):
    rows = _good_rows(8)
    obs = [5, 2, 10, 10, 0, 3, 4, 20]
    vis = [0, 0, 1.0, 0.9, 0, 0.29, 0.41, 1.5]
    # 0: seen 5x never contributing; 1: too few views to judge; 2: ratio 0.1 is not below 0.1;
    # 3: 0.09; 4: never seen; 5: 0.097; 6: 0.1025; 7: 0.075
    mask, stats = _prune(rows, device, obs, vis, min_obs=3, min_visibility_ratio=0.1)
    np.testing.assert_array_equal(mask, _flags(8, [0, 3, 5, 7]))
    assert stats == PruneStats(total=4, invalid=0, opacity=0, scale=0, hidden=4)
    mask, _ = _prune(rows, device)  # without statistics the test is skipped
    assert not mask.any()


def test_prune_matches_reference_with_first_reason(device):
    n = 300
    rng = np.random.default_rng(3)
    rows = _good_rows(n, seed=3)
    rows["opacity_logits"] = rng.normal(scale=3.0, size=n)
    rows["log_scales"] = np.log(rng.uniform(0.01, 0.4, size=(n, 3)))
    rows["means"][rng.choice(n, 10, replace=False), 0] = np.nan
    obs = rng.integers(0, 8, size=n)
    vis = rng.uniform(0.0, 1.0, size=n) * obs * rng.choice([0.05, 1.0], size=n)
    mask, stats = _prune(rows, device, obs, vis)

    invalid = ~np.isfinite(rows["means"]).all(axis=1)
    opacity = ~invalid & (_sigmoid(rows["opacity_logits"]) < 0.05)
    scale = ~invalid & ~opacity & (np.sqrt((np.exp(rows["log_scales"]) ** 2).sum(axis=1)) > 0.5)
    hidden = ~invalid & ~opacity & ~scale & (obs >= 3) & (vis < 0.1 * obs)
    expected = invalid | opacity | scale | hidden
    np.testing.assert_array_equal(mask, expected)
    assert stats == PruneStats(expected.sum(), invalid.sum(), opacity.sum(), scale.sum(), hidden.sum())
    assert min(invalid.sum(), opacity.sum(), scale.sum(), hidden.sum()) > 0  # every reason exercised
    assert "pruned" in str(stats)


# ---- merging ---------------------------------------------------------------------------------------


def _gaussian(u, v, z, scales=(0.01, 0.01, 0.002), R_cam=None, colour=(0.6, 0.4, 0.3), opacity=0.8, sh_rest=None):
    """A Gaussian centred on pixel (u, v) at depth z in the view T_WC, its axes R_cam in the camera frame."""
    X = np.array([(u - CAM.cx) / CAM.fx * z, (v - CAM.cy) / CAM.fy * z, z])
    R_cam = np.eye(3) if R_cam is None else R_cam
    sh = np.zeros((NUM_SH, 3))
    sh[0] = (np.asarray(colour, dtype=np.float64) - 0.5) / SH_C0
    if sh_rest is not None:
        sh[1:] = sh_rest
    return {
        "mean": T_WC[:3, :3] @ X + T_WC[:3, 3],
        "R": T_WC[:3, :3] @ R_cam,
        "scales": np.asarray(scales, dtype=np.float64),
        "opacity": opacity,
        "sh": sh,
    }


def _merge_map(gs, device):
    return GaussianMap.from_numpy(
        np.array([g["mean"] for g in gs], np.float32),
        np.array([matrix_to_quat(g["R"]) for g in gs], np.float32),
        np.array([np.log(g["scales"]) for g in gs], np.float32),
        np.array([_logit(g["opacity"]) for g in gs], np.float32),
        np.array([g["sh"] for g in gs], np.float32),
        device=device,
    )


def _cov(g):
    M = g["R"] @ np.diag(g["scales"])
    return M @ M.T


def _cov_from_map(q, log_s):
    q = np.asarray(q, np.float64) / np.linalg.norm(q)
    x, y, z, w = q
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    M = R @ np.diag(np.exp(np.asarray(log_s, np.float64)))
    return M @ M.T


def _footprint(g):
    """Reference EWA footprint in the view T_WC: (u, v), depth, dilated 2D covariance."""
    T_CW = invert_pose(T_WC)
    W = T_CW[:3, :3]
    x, y, z = W @ g["mean"] + T_CW[:3, 3]
    J = np.array([[CAM.fx / z, 0.0, -CAM.fx * x / z**2], [0.0, CAM.fy / z, -CAM.fy * y / z**2]]) @ W
    return np.array([CAM.fx * x / z + CAM.cx, CAM.fy * y / z + CAM.cy]), z, J @ _cov(g) @ J.T + 0.3 * np.eye(2)


def _duplicate_tests(a, b, px=0.5, depth_rel=0.01, size_rel=0.2, colour=0.05):
    """Which of the four duplicate criteria the pair passes (NumPy, float64)."""
    (uv_a, z_a, c_a), (uv_b, z_b, c_b) = _footprint(a), _footprint(b)
    size = np.linalg.norm(c_a - c_b) / (0.5 * (np.linalg.norm(c_a) + np.linalg.norm(c_b)))
    return {
        "px": np.linalg.norm(uv_a - uv_b) <= px,
        "depth": abs(np.log(z_a / z_b)) <= depth_rel,
        "size": size <= size_rel,
        "colour": SH_C0 * np.abs(a["sh"][0] - b["sh"][0]).max() <= colour,
    }


def _merged_reference(a, b):
    union = 1.0 - (1.0 - a["opacity"]) * (1.0 - b["opacity"])
    return {
        "mean": 0.5 * (a["mean"] + b["mean"]),
        "cov": 0.5 * (_cov(a) + _cov(b)),
        "sh": 0.5 * (a["sh"] + b["sh"]),
        "opacity": max(min(union, 0.99), a["opacity"], b["opacity"]),
    }


def _assert_merged(fields, row, ref):
    np.testing.assert_allclose(fields["means"][row], ref["mean"], atol=1e-6)
    np.testing.assert_allclose(fields["sh"][row], ref["sh"], atol=1e-5)
    cov = _cov_from_map(fields["rotations"][row], fields["log_scales"][row])
    np.testing.assert_allclose(cov, ref["cov"], atol=1e-4 * np.abs(ref["cov"]).max())
    np.testing.assert_allclose(_sigmoid(fields["opacity_logits"][row]), ref["opacity"], rtol=1e-5)


def test_identical_footprints_merge_into_the_average(device):
    rng = np.random.default_rng(0)
    # B: a tilted, slightly elongated, thicker disc at 0.1 px and 0.2 % depth from A: the same
    # footprint (size within a few %) but a different 3D covariance, so the average is not trivial
    a = _gaussian(300.0, 200.0, 2.0, opacity=0.6, sh_rest=rng.normal(scale=0.1, size=(NUM_SH - 1, 3)))
    b = _gaussian(
        300.1,
        200.0,
        2.004,
        scales=(0.01, 0.0105, 0.004),
        R_cam=_rot(2, 30.0) @ _rot(0, 8.0),
        colour=(0.62, 0.41, 0.29),
        opacity=0.7,
        sh_rest=rng.normal(scale=0.1, size=(NUM_SH - 1, 3)),
    )
    assert all(_duplicate_tests(a, b).values())
    assert not np.allclose(_cov(a), _cov(b), atol=1e-6)
    gmap = _merge_map([a, b], device)
    mask, n_merged = merge_duplicates(gmap, CAM, T_WC)
    np.testing.assert_array_equal(mask.numpy(), [0, 1])
    assert n_merged.numpy()[0] == 1
    _assert_merged(gmap.to_numpy(), 0, _merged_reference(a, b))
    gmap.remove(mask)
    assert len(gmap) == 1


def test_only_duplicates_merge(device):
    """Pairs failing one criterion each, side by side with a pair that passes all."""
    base = {"z": 2.0, "colour": (0.6, 0.4, 0.3), "scales": (0.01, 0.01, 0.002)}
    pairs = {
        "duplicate": {"du": 0.2},
        "colour": {"colour": (0.7, 0.4, 0.3)},
        "px": {"du": 5.0},
        "px_near": {"du": 0.6},  # inside the hash grid query radius, outside the tolerance
        "depth": {"z": 2.1, "scales": (0.0105, 0.0105, 0.0021)},  # same footprint size, 5 % deeper
        "depth_near": {"z": 2.026, "scales": (0.01013, 0.01013, 0.002026)},  # 1.3 %: inside the query radius
        "size": {"scales": (0.02, 0.02, 0.004)},
    }
    gs, failing = [], {}
    for k, (name, change) in enumerate(pairs.items()):
        u = 60.0 + 80.0 * k
        a = _gaussian(u, 240.0, base["z"], base["scales"], colour=base["colour"])
        b = _gaussian(
            u + change.get("du", 0.0),
            240.0,
            change.get("z", base["z"]),
            change.get("scales", base["scales"]),
            colour=change.get("colour", base["colour"]),
        )
        failing[name] = [test for test, ok in _duplicate_tests(a, b).items() if not ok]
        gs += [a, b]
    # the pair's only failing criterion is the one it is named after
    assert failing == {name: [name.removesuffix("_near")] if name != "duplicate" else [] for name in pairs}
    # duplicates outside the view: behind the camera, centred off the image
    behind = _gaussian(320.0, 240.0, 2.0)
    behind["mean"] = 2.0 * T_WC[:3, 3] - behind["mean"]
    gs += [behind, dict(behind), _gaussian(-3.0, 240.0, 2.0), _gaussian(-3.0, 240.0, 2.0)]

    gmap = _merge_map(gs, device)
    mask, n_merged = merge_duplicates(gmap, CAM, T_WC)
    np.testing.assert_array_equal(mask.numpy(), _flags(len(gs), [1]))
    assert n_merged.numpy()[0] == 1


def test_triple_cluster_merges_one_pair_per_pass(device):
    # all three pairs are duplicates; 0 and 1 are the closest
    gs = [_gaussian(400.0 + du, 100.0, 3.0 * (1.0 + 0.001 * k)) for k, du in enumerate((0.0, 0.05, 0.35))]
    assert all(all(_duplicate_tests(gs[i], gs[j]).values()) for i, j in ((0, 1), (0, 2), (1, 2)))
    original = _merge_map(gs, device).to_numpy()
    gmap = _merge_map(gs, device)
    mask, n_merged = merge_duplicates(gmap, CAM, T_WC)
    assert mask.numpy().tolist() == [0, 1, 0] and n_merged.numpy()[0] == 1
    # the survivor absorbed exactly one partner; the third Gaussian is untouched
    fields = gmap.to_numpy()
    _assert_merged(fields, 0, _merged_reference(gs[0], gs[1]))
    for name in fields:
        np.testing.assert_array_equal(fields[name][2], original[name][2])
    gmap.remove(mask)
    mask, n_merged = merge_duplicates(gmap, CAM, T_WC)
    assert mask.numpy().tolist() == [0, 1] and n_merged.numpy()[0] == 1


def test_excluded_rows_take_no_part_and_stay_flagged(device):
    gs = [_gaussian(100.0, 100.0, 2.0), _gaussian(100.1, 100.0, 2.0), _gaussian(200.0, 100.0, 2.0)]
    gmap = _merge_map(gs, device)
    before = gmap.to_numpy()
    exclude = wp.array([0, 1, 1], dtype=wp.int32, device=device)
    mask, n_merged = merge_duplicates(gmap, CAM, T_WC, exclude=exclude)
    assert mask.numpy().tolist() == [0, 1, 1] and n_merged.numpy()[0] == 0
    np.testing.assert_array_equal(gmap.to_numpy()["means"], before["means"])


def test_merge_property_random_clusters(device):
    """Clusters of 1-4 near-duplicates (some of mixed colour) far apart: every merge joins two
    duplicates of one cluster, mutual partners, no Gaussian twice; survivors hold the reference merge."""
    rng = np.random.default_rng(7)
    gs, cluster = [], []
    for c, (u, v) in enumerate((u, v) for u in range(30, 630, 40) for v in range(30, 470, 60)):
        z = rng.uniform(1.0, 4.0)
        R = _rot(2, rng.uniform(0, 180)) @ _rot(0, rng.uniform(-40, 40))
        colour = rng.uniform(0.2, 0.8, size=3)
        mixed = rng.random() < 0.25
        for _ in range(rng.integers(1, 5)):
            gs.append(
                _gaussian(
                    u + rng.uniform(-0.1, 0.1),
                    v + rng.uniform(-0.1, 0.1),
                    z * (1.0 + rng.uniform(-0.002, 0.002)),
                    scales=0.005 * z * rng.uniform(0.97, 1.03, size=3) * [1.0, 1.0, 0.2],
                    R_cam=R @ _rot(2, rng.uniform(-3, 3)),
                    colour=rng.uniform(0.2, 0.8, size=3) if mixed else colour + rng.uniform(-0.01, 0.01, 3),
                    opacity=rng.uniform(0.1, 0.95),
                    sh_rest=rng.normal(scale=0.1, size=(NUM_SH - 1, 3)),
                )
            )
            cluster.append(c)
    cluster = np.array(cluster)
    n = len(gs)
    scratch = MergeScratch(device)
    gmap = _merge_map(gs, device)
    mask, n_merged = merge_duplicates(gmap, CAM, T_WC, scratch=scratch)
    m = mask.numpy().astype(bool)
    best = scratch.best.numpy()[:n]
    fields = gmap.to_numpy()

    removed = np.flatnonzero(m)
    survivors = best[removed]
    assert len(removed) == n_merged.numpy()[0] > 10
    assert len(set(survivors.tolist())) == len(removed)  # no survivor absorbs two
    assert not m[survivors].any()  # never both members of a pair
    assert (best[survivors] == removed).all() and (survivors < removed).all()
    for j, i in zip(removed, survivors, strict=True):
        assert cluster[i] == cluster[j] and all(_duplicate_tests(gs[i], gs[j]).values())
        _assert_merged(fields, i, _merged_reference(gs[i], gs[j]))
    # at most one pair per two members, at least one per cluster holding a duplicate pair
    for c in np.unique(cluster):
        members = np.flatnonzero(cluster == c)
        merged = m[members].sum()
        has_pair = any(all(_duplicate_tests(gs[i], gs[j]).values()) for i in members for j in members if i < j)
        assert merged <= len(members) // 2 and (merged >= 1) == has_pair
    untouched = np.setdiff1d(np.arange(n), np.concatenate([removed, survivors]))
    np.testing.assert_array_equal(fields["means"][untouched], np.array([g["mean"] for g in gs], np.float32)[untouched])


# ---- the Maintainer stage --------------------------------------------------------------------------


def test_gaussians_out_of_view_spread_over_the_hash_grid(device):
    """Gaussians without a footprint (here all behind the camera) take no part in merging, and must
    not pile up in one hash-grid cell: a query reaching that cell would walk all of them (the merge
    kernel's time was the slowest thread's).  The embedding is read back through the scratch buffers
    and its cells counted as ``wp.HashGrid`` wraps them (128^3, cell = the query radius)."""
    rows = _good_rows(20000, seed=3)
    R, t = T_WC[:3, :3], T_WC[:3, 3]
    rows["means"] = (rows["means"] * 0.2 - np.array([0.0, 0.0, 2.0])) @ R.T + t  # behind the camera
    scratch = MergeScratch(device)
    mask, n_merged = merge_duplicates(_map(rows, device), CAM, T_WC, scratch=scratch)
    assert int(n_merged.numpy()[0]) == 0 and not mask.numpy().any()
    assert not scratch.valid.numpy()[:20000].any()
    cell = 0.5 * 1.4142136  # the default max_footprint_px's query radius
    cells = np.floor(scratch.points.numpy()[:20000] / cell).astype(np.int64) % 128
    _, per_cell = np.unique(cells, axis=0, return_counts=True)
    assert per_cell.max() <= 4


def test_maintainer_prunes_merges_and_compacts_every_column(device):
    # rows: 0 and 3 a duplicate pair (merged into 0), 1 transparent (pruned), 2 kept, 4 hidden behind
    # surfaces by the mapper's statistics (seen in 5 renders, contributing in none: pruned)
    a = _gaussian(300.0, 200.0, 2.0, opacity=0.6)
    dup = _gaussian(300.1, 200.0, 2.004, opacity=0.7)
    gs = [a, _gaussian(100.0, 100.0, 2.0, opacity=0.02), _gaussian(500.0, 300.0, 3.0), dup, _gaussian(50.0, 400.0, 2.5)]
    gmap = _merge_map(gs, device)
    gmap.add_column("obs_count", wp.int32).assign(np.array([3, 3, 3, 3, 5], np.int32))
    gmap.add_column("vis_count", wp.float32).assign(np.array([3, 3, 3, 3, 0], np.float32))
    tag = gmap.add_column("tag", wp.float32)  # any other column of the map follows the removal
    tag.assign(np.arange(5, dtype=np.float32))
    pruned, merged = Maintainer(MappingConfig(), CAM, device).maintain(gmap, T_WC)
    assert (pruned, merged) == (2, 1) and len(gmap) == 2
    np.testing.assert_array_equal(gmap.column("tag").numpy()[:2], [0.0, 2.0])
    np.testing.assert_array_equal(gmap.column("obs_count").numpy()[:2], [3, 3])
    _assert_merged(gmap.to_numpy(), 0, _merged_reference(a, dup))
    np.testing.assert_allclose(gmap.to_numpy()["means"][1], gs[2]["mean"], atol=1e-6)
    assert Maintainer(MappingConfig(), CAM, device).maintain(GaussianMap(4, 1, device), T_WC) == (0, 0)


def test_maintainer_without_merging_prunes_only(device):
    """mapping.merge_footprint_px=0: the duplicate pair stays, the transparent Gaussian is pruned."""
    a = _gaussian(300.0, 200.0, 2.0, opacity=0.6)
    gs = [a, _gaussian(100.0, 100.0, 2.0, opacity=0.02), _gaussian(300.1, 200.0, 2.004, opacity=0.7)]
    gmap = _merge_map(gs, device)
    pruned, merged = Maintainer(MappingConfig(merge_footprint_px=0.0), CAM, device).maintain(gmap, T_WC)
    assert (pruned, merged) == (1, 0) and len(gmap) == 2
    np.testing.assert_allclose(gmap.to_numpy()["means"][1], gs[2]["mean"], atol=1e-6)


def test_least_visible_gaussians_go_first(device):
    from rgs_warp.config import MappingConfig
    from rgs_warp.maintenance import Maintainer, least_visible_mask

    n = 10
    gmap = flat_map(n, -3.0, device)
    gmap.opacity_logits.zero_()
    gmap.add_column("obs_count", wp.int32)
    gmap.add_column("vis_count", wp.float32)
    # all opacity 0.5; rows 3 and 7 were inside 9 views and contributed in 0 and 1: hidden
    obs, vis = np.zeros(gmap.capacity, np.int32), np.zeros(gmap.capacity, np.float32)
    obs[:n], vis[:n] = 9, 9.0
    vis[3], vis[7] = 0.0, 1.0
    gmap.column("obs_count").assign(obs)
    gmap.column("vis_count").assign(vis)
    assert np.flatnonzero(least_visible_mask(gmap, 8)).tolist() == [3, 7]
    maintainer = Maintainer(MappingConfig(max_gaussians=9, cap_headroom=0.9), CAM, device)
    assert maintainer.cap(gmap) == 2 and len(gmap) == 8  # down to 0.9 x 9
    assert maintainer.cap(gmap) == 0
