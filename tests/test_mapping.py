"""Mapper (supplement §4.5): every kernel of kernels/mapping.py against a NumPy reference (the regularizer
also against finite differences of its formula), then the Mapper on a synthetic room: colour refinement
at the keyframes' poses, and its per-Gaussian statistics and Adam moments (map columns) when rows are
appended or removed."""

import numpy as np
import pytest
import warp as wp

from helpers_maps import SH_C0, map_from_rgbd
from rgs_warp.config import DensifyConfig, MappingConfig
from rgs_warp.datasets.synthetic import SequenceRenderer, SyntheticConfig
from rgs_warp.datasets.synthetic.textures import linear_to_srgb
from rgs_warp.eval.photometric import psnr
from rgs_warp.kernels import mapping as km
from rgs_warp.keyframes import KeyframeBuffer
from rgs_warp.mapping import STATISTICS, Mapper
from rgs_warp.render import Renderer
from rgs_warp.types import GaussianMap


def assert_same_values(a, b, device, err_msg="") -> None:
    """Captured-graph steps against eager steps: bit for bit on the CPU; on a GPU the float atomics of the
    renderer's and the reductions' sums add in a varying order.  Adam divides each gradient by its running
    magnitude, so where a Gaussian's gradient is near zero a rounding's difference can flip its step, a
    whole learning rate (1e-3) either way (the likely reading of what was measured; not traced).
    Measured on an H200: 14 steps 2.4e-7 apart, 16 steps three rotations 1e-3 apart; two
    eager runs of the tracker differ as much as a replay does (experiments/results/tracking.md)."""
    if wp.get_device(device).is_cpu:
        np.testing.assert_array_equal(a, b, err_msg=err_msg)
    else:
        np.testing.assert_allclose(a, b, rtol=1e-3, atol=5e-3, err_msg=err_msg)


def _blocks(shape) -> list[int]:
    return [(shape[0] * shape[1] + km.REDUCE_BLOCK - 1) // km.REDUCE_BLOCK]


def _arr(a, device, dtype=wp.float32):
    return wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=dtype, device=device)


# ---- loss and image gradients -----------------------------------------------------------------------
def _mapping_loss_reference(obs, obs_depth, color, depth, g, b, robust_scale, use_depth, lam_d, l1_w):
    """Per-pixel loss, dL/dx of the L1 part (Cauchy weights held constant), dL/dD_hat and the row sums, in
    float64."""
    n = obs.shape[0] * obs.shape[1]
    x = g * color + b
    r = obs - x
    mean_abs = np.abs(r).mean(axis=2)
    w = 1.0 / (1.0 + (mean_abs / robust_scale) ** 2) if robust_scale > 0 else np.ones_like(mean_abs)
    grad_x = -l1_w * w[..., None] * np.sign(r) / n
    loss = l1_w * w * np.abs(r).sum(axis=2) / n
    ok = (obs_depth > 0) & bool(use_depth)
    e = np.where(ok, depth - obs_depth, 0.0)
    loss = loss + lam_d * np.abs(e) / n
    d_depth = lam_d * np.sign(e) / n
    sums = np.zeros(km.L_COLUMNS)
    sums[[km.L_LOSS, km.L_ABS, km.L_PIXELS, km.L_DEPTH, km.L_DEPTH_PIXELS]] = (
        loss.sum(),
        mean_abs.sum(),
        n,
        np.abs(e).sum(),
        ok.sum(),
    )
    return x, w, grad_x, d_depth, sums


@pytest.mark.parametrize("use_depth", [1, 0])
@pytest.mark.parametrize("robust_scale", [0.25, 0.0])
def test_mapping_loss_matches_numpy(device, robust_scale, use_depth):
    rng = np.random.default_rng(10)
    shape = (23, 31)  # 713 pixels: a partly filled last block
    obs = rng.uniform(0, 1, shape + (3,))
    color = rng.uniform(0.1, 0.9, shape + (3,))
    depth = rng.uniform(1.0, 3.0, shape)
    obs_depth = rng.uniform(1.0, 3.0, shape)
    obs_depth[rng.uniform(size=shape) < 0.2] = 0.0  # pixels without depth take no depth term
    g, b, lam_d, l1_w, row = 1.2, -0.03, 0.7, 0.8, 1
    x_out = wp.zeros(shape, dtype=wp.vec3, device=device)
    grad_x = wp.zeros(shape, dtype=wp.vec3, device=device)
    d_depth = wp.zeros(shape, dtype=wp.float32, device=device)
    loss = wp.zeros((3, km.L_COLUMNS), dtype=wp.float64, device=device)
    wp.launch_tiled(
        km.mapping_loss,
        dim=_blocks(shape),
        inputs=[_arr(obs, device, wp.vec3), _arr(obs_depth, device), _arr(color, device, wp.vec3), _arr(depth, device)]
        + [wp.array([[0.5, 0.5], [g, b]], dtype=wp.vec2, device=device), 1, robust_scale, use_depth, lam_d, l1_w]
        + [row - 1, wp.array([1], dtype=wp.int32, device=device)],  # the row is row + counter[0]
        outputs=[x_out, grad_x, d_depth, loss],
        block_dim=km.REDUCE_BLOCK,
        device=device,
    )
    # the reference on the float32 inputs the kernel saw
    obs, obs_depth, color, depth = (a.astype(np.float32).astype(np.float64) for a in (obs, obs_depth, color, depth))
    x_ref, w, grad_ref, d_depth_ref, sums = _mapping_loss_reference(
        obs, obs_depth, color, depth, g, b, robust_scale, use_depth, lam_d, l1_w
    )
    assert (w.min() < 0.5) == (robust_scale > 0)  # the Cauchy weights do vary
    np.testing.assert_allclose(x_out.numpy(), x_ref, atol=1e-6)
    np.testing.assert_allclose(grad_x.numpy(), grad_ref, rtol=1e-5, atol=1e-12)
    np.testing.assert_allclose(d_depth.numpy(), d_depth_ref, rtol=1e-6, atol=0)
    h = loss.numpy()
    np.testing.assert_allclose(h[row], sums, rtol=1e-5)
    assert np.all(h[[0, 2]] == 0)  # other rows untouched
    assert (h[row, km.L_DEPTH_PIXELS] > 0) == bool(use_depth)

    # the L1 part's value against finite differences in x, weights frozen (one IRLS step)
    def l1(xv):
        return l1_w * np.sum(w * np.abs(obs - xv).sum(axis=2)) / w.size

    eps = 1e-6
    r = obs - x_ref
    pixels = np.argwhere(np.abs(r) > 1e-2)[rng.choice(np.count_nonzero(np.abs(r) > 1e-2), 12, replace=False)]
    for idx in map(tuple, pixels):
        xp, xm = x_ref.copy(), x_ref.copy()
        xp[idx] += eps
        xm[idx] -= eps
        fd = (l1(xp) - l1(xm)) / (2 * eps)
        np.testing.assert_allclose(grad_x.numpy()[idx], fd, rtol=1e-4)


def test_scale_image_grad_multiplies_by_the_gain(device):
    rng = np.random.default_rng(11)
    grad = rng.normal(size=(7, 9, 3))
    out = wp.zeros((7, 9), dtype=wp.vec3, device=device)
    exposure = wp.array([[0.7, 0.1], [1.3, -0.2]], dtype=wp.vec2, device=device)
    wp.launch(
        km.scale_image_grad, dim=(7, 9), inputs=[_arr(grad, device, wp.vec3), exposure, 1], outputs=[out], device=device
    )
    np.testing.assert_allclose(out.numpy(), 1.3 * grad.astype(np.float32), rtol=1e-6)


# ---- regularizer ------------------------------------------------------------------------------------
REG = {"w_e": 0.3, "log_r": np.log(10.0), "w_o": 0.2, "o_max": 6.0, "w_a": 1.5}


def _regularizer(means, log_scales, logits, ema):
    """R = w_e relu(l_max - l_mid - log r)^2 + w_o relu(|logit| - o_max)^2 + w_a |mu - mu_ema|^2, summed."""
    ls = np.sort(log_scales, axis=1)
    elong = np.maximum(ls[:, 2] - ls[:, 1] - REG["log_r"], 0.0)
    over = np.maximum(np.abs(logits) - REG["o_max"], 0.0)
    return np.sum(REG["w_e"] * elong**2 + REG["w_o"] * over**2 + REG["w_a"] * np.sum((means - ema) ** 2, axis=1))


def _regularizer_grad(means, log_scales, logits, ema):
    order = np.argsort(log_scales, axis=1)
    rows = np.arange(len(means))
    a, b = order[:, 2], order[:, 1]  # largest, middle
    excess = np.maximum(log_scales[rows, a] - log_scales[rows, b] - REG["log_r"], 0.0)
    g_ls = np.zeros_like(log_scales)
    g_ls[rows, a] += 2 * REG["w_e"] * excess
    g_ls[rows, b] -= 2 * REG["w_e"] * excess
    over = np.maximum(np.abs(logits) - REG["o_max"], 0.0)
    return 2 * REG["w_a"] * (means - ema), g_ls, 2 * REG["w_o"] * over * np.sign(logits)


def test_regularize_matches_the_gradient_of_its_formula(device):
    rng = np.random.default_rng(12)
    needle = np.log([0.1, 0.005, 0.004])  # largest / middle = 20 > 10
    disc = np.log([0.1, 0.1, 0.001])  # two equal large scales: a surfel, left alone
    shapes = [np.roll(needle, k) for k in range(3)] + [np.roll(needle[::-1], k) for k in range(3)]
    shapes += [np.roll(disc, k) for k in range(3)]
    shapes += list(rng.normal(-4.0, 1.5, (15, 3)))
    log_scales = np.array(shapes)
    n = len(log_scales)
    n_disc = slice(6, 9)
    logits = rng.normal(0, 3, n)
    logits[:4] = [8.0, -9.0, 6.5, -7.0]  # saturated both ways
    means = rng.normal(0, 1, (n, 3))
    ema = means + rng.normal(0, 0.05, (n, 3))
    pre = [rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.normal(size=n)]  # the gradients are added to
    means, log_scales, logits, ema = (a.astype(np.float32).astype(np.float64) for a in (means, log_scales, logits, ema))
    pre = [p.astype(np.float32).astype(np.float64) for p in pre]

    grads = [_arr(pre[0], device, wp.vec3), _arr(pre[1], device, wp.vec3), _arr(pre[2], device)]
    wp.launch(
        km.regularize,
        dim=n,
        inputs=[_arr(means, device, wp.vec3), _arr(log_scales, device, wp.vec3), _arr(logits, device)]
        + [_arr(ema, device, wp.vec3), REG["w_e"], REG["log_r"], REG["w_o"], REG["o_max"], REG["w_a"]],
        outputs=grads,
        device=device,
    )
    added = [gr.numpy() - p for gr, p in zip(grads, pre, strict=True)]
    ref = _regularizer_grad(means, log_scales, logits, ema)
    for got, want in zip(added, ref, strict=True):
        np.testing.assert_allclose(got, want, atol=2e-6)
    assert np.all(np.abs(ref[1][:6]).max(axis=1) > 0.3)  # needles get an elongation gradient ...
    assert np.all(grads[1].numpy()[n_disc] == pre[1][n_disc].astype(np.float32))  # ... discs none at all
    assert np.all(np.sign(ref[2][:4]) == np.sign(logits[:4])) and np.all(ref[2][4:][np.abs(logits[4:]) < 6] == 0)

    # the formula's own gradient by central differences, so a sign error in R itself is caught
    eps = 1e-6
    params = [means, log_scales, logits]
    for j, got in enumerate(added):
        fd = np.zeros_like(params[j])
        for idx in np.ndindex(fd.shape):
            plus, minus = list(params), list(params)
            plus[j], minus[j] = params[j].copy(), params[j].copy()
            plus[j][idx] += eps
            minus[j][idx] -= eps
            fd[idx] = (_regularizer(*plus, ema) - _regularizer(*minus, ema)) / (2 * eps)
        np.testing.assert_allclose(got, fd, atol=2e-5)


# ---- statistics -------------------------------------------------------------------------------------
def test_update_statistics_counts_renders_and_contributions(device):
    rng = np.random.default_rng(13)
    n = 60
    radii = rng.integers(1, 20, (n, 2))
    radii[rng.uniform(size=n) < 0.3] = 0  # culled
    grad_op = rng.normal(size=n).astype(np.float32)
    grad_op[rng.uniform(size=n) < 0.3] = 0.0  # in view but covering no pixel
    obs = rng.integers(0, 10, n)
    vis = np.minimum(obs, rng.integers(0, 10, n)).astype(np.float32)
    before = np.where(rng.uniform(size=n) < 0.5, grad_op, rng.normal(size=n)).astype(np.float32)  # accumulated
    obs_out, vis_out = wp.array(obs, dtype=wp.int32, device=device), wp.array(vis, dtype=wp.float32, device=device)
    wp.launch(
        km.update_statistics,
        dim=n,
        inputs=[wp.array(radii, dtype=wp.vec2i, device=device), wp.array(grad_op, device=device)]
        + [wp.array(before, device=device)],
        outputs=[obs_out, vis_out],
        device=device,
    )
    seen = radii[:, 0] > 0
    changed = grad_op != before
    assert (seen & ~changed).any() and (~seen & changed).any() and (seen & changed).any()
    np.testing.assert_array_equal(obs_out.numpy(), obs + seen)
    np.testing.assert_array_equal(vis_out.numpy(), vis + (seen & changed))


def test_update_ema(device):
    rng = np.random.default_rng(14)
    means, ema = rng.normal(size=(40, 3)).astype(np.float32), rng.normal(size=(40, 3)).astype(np.float32)
    out = wp.array(ema, dtype=wp.vec3, device=device)
    wp.launch(
        km.update_ema, dim=40, inputs=[wp.array(means, dtype=wp.vec3, device=device), 0.1], outputs=[out], device=device
    )
    np.testing.assert_allclose(out.numpy(), 0.9 * ema.astype(np.float64) + 0.1 * means, atol=1e-6)


# ---- the Mapper on a synthetic room -----------------------------------------------------------------
# room0 at 96x54 (fx = 48), keyframes 0, 4, 8 of 100 frames (~15 cm / 15 deg apart), ray traced without
# noise.  The map holds discs on the ground-truth depth of the keyframes (tests/helpers_maps.py).
SIZE = (96, 54)
KEYFRAMES = (0, 4, 8)


@pytest.fixture(scope="module")
def room(device):
    cfg = SyntheticConfig(scene="room0", width=SIZE[0], height=SIZE[1], n_frames=100)
    seq = SequenceRenderer(cfg, device=device)
    cam = cfg.camera
    frames = []
    for i in KEYFRAMES:
        rgb, depth = seq.renderer.render(cam, seq.poses[i : i + 1], seq.poses[i], n_ss=2, seed=i)
        frames.append((np.clip(linear_to_srgb(rgb), 0, 1).astype(np.float32), depth, seq.poses[i]))
    return {"camera": cam, "frames": frames}


def _room_map(room, device):
    return map_from_rgbd(room["frames"], room["camera"], stride=2, sigma_per_spacing=0.5, device=device)


def _keyframes(room, frames, device, first_id: int = 0) -> tuple[KeyframeBuffer, list[int]]:
    cam = room["camera"]
    kf = KeyframeBuffer(4, cam.width, cam.height, device)
    return kf, [kf.add(i, T, rgb, depth) for i, (rgb, depth, T) in enumerate(frames, start=first_id)]


@pytest.mark.slow
def test_mapping_refines_corrupted_colours(device, room):
    # Measured (CPU): +1.3 / +1.8 / +2.0 dB in 60 iterations with the higher SH bands at 1/20 of the
    # colour rate (mapping.lr_color_rest_factor); at the full rate they took up part of the noise as
    # view dependence (PSNR 16.9 / 17.0 / 16.8 -> 20.5 / 21.4 / 21.0 dB). Mean L1 of the first 6
    # iterations 0.109, of the last 6 0.081 (at the full rate 0.106 -> 0.056).
    cam = room["camera"]
    gmap = _room_map(room, device)
    n = len(gmap)
    sh = gmap.sh.numpy()
    sh[:n, 0] += np.random.default_rng(0).normal(0, 0.3 / SH_C0, (n, 3))  # colour noise of std 0.3
    gmap.sh.assign(sh)
    kf, slots = _keyframes(room, room["frames"], device)
    poses = kf.poses.copy()
    renderer = Renderer(device)

    def psnrs():
        frames = zip(slots, room["frames"], strict=True)
        return np.array([psnr(renderer.forward(gmap, cam, kf.poses[s]).color.numpy(), f[0]) for s, f in frames])

    before = psnrs()
    joint = MappingConfig(views_per_iter=0)  # Table 1's step: every window view each iteration
    mapper = Mapper(joint, cam, gmap, device, renderer=renderer)
    result = mapper.optimize(kf, slots, 60)
    gain = psnrs() - before
    assert np.all(gain > 1.0), gain
    assert result.iters == 60
    assert np.array_equal(kf.poses, poses)
    h = result.l1_history
    assert h[-6:].mean() < 0.85 * h[:6].mean(), h
    assert np.polyfit(np.arange(len(h)), h, 1)[0] < 0
    assert np.all(np.isfinite(result.depth_l1_history))  # RGB-D: every keyframe has depth
    # each of the 60 iterations renders the 3 keyframes of the window
    assert np.all(gmap.column("obs_count").numpy()[:n] <= 180) and gmap.column("obs_count").numpy()[:n].max() > 0


@pytest.mark.parametrize("per_iter, per_step", [(0, 3), (1, 1), (2, 2)])
@pytest.mark.slow
def test_views_per_iteration_renders_a_random_subset(device, room, per_iter, per_step):
    """``mapping.views_per_iter``: each iteration renders that many views of the window, a fresh
    subset each time (every view still seen over the iterations); 0 renders all of them."""
    import dataclasses

    cam = room["camera"]
    kf, slots = _keyframes(room, room["frames"], device)
    renderer = Renderer(device)
    # graph off: a replayed step renders without calling renderer.forward (mapping.graph=auto is on on a GPU)
    cfg = dataclasses.replace(MappingConfig(), views_per_iter=per_iter, graph="off")
    mapper = Mapper(cfg, cam, _room_map(room, device), device, renderer=renderer)
    rendered, steps = [], []  # the views rendered since the last Adam step; those of each step
    forward, adam_step = renderer.forward, mapper.adam.step

    def counted_forward(*args, **kwargs):
        rendered.append(kwargs["view"])
        return forward(*args, **kwargs)

    def recorded_step(*args, **kwargs):
        steps.append(rendered.copy())
        rendered.clear()
        return adam_step(*args, **kwargs)

    renderer.forward, mapper.adam.step = counted_forward, recorded_step
    mapper.optimize(kf, slots, 8)
    assert [len(v) for v in steps] == [per_step] * 8
    assert rendered == []  # nothing rendered outside the steps
    assert len({j for v in steps for j in v}) >= 2  # not always the same view


def _rows(n, rng):
    q = rng.normal(size=(n, 4))
    return (
        rng.normal(0, 0.3, (n, 3)) + [0, 0, 2],
        q / np.linalg.norm(q, axis=1, keepdims=True),
        np.log(rng.uniform(0.01, 0.05, (n, 3))),
        rng.normal(0, 1, n),
        rng.normal(0, 0.5, (n, 9, 3)),
    )


def _moments(mapper, rows):
    gmap = mapper.gmap
    return {
        name: [m.numpy().reshape(gmap.capacity, -1)[:rows].copy() for m in mapper.adam.moments(name)]
        for name in GaussianMap.PARAMETERS
    }


def _stats(mapper, rows):
    return [mapper.gmap.column(name).numpy()[:rows].copy() for name in STATISTICS]


def test_statistics_follow_appended_and_removed_rows(device, room):
    cam = room["camera"]
    gmap = _room_map(room, device)
    kf, slots = _keyframes(room, room["frames"], device)
    mapper = Mapper(MappingConfig(), cam, gmap, device)
    mapper.optimize(kf, slots, 6)
    rng = np.random.default_rng(19)
    for extra in (37, 5):  # the first append grows the map's capacity, the second fits
        n = len(gmap)
        capacity = gmap.capacity
        stats, moments = _stats(mapper, n), _moments(mapper, n)
        assert stats[0].max() > 0 and stats[1].max() > 0 and np.abs(moments["means"][0]).max() > 0
        gmap.append(*_rows(extra, rng))
        assert (gmap.capacity > capacity) == (extra == 37)
        new = slice(n, n + extra)
        obs, vis, ema = _stats(mapper, n + extra)
        for got, want in zip((obs, vis, ema), stats, strict=True):
            np.testing.assert_array_equal(got[:n], want)  # the old rows keep theirs
        assert np.all(obs[new] == 0) and np.all(vis[new] == 0)
        np.testing.assert_array_equal(ema[new], gmap.means.numpy()[new])
        after = _moments(mapper, n + extra)
        for name in GaussianMap.PARAMETERS:
            for got, want in zip(after[name], moments[name], strict=True):
                np.testing.assert_array_equal(got[:n], want)
                assert np.all(got[n:] == 0), name
        mapper.optimize(kf, slots, 3)  # moments and statistics nonzero again

    n = len(gmap)
    stats, moments = _stats(mapper, n), _moments(mapper, n)
    fields = {name: value.copy() for name, value in gmap.to_numpy().items()}  # (views on the CPU)
    mask = rng.uniform(size=n) < 0.3
    mask[-3:] = True  # some of the rows appended last
    gmap.remove(wp.array(mask.astype(np.int32), dtype=wp.int32, device=device))
    keep = ~mask
    assert len(gmap) == keep.sum()
    for got, want in zip(_stats(mapper, len(gmap)), stats, strict=True):
        np.testing.assert_array_equal(got, want[keep])
    for name, value in gmap.to_numpy().items():
        np.testing.assert_array_equal(value, fields[name][keep])
    after = _moments(mapper, len(gmap))
    for name in GaussianMap.PARAMETERS:
        for got, want in zip(after[name], moments[name], strict=True):
            np.testing.assert_array_equal(got, want[keep])
    with pytest.raises(ValueError, match="mask"):
        gmap.remove(wp.zeros(len(gmap) + 1, dtype=wp.int32, device=device))
    result = mapper.optimize(kf, slots, 3)  # the compacted state is usable
    assert np.all(np.isfinite(result.l1_history)) and np.isfinite(gmap.means.numpy()[: len(gmap)]).all()


def test_densification_keeps_map_moments_and_statistics_aligned(device, room):
    # method=baseline: the densifier clones, splits and culls inside optimize; every surviving row must
    # keep its own Adam moments, m_i, v_i and EMA, and the appended rows start fresh (the column fills)
    cam = room["camera"]
    gmap = _room_map(room, device)
    n0 = len(gmap)
    logits = gmap.opacity_logits.numpy()
    logits[:n0:7] = -5.0  # opacity 0.007: culled at the densification step (0.05)
    gmap.opacity_logits.assign(logits)
    max_scale = np.exp(gmap.log_scales.numpy()[:n0].max(axis=1))
    # clone below the median largest scale, split above: both happen
    densify = DensifyConfig(start=0, interval=3, opacity_reset_interval=0, scene_extent_m=np.median(max_scale) / 0.01)
    kf, slots = _keyframes(room, room["frames"], device)
    mapper = Mapper(MappingConfig(), cam, gmap, device, densify=densify)
    snapshot = {}
    step = mapper.densifier.step

    def step_and_snapshot(iteration, *args):
        # the state right before densification (after the Adam step of iteration 3), the rows it
        # appends and the rows it flags (copies: on the CPU .numpy() views the device memory)
        n = len(gmap)
        fields = {name: value.copy() for name, value in gmap.to_numpy().items()}
        state = {"n": n, "fields": fields, "moments": _moments(mapper, n), "stats": _stats(mapper, n)}
        out = step(iteration, *args)
        if out.remove is not None:
            appended = gmap.means.numpy()[n : len(gmap)].copy()
            snapshot.update(state, appended=appended, remove=out.remove.numpy().astype(bool))
        return out

    mapper.densifier.step = step_and_snapshot
    result = mapper.optimize(kf, slots, 3)
    assert snapshot["n"] == n0 and mapper.total_iters == 3
    assert result.cloned > 0 and result.split > 0 and result.pruned >= len(range(0, n0, 7))
    n = len(gmap)
    assert n == n0 + result.cloned + result.split - result.pruned
    fields = gmap.to_numpy()
    # survivors first, in their order: the old rows not flagged (neither culled nor split); then the
    # appended rows not flagged
    remove = snapshot["remove"]
    assert len(remove) == n0 + result.cloned + 2 * result.split and np.count_nonzero(~remove) == n
    kept = np.flatnonzero(~remove[:n0])
    n_kept = len(kept)
    assert 0 < n_kept < n0 and n_kept < n
    for name in ("means", "log_scales", "sh"):
        np.testing.assert_array_equal(fields[name][:n_kept], snapshot["fields"][name][kept], err_msg=name)
    np.testing.assert_array_equal(fields["means"][n_kept:], snapshot["appended"][~remove[n0:]])
    after = _moments(mapper, n)
    for name in GaussianMap.PARAMETERS:
        for got, want in zip(after[name], snapshot["moments"][name], strict=True):
            assert np.abs(want[kept]).max() > 0, name  # real moments are compared
            np.testing.assert_array_equal(got[:n_kept], want[kept], err_msg=name)
            assert not got[n_kept:].any(), name  # appended rows: zero moments
    obs, vis, ema = _stats(mapper, n)
    for got, want in zip((obs, vis, ema), snapshot["stats"], strict=True):
        np.testing.assert_array_equal(got[:n_kept], want[kept])
    assert not np.array_equal(ema[:n_kept], fields["means"][:n_kept])  # the EMA lags: a real check
    assert not obs[n_kept:].any() and not vis[n_kept:].any()
    np.testing.assert_array_equal(ema[n_kept:], fields["means"][n_kept:])  # fresh EMA at the position
    # the densifier's statistics restarted and follow the map's capacity
    assert mapper.densifier.grad_norm_sum.shape[0] == gmap.capacity
    assert not mapper.densifier.visible_count.numpy().any()
    # the state is usable: another call densifies again at iteration 6
    again = mapper.optimize(kf, slots, 3)
    assert again.cloned + again.split > 0 and np.isfinite(again.l1_history).all()
    # a removal outside a densification step (maintenance) compacts the densifier's statistics too
    mapper.optimize(kf, slots, 2)  # iterations 7, 8: statistics, no densification
    n = len(gmap)
    d = mapper.densifier
    grad_sum, seen = d.grad_norm_sum.numpy()[:n].copy(), d.visible_count.numpy()[:n].copy()
    assert seen.max() > 0
    mask = np.random.default_rng(20).uniform(size=n) < 0.3
    gmap.remove(wp.array(mask.astype(np.int32), dtype=wp.int32, device=device))
    np.testing.assert_array_equal(d.grad_norm_sum.numpy()[: len(gmap)], grad_sum[~mask])
    np.testing.assert_array_equal(d.visible_count.numpy()[: len(gmap)], seen[~mask])


def test_window_psnr_matches_numpy(device, room):
    # the convergence curves' number: the mean over the window of the PSNR of clip(g I_hat + b, 0, 1)
    # against the keyframe image, each keyframe at its own exposure
    cam = room["camera"]
    gmap = _room_map(room, device)
    kf, slots = _keyframes(room, room["frames"], device)
    kf.exposure[slots[1]] = (1.2, -0.05)
    renderer = Renderer(device)
    mapper = Mapper(MappingConfig(), cam, gmap, device, renderer=renderer)
    expected = []
    for s in slots:
        g, b = kf.exposure[s]
        x = np.clip(g * renderer.forward(gmap, cam, kf.poses[s]).color.numpy().astype(np.float64) + b, 0.0, 1.0)
        expected.append(psnr(x, kf.rgb[s].numpy()))
    assert mapper.window_psnr(kf, slots) == pytest.approx(np.mean(expected), abs=1e-3)
    assert np.ptp(expected) > 0.5  # the exposure of keyframe 1 counts


@pytest.mark.slow
def test_history_views_are_rendered_in_their_share(device, room):
    # mapping.history: each view an iteration renders is an older keyframe (another buffer here, as the
    # SLAM's KeyframeHistory) with this probability
    cam = room["camera"]
    gmap = _room_map(room, device)
    n = len(gmap)
    sh = gmap.sh.numpy()
    sh[:n, 0] += np.random.default_rng(0).normal(0, 0.3 / SH_C0, (n, 3))
    gmap.sh.assign(sh)
    window_kf, window = _keyframes(room, room["frames"][:1], device)
    older_kf, older = _keyframes(room, room["frames"][1:], device, first_id=1)
    history = [(older_kf, s) for s in older]
    share = 0.5
    cfg = MappingConfig(history=share, graph="off")  # replays skip the count
    drawn = []

    def counting(mapper):
        render = mapper.renderer.forward

        def counted(*args, **kwargs):
            drawn.append(kwargs["view"] != 0)  # the window's keyframe is frame 0, the older ones 1 and 2
            return render(*args, **kwargs)

        mapper.renderer.forward = counted
        return mapper

    mapper = counting(Mapper(cfg, cam, gmap, device))
    mapper.optimize(window_kf, window, 40, history=history)
    assert len(drawn) == 40
    assert np.mean(drawn) == pytest.approx(share, abs=0.24)  # 3 standard deviations of 40 draws
    drawn.clear()
    off = counting(Mapper(MappingConfig(history=0.0, graph="off"), cam, gmap, device))  # replays skip the count
    off.optimize(window_kf, window, 10, history=history)  # history off: the views are ignored
    assert drawn == [False] * 10


@pytest.mark.slow
def test_history_keeps_older_keyframes_fitted(device, room):
    # What the history is for: a window whose views disagree with older keyframes (here a frame 30 %
    # darker) pulls the Gaussians they share away from them; views of the older keyframes hold them.
    # Measured (CPU): the older keyframes' PSNR goes from 20.7 dB (the map as built) to 21.3 dB after
    # 150 iterations without the history (the window's views fit the geometry but darken the colour),
    # to 24.4 dB with half the views from it (at 60 iterations: 21.8 against 22.5).
    cam = room["camera"]
    renderer = Renderer(device)
    after = {}
    for share in (0.0, 0.5):
        gmap = _room_map(room, device)
        rgb, depth, T = room["frames"][2]
        window_kf, window = _keyframes(room, [(0.7 * rgb, depth, T)], device)
        older_kf, older = _keyframes(room, room["frames"][:2], device)
        mapper = Mapper(MappingConfig(history=share), cam, gmap, device, renderer=renderer)
        mapper.optimize(window_kf, window, 150, history=[(older_kf, s) for s in older])
        after[share] = np.mean(
            [psnr(renderer.forward(gmap, cam, older_kf.poses[s]).color.numpy(), older_kf.rgb[s].numpy()) for s in older]
        )
    print(after)
    assert after[0.5] > after[0.0] + 2.0, after


@pytest.mark.slow
def test_mapping_renders_do_not_overflow_between_views(device, room):
    # Consecutive mapping iterations render different views; a dense one after a sparse one must not
    # find its intersection buffers sized by the sparse one (dropped intersections: a wrong image and
    # gradient). The Mapper passes each view's key, so the renderer also sizes it by what that view's
    # last render needed: only a view's first render can overflow (here at most once; without the
    # keys 5 of these 24 did).
    cam = room["camera"]
    gmap = _room_map(room, device)
    rgb, depth, T = room["frames"][0]
    far = T.copy()
    far[:3, 3] -= 50.0 * T[:3, 2]  # 50 m behind the first keyframe, looking the same way: the room is tiny
    kf, slots = _keyframes(room, [(rgb, depth, T), (rgb, np.zeros_like(depth), far)], device)
    mapper = Mapper(MappingConfig(), cam, gmap, device)
    mapper.optimize(kf, slots, 24)
    mapper.renderer.forward(gmap, cam, T)  # reads the last mapping render's count
    assert mapper.renderer.overflowed_renders <= 1


@pytest.mark.slow
def test_mapping_steps_replayed_from_graphs_match_eager_steps(device, room):
    """``mapping.graph=on`` (Warp's CPU graphs here): a view's first step in a call runs eagerly, the
    second is captured, the rest replay it, each step reading its loss row and learning rates from the
    device counter.  The map, its moments and statistics, the loss history and Adam's clock come out
    bit for bit as with eager steps; with history views besides the window's (without them: the next
    test)."""
    history = 0.5
    cam = room["camera"]
    out = {}
    for graph in ("off", "on"):
        gmap = _room_map(room, device)
        kf, slots = _keyframes(room, room["frames"][:2], device)
        older_kf, older = _keyframes(room, room["frames"][2:], device)
        mapper = Mapper(MappingConfig(graph=graph, history=history), cam, gmap, device, seed=3)
        result = mapper.optimize(kf, slots, 14, history=[(older_kf, s) for s in older])
        columns = {name: gmap.column(name).numpy()[: len(gmap)].copy() for name in ("obs_count", "vis_count")}
        moments = {name: [a.numpy().copy() for a in mapper.adam.moments(name)] for name in GaussianMap.PARAMETERS}
        out[graph] = (gmap.to_numpy(), columns, moments, result, mapper.adam.t)
        if graph == "on":  # the mapper's running counts, as metrics.json reports them
            assert mapper.graph_counts == {**result.graph_steps, "overflowed": result.graph_overflows}
    (p0, c0, m0, r0, t0), (p1, c1, m1, r1, t1) = out["off"], out["on"]
    assert r1.graph_steps["captured"] >= 1 and r1.graph_steps["replayed"] >= 6 and r1.graph_overflows == 0
    assert r0.graph_steps == {"eager": 0, "captured": 0, "replayed": 0}
    assert sum(r1.graph_steps.values()) == 14 and t0 == t1 == 14
    for name in GaussianMap.PARAMETERS:
        assert_same_values(p1[name], p0[name], device, err_msg=name)
        for a, b in zip(m1[name], m0[name], strict=True):
            assert_same_values(a, b, device, err_msg=name)
    for name in c0:
        np.testing.assert_array_equal(c1[name], c0[name], err_msg=name)
    assert_same_values(r1.loss_history, r0.loss_history, device)


@pytest.mark.slow
def test_mapping_graphs_captured_again_when_the_renderer_reallocates(device, room):
    """Views of different density (the room from a keyframe, and from 40 and 60 m behind two others),
    in a set order: each rendered once eagerly, then captured in turn and replayed; then the renderer's
    buffers grow (as a denser view's render would make them), which drops every graph (they hold the old
    addresses), and the views are captured again.  The steps equal eager steps bit for bit (the eager run sizes each
    view by its own count, so neither run drops intersections), as do the renderer's overflow counts."""
    cam = room["camera"]
    frames = []
    for k, (rgb, depth, T) in enumerate(room["frames"]):
        if k:
            T = T.copy()
            T[:3, 3] -= (20.0 + 20.0 * k) * T[:3, 2]
            depth = np.zeros_like(depth)
        frames.append((rgb, depth, T))
    order = [0, 1, 2, 0, 1, 2, 0, 2, 1, 0, 2, 1, 1, 0, 2, 0]

    class Scripted:  # optimize renders the first of the reversed permutation: the scripted view
        def __init__(self, renderer):
            self.k, self.renderer = 0, renderer

        def permutation(self, n):
            view = order[self.k]
            if self.k == 9:  # as a denser view's render would: the buffers grow, at new addresses
                self.renderer.reserve_intersections(4 * self.renderer.intersection_capacity)
            self.k += 1
            return np.array([v for v in range(n) if v != view] + [view])

    out = {}
    for graph in ("off", "on"):
        gmap = _room_map(room, device)
        kf, slots = _keyframes(room, frames, device)
        mapper = Mapper(MappingConfig(graph=graph, history=0.0), cam, gmap, device)
        mapper.rng = Scripted(mapper.renderer)
        out[graph] = (mapper.optimize(kf, slots, len(order)), gmap.to_numpy(), mapper.renderer.overflowed_renders)
    on, off = out["on"], out["off"]
    assert on[0].graph_steps["captured"] > len(frames) and on[0].graph_steps["replayed"] > 0  # captured again
    assert on[0].graph_overflows == 0 and on[2] == off[2]
    assert_same_values(on[0].loss_history, off[0].loss_history, device)
    for name in GaussianMap.PARAMETERS:
        assert_same_values(on[1][name], off[1][name], device, err_msg=name)


def test_count_overflow_counts_renders_beyond_their_capacity(device):
    # what a replayed mapping step adds when its render needed more intersections than its graph holds
    overflows = wp.zeros(1, dtype=wp.int32, device=device)
    for needed, capacity in ((10, 12), (12, 12), (13, 12), (500, 12)):
        wp.launch(
            km.count_overflow,
            dim=1,
            inputs=[wp.array([needed], dtype=wp.int32, device=device), capacity],
            outputs=[overflows],
            device=device,
        )
    assert int(overflows.numpy()[0]) == 2


@pytest.mark.slow
def test_stop_ends_the_call_after_the_iterations_it_asked_for(device, room):
    """``optimize(stop=...)`` (asynchronous mapping keeping pace: ``mapping.min_iters``): asked after every
    iteration but the last with the iterations done; True ends the call there, and the result holds
    only the iterations that ran."""
    cam = room["camera"]
    kf, slots = _keyframes(room, room["frames"], device)
    asked = []

    def stop(done):
        asked.append(done)
        return done == 4

    runs = {}
    for name, iters, hook in (("stopped", 20, stop), ("short", 4, None)):
        gmap = _room_map(room, device)
        mapper = Mapper(MappingConfig(graph="off"), cam, gmap, device, seed=5)
        result = mapper.optimize(kf, slots, iters, stop=hook)
        runs[name] = (result, mapper.total_iters, gmap.means.numpy()[: len(gmap)])
    result, total, _ = runs["stopped"]
    assert asked == [1, 2, 3, 4]
    assert result.iters == 4 and total == 4
    assert len(result.loss_history) == len(result.l1_history) == len(result.depth_l1_history) == 4
    assert np.all(np.isfinite(result.l1_history))
    # the map moved about as far as in a call of 4 iterations (the same views; the learning rates differ,
    # their cosine schedule planned over 20 iterations instead of 4)
    short = runs["short"]
    assert short[0].iters == 4
    moved_stopped = np.abs(runs["stopped"][2] - _room_map(room, device).means.numpy()[: len(short[2])]).max()
    moved_short = np.abs(short[2] - _room_map(room, device).means.numpy()[: len(short[2])]).max()
    assert moved_stopped > 0 and moved_short > 0
    assert 0.5 < moved_stopped / moved_short < 4.0

    # never asked after the last iteration: a stop that always says yes still runs one iteration
    gmap = _room_map(room, device)
    mapper = Mapper(MappingConfig(graph="off"), cam, gmap, device)
    assert mapper.optimize(kf, slots, 1, stop=lambda done: pytest.fail("asked after the last")).iters == 1
    assert mapper.optimize(kf, slots, 5, stop=lambda done: True).iters == 1


def test_window_psnr_of_a_view_after_one_that_saw_little_of_the_map(device, room):
    # the renderer's intersection buffers are sized by the render before: after a view that saw little of the
    # map a dense one would drop intersections; the PSNR is of the whole render
    cam = room["camera"]
    gmap = _room_map(room, device)
    kf, slots = _keyframes(room, room["frames"], device)
    renderer = Renderer(device)
    mapper = Mapper(MappingConfig(), cam, gmap, device, renderer=renderer)
    expected = psnr(
        np.clip(Renderer(device).forward(gmap, cam, kf.poses[slots[0]]).color.numpy(), 0, 1), kf.rgb[slots[0]].numpy()
    )
    away = kf.poses[slots[0]].copy()
    away[:3, :3] = away[:3, :3] @ np.diag([-1.0, 1.0, -1.0])  # turned round: the room's far side, barely covered
    few = renderer.forward(gmap, cam, away).num_intersections
    many = renderer.forward(gmap, cam, kf.poses[slots[0]]).num_intersections
    assert few * 2 < many  # the case: sized by the render before, the dense view would overflow
    renderer.forward(gmap, cam, away)
    assert mapper.window_psnr(kf, [slots[0]]) == pytest.approx(expected, abs=1e-3)
