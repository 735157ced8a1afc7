"""Densifier (3DGS adaptive density control) against NumPy references: gradient statistics from the
renderer's screen-space gradients, clone / split / prune flags / opacity reset, the rows it appends and
flags, the schedule, and an end-to-end run where the map grows where the residual is.  The bookkeeping
of the optimiser state around it (map columns) is tested in test_mapping.py."""

from types import SimpleNamespace

import numpy as np
import pytest
import warp as wp

from helpers_maps import flat_map
from helpers_render import BACKGROUND, CAMERA, T_WC, to_map
from reference_render import random_scene
from rgs_warp.densification import Densifier
from rgs_warp.kernels.math import vec10
from rgs_warp.render import Renderer
from rgs_warp.types import GaussianMap

W, H = 64, 48
FIELD_KEYS = ("means", "rotations", "log_scales", "opacity_logits", "sh")


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-np.asarray(x, np.float64)))


def _random_quats(rng, n):
    q = rng.standard_normal((n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _map(rng, log_scales, opacity_logits, device, means=None, capacity=None):
    n = len(log_scales)
    return GaussianMap.from_numpy(
        rng.standard_normal((n, 3)) if means is None else means,
        _random_quats(rng, n),
        np.asarray(log_scales, np.float32),
        np.asarray(opacity_logits, np.float32),
        rng.standard_normal((n, 4, 3)) * 0.3,
        device=device,
        capacity=capacity,
    )


def _step(densifier, iteration, gmap, scene_extent):
    """``densifier.step`` followed by the removal its caller owes (as the Mapper does): the flagged rows
    leave the map, and with it its statistics columns."""
    out = densifier.step(iteration, scene_extent)
    total = len(gmap)
    if out.remove is not None:
        assert out.remove.shape[0] == total
        gmap.remove(out.remove)
    return {
        "cloned": out.cloned,
        "split": out.split,
        "pruned": total - out.split - len(gmap),
        "opacity_reset": out.opacity_reset,
    }


def _feed(densifier, gmap, grad_ndc, visible, loss_share=1.0):
    """Accumulate one fake render whose screen-space gradients have NDC norms ``grad_ndc`` (split over
    u and v) where ``visible``: the pixel gradient is the NDC one / (W/2) resp. / (H/2)."""
    n = len(gmap)
    g = np.zeros((n, 10), np.float32)
    g[:, 0] = 0.6 * np.asarray(grad_ndc) / (W / 2)
    g[:, 1] = -0.8 * np.asarray(grad_ndc) / (H / 2)
    g[:, 2:] = 7.0  # other components must not enter the norm
    radii = np.where(np.asarray(visible)[:, None], 3, 0).astype(np.int32) * np.ones((1, 2), np.int32)
    fake = SimpleNamespace(
        grad2d=wp.array(g, dtype=vec10, device=gmap.device),
        radii=wp.array(radii, dtype=wp.vec2i, device=gmap.device),
        image_shape=(H, W),
    )
    densifier.accumulate(fake, loss_share)


def test_accumulate_matches_numpy_from_renderer(device):
    rng = np.random.default_rng(0)
    scene = random_scene(rng, 300, T_WC)
    gmap = to_map(scene, device)
    renderer = Renderer(device)
    densifier = Densifier(gmap)
    expected_sum = np.zeros(len(gmap))
    expected_count = np.zeros(len(gmap), np.int64)
    for k in range(2):
        pose = T_WC.copy()
        pose[:3, 3] += 0.05 * k
        renderer.forward(gmap, CAMERA, pose, BACKGROUND)
        d_color = rng.standard_normal((CAMERA.height, CAMERA.width, 3)).astype(np.float32)
        renderer.backward(wp.array(d_color, dtype=wp.vec3, device=device))
        densifier.accumulate(renderer)
        g = renderer.grad2d.numpy()[: len(gmap)].astype(np.float64)
        seen = renderer.radii.numpy()[: len(gmap), 0] > 0
        norm = np.hypot(g[:, 0] * CAMERA.width / 2, g[:, 1] * CAMERA.height / 2)
        expected_sum += np.where(seen, norm, 0.0)
        expected_count += seen
    assert 0 < expected_count.sum() < 2 * len(gmap)  # some Gaussians culled (behind the camera)
    assert (expected_sum > 0).sum() > 50
    np.testing.assert_array_equal(densifier.visible_count.numpy()[: len(gmap)], expected_count)
    np.testing.assert_allclose(densifier.grad_norm_sum.numpy()[: len(gmap)], expected_sum, rtol=1e-5, atol=1e-12)


def test_loss_share_counts_each_view_with_its_whole_loss(device):
    # a mapping iteration averaging 4 views holds 1/4 of each view's gradient: divided back out
    rng = np.random.default_rng(10)
    gmap = _map(rng, np.full((5, 3), -3.0), np.zeros(5), device)
    grads = rng.uniform(1e-4, 1e-3, 5)
    densifier = Densifier(gmap)
    _feed(densifier, gmap, grads / 4, np.ones(5, bool), loss_share=0.25)
    np.testing.assert_allclose(densifier.grad_norm_sum.numpy()[:5], grads, rtol=1e-5)


def test_clone_split_and_untouched(device):
    rng = np.random.default_rng(1)
    extent = 2.0  # clone when the largest scale <= 0.02
    small, large = np.log([0.01, 0.015, 0.005]), np.log([0.1, 0.03, 0.05])
    # 0: small, high grad -> clone; 1: large, high -> split; 2: small, low; 3: large, low;
    # 4: large, high but never visible; 5: small, just above the threshold -> clone
    log_s = np.array([small, large, small, large, large, small])
    gmap = _map(rng, log_s, np.full(6, 2.0), device)
    before = gmap.to_numpy()
    densifier = Densifier(gmap)
    grads = np.array([1e-3, 5e-4, 1e-4, 1.95e-4, 1.0, 2.05e-4])
    _feed(densifier, gmap, grads, np.array([1, 1, 1, 1, 0, 1], bool))
    _feed(densifier, gmap, grads, np.array([1, 1, 1, 1, 0, 1], bool))
    out = _step(densifier, 600, gmap, extent)
    assert out == {"cloned": 2, "split": 1, "pruned": 0, "opacity_reset": False}

    after = gmap.to_numpy()
    assert len(gmap) == 6 - 1 + 2 + 2
    # survivors in order, then the clones of 0 and 5 and the children of 1 in parent order
    rows = [0, 2, 3, 4, 5, 0, 1, 1, 5]
    exact, children = [0, 1, 2, 3, 4, 5, 8], [6, 7]
    for key in FIELD_KEYS:
        np.testing.assert_array_equal(after[key][exact], before[key][[rows[i] for i in exact]], err_msg=key)
    for key in ("rotations", "opacity_logits", "sh"):
        np.testing.assert_array_equal(after[key][children], before[key][[1, 1]], err_msg=key)
    np.testing.assert_allclose(np.exp(after["log_scales"][children]), np.exp(before["log_scales"][[1, 1]]) / 1.6, 1e-5)
    # children within the parent's 3 sigma (Mahalanobis), distinct from it and from each other
    q = before["rotations"][1]
    R = _rotation(q / np.linalg.norm(q))
    s = np.exp(before["log_scales"][1])
    z = (after["means"][children] - before["means"][1]) @ R / s
    assert np.all(np.linalg.norm(z, axis=1) < 3.0), z
    assert np.all(np.abs(z).max(axis=1) > 1e-3)
    assert np.abs(z[0] - z[1]).max() > 1e-3
    # statistics restart after densifying
    assert not densifier.grad_norm_sum.numpy().any() and not densifier.visible_count.numpy().any()


def _rotation(q):
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def test_split_children_follow_the_parent_gaussian(device):
    rng = np.random.default_rng(2)
    n = 150
    gmap = _map(rng, np.tile(np.log([0.2, 0.05, 0.01]), (n, 1)), np.full(n, 1.0), device)
    before = gmap.to_numpy()
    densifier = Densifier(gmap, seed=3)
    _feed(densifier, gmap, np.full(n, 1e-3), np.ones(n, bool))
    out = _step(densifier, 700, gmap, 1.0)
    assert out["split"] == n and out["cloned"] == 0 and len(gmap) == 2 * n
    after = gmap.to_numpy()
    parents = np.repeat(np.arange(n), 2)
    R = np.stack([_rotation(q) for q in before["rotations"]])[parents]
    d = after["means"] - before["means"][parents]
    z = np.einsum("nij,ni->nj", R, d) / np.exp(before["log_scales"][parents])  # R^T d / s per axis
    # standard normal in the parent's frame: a wrong rotation or scale gives variances far from 1
    np.testing.assert_allclose((z**2).mean(axis=0), 1.0, atol=0.3)
    np.testing.assert_allclose(z.mean(axis=0), 0.0, atol=0.25)
    assert np.abs(z).max() < 5.0
    # deterministic given the seed
    gmap2 = GaussianMap.from_numpy(*(before[key] for key in FIELD_KEYS), device=device)
    densifier2 = Densifier(gmap2, seed=3)
    _feed(densifier2, gmap2, np.full(n, 1e-3), np.ones(n, bool))
    _step(densifier2, 700, gmap2, 1.0)
    np.testing.assert_array_equal(gmap2.to_numpy()["means"], after["means"])


def test_prune_low_opacity_and_oversized(device):
    rng = np.random.default_rng(4)
    # 0: transparent (0.04 < 0.05); 1: opaque; 2: oversized (0.3 > 0.1 * 2.0); 3: transparent and above
    # the gradient threshold (its clone is transparent too: both go)
    log_s = np.log([[0.01] * 3, [0.01] * 3, [0.3, 0.01, 0.01], [0.01] * 3])
    logits = np.log([0.04 / 0.96, 0.9 / 0.1, 0.9 / 0.1, 0.04 / 0.96])
    for iteration, expected_left in ((600, [1, 2]), (3100, [1])):
        gmap = _map(rng, log_s, logits, device)
        before = gmap.to_numpy()
        densifier = Densifier(gmap)
        _feed(densifier, gmap, np.array([0.0, 0.0, 0.0, 1e-3]), np.ones(4, bool))
        out = _step(densifier, iteration, gmap, 2.0)
        assert out["cloned"] == 1 and out["pruned"] == 5 - len(expected_left)
        np.testing.assert_array_equal(gmap.to_numpy()["means"], before["means"][expected_left])


@pytest.mark.parametrize("value", [0.1, 0.15])  # float32(logit(0.15)) rounds to an opacity above 0.15
def test_opacity_reset_of_the_seen_gaussians(device, value):
    rng = np.random.default_rng(5)
    logit = np.log(value / (1 - value))
    logits = np.array([4.0, 0.0, logit + 0.01, logit - 0.01, -8.0, 3.0], np.float32)
    gmap = _map(rng, np.full((6, 3), np.log(0.01)), logits, device)
    densifier = Densifier(gmap, start=0, interval=100, opacity_reset_interval=250, opacity_reset_value=value)
    _feed(densifier, gmap, np.zeros(6), np.array([1, 1, 1, 1, 1, 0], bool))  # the last one unseen
    out = _step(densifier, 750, gmap, 1.0)  # not a densification step: nothing pruned
    assert out == {"cloned": 0, "split": 0, "pruned": 0, "opacity_reset": True}
    after = gmap.to_numpy()["opacity_logits"]
    assert np.all(_sigmoid(after[:5]) <= value)
    np.testing.assert_allclose(_sigmoid(after[:3]), value, rtol=1e-5)
    np.testing.assert_array_equal(after[3:5], logits[3:5])  # already below: untouched
    assert after[5] == logits[5]  # not seen since the statistics restarted: outside the window


def test_reset_value_must_stay_above_the_culling(device):
    # a reset to 0.01 with culling at 0.05 would remove every Gaussian at the next densification step
    gmap = GaussianMap(8, sh_degree=1, device=device)
    with pytest.raises(ValueError, match="opacity_reset_value"):
        Densifier(gmap, opacity_reset_value=0.01, cull_opacity=0.05)
    Densifier(gmap, opacity_reset_value=0.01, cull_opacity=0.05, opacity_reset_interval=0)  # never reset: fine


def test_step_appends_rows_and_flags_parents_and_culled(device):
    rng = np.random.default_rng(6)
    n = 40
    log_s = np.where(rng.random((n, 1)) < 0.5, np.log(0.005), np.log(0.1)) * np.ones((1, 3))
    logits = np.where(rng.random(n) < 0.2, -4.0, 2.0)  # ~20% below the culling opacity
    gmap = _map(rng, log_s, logits, device, capacity=n)  # full: densification must grow it
    before = gmap.to_numpy()
    high = rng.random(n) < 0.6
    densifier = Densifier(gmap)
    _feed(densifier, gmap, np.where(high, 1e-3, 0.0), np.ones(n, bool))
    out = densifier.step(800, 1.0)
    small = log_s[:, 0] < np.log(0.01)
    cloned, split = np.flatnonzero(high & small), np.flatnonzero(high & ~small)
    assert (out.cloned, out.split, out.opacity_reset) == (len(cloned), len(split), False)
    assert len(cloned) and len(split)
    # appended after the old rows in parent order (a clone: one row, a split: two), nothing removed yet
    parents = np.concatenate([[i] * (1 if small[i] else 2) for i in np.flatnonzero(high)])
    assert gmap.capacity > n and len(gmap) == n + len(parents)
    after = gmap.to_numpy()
    for key in FIELD_KEYS:
        np.testing.assert_array_equal(after[key][:n], before[key], err_msg=key)
    np.testing.assert_array_equal(after["opacity_logits"][n:], before["opacity_logits"][parents])
    # flags: the split parents and every culled row (the culled parents' offspring included)
    expected = np.concatenate([~(logits > 0) | (high & ~small), ~(logits[parents] > 0)])
    np.testing.assert_array_equal(out.remove.numpy().astype(bool), expected)
    assert not densifier.visible_count.numpy().any()  # statistics restart after densifying


@pytest.mark.parametrize(
    "iteration, densified, reset",
    [(0, False, False), (5, False, False), (7, False, False), (10, True, False), (12, False, False)]
    + [(15, True, False), (20, True, True), (25, True, False), (30, False, False), (40, False, False)],
)
def test_schedule(device, iteration, densified, reset):
    # start 5 < it < stop 30, every 5: densify at 10, 15, 20, 25; opacity reset at 20 (every 20, same window)
    rng = np.random.default_rng(7)
    n = 8
    gmap = _map(rng, np.full((n, 3), np.log(0.005)), np.full(n, 2.0), device)
    before = gmap.to_numpy()
    densifier = Densifier(gmap, start=5, stop=30, interval=5, opacity_reset_interval=20)
    _feed(densifier, gmap, np.full(n, 1e-3), np.ones(n, bool))
    out = _step(densifier, iteration, gmap, 1.0)
    assert (out["cloned"] == n) == densified and out["split"] == 0
    assert out["opacity_reset"] == reset
    if not densified and not reset:
        after = gmap.to_numpy()
        for key in FIELD_KEYS:
            np.testing.assert_array_equal(after[key], before[key])
        assert densifier.visible_count.numpy()[:n].tolist() == [1] * n  # statistics kept for later


def test_statistics_compact_and_grow_with_the_map(device):
    rng = np.random.default_rng(8)
    n = 10
    gmap = _map(rng, np.full((n, 3), -3.0), np.zeros(n), device)
    densifier = Densifier(gmap)
    grads = rng.uniform(1e-4, 1e-3, n)
    _feed(densifier, gmap, grads, np.ones(n, bool))
    mask = rng.random(n) < 0.4
    gmap.remove(mask)
    kept = len(gmap)
    np.testing.assert_allclose(densifier.grad_norm_sum.numpy()[:kept], grads[~mask], rtol=1e-5)
    np.testing.assert_array_equal(densifier.visible_count.numpy()[:kept], 1)
    extra = _map(rng, np.full((3, 3), -3.0), np.zeros(3), device).to_numpy()
    gmap.append(*(extra[key] for key in FIELD_KEYS))  # appended rows start with zero statistics
    assert not densifier.grad_norm_sum.numpy()[kept : kept + 3].any()
    assert not densifier.visible_count.numpy()[kept : kept + 3].any()


def _plane_map(rng, device):
    """A 16x12 grid of Gaussians on the plane z = 2 in front of CAMERA (identity pose) covering the image:
    half of them large (split candidates), half small (clone candidates), of random colours."""
    f, z = CAMERA.fx, 2.0
    u, v = np.meshgrid(np.linspace(0, W - 1, 16), np.linspace(0, H - 1, 12))
    u, v = u.ravel(), v.ravel()
    means = np.stack([(u - CAMERA.cx) / f * z, (v - CAMERA.cy) / f * z, np.full(u.shape, z)], axis=1)
    n = len(means)
    spacing = (W - 1) / 15 / f * z  # ~0.14 m between neighbours
    scale = np.where(rng.random(n) < 0.5, 0.6 * spacing, 0.008)  # split (> 0.01) or clone (<= 0.01)
    log_s = np.log(np.stack([scale, scale, np.full(n, 0.005)], axis=1))
    sh = np.zeros((n, 4, 3))
    sh[:, 0] = rng.normal(0.0, 0.5, (n, 3))  # colours apart from the background: positions matter
    return GaussianMap.from_numpy(
        means, np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)), log_s, np.full(n, 3.0), sh, device=device
    ), u


def test_map_grows_where_the_residual_is(device):
    """A target that only the left of the image disagrees with (a fine checkerboard left of u = 24, the
    map's own render elsewhere): the map grows on the left and stays as it was on the right.  The map
    is not optimised between densification steps, so that the residual stays where the target put
    it (Adam's normalised steps would carry changes across the image within a few iterations)."""
    rng = np.random.default_rng(9)
    gmap, u0 = _plane_map(rng, device)
    before = gmap.to_numpy()
    renderer = Renderer(device)
    identity, background = np.eye(4), (0.5, 0.5, 0.5)
    target = renderer.forward(gmap, CAMERA, identity, background).color.numpy().copy()
    yy, xx = np.mgrid[0:H, 0:W]
    checker = ((xx // 2 + yy // 2) % 2).astype(np.float32)
    target[:, :24] = checker[:, :24, None] * np.array([0.9, 0.2, 0.1], np.float32)
    densifier = Densifier(gmap, start=2, stop=20, interval=4, opacity_reset_interval=0)

    def run(iterations):
        for it in iterations:
            res = renderer.forward(gmap, CAMERA, identity, background)
            # L1 averaged over pixels and channels, as in 3DGS (the scale the threshold assumes)
            d = np.sign(res.color.numpy() - target) / (3 * W * H)
            renderer.backward(wp.array(d.astype(np.float32), dtype=wp.vec3, device=device))
            densifier.accumulate(renderer)
            out = _step(densifier, it, gmap, 1.0)
        return out, gmap.to_numpy()

    def columns(m):
        return m["means"][:, 0] / m["means"][:, 2] * CAMERA.fx + CAMERA.cx

    def assert_untouched_right_of(u_min, after):
        right, right0 = columns(after) > u_min, u0 > u_min
        for key in FIELD_KEYS:
            np.testing.assert_array_equal(after[key][right], before[key][right0], err_msg=key)

    # first densification (iteration 4): the residual covers columns < 24, a large Gaussian reaches
    # ~8 px, so only Gaussians left of ~32 px grow (children within 3 sigma = 7.5 px of them)
    out, after = run(range(1, 5))
    assert out["cloned"] > 10 and out["split"] > 10 and out["pruned"] == 0
    assert len(gmap) == len(u0) + out["cloned"] + out["split"]  # split parents replaced by two
    u = columns(after)
    assert (u < 24).sum() > 1.5 * (u0 < 24).sum()
    assert u[len(u0) - out["split"] :].max() < 32 + 7.5  # the appended rows
    assert_untouched_right_of(40, after)
    # second (iteration 8): the first one's children changed the render up to ~40 px: growth follows,
    # the far right stays as it was
    count = len(gmap)
    out, after = run(range(5, 9))
    assert out["cloned"] + out["split"] > 10 and len(gmap) > count
    assert_untouched_right_of(48, after)


def test_densification_stops_growing_at_the_cap(device):
    from rgs_warp.densification import Densifier

    n = 6
    for cap, expected in ((0, 2 * n), (n + 1, n)):  # every Gaussian would clone: 12 rows, over a cap of 7
        gmap = flat_map(n, -5.0, device)
        densifier = Densifier(gmap, start=0, interval=10, max_gaussians=cap)
        densifier.grad_norm_sum.fill_(1.0)
        densifier.visible_count.fill_(1)
        step = densifier.step(10, 6.0)
        gmap.remove(step.remove)
        assert len(gmap) == expected, cap
