"""DenseMatcher: Eq. 11-12 against hand computations, matches of known flow (translated images and
a rendered synthetic pair with ground-truth poses and depth), forward-backward rejection of
occluded pixels, aggregation and thinning, neighbour selection, and the Triangulator hand-off."""

import cv2
import numpy as np
import pytest
import warp as wp

from rgs_warp.config import MAX_PATCH_RADIUS, MatchingConfig, TriangulationConfig
from rgs_warp.geometry import invert_pose, se3_exp
from rgs_warp.kernels.matching import (
    EpipolarSearch,
    epipolar_search,
    epipolar_search_parts,
    grey_image,
    score_matches,
)
from rgs_warp.kernels.math import NO_MATCH, refine_zncc
from rgs_warp.keyframes import KeyframeBuffer
from rgs_warp.matching import DenseMatcher
from rgs_warp.triangulation import Triangulator
from rgs_warp.types import Camera

H, W = 72, 112
CAM = Camera(fx=56.0, fy=56.0, cx=55.5, cy=35.5, width=W, height=H)
DEPTH_M = 2.0


def unit_rows_np(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def _texture(h, w, seed=0):
    rng = np.random.default_rng(seed)
    noise = rng.random((h // 3 + 1, w // 3 + 1, 3)).astype(np.float32)
    return cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC).clip(0, 1)


def _translated(T_x_m: float):
    """Pose moved right by T_x_m; on the fronto-parallel plane at DEPTH_M the image content moves
    left by disparity = fx * T_x_m / DEPTH_M."""
    T = np.eye(4)
    T[0, 3] = T_x_m
    return T


def _shifted(big, disparity_px: int):
    return big[:, 16 + disparity_px : 16 + disparity_px + W]


def _buffer(images, poses, device, depth=True):
    buf = KeyframeBuffer(len(images), W, H, device)
    for i, (img, T) in enumerate(zip(images, poses, strict=True)):
        buf.add(i, T, img, np.full((H, W), DEPTH_M, np.float32) if depth else None)
    return buf


def _scene(disparities, seed=0):
    big = _texture(H, W + 48, seed)
    images = [_shifted(big, 0)] + [_shifted(big, d) for d in disparities]
    poses = [np.eye(4)] + [_translated(d * DEPTH_M / CAM.fx) for d in disparities]
    return images, poses


def test_eq11_eq12_against_hand_computation(device):
    # weights (1, 0.5, 0.25), sigma_fb = 1 px, sigma_epi = 2 px, gamma (0.5, 1.5)
    ref = [(10.0, 20.0)] * 5
    fwd = [(15.0, 20.0)] * 5
    sim = [0.8, 0.8, 0.8, 1.0, -0.5]
    epi = [2.0, 2.0, 2.0, 0.0, 40.0]
    bwd = [(11.0, 20.0), (30.0, 20.0), (10.0, 20.0), (10.0, 20.0), (50.0, 20.0)]
    bwd_sim = [0.9, 0.9, NO_MATCH, 0.9, 0.9]
    # e^-0.5 = 0.6065307: fb error 1 px, epipolar distance 2 px (one sigma each)
    want = [
        (0.8 + 0.5 * 0.6065307 + 0.25 * 0.6065307 - 0.5) / 1.0,  # 0.7548980
        (0.8 + 0.0 + 0.25 * 0.6065307 - 0.5) / 1.0,  # fb error 20 px: rho_fb ~ 0 -> 0.4516327
        0.0,  # no backward match
        1.0,  # score 1.75 clipped
        0.0,  # score -0.5 clipped
    ]
    n = len(ref)
    kw = {"device": device}
    match_uv = wp.zeros((n, 2), dtype=wp.vec2d, **kw)
    conf = wp.zeros((n, 2), dtype=wp.float32, **kw)
    wp.launch(
        score_matches,
        dim=n,
        inputs=[
            wp.array(ref, dtype=wp.vec2, **kw),
            wp.array(fwd, dtype=wp.vec2, **kw),
            wp.array(sim, dtype=wp.float32, **kw),
            wp.array(epi, dtype=wp.float32, **kw),
            wp.array(bwd, dtype=wp.vec2, **kw),
            wp.array(bwd_sim, dtype=wp.float32, **kw),
            1,
            wp.vec3(1.0, 0.5, 0.25),
            1.0,
            2.0,
            0.5,
            1.5,
        ],
        outputs=[match_uv, conf],
        **kw,
    )
    np.testing.assert_allclose(conf.numpy()[:, 1], want, atol=1e-6)
    np.testing.assert_array_equal(conf.numpy()[:, 0], 0.0)
    np.testing.assert_array_equal(match_uv.numpy()[:, 1], fwd)


@pytest.mark.parametrize("use_depth", [True, False])
def test_translated_pair_matches_known_disparity(device, use_depth):
    images, poses = _scene([6])
    buf = _buffer(images, poses, device)
    matcher = DenseMatcher(MatchingConfig(n_neighbours=1), CAM, device)
    m = matcher.match(0, buf, neighbours=[1], use_depth=use_depth, thin=False)
    ref = m.ref_uv.numpy()
    uv = m.match_uv.numpy()[:, 0]
    conf = m.confidence.numpy()[:, 0]
    truth = ref - [6.0, 0.0]
    interior = (truth[:, 0] > 12) & (truth[:, 0] < W - 13) & (ref[:, 1] > 8) & (ref[:, 1] < H - 9)
    good = interior & (conf > 0.5)
    assert good.sum() > 0.8 * interior.sum()
    err = np.linalg.norm(uv[good] - truth[good], axis=1)
    assert np.median(err) < 0.15 and np.mean(err < 2.0) > 0.99, np.percentile(err, [50, 99])
    # ref pixels whose match would leave the neighbour image get no confident match
    outside = ref[:, 0] - 6.0 < -3.0
    assert outside.any() and np.all(conf[outside] < 0.5)


def test_rendered_pair_with_ground_truth(device):
    """A SyntheticDataset-style pair (office0, 8 cm apart): confident matches land on the true
    correspondence computed from the ground-truth depth and poses."""
    from rgs_warp.datasets.synthetic import SequenceRenderer, SyntheticConfig

    config = SyntheticConfig(scene="office0", width=192, height=108, n_frames=60, supersample=2)
    seq = SequenceRenderer(config, device)
    cam = config.camera
    frames = [seq.render(i) for i in (10, 13)]
    for use_depth in (True, False):
        buf = KeyframeBuffer(2, cam.width, cam.height, device)
        for i, (rgb, depth) in zip((10, 13), frames, strict=True):
            buf.add(i, seq.poses[i], rgb, depth)
        m = DenseMatcher(MatchingConfig(n_neighbours=1), cam, device).match(
            0, buf, [1], use_depth=use_depth, thin=False
        )
        ref = m.ref_uv.numpy()
        uv = m.match_uv.numpy()[:, 0]
        conf = m.confidence.numpy()[:, 0]
        depth0 = frames[0][1]
        d = depth0[np.round(ref[:, 1]).astype(int), np.round(ref[:, 0]).astype(int)]
        X = np.stack([(ref[:, 0] - cam.cx) / cam.fx * d, (ref[:, 1] - cam.cy) / cam.fy * d, d], 1)
        T = invert_pose(seq.poses[13]) @ seq.poses[10]
        Xn = X @ T[:3, :3].T + T[:3, 3]
        truth = np.stack([cam.fx * Xn[:, 0] / Xn[:, 2] + cam.cx, cam.fy * Xn[:, 1] / Xn[:, 2] + cam.cy], 1)
        good = conf > 0.5
        err = np.linalg.norm(uv[good] - truth[good], axis=1)
        assert good.sum() > 150, good.sum()
        assert np.mean(err < 2.0) > 0.9, (use_depth, np.mean(err < 2.0), np.percentile(err, [50, 90]))


def test_forward_backward_rejects_non_mutual_matches(device):
    """The reference shows a patch twice on one row (a slightly noisy copy, e.g. a repeated
    texture); in the neighbour the copy is occluded.  The copy's pixels then match the original's
    position on their epipolar line with high similarity and no epipolar error, and only the
    forward-backward term (the backward search returns to the original) rejects them."""
    rng = np.random.default_rng(3)
    big = _texture(H, W + 48)
    big[24:48, 82:106] = 0.9 * big[24:48, 36:60] + 0.05 + rng.normal(0, 0.02, (24, 24, 3)).astype(np.float32)
    ref, nb = _shifted(big, 0), _shifted(big, 6).copy()
    nb[20:52, 58:86] = _texture(32, 28, seed=9)  # occludes the copy (neighbour columns 60-83)
    buf = _buffer([ref, nb], [np.eye(4), _translated(6 * DEPTH_M / CAM.fx)], device, depth=False)
    ref_u, ref_v = np.meshgrid(np.arange(28) * 4 + 1.5, np.arange(18) * 4 + 1.5)
    copy = ((ref_v >= 28) & (ref_v < 44) & (ref_u >= 70) & (ref_u < 86)).ravel()
    conf = {}
    for w_fb in (1.0, 0.0):
        # without the fb term, gamma moves down by its weight: the other terms face the same bar
        cfg = MatchingConfig(n_neighbours=1, w_fb=w_fb, gamma0=0.5 + w_fb, gamma1=1.5 + w_fb)
        m = DenseMatcher(cfg, CAM, device).match(0, buf, [1], use_depth=False, thin=False)
        conf[w_fb] = m.confidence.numpy()[:, 0].copy()
        if w_fb == 0.0:
            matched = m.match_uv.numpy()[copy, 0, 0]
    ref_u = ref_u.ravel()
    assert np.median(np.abs(matched - (ref_u[copy] - 52))) < 1.0  # the copy matched the original
    assert np.mean(conf[0.0][copy] > 0.5) > 0.6  # edge pixels of the copy see different surroundings
    assert np.mean(conf[1.0][copy] > 0.5) < 0.1


def test_aggregation_thinning_and_triangulation(device):
    images, poses = _scene([6, 10])
    buf = _buffer(images, poses, device)
    matcher = DenseMatcher(MatchingConfig(n_neighbours=3, thin_spacing=2.0), CAM, device)  # room for 3, given 2
    raw = matcher.match(0, buf, neighbours=[1, 2], thin=False)
    raw_conf = raw.confidence.numpy().copy()
    assert raw_conf.shape == raw.match_uv.shape == (28 * 18, 2) and raw.P.shape == (3,)
    np.testing.assert_allclose(raw.aggregated.numpy(), raw_conf.mean(1), atol=1e-6)
    assert int(raw.kept_count.numpy()[0]) == int((raw_conf.mean(1) > 0).sum())

    m = matcher.match(0, buf, neighbours=[1, 2], thin=True)
    conf = m.confidence.numpy()
    agg = m.aggregated.numpy()
    kept = agg > 0
    assert int(m.kept_count.numpy()[0]) == kept.sum() > 50
    np.testing.assert_allclose(conf[kept], raw_conf[kept], atol=1e-6)  # survivors keep their confidences
    assert np.all(conf[~kept] == 0)
    hf, wf = m.grid
    ys, xs = np.divmod(np.nonzero(kept)[0], wf)
    dist = np.hypot(ys[:, None] - ys[None], xs[:, None] - xs[None]) + 1e9 * np.eye(kept.sum())
    assert dist.min() >= 2.0  # blue-noise spacing on the feature grid
    # every matched pixel lies within the spacing of a kept one (thinning, not deletion)
    yc, xc = np.divmod(np.nonzero(raw_conf.mean(1) > 0)[0], wf)
    assert np.hypot(yc[:, None] - ys[None], xc[:, None] - xs[None]).min(1).max() < 2.0

    tri = Triangulator(TriangulationConfig(), device).triangulate(m.P, m.ref_uv, m.match_uv, m.confidence)
    valid = tri.valid.numpy() == 1
    confident = agg > 0.5
    assert np.mean(valid[confident]) > 0.9
    z = tri.X.numpy()[valid & confident][:, 2]
    assert np.median(np.abs(z - DEPTH_M)) < 0.01 * DEPTH_M


def test_select_neighbours_by_proximity_and_parallax(device):
    cfg = MatchingConfig(n_neighbours=2, target_parallax_deg=5.0, scene_depth_m=2.0, max_view_angle_deg=45.0)
    poses = {
        "ref": np.eye(4),
        "tiny": _translated(0.005),  # 0.14 deg: no parallax
        "ideal": _translated(0.17),  # 4.9 deg
        "wide": _translated(0.7),  # 19.3 deg
        "turned": se3_exp(np.array([0.17, 0, 0, 0, np.pi / 2, 0])),  # looks elsewhere
    }
    buf = KeyframeBuffer(5, W, H, device)
    slots = {name: buf.add(i, T, np.zeros((H, W, 3), np.float32)) for i, (name, T) in enumerate(poses.items())}
    names = {v: k for k, v in slots.items()}
    matcher = DenseMatcher(cfg, CAM, device)
    assert [names[s] for s in matcher.select_neighbours(slots["ref"], buf)] == ["ideal", "wide"]
    matcher.cfg.n_neighbours = 4
    assert [names[s] for s in matcher.select_neighbours(slots["ref"], buf)] == ["ideal", "wide", "tiny"]
    # judged at a scene 8 m away, the 0.7 m baseline gives the 5 deg and comes first
    assert [names[s] for s in matcher.select_neighbours(slots["ref"], buf, scene_depth_m=8.0)][0] == "wide"


@wp.kernel
def _refine_kernel(
    query_grey: wp.array2d(dtype=wp.float32),
    q: wp.array(dtype=wp.vec2),
    target_grey: wp.array2d(dtype=wp.float32),
    coarse: wp.array(dtype=wp.vec2),
    refine_radius: int,
    patch_radius: int,
    out: wp.array(dtype=wp.vec2),
):
    i = wp.tid()
    out[i] = refine_zncc(query_grey, q[i], target_grey, coarse[i], refine_radius, patch_radius)


def _bilinear(img, u, v):
    """Clamped bilinear sample at (u, v) (pixel centres at integers), as kernels.math.bilinear_corner."""
    h, w = img.shape
    u, v = min(max(u, 0.0), w - 1.0), min(max(v, 0.0), h - 1.0)
    x0, y0 = min(int(u), w - 2), min(int(v), h - 2)
    fx, fy = u - x0, v - y0
    top = (1 - fx) * img[y0, x0] + fx * img[y0, x0 + 1]
    bottom = (1 - fx) * img[y0 + 1, x0] + fx * img[y0 + 1, x0 + 1]
    return (1 - fy) * top + fy * bottom


def _zncc_reference(a_img, q, b_img, t, r):
    offsets = [(dx, dy) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
    a = np.array([_bilinear(a_img, q[0] + dx, q[1] + dy) for dx, dy in offsets])
    b = np.array([_bilinear(b_img, t[0] + dx, t[1] + dy) for dx, dy in offsets])
    n = len(offsets)
    if a.var() * n < 1e-4 * n or b.var() * n < 1e-4 * n:
        return NO_MATCH
    return float(np.corrcoef(a, b)[0, 1])


def _parabola(sm, s0, sp):
    c = sm - 2 * s0 + sp
    return 0.0 if c >= 0 else float(np.clip(0.5 * (sm - sp) / c, -0.5, 0.5))


def _refine_reference(a_img, q, b_img, coarse, R, r):
    """The ZNCC refinement of kernels/math.py written from its docstring, in float64."""
    scores = {
        (dx, dy): _zncc_reference(a_img, q, b_img, (coarse[0] + dx, coarse[1] + dy), r)
        for dy in range(-R, R + 1)
        for dx in range(-R, R + 1)
    }
    (bx, by), best = max(scores.items(), key=lambda kv: kv[1])  # first of equal scores, row by row
    if best <= NO_MATCH:
        return np.array(coarse)
    z = lambda dx, dy: _zncc_reference(a_img, q, b_img, (coarse[0] + dx, coarse[1] + dy), r)  # noqa: E731
    off_x = _parabola(z(bx - 1, by), best, z(bx + 1, by)) if abs(bx) < R else 0.0
    off_y = _parabola(z(bx, by - 1), best, z(bx, by + 1)) if abs(by) < R else 0.0
    return np.array([coarse[0] + bx + off_x, coarse[1] + by + off_y])


@pytest.mark.parametrize("R, r", [(3, 3), (2, 1), (4, MAX_PATCH_RADIUS)])
def test_zncc_refinement_against_reference(device, R, r):
    """grey_image (kernels/matching.py) and refine_zncc (kernels/math.py) against a float64 NumPy
    reference on smooth random images, the target the query moved by a known sub-pixel shift: the same
    best shift and parabola offsets, and the shift recovered; a flat query patch keeps the coarse match."""
    rng = np.random.default_rng(1)
    a_rgb = _texture(40, 48, seed=3)
    shift = np.array([2.3, -1.4])
    # the target image: the query image resampled at (x - shift), so query point q is at q + shift
    ys, xs = np.mgrid[0:40, 0:48].astype(np.float32)
    b_rgb = cv2.remap(a_rgb, xs - np.float32(shift[0]), ys - np.float32(shift[1]), cv2.INTER_CUBIC, cv2.BORDER_REFLECT)
    b_rgb[:, :8] = 0.5  # a flat band: queries there have no texture
    a_rgb[:, :8] = 0.5
    kw = {"device": device}
    greys = []
    for img in (a_rgb, b_rgb):
        g = wp.zeros(img.shape[:2], dtype=wp.float32, **kw)
        wp.launch(grey_image, dim=g.shape, inputs=[wp.array(img, dtype=wp.vec3, **kw)], outputs=[g], device=device)
        np.testing.assert_allclose(g.numpy(), img.mean(axis=2), atol=1e-6)
        greys.append(g)
    a_grey, b_grey = (g.numpy().astype(np.float64) for g in greys)
    n = 40
    q = np.column_stack([rng.uniform(14, 34, n), rng.uniform(12, 28, n)])
    q[:4, 0] = rng.uniform(1, 4, 4)  # flat query patches
    coarse = q + shift + rng.uniform(-1.6, 1.6, (n, 2))
    out = wp.zeros(n, dtype=wp.vec2, **kw)
    inputs = [greys[0], wp.array(q.astype(np.float32), dtype=wp.vec2, **kw), greys[1]]
    inputs += [wp.array(coarse.astype(np.float32), dtype=wp.vec2, **kw), R, r]
    wp.launch(_refine_kernel, dim=n, inputs=inputs, outputs=[out], device=device)
    got = out.numpy()
    want = np.array([_refine_reference(a_grey, q[i], b_grey, coarse[i].astype(np.float32), R, r) for i in range(n)])
    np.testing.assert_allclose(got, want, atol=2e-3)
    np.testing.assert_allclose(got[:4], coarse[:4], atol=1e-5)  # flat: the coarse match stays
    if r >= 2:  # a patch wide enough to lock on: the planted shift's pixel, to the parabola's bias
        err = np.linalg.norm(got[4:] - (q[4:] + shift), axis=1)
        assert np.median(err) < 0.2 and err.max() < 0.5


def _search_params(K, T, stride, band):
    """An EpipolarSearch into the camera T (query to target): depths 0.1-10 m without depth, 5 %
    tolerance with it, segments of at least +/- 2 feature px, at most 512 samples."""
    e = EpipolarSearch()
    e.K, e.R_tq, e.t_tq = wp.vec4(*K), wp.mat33(*T[:3, :3].ravel()), wp.vec3(*T[:3, 3])
    e.stride, e.depth_range, e.depth_rel_tol = stride, wp.vec2(0.1, 10.0), 0.05
    e.min_radius, e.band, e.max_steps = 2.0, band, 512
    return e


@pytest.mark.parametrize("parts", [5, 16])
def test_epipolar_scan_in_parts_equals_one_thread_a_query(device, parts):
    """kernels/matching.py: the descriptor scan spread over ``parts`` threads a query
    (``epipolar_search_parts``) gives ``epipolar_search`` bit for bit what one thread scanning every
    sample in order gives (parts=1), ties included (a target grid of 4 distinct descriptors ties
    along every segment), for queries with depth, without (long segments) and skipped."""
    rng = np.random.default_rng(2)
    hf, wf, dim, stride = 12, 16, 8, 4
    h, w = hf * stride, wf * stride
    kw = {"device": device}
    palette = unit_rows_np(rng.normal(size=(4, dim)))
    target = palette[rng.integers(0, 4, (hf, wf))].astype(np.float32)
    n = hf * wf
    query = unit_rows_np(palette[rng.integers(0, 4, n)] + 0.05 * rng.normal(size=(n, dim))).astype(np.float32)
    uv = ((np.mgrid[0:hf, 0:wf][::-1].reshape(2, -1).T) * stride + 0.5 * (stride - 1)).astype(np.float32)
    depth = rng.uniform(1.0, 3.0, (h, w)).astype(np.float32)
    depth[rng.random((h, w)) < 0.3] = 0.0  # holes: full segments
    query_sim = np.ones(n, np.float32)
    query_sim[::7] = NO_MATCH  # skipped queries
    T = se3_exp(np.array([0.2, -0.05, 0.03, 0.02, 0.05, -0.01]))
    grey = wp.array(rng.random((h, w)).astype(np.float32), **kw)
    inputs = [wp.array(query, **kw), wp.array(uv, dtype=wp.vec2, **kw), wp.array(query_sim, **kw)]
    inputs += [wp.array(depth, **kw), grey, wp.array(target, **kw), grey]
    e = _search_params((40.0, 40.0, 31.5, 23.5), T, stride, band=1)
    results = []
    for p in (1, parts):
        part_sim = wp.zeros((n, p), dtype=wp.float32, **kw)
        part_cell = wp.zeros((n, p), dtype=wp.vec3i, **kw)
        part_inputs = inputs[:4] + [inputs[5], e]
        wp.launch(epipolar_search_parts, dim=(n, p), inputs=part_inputs, outputs=[part_sim, part_cell], device=device)
        outs = [wp.zeros(n, dtype=wp.vec2, **kw), wp.zeros(n, dtype=wp.float32, **kw), wp.zeros(n, **kw)]
        search = [e, 3, 2, part_sim, part_cell]
        wp.launch(epipolar_search, dim=n, inputs=inputs + search, outputs=outs, device=device)
        results.append([o.numpy() for o in outs])
    for a, b in zip(*results, strict=True):
        np.testing.assert_array_equal(a, b)
    sim = results[0][1]
    assert np.all(sim[::7] == NO_MATCH) and (sim > 0.9).mean() > 0.5  # skipped; most find their descriptor


def _segment_reference(uv, depth, hf, wf, K, T, stride, depth_range, tol, min_radius, band, max_steps):
    """epipolar_segment of kernels/matching.py from its docstring, in float64: (g0, direction, normal,
    t_lo, n_steps, step), n_steps 0 where nothing is scanned."""
    fx, fy, cx, cy = K
    ray = T[:3, :3] @ np.array([(uv[0] - cx) / fx, (uv[1] - cy) / fy, 1.0])
    t = T[:3, 3]
    d = _bilinear(depth, uv[0], uv[1])
    x0, y0 = min(int(uv[0]), depth.shape[1] - 2), min(int(uv[1]), depth.shape[0] - 2)
    corners = depth[y0 : y0 + 2, x0 : x0 + 2]
    if corners.min() <= 0 or corners.max() - corners.min() > tol * 0.5 * (corners.max() + corners.min()):
        d = 0.0
    near, far = (d * (1 - tol), d * (1 + tol)) if d > 0 else depth_range
    if ray[2] > 0:
        near = max(near, (0.05 - t[2]) / ray[2])
    elif ray[2] < 0:
        far = min(far, (0.05 - t[2]) / ray[2])
    if near >= far:
        return None

    def grid(X):
        p = np.array([fx * X[0] / X[2] + cx, fy * X[1] / X[2] + cy])
        return (p - 0.5 * (stride - 1)) / stride

    g0, g1 = grid(near * ray + t), grid(far * ray + t)
    length = np.linalg.norm(g1 - g0)
    direction = (g1 - g0) / length if length > 1e-6 else np.array([1.0, 0.0])
    if length < 2 * min_radius:
        g0, length = 0.5 * (g0 + g1) - min_radius * direction, 2 * min_radius
    margin, t_lo, t_hi = band + 0.5, 0.0, length
    for axis, top in ((0, wf - 1), (1, hf - 1)):
        if abs(direction[axis]) > 1e-9:
            ta, tb = (-margin - g0[axis]) / direction[axis], (top + margin - g0[axis]) / direction[axis]
            t_lo, t_hi = max(t_lo, min(ta, tb)), min(t_hi, max(ta, tb))
        elif not -margin <= g0[axis] <= top + margin:
            t_hi = -1.0
    if t_lo > t_hi:
        return None
    n_steps = min(int(np.ceil(t_hi - t_lo)) + 1, max_steps)
    return g0, direction, np.array([-direction[1], direction[0]]), t_lo, n_steps, (t_hi - t_lo) / max(n_steps - 1, 1)


def test_epipolar_scan_against_reference(device):
    """kernels/matching.py: the best similarity of ``epipolar_search``'s descriptor scan (in parts)
    against a float64 NumPy scan of every sample and band offset of the same segment, for queries
    with depth (short segments) and without (long ones); a sample's rounding to a cell may differ
    between float32 and float64, so 99 % of the queries, not all, must agree (all do here; dropping a
    segment's last sample leaves 85 %)."""
    rng = np.random.default_rng(3)
    hf, wf, dim, stride, band = 12, 16, 8, 4, 1
    h, w = hf * stride, wf * stride
    kw = {"device": device}
    target = unit_rows_np(rng.normal(size=(hf, wf, dim))).astype(np.float32)
    n = hf * wf
    query = unit_rows_np(rng.normal(size=(n, dim))).astype(np.float32)
    uv = ((np.mgrid[0:hf, 0:wf][::-1].reshape(2, -1).T) * stride + 0.5 * (stride - 1)).astype(np.float32)
    depth = np.repeat(np.repeat(rng.uniform(1.0, 3.0, (hf, wf)), stride, 0), stride, 1).astype(np.float32)
    depth[:, : w // 3] = 0.0  # no depth: full segments
    T = se3_exp(np.array([0.15, -0.04, 0.02, 0.03, -0.04, 0.01]))
    K = (40.0, 40.0, 31.5, 23.5)
    grey = wp.array(rng.random((h, w)).astype(np.float32), **kw)
    inputs = [wp.array(query, **kw), wp.array(uv, dtype=wp.vec2, **kw), wp.full(n, 1.0, dtype=wp.float32, **kw)]
    inputs += [wp.array(depth, **kw), grey, wp.array(target, **kw), grey]
    e = _search_params(K, T, stride, band)
    part_sim = wp.zeros((n, 16), dtype=wp.float32, **kw)
    part_cell = wp.zeros((n, 16), dtype=wp.vec3i, **kw)
    part_inputs = inputs[:4] + [inputs[5], e]
    wp.launch(
        epipolar_search_parts, dim=part_sim.shape, inputs=part_inputs, outputs=[part_sim, part_cell], device=device
    )
    outs = [wp.zeros(n, dtype=wp.vec2, **kw), wp.zeros(n, dtype=wp.float32, **kw), wp.zeros(n, **kw)]
    wp.launch(epipolar_search, dim=n, inputs=inputs + [e, 0, 2, part_sim, part_cell], outputs=outs, device=device)
    got = outs[1].numpy()
    want = np.full(n, NO_MATCH)
    long_segment = np.zeros(n, bool)
    for i in range(n):
        seg = _segment_reference(uv[i], depth, hf, wf, K, T, stride, (0.1, 10.0), 0.05, 2.0, band, 512)
        if seg is None:
            continue
        g0, direction, normal, t_lo, n_steps, step = seg
        long_segment[i] = n_steps > 12
        for s in range(n_steps):
            for k in range(-band, band + 1):
                x, y = np.round(g0 + (t_lo + s * step) * direction + k * normal).astype(int)
                if 0 <= x < wf and 0 <= y < hf:
                    want[i] = max(want[i], float(query[i] @ target[y, x]))
    agree = np.abs(got - want) < 1e-5
    assert long_segment.sum() > 20 and (~long_segment & (want > NO_MATCH)).sum() > 50  # both kinds are tested
    assert agree.mean() > 0.99, np.flatnonzero(~agree)
