"""Co-visibility IoU on the device against NumPy; keyframe decisions; FIFO keyframe buffer."""

import numpy as np
import pytest
import warp as wp

from rgs_warp.config import KeyframeConfig
from rgs_warp.geometry import se3_exp
from rgs_warp.kernels.covisibility import reprojected_iou, visibility_iou
from rgs_warp.keyframes import FrameViews, KeyframeBuffer, KeyframeHistory, KeyframeSelector
from rgs_warp.types import Camera


def test_visibility_iou_matches_numpy(device):
    rng = np.random.default_rng(0)
    alpha = rng.random((37, 53)).astype(np.float32)
    last = (rng.random((37, 53)) > 0.4).astype(np.uint8)
    mask = wp.zeros((37, 53), dtype=wp.uint8, device=device)
    counts = wp.zeros(3, dtype=wp.int32, device=device)
    for _ in range(2):  # counts are reset on every call
        visibility_iou(wp.array(alpha, device=device), wp.array(last, device=device), 0.3, mask, counts)
    vis = alpha > 0.3
    np.testing.assert_array_equal(mask.numpy(), vis.astype(np.uint8))
    np.testing.assert_array_equal(counts.numpy(), [(vis & (last > 0)).sum(), (vis | (last > 0)).sum(), vis.sum()])


def _reprojected_iou_numpy(alpha, depth, last_mask, last_depth, thr, T, K, tol):
    """Independent reference: the same counts from whole-image NumPy operations in float64."""
    fx, fy, cx, cy = K
    h, w = alpha.shape
    vis = alpha > thr
    z = np.where(vis, depth / np.maximum(alpha, 1e-12), 0.0)
    v, u = np.mgrid[0:h, 0:w]
    X = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], -1) @ T[:3, :3].T + T[:3, 3]
    ok = vis & (X[..., 2] > 1e-6)
    zr = np.where(ok, X[..., 2], 1.0)
    ur = np.floor(fx * X[..., 0] / zr + cx + 0.5).astype(int)
    vr = np.floor(fy * X[..., 1] / zr + cy + 0.5).astype(int)
    ok &= (ur >= 0) & (ur < w) & (vr >= 0) & (vr < h)
    ur, vr = np.clip(ur, 0, w - 1), np.clip(vr, 0, h - 1)
    d_ref = last_depth[vr, ur]
    ok &= (last_mask[vr, ur] > 0) & (np.abs(X[..., 2] - d_ref) <= tol * d_ref)
    return np.array([ok.sum(), vis.sum(), (last_mask > 0).sum()]), vis.astype(np.uint8), z


def test_reprojected_iou_matches_numpy(device):
    rng = np.random.default_rng(1)
    h, w, K = 31, 47, (40.0, 42.0, 23.0, 15.0)
    alpha = rng.random((h, w)).astype(np.float32)
    # a slanted plane with noise; the reference saw it with a depth error in places (occlusions)
    v, u = np.mgrid[0:h, 0:w]
    plane = (2.0 + 0.02 * u + 0.01 * v).astype(np.float32)
    depth = (plane * alpha).astype(np.float32)
    last_mask = (rng.random((h, w)) > 0.2).astype(np.uint8)
    last_depth = (plane * np.where(rng.random((h, w)) > 0.8, 0.7, 1.0)).astype(np.float32)
    T = se3_exp(np.array([0.05, -0.02, 0.01, 0.01, 0.08, -0.02]))
    mask = wp.zeros((h, w), dtype=wp.uint8, device=device)
    z_out = wp.zeros((h, w), dtype=wp.float32, device=device)
    counts = wp.zeros(3, dtype=wp.int32, device=device)
    args = [wp.array(a, device=device) for a in (alpha, depth, last_mask, last_depth)]
    for _ in range(2):  # counts are reset on every call
        reprojected_iou(*args, 0.3, T, K, 0.05, mask, z_out, counts)
    want, want_mask, want_z = _reprojected_iou_numpy(alpha, depth, last_mask, last_depth, 0.3, T, K, 0.05)
    got = counts.numpy()
    assert 0 < want[0] < want[1]  # some pixels shared, some not: the test can tell them apart
    # float32 against float64: a pixel whose point lands on a pixel boundary may round either way
    assert abs(int(got[0]) - int(want[0])) <= 2 and got[1] == want[1] and got[2] == want[2]
    np.testing.assert_array_equal(mask.numpy(), want_mask)
    np.testing.assert_allclose(z_out.numpy(), want_z, rtol=1e-5)


def _sphere_view(camera, yaw_deg, device, radius=2.0):
    """A camera at the centre of a sphere, turned by ``yaw_deg``: every pixel covered (alpha 0.9), its
    depth the sphere's along the ray."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    xn, yn = (u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy
    z = radius / np.sqrt(1.0 + xn**2 + yn**2)
    T = se3_exp(np.array([0, 0, 0, 0, np.radians(yaw_deg), 0]))
    alpha = np.full(z.shape, 0.9, np.float32)
    return wp.array(alpha, device=device), wp.array((0.9 * z).astype(np.float32), device=device), T


@pytest.mark.parametrize("covisibility", ["pixels", "reprojected"])
def test_selector_sees_a_turn_within_the_map(device, covisibility):
    """The map covers every view of a camera turning inside a sphere: the pixel masks stay full (IoU 1,
    no keyframe however far it turns), while the reprojected IoU falls with the turn."""
    cfg = KeyframeConfig(iou_threshold=0.8, covisibility=covisibility)
    cam = Camera(20.0, 20.0, 19.5, 9.5, 40, 20)  # 90 deg wide
    sel = KeyframeSelector(cfg, cam, device)
    a, d, T0 = _sphere_view(cam, 0.0, device)
    sel.should_add(a, T0, depth=d)
    sel.accept(T0)
    same = sel.should_add(a, T0, depth=d)
    assert same.iou == pytest.approx(1.0) and not same.is_keyframe
    a3, d3, T3 = _sphere_view(cam, 3.0, device)
    small = sel.should_add(a3, T3, depth=d3)
    a30, d30, T30 = _sphere_view(cam, 30.0, device)
    turned = sel.should_add(a30, T30, depth=d30)
    if covisibility == "pixels":
        assert turned.iou == pytest.approx(1.0) and not turned.is_keyframe
    else:
        # 30 of 90 degrees turned: about two thirds of the view still shared, IoU about 0.5
        assert 0.35 < turned.iou < 0.65 and turned.is_keyframe
        assert 0.85 < small.iou < 1.0 and not small.is_keyframe  # a 3 deg turn: below every bound


def test_selector_reprojected_needs_depth(device):
    cam = Camera(20.0, 20.0, 19.5, 9.5, 40, 20)
    sel = KeyframeSelector(KeyframeConfig(covisibility="reprojected"), cam, device)
    with pytest.raises(ValueError, match="rendered depth"):
        sel.should_add(_sphere_view(cam, 0.0, device)[0], np.eye(4))


def _alpha(width, height, x0, x1, device):
    a = np.zeros((height, width), np.float32)
    a[:, x0:x1] = 0.9
    return wp.array(a, device=device)


def test_selector_decisions(device):
    cfg = KeyframeConfig(
        iou_threshold=0.8, alpha_threshold=0.5, min_translation_m=0.05, min_rotation_deg=5.0, covisibility="pixels"
    )
    sel = KeyframeSelector(cfg, Camera(20.0, 20.0, 19.5, 4.5, 40, 10), device)
    T0 = np.eye(4)
    d = sel.should_add(_alpha(40, 10, 0, 20, device), T0)
    assert d.is_keyframe and d.reason == "first frame"
    sel.accept(T0)
    # Same view: IoU 1, no keyframe.
    d = sel.should_add(_alpha(40, 10, 0, 20, device), T0)
    assert not d.is_keyframe and d.iou == pytest.approx(1.0) and d.coverage == pytest.approx(0.5)
    # Half the visible area changed (IoU 10/30) and moved 10 cm: keyframe.
    T1 = se3_exp(np.array([0.1, 0, 0, 0, 0, 0]))
    d = sel.should_add(_alpha(40, 10, 10, 30, device), T1)
    assert d.is_keyframe and d.iou == pytest.approx(1 / 3) and d.translation_m == pytest.approx(0.1)
    # Same low overlap but hardly moved: rejected by the motion bounds.
    T2 = se3_exp(np.array([0.01, 0, 0, 0, 0.01, 0]))
    d = sel.should_add(_alpha(40, 10, 10, 30, device), T2)
    assert not d.is_keyframe and d.reason == "motion below bounds"
    # A rotation above the bound alone suffices.
    T3 = se3_exp(np.array([0, 0, 0, 0, np.radians(8), 0]))
    d = sel.should_add(_alpha(40, 10, 10, 30, device), T3)
    assert d.is_keyframe and d.rotation_deg == pytest.approx(8.0)
    sel.accept(T3)
    d = sel.should_add(_alpha(40, 10, 10, 30, device), T3)
    assert d.iou == pytest.approx(1.0)  # the accepted frame's mask is now the reference


@pytest.mark.parametrize("ratio", [0.0, 1.5])
def test_selector_tracking_loss_trigger(device, ratio):
    cfg = KeyframeConfig(
        iou_threshold=0.8, min_translation_m=0.05, min_rotation_deg=5.0, max_loss_ratio=ratio, covisibility="pixels"
    )
    sel = KeyframeSelector(cfg, Camera(20.0, 20.0, 19.5, 4.5, 40, 10), device)
    same = _alpha(40, 10, 0, 20, device)  # IoU 1 throughout: only the loss can make a keyframe
    T0, T_far = np.eye(4), se3_exp(np.array([0.1, 0, 0, 0, 0, 0]))
    sel.should_add(same, T0)
    sel.accept(T0)
    assert not sel.should_add(same, T0, loss=0.10).is_keyframe  # the reference after the keyframe
    assert not sel.should_add(same, T_far, loss=0.14).is_keyframe  # below 1.5 x 0.10
    assert not sel.should_add(same, T0, loss=0.20).is_keyframe  # above, but has not moved
    d = sel.should_add(same, T_far, loss=0.16)
    assert d.is_keyframe == (ratio > 0) and (ratio == 0 or d.reason.startswith("tracking loss 0.1600"))
    sel.accept(T_far)  # a new keyframe: a new reference
    assert not sel.should_add(same, T_far, loss=0.30).is_keyframe
    assert not sel.should_add(same, T0, loss=0.40).is_keyframe
    assert sel.should_add(same, T0, loss=0.46).is_keyframe == (ratio > 0)


def test_buffer_fifo(device):
    buf = KeyframeBuffer(3, 4, 2, device)
    for k in range(5):
        rgb = np.full((2, 4, 3), k, np.float32)
        buf.add(frame_id=10 * k, T_WC=np.eye(4) * (k + 1), rgb=rgb, depth=np.full((2, 4), k, np.float32))
    assert len(buf) == 3
    slots = buf.slots()
    assert [buf.frame_ids[s] for s in slots] == [20, 30, 40]
    np.testing.assert_array_equal(buf.rgb.numpy()[slots[-1]], np.full((2, 4, 3), 4))
    np.testing.assert_array_equal(buf.depth.numpy()[slots[0]], np.full((2, 4), 2))


def _evict_into(history: KeyframeHistory, n: int, device) -> None:
    """``n`` keyframes (frame ids 0..n-1, images filled with the id) through a one-slot buffer into
    ``history``, each kept as the buffer is about to evict it."""
    buf = KeyframeBuffer(1, 4, 2, device)
    for k in range(n):
        if len(buf) == buf.capacity:
            history.keep(buf, buf.slots()[0])
        buf.add(k, np.eye(4) * (k + 1), np.full((2, 4, 3), k, np.float32), np.full((2, 4), k, np.float32), (1 + k, k))


def test_history_keeps_evicted_keyframes_then_a_uniform_sample(device):
    history = KeyframeHistory(3, 4, 2, device, seed=0)
    _evict_into(history, 4, device)  # 3 evicted: all kept, whole
    kept = {int(history.buffer.frame_ids[s]): s for _, s in history.views()}
    assert sorted(kept) == [0, 1, 2] and history.offered == 3
    for k, s in kept.items():
        np.testing.assert_array_equal(history.buffer.rgb[s].numpy(), np.full((2, 4, 3), k))
        np.testing.assert_array_equal(history.buffer.depth[s].numpy(), np.full((2, 4), k))
        np.testing.assert_array_equal(history.buffer.exposure[s], [1 + k, k])
        np.testing.assert_array_equal(history.buffer.poses[s], np.eye(4) * (k + 1))
    # reservoir sampling: over many runs, each of 30 evicted keyframes is kept with probability 3/30
    counts = np.zeros(30)
    for seed in range(300):
        h = KeyframeHistory(3, 4, 2, device, seed=seed)
        _evict_into(h, 31, device)
        assert len(h) == 3
        counts[[int(h.buffer.frame_ids[s]) for _, s in h.views()]] += 1
    # expected 30 each; a FIFO would keep only 27-29, a keep-the-first only 0-2
    assert counts[:3].sum() < 3 * 30 * 1.6 and counts[-3:].sum() < 3 * 30 * 1.6, counts
    assert counts[:15].sum() == pytest.approx(counts[15:].sum(), rel=0.25), counts


def test_history_holds_device_memory_for_the_keyframes_it_keeps(device):
    # mapping.history_size 64 of 1200x680 frames would be 0.8 GiB held from the start; it grows as it keeps
    history = KeyframeHistory(64, 4, 2, device, seed=0)
    assert history.buffer.rgb.allocated == history.buffer.depth.allocated == 0
    _evict_into(history, 4, device)
    assert len(history) == history.buffer.rgb.allocated == history.buffer.depth.allocated == 3
    for _, s in history.views():  # each slot its own image
        k = int(history.buffer.frame_ids[s])
        np.testing.assert_array_equal(history.buffer.rgb[s].numpy(), np.full((2, 4, 3), k))


def test_history_state_round_trip(device):
    history = KeyframeHistory(2, 4, 2, device, seed=1)
    _evict_into(history, 6, device)
    restored = KeyframeHistory(2, 4, 2, device, seed=99)
    restored.load_state_dict(history.state_dict())
    assert restored.offered == history.offered == 5
    assert [int(restored.buffer.frame_ids[s]) for _, s in restored.views()] == [
        int(history.buffer.frame_ids[s]) for _, s in history.views()
    ]
    for (_, a), (_, b) in zip(restored.views(), history.views(), strict=True):
        np.testing.assert_array_equal(restored.buffer.rgb[a].numpy(), history.buffer.rgb[b].numpy())
    # the same draws afterwards
    _evict_into(history, 3, device)
    _evict_into(restored, 3, device)
    assert history.offered == restored.offered
    assert sorted(int(history.buffer.frame_ids[s]) for _, s in history.views()) == sorted(
        int(restored.buffer.frame_ids[s]) for _, s in restored.views()
    )


def test_frame_views_keep_every_nth_frame_after_a_keyframe_a_sample_of_the_run_on_the_device(device):
    views = FrameViews(2, 3, 4, 2, device, seed=0)
    assert [i for i in range(10, 20) if views.wants(i, 10)] == [13, 16, 19]
    for i in (13, 16, 19):
        views.keep(i, np.eye(4) * i, np.full((2, 4, 3), i, np.float32), np.full((2, 4), i, np.float32), (1.0, 0.1 * i))
    assert views.frame_ids == [13, 16, 19]  # every frame kept, for the evaluation
    on_device = {int(b.frame_ids[s]): s for b, s in views.views()}
    assert len(on_device) == 2 and set(on_device) <= {13, 16, 19} and views.offered == 3
    for i, s in on_device.items():
        np.testing.assert_array_equal(views.buffer.rgb[s].numpy(), np.full((2, 4, 3), i))
    # over many runs each of 30 kept frames is on the device with probability 2/30: the whole run, not its end
    counts = np.zeros(30)
    for seed in range(300):
        v = FrameViews(2, 1, 4, 2, device, seed=seed)
        for i in range(30):
            v.keep(i, np.eye(4), np.zeros((2, 4, 3), np.float32), np.zeros((2, 4), np.float32), (1.0, 0.0))
        counts[[int(b.frame_ids[s]) for b, s in v.views()]] += 1
    assert counts[:10].sum() > 150 and counts[20:].sum() < 250  # uniform: 200 each third (the latest: 0 and 600)
    restored = FrameViews(2, 3, 4, 2, device, seed=5)
    restored.load_state_dict(views.state_dict())
    assert restored.frame_ids == views.frame_ids and restored.buffer.slots() == views.buffer.slots()
    assert restored.offered == 3 and restored.rng.integers(1000) == views.rng.integers(1000)
    for s in views.buffer.slots():
        np.testing.assert_array_equal(restored.buffer.depth[s].numpy(), views.buffer.depth[s].numpy())
        np.testing.assert_array_equal(restored.buffer.exposure[s], views.buffer.exposure[s])


def test_frame_views_and_history_load_an_earlier_versions_state(device):
    """Checkpoints written before the views were a sample: the history's count was named "evicted", the
    frame views saved neither a count nor a generator."""
    views = FrameViews(4, 3, 4, 2, device)
    for i in (13, 16):
        views.keep(i, np.eye(4), np.full((2, 4, 3), i, np.float32), np.full((2, 4), i, np.float32), (1.0, 0.0))
    earlier = {k: v for k, v in views.state_dict().items() if k not in ("offered", "rng")}
    restored = FrameViews(4, 3, 4, 2, device)
    restored.load_state_dict(earlier)
    assert restored.frame_ids == [13, 16] and restored.offered == 2
    assert sorted(int(b.frame_ids[s]) for b, s in restored.views()) == [13, 16]
    history = KeyframeHistory(2, 4, 2, device, seed=1)
    _evict_into(history, 6, device)
    state = history.state_dict()
    state["evicted"] = state.pop("offered")
    restored_history = KeyframeHistory(2, 4, 2, device, seed=99)
    restored_history.load_state_dict(state)
    assert restored_history.offered == history.offered == 5
