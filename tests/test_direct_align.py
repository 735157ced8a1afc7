"""Direct alignment of tracking (kernels/direct.py, direct_align.py): the reference image and the
normal equations against a NumPy re-implementation of the documented maths, their gradient against
finite differences of their cost, the damped Gauss-Newton step against NumPy's solve, the point-to-plane
term of ``tracking.geometric`` (its residual and Jacobian against finite differences, its sums, the noise
scales from the residuals' median), then the tracker with ``tracking.direct_levels`` on the synthetic room
of test_tracking.py."""

import numpy as np
import pytest
import warp as wp

from helpers_maps import perturbed, room_scene
from rgs_warp.config import TrackingConfig
from rgs_warp.geometry import invert_pose, rotation_angle_deg, se3_exp
from rgs_warp.kernels import direct as dk
from rgs_warp.kernels.math import N_TERMS, TERM_COLOUR, TERM_GEOMETRIC
from rgs_warp.motion_model import pose_error
from rgs_warp.tracking import Tracker

# ---- NumPy references ---------------------------------------------------------------------------------


def _bilinear(image: np.ndarray, u: float, v: float):
    """Bilinear sample of an (H, W[, C]) image with pixel centres at integer coordinates (u, v inside)."""
    h, w = image.shape[:2]
    x0, y0 = min(int(np.floor(u)), w - 2), min(int(np.floor(v)), h - 2)
    fx, fy = u - x0, v - y0
    top = (1 - fx) * image[y0, x0] + fx * image[y0, x0 + 1]
    bottom = (1 - fx) * image[y0 + 1, x0] + fx * image[y0 + 1, x0 + 1]
    return (1 - fy) * top + fy * bottom


def _depth_sample(depth: np.ndarray, u: float, v: float, margins: list) -> float:
    """Bilinear depth, 0 unless all four corners are valid and spread at most DEPTH_EDGE_SPREAD of their
    mean (of lowest and highest); the spread's distance to that threshold goes to ``margins``."""
    h, w = depth.shape
    x0, y0 = min(int(np.floor(u)), w - 2), min(int(np.floor(v)), h - 2)
    corners = depth[y0 : y0 + 2, x0 : x0 + 2].astype(np.float64)
    lo, hi = corners.min(), corners.max()
    if lo > 0:
        margins.append(abs((hi - lo) / (0.5 * (hi + lo)) - dk.DEPTH_EDGE_SPREAD))
    if lo <= 0 or hi - lo > dk.DEPTH_EDGE_SPREAD * 0.5 * (hi + lo):
        return 0.0
    return float(_bilinear(depth.astype(np.float64), u, v))


def _huber(e: float) -> float:
    a = abs(e)
    return 0.5 * a * a if a <= dk.HUBER else dk.HUBER * (a - 0.5 * dk.HUBER)


def _reference_sums(ref_rgb, ref_depth, rgb, depth, depth_mode, K, T_rel, affine, sigma_colour=dk.SIGMA_COLOUR):
    """The 46 sums of ``normal_equations`` in float64, their sums of absolute contributions (the scale
    of float32 rounding) and counts of the branches taken (``stats``, with the colour residuals under
    "residuals"); ``sigma_colour``: the colour residuals' noise scale."""
    fx, fy, cx, cy = K
    h, w = ref_depth.shape
    grey = rgb.astype(np.float64).mean(axis=2)
    ref_grey = ref_rgb.astype(np.float64).mean(axis=2)
    g, b = affine
    sums, scale = np.zeros(dk.N_COLUMNS), np.zeros(dk.N_COLUMNS)
    upper = np.triu_indices(dk.N_PARAMS)  # row-major, i <= j
    stats = dict.fromkeys(("colour", "depth", "occluded", "colour_huber", "depth_huber", "no_depth_grad"), 0)
    # the closest any discontinuous test (image border, occlusion, depth edge) came to its threshold,
    # relative: float32 rounding in the kernel must not decide a pixel differently
    margins = []
    residuals = []

    def add(J, r, sigma, kind):
        e = r / sigma
        weight = (1.0 if abs(e) <= dk.HUBER else dk.HUBER / abs(e)) / sigma**2
        stats[kind + "_huber"] += abs(e) > dk.HUBER
        terms = np.concatenate([weight * np.outer(J, J)[upper], weight * J * r, [_huber(e)]])
        sums[: dk.S_COUNT] += terms
        scale[: dk.S_COUNT] += np.abs(terms)

    for y in range(h):
        for x in range(w):
            d = float(ref_depth[y, x])
            if d <= 0:
                continue
            p = d * np.array([(x - cx) / fx, (y - cy) / fy, 1.0])
            q = T_rel[:3, :3] @ p + T_rel[:3, 3]
            z = q[2]
            u, v = fx * q[0] / z + cx, fy * q[1] / z + cy
            margins += [abs(u - 1), abs(u - (w - 2)), abs(v - 1), abs(v - (h - 2))]
            if not (1 <= u <= w - 2 and 1 <= v <= h - 2):
                continue
            du = np.array([fx / z, 0.0, -fx * q[0] / z**2])
            dv = np.array([0.0, fy / z, -fy * q[1] / z**2])
            if depth_mode != dk.DEPTH_NONE:
                D = _depth_sample(depth, u, v, margins)
                if D > 0:
                    margins.append(abs(abs(D - z) / z - dk.MAX_DEPTH_GAP))
                if D > 0 and abs(D - z) > dk.MAX_DEPTH_GAP * z:
                    stats["occluded"] += 1
                    continue
            if depth_mode == dk.DEPTH_PROJECTIVE:
                right, left = _depth_sample(depth, u + 1, v, margins), _depth_sample(depth, u - 1, v, margins)
                down, up = _depth_sample(depth, u, v + 1, margins), _depth_sample(depth, u, v - 1, margins)
                if D > 0 and min(right, left, down, up) > 0:
                    a = 0.5 * (right - left) * du + 0.5 * (down - up) * dv - np.array([0.0, 0.0, 1.0])
                    add(np.concatenate([a, np.cross(q, a), [0.0, 0.0]]), D - z, dk.SIGMA_DEPTH * d, "depth")
                    stats["depth"] += 1
                elif D > 0:
                    stats["no_depth_grad"] += 1
            gx = 0.5 * (_bilinear(grey, u + 1, v) - _bilinear(grey, u - 1, v))
            gy = 0.5 * (_bilinear(grey, u, v + 1) - _bilinear(grey, u, v - 1))
            a = gx * du + gy * dv
            i_ref = ref_grey[y, x]
            J = np.concatenate([a, np.cross(q, a), [-i_ref, -1.0]])
            r = _bilinear(grey, u, v) - (g * i_ref + b)
            add(J, r, sigma_colour, "colour")
            residuals.append(r)
            stats["colour"] += 1
            sums[dk.S_COUNT] += 1
    stats["margin"] = min(margins)
    stats["residuals"] = np.array(residuals)
    return sums, scale, stats


def _kernel_sums(
    device, ref_rgb, ref_depth, rgb, depth, depth_mode, K, T_rel, affine, sigma_colour=dk.SIGMA_COLOUR, histogram=None
) -> np.ndarray:
    """``normal_equations`` launched as ``DirectAlignment.align`` does, on zeroed sums (and ``histogram``, a
    zeroed (N_TERMS, HIST_BINS) array, or a fresh one)."""
    h, w = ref_depth.shape
    sums = wp.zeros(dk.N_COLUMNS, dtype=wp.float64, device=device)
    if histogram is None:
        histogram = wp.zeros((N_TERMS, dk.HIST_BINS), dtype=wp.int32, device=device)
    wp.launch_tiled(
        dk.normal_equations,
        dim=[(h * w + dk.BLOCK - 1) // dk.BLOCK],
        inputs=[
            wp.array(ref_rgb, dtype=wp.vec3, device=device),
            wp.array(ref_depth, dtype=wp.float32, device=device),
            wp.array(rgb, dtype=wp.vec3, device=device),
            wp.array(depth, dtype=wp.float32, device=device),
            int(depth_mode),
            wp.vec4(*K),
            wp.array([T_rel], dtype=wp.mat44d, device=device),
            wp.array(np.asarray(affine, dtype=np.float64), dtype=wp.float64, device=device),
            wp.array([sigma_colour, 1.0], dtype=wp.float32, device=device),
        ],
        outputs=[sums, histogram],
        block_dim=dk.BLOCK,
        device=device,
    )
    return sums.numpy()


# ---- reference image ----------------------------------------------------------------------------------


def test_reference_image_divides_by_opacity_where_covered(device):
    """``reference_image``: colour / alpha and depth / alpha where alpha >= min_alpha (and > 0), else 0."""
    rng = np.random.default_rng(0)
    shape = (11, 13)
    alpha = rng.uniform(0, 1, shape).astype(np.float32)
    alpha[0, :3] = 0.0  # no opacity at all: no reference even with min_alpha 0
    alpha[1, :3] = 0.6  # exactly min_alpha: a reference
    color = (alpha[..., None] * rng.uniform(0, 1, shape + (3,))).astype(np.float32)
    depth = (alpha * rng.uniform(1, 3, shape)).astype(np.float32)
    rgb_out = wp.zeros(shape, dtype=wp.vec3, device=device)
    depth_out = wp.zeros(shape, dtype=wp.float32, device=device)
    for min_alpha in (0.0, 0.6):
        wp.launch(
            dk.reference_image,
            dim=shape,
            inputs=[wp.array(color, dtype=wp.vec3, device=device), wp.array(depth, device=device)]
            + [wp.array(alpha, device=device), min_alpha],
            outputs=[rgb_out, depth_out],
            device=device,
        )
        keep = (alpha >= np.float32(min_alpha)) & (alpha > 0)
        assert keep.any() and (~keep).any() and keep[1, :3].all()
        safe = np.where(keep, alpha, 1.0)
        expected = np.where(keep[..., None], color / safe[..., None], 0.0)
        np.testing.assert_allclose(rgb_out.numpy(), expected, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(depth_out.numpy(), np.where(keep, depth / safe, 0.0), rtol=1e-6, atol=1e-7)


# ---- normal equations ---------------------------------------------------------------------------------
NE_SHAPE = (17, 23)
NE_K = (20.0, 19.0, 11.3, 7.8)


def _pattern(shape, shift=(0.0, 0.0)):
    """A smooth colour pattern (each channel its own sinusoids), optionally shifted by (dx, dy) px."""
    y, x = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    x, y = x + shift[0], y + shift[1]
    return np.stack(
        [
            0.5 + 0.3 * np.sin(x / 3.1 + 0.4) * np.cos(y / 4.3),
            0.45 + 0.25 * np.sin(x / 4.7 - y / 3.9 + 1.0),
            0.5 + 0.2 * np.cos(x / 2.9 + y / 5.3),
        ],
        axis=-1,
    )


def _normal_equation_inputs():
    """Reference and frame images at NE_SHAPE: smooth colour, a depth map with an edge and holes; the frame
    a shifted, brighter copy with a bright patch (colour outliers), a depth ripple (depth outliers), an
    occluder in front, an edge and holes of its own."""
    h, w = NE_SHAPE
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    ref_rgb = _pattern(NE_SHAPE)
    ref_depth = 2.0 + 0.01 * x + 0.1 * np.sin(y / 5.0)
    ref_depth[:, 16:] += 0.6  # a depth edge
    ref_depth[[3, 9, 12], [5, 14, 2]] = 0.0  # no reference
    rgb = 1.05 * _pattern(NE_SHAPE, (0.15, -0.1)) + 0.01
    rgb[10:13, 4:8] += 0.15  # colour outliers
    depth = ref_depth + 0.06 * np.sin(x / 2.0 + y / 3.0)  # the ripple's peaks are depth outliers
    depth[4:7, 8:12] *= 0.7  # an occluder
    depth[[2, 7, 13, 14], [3, 18, 10, 11]] = 0.0  # no measurement
    return [a.astype(np.float32) for a in (ref_rgb, ref_depth, rgb, depth)]


NE_T_REL = se3_exp(np.array([0.004, -0.003, 0.006, 0.01, -0.015, 0.008]))


def _histogram(values: np.ndarray) -> np.ndarray:
    """Counts of |values| on the kernels' log2 bins (HIST_PER_OCTAVE a factor of 2 from 2^HIST_MIN_LOG2, the
    ends open; 0 in the first)."""
    a = np.abs(np.asarray(values, dtype=np.float64))
    k = np.zeros(a.shape, dtype=np.int64)
    pos = a > 0
    k[pos] = np.clip(np.floor((np.log2(a[pos]) - dk.HIST_MIN_LOG2) * dk.HIST_PER_OCTAVE), 0, dk.HIST_BINS - 1)
    return np.bincount(k, minlength=dk.HIST_BINS)


def _assert_same_histogram(got: np.ndarray, expected: np.ndarray) -> None:
    """Equal counts, but for a value that float32 rounding moves across a bin edge (the cumulative counts
    differ by at most 1 there)."""
    assert got.sum() == expected.sum() > 0
    assert np.abs(np.cumsum(got) - np.cumsum(expected)).max() <= 1, (got, expected)


@pytest.mark.parametrize("depth_mode", [dk.DEPTH_NONE, dk.DEPTH_PROJECTIVE, dk.DEPTH_GEOMETRIC])
def test_normal_equations_match_numpy(device, depth_mode):
    """``normal_equations``: the 46 float64 sums (J^T W J upper triangle, J^T W r, Huber cost, pixel count)
    equal a NumPy re-implementation of the documented warp, samplers, residuals, occlusion test and IRLS
    weights, on images that exercise every branch (holes, depth edge, occluder, Huber outliers).
    DEPTH_GEOMETRIC: the occlusion test without the depth residual, the colour's noise read from the
    scales, and the colour residuals' histogram (row TERM_COLOUR; no histogram in the other modes)."""
    ref_rgb, ref_depth, rgb, depth = _normal_equation_inputs()
    affine = (1.03, 0.0)
    geometric = depth_mode == dk.DEPTH_GEOMETRIC
    sigma = 0.015 if geometric else dk.SIGMA_COLOUR
    ref, scale, stats = _reference_sums(ref_rgb, ref_depth, rgb, depth, depth_mode, NE_K, NE_T_REL, affine, sigma)
    histogram = wp.zeros((N_TERMS, dk.HIST_BINS), dtype=wp.int32, device=device)
    got = _kernel_sums(device, ref_rgb, ref_depth, rgb, depth, depth_mode, NE_K, NE_T_REL, affine, sigma, histogram)
    # every branch is taken (both Huber regimes; with depth: occlusions, depth residuals with and
    # without a usable depth gradient), and no pixel sits on a threshold float32 rounding could flip
    assert 0.05 * stats["colour"] < stats["colour_huber"] < 0.6 * stats["colour"], stats
    if depth_mode != dk.DEPTH_NONE:
        assert stats["occluded"] > 0, stats
    if depth_mode == dk.DEPTH_PROJECTIVE:
        assert stats["no_depth_grad"] > 0, stats
        assert 0.1 * stats["depth"] < stats["depth_huber"] < 0.6 * stats["depth"], stats
    else:
        assert stats["depth"] == 0
    assert stats["margin"] > 1e-3, stats
    assert got[dk.S_COUNT] == ref[dk.S_COUNT] == stats["colour"]
    # float32 in the kernel: errors relative to the column's sum of absolute contributions
    np.testing.assert_array_less(np.abs(got - ref)[: dk.S_COUNT], 1e-4 * scale[: dk.S_COUNT])
    # the comparison can fail: the rotation's Jacobian with the wrong sign (a x q) is far off
    flip = np.array([1, 1, 1, -1, -1, -1, 1, 1.0])
    upper = np.triu_indices(dk.N_PARAMS)
    wrong = ref.copy()
    wrong[: dk.N_UPPER] *= np.outer(flip, flip)[upper]
    wrong[dk.S_GRAD : dk.S_COST] *= flip
    assert np.any(np.abs(got - wrong)[: dk.S_COUNT] > 1e-2 * scale[: dk.S_COUNT])
    counts = histogram.numpy()
    if geometric:
        _assert_same_histogram(counts[TERM_COLOUR], _histogram(stats["residuals"]))
        assert not counts[TERM_GEOMETRIC].any()
        # and the noise scale matters: at the fixed SIGMA_COLOUR the sums differ
        fixed, _, _ = _reference_sums(ref_rgb, ref_depth, rgb, depth, depth_mode, NE_K, NE_T_REL, affine)
        assert np.any(np.abs(got - fixed)[: dk.S_COUNT] > 1e-2 * scale[: dk.S_COUNT])
    else:
        assert not counts.any()


# ---- gradient ---------------------------------------------------------------------------------------
def _smooth_inputs(shape, period: float):
    """Sinusoidal colour and depth (central differences approximate their derivatives), the frame a shifted,
    brighter copy; no reference within 5 px of the border, so that no warped point crosses the image border
    (the sampler's limit) under the finite differences' perturbations."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)

    def colour(dx, dy):
        X, Y = x + dx, y + dy
        return np.stack(
            [
                0.5 + 0.3 * np.sin(X / period + 0.3) * np.cos(Y / (1.3 * period)),
                0.45 + 0.25 * np.sin((X - Y) / (1.1 * period) + 1.0),
                0.5 + 0.2 * np.cos((X + Y) / (0.9 * period)),
            ],
            axis=-1,
        )

    def surface(dx, dy):
        return 2.0 + 0.2 * np.sin((x + dx) / (2 * period)) * np.cos((y + dy) / (2.5 * period)) + 0.005 * x

    ref_depth = surface(0.0, 0.0)
    band = np.zeros(shape, bool)
    band[5:-5, 5:-5] = True
    ref_depth[~band] = 0.0
    rgb = 1.1 * colour(0.3, -0.2) - 0.02
    depth = surface(0.4, -0.3) + 0.01
    return [a.astype(np.float32) for a in (colour(0.0, 0.0), ref_depth, rgb, depth)]


@pytest.mark.parametrize("depth_mode", [dk.DEPTH_NONE, dk.DEPTH_PROJECTIVE])
def test_normal_equations_gradient_matches_finite_differences(device, depth_mode):
    """The sums' J^T W r is the gradient of their Huber cost (IRLS): against central differences of the
    cost column under a left twist T_rel -> Exp(xi) T_rel and under g, b.  The twist's Jacobian takes the
    image gradient from central differences of bilinear samples, the finite differences differentiate the
    bilinear interpolant itself, so they agree to a few percent on sinusoids (measured: <= 2 % a component,
    1.2 % of the norm); a rotation of 8.6 deg about the axis spreads the warped points' sub-pixel phases
    (a near-identity warp leaves them all alike, and the two derivatives then differ by 10 % and more).  The
    affine part is exact."""
    shape, K = (30, 40), (30.0, 30.0, 19.5, 14.5)
    ref_rgb, ref_depth, rgb, depth = _smooth_inputs(shape, 4.0)
    T_rel = se3_exp(np.array([0.01, -0.005, 0.03, 0.01, -0.01, 0.15]))
    affine = np.array([1.0, 0.0])
    _, _, stats = _reference_sums(ref_rgb, ref_depth, rgb, depth, depth_mode, K, T_rel, affine)
    assert stats["colour_huber"] > 0.05 * stats["colour"] and stats["colour_huber"] < 0.6 * stats["colour"], stats
    if depth_mode:
        assert stats["depth"] > 0.5 * stats["colour"] and stats["occluded"] == 0, stats

    def sums(T, a):
        return _kernel_sums(device, ref_rgb, ref_depth, rgb, depth, depth_mode, K, T, a)

    base = sums(T_rel, affine)
    analytic = base[dk.S_GRAD : dk.S_COST]
    numeric = np.zeros(dk.N_PARAMS)
    for k in range(dk.N_PARAMS):
        # 0.1 mm / 0.1 mrad moves the points by ~1.5e-3 px; 2^-12 is exact in float32 around 1 and 0
        eps = 1e-4 if k < 6 else 2.0**-12
        costs = []
        for sign in (1.0, -1.0):
            T, a = T_rel, affine.copy()
            if k < 6:
                T = se3_exp(sign * eps * np.eye(6)[k]) @ T_rel
            else:
                a[k - 6] += sign * eps
            s = sums(T, a)
            assert s[dk.S_COUNT] == base[dk.S_COUNT]  # the same pixels: the cost is continuous
            costs.append(s[dk.S_COST])
        numeric[k] = (costs[0] - costs[1]) / (2 * eps)
    twist_norm = np.linalg.norm(numeric[:6])
    tol = 0.05 * np.abs(numeric[:6]) + 0.01 * twist_norm
    np.testing.assert_array_less(np.abs(analytic[:6] - numeric[:6]), tol)
    np.testing.assert_allclose(analytic[6:], numeric[6:], rtol=1e-3)
    # the check can fail: the rotation's Jacobian with the wrong sign (a x q) misses by far
    assert np.any(np.abs(-analytic[3:6] - numeric[3:6]) > tol[3:6])
    if depth_mode:  # the depth residuals (no pixel occluded: the rest is the colour's) weigh in the check
        colour_only = _kernel_sums(device, ref_rgb, ref_depth, rgb, depth, 0, K, T_rel, affine)
        assert np.linalg.norm((analytic - colour_only[dk.S_GRAD : dk.S_COST])[:6]) > 0.3 * twist_norm


# ---- the step ---------------------------------------------------------------------------------------
def _solve(sums: np.ndarray, T_rel: np.ndarray, affine, T_CW_ref: np.ndarray, device):
    """``solve_step`` on the sums; (T_rel, affine, T_CW_out, T_WC_out) after it, the outputs' initial values
    NaN (left so when no step is taken)."""
    arrays = [
        wp.array(sums, dtype=wp.float64, device=device),
        wp.array([T_CW_ref], dtype=wp.mat44d, device=device),
        wp.array([T_rel], dtype=wp.mat44d, device=device),
        wp.array(np.asarray(affine, np.float64), dtype=wp.float64, device=device),
        wp.array([np.full((4, 4), np.nan)], dtype=wp.mat44d, device=device),
        wp.array([np.full((4, 4), np.nan, np.float32)], dtype=wp.mat44, device=device),
    ]
    wp.launch(dk.solve_step, dim=1, inputs=arrays[:2], outputs=arrays[2:], device=device)
    return [a.numpy()[0] if a.dtype != wp.float64 else a.numpy() for a in arrays[2:]]


def _system(H: np.ndarray, g: np.ndarray, count: float) -> np.ndarray:
    sums = np.zeros(dk.N_COLUMNS)
    sums[: dk.N_UPPER] = H[np.triu_indices(dk.N_PARAMS)]
    sums[dk.S_GRAD : dk.S_COST] = g
    sums[dk.S_COST] = 123.0
    sums[dk.S_COUNT] = count
    return sums


def test_solve_step_takes_the_damped_gauss_newton_step(device):
    """``solve_step``: delta solves (H with its diagonal x (1 + DAMPING)) delta = -g (NumPy), the twist
    left-multiplies T_rel, (g, b) += delta[6:], T_CW_out = T_rel T_CW_ref and T_WC_out its inverse
    (float32).  A step longer than MAX_STEP_M / MAX_STEP_RAD is scaled down as a whole to that length."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(dk.N_PARAMS, dk.N_PARAMS))
    D = np.diag(np.exp(rng.uniform(-2, 2, dk.N_PARAMS)))  # unknowns of different scales
    H = D @ (A @ A.T + 0.5 * np.eye(dk.N_PARAMS)) @ D  # SPD
    g = rng.normal(size=dk.N_PARAMS)
    T_rel = se3_exp(np.array([0.01, -0.02, 0.005, 0.1, 0.05, -0.2]))  # rotated: left != right update
    T_CW_ref = se3_exp(np.array([0.5, 1.0, -0.3, -0.4, 0.9, 0.2]))
    affine = (1.1, -0.03)
    damped = H + dk.DAMPING * np.diag(np.diag(H))
    for factor in (1e4, 1e2):  # a short step, then one the limit shortens
        delta = np.linalg.solve(factor * damped, -g)
        scale = min(1.0, dk.MAX_STEP_M / np.linalg.norm(delta[:3]), dk.MAX_STEP_RAD / np.linalg.norm(delta[3:6]))
        T_out, affine_out, T_CW, T_WC = _solve(_system(factor * H, g, 1000.0), T_rel, affine, T_CW_ref, device)
        expected = se3_exp(scale * delta[:6]) @ T_rel
        # float64 throughout, but the kernel's 1 + DAMPING is a float32 constant (1.0001 + 1.7e-8, a
        # damping 1.7e-4 relatively larger): 4e-7 of the step measured, 1e-6 allowed
        atol = 1e-6 * np.abs(scale * delta).max()
        np.testing.assert_allclose(T_out, expected, rtol=0, atol=atol)
        np.testing.assert_allclose(affine_out, np.asarray(affine) + scale * delta[6:], rtol=0, atol=atol)
        np.testing.assert_allclose(T_CW, expected @ T_CW_ref, rtol=0, atol=atol)
        assert T_WC.dtype == np.float32
        np.testing.assert_allclose(T_WC, invert_pose(expected @ T_CW_ref), rtol=0, atol=2e-6)
        # the comparisons can fail: the right update, or the undamped step, are off by more than atol
        assert np.abs(T_out - T_rel @ se3_exp(scale * delta[:6])).max() > 10 * atol
        undamped = scale * np.linalg.solve(factor * H, -g)
        assert np.abs(affine_out - np.asarray(affine) - undamped[6:]).max() > 10 * atol
        if factor == 1e4:
            assert scale == 1.0
        else:  # shortened: the longer part (relative to its limit) at its limit, the direction kept
            assert scale < 0.5
            rho, phi = np.linalg.norm(scale * delta[:3]), np.linalg.norm(scale * delta[3:6])
            assert max(rho / dk.MAX_STEP_M, phi / dk.MAX_STEP_RAD) == pytest.approx(1.0, rel=1e-6)


def test_solve_step_takes_no_step_without_a_usable_system(device):
    """``solve_step`` leaves T_rel, (g, b) and the output poses as they were with fewer than MIN_PIXELS
    pixels, with an H that is not positive definite, or with a non-finite sum; the same system with
    MIN_PIXELS pixels and a positive definite H does step."""
    rng = np.random.default_rng(4)
    Q, _ = np.linalg.qr(rng.normal(size=(dk.N_PARAMS, dk.N_PARAMS)))
    eigen = np.linspace(1.0, 8.0, dk.N_PARAMS) * 100.0
    g = rng.normal(size=dk.N_PARAMS)
    T_rel = se3_exp(np.array([0.01, -0.02, 0.005, 0.1, 0.05, -0.2]))
    T_CW_ref = se3_exp(np.array([0.5, 1.0, -0.3, -0.4, 0.9, 0.2]))
    affine = (1.1, -0.03)
    H = Q @ np.diag(eigen) @ Q.T
    indefinite = Q @ np.diag(np.r_[-0.5, eigen[1:]]) @ Q.T  # its diagonal stays positive
    assert np.all(np.diag(indefinite) > 0)
    nan_sums = _system(H, g, 1000.0)
    nan_sums[dk.S_GRAD + 2] = np.nan
    cases = {
        "few pixels": _system(H, g, dk.MIN_PIXELS - 1),
        "indefinite": _system(indefinite, g, 1000.0),
        "not finite": nan_sums,
        "steps": _system(H, g, dk.MIN_PIXELS),
    }
    for name, sums in cases.items():
        T_out, affine_out, T_CW, T_WC = _solve(sums, T_rel, affine, T_CW_ref, device)
        if name == "steps":
            delta = np.linalg.solve(H + dk.DAMPING * np.diag(np.diag(H)), -g)
            np.testing.assert_allclose(affine_out, np.asarray(affine) + delta[6:], rtol=1e-6)
            assert np.all(np.isfinite(T_CW)) and np.all(np.isfinite(T_WC))
        else:
            assert np.array_equal(T_out, T_rel) and np.array_equal(affine_out, affine), name
            assert np.all(np.isnan(T_CW)) and np.all(np.isnan(T_WC)), name


# ---- Gauss-Newton on an exactly warped scene --------------------------------------------------------
def _textured_plane(T_rel: np.ndarray, gain: float, bias: float):
    """A slanted plane (depth 2 m at the centre) with a smooth texture, 48x36 at f = 40: the reference's
    image and depth, and the frame's (camera T_rel from the reference's, brightness g I + b), by ray casting."""
    h, w = 36, 48
    K = (40.0, 40.0, 23.5, 17.5)
    n = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    c = 2.0 * n[2]  # the plane n . X = c
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.stack([(x - K[2]) / K[0], (y - K[3]) / K[1], np.ones_like(x)], axis=-1)

    def texture(X):  # periods of 16-40 px: bilinear resampling keeps their contrast to ~1 %
        a, b = X[..., 0], X[..., 1] + 0.5 * X[..., 2]
        return np.stack(
            [
                0.5 + 0.3 * np.sin(a / 0.2) * np.cos(b / 0.25),
                0.45 + 0.25 * np.sin((a - b) / 0.22 + 1.0),
                0.5 + 0.2 * np.cos((a + b) / 0.18),
            ],
            axis=-1,
        )

    def view(T):  # the plane seen from camera T (from the reference's)
        R, t = T[:3, :3], T[:3, 3]
        m = R @ n  # in that camera: m . X' = c + m . t
        Z = (c + m @ t) / (rays @ m)
        return texture((Z[..., None] * rays - t) @ R), Z

    ref_rgb, ref_depth = view(np.eye(4))
    rgb, depth = view(T_rel)
    return K, [a.astype(np.float32) for a in (ref_rgb, ref_depth, gain * rgb + bias, depth)]


def _gauss_newton(device, K, images, depth_mode: int, iters: int, brightness: bool = True):
    """``iters`` steps of ``normal_equations`` (and in DEPTH_GEOMETRIC ``geometric_equations``, a first pass
    that only estimates the noise scales and ``solve_scales`` after each) + ``solve_step`` from T_rel = I,
    (g, b) = (1, 0), as ``DirectAlignment.align`` at one level; ``brightness`` False holds (g, b) (their rows
    of the system replaced by the identity's, on the host).  Returns T_rel, (g, b) and the scales."""
    ref_rgb, ref_depth, rgb, depth = images
    h, w = ref_depth.shape
    geometric = depth_mode == dk.DEPTH_GEOMETRIC
    ref_depth_wp = wp.array(ref_depth, dtype=wp.float32, device=device)
    depth_wp = wp.array(depth, dtype=wp.float32, device=device)
    inputs = [
        wp.array(ref_rgb, dtype=wp.vec3, device=device),
        ref_depth_wp,
        wp.array(rgb, dtype=wp.vec3, device=device),
        depth_wp,
        depth_mode,
        wp.vec4(*K),
    ]
    T_rel = wp.array([np.eye(4)], dtype=wp.mat44d, device=device)
    affine = wp.array([1.0, 0.0], dtype=wp.float64, device=device)
    scales = wp.array([dk.SIGMA_COLOUR, 1.0], dtype=wp.float32, device=device)
    T_CW_ref = wp.array([np.eye(4)], dtype=wp.mat44d, device=device)
    T_CW, T_WC = wp.zeros(1, dtype=wp.mat44d, device=device), wp.zeros(1, dtype=wp.mat44, device=device)
    sums = wp.zeros(dk.N_COLUMNS, dtype=wp.float64, device=device)
    histogram = wp.zeros((N_TERMS, dk.HIST_BINS), dtype=wp.int32, device=device)
    blocks = [(h * w + dk.BLOCK - 1) // dk.BLOCK]
    rows, cols = np.triu_indices(dk.N_PARAMS)
    for k in range(iters + int(geometric)):
        sums.zero_()
        histogram.zero_()
        wp.launch_tiled(
            dk.normal_equations,
            dim=blocks,
            inputs=inputs + [T_rel, affine, scales],
            outputs=[sums, histogram],
            block_dim=dk.BLOCK,
            device=device,
        )
        if geometric:
            wp.launch_tiled(
                dk.geometric_equations,
                dim=blocks,
                inputs=[ref_depth_wp, depth_wp, wp.vec4(*K), T_rel, scales],
                outputs=[sums, histogram],
                block_dim=dk.BLOCK,
                device=device,
            )
        if not brightness:
            s = sums.numpy()
            s[: dk.N_UPPER][cols >= 6] = (rows == cols)[cols >= 6]
            s[dk.S_GRAD + 6 : dk.S_COST] = 0.0
            sums = wp.array(s, dtype=wp.float64, device=device)
        if k > 0 or not geometric:
            wp.launch(dk.solve_step, dim=1, inputs=[sums, T_CW_ref], outputs=[T_rel, affine, T_CW, T_WC], device=device)
        if geometric:
            wp.launch(dk.solve_scales, dim=N_TERMS, inputs=[histogram], outputs=[scales], device=device)
    return T_rel.numpy()[0], affine.numpy(), scales.numpy()


def _relative_error(T: np.ndarray, T_ref: np.ndarray) -> tuple[float, float]:
    E = T @ invert_pose(T_ref)
    return float(np.linalg.norm(E[:3, 3])), rotation_angle_deg(E[:3, :3])


@pytest.mark.parametrize("depth_mode", [dk.DEPTH_NONE, dk.DEPTH_PROJECTIVE, dk.DEPTH_GEOMETRIC])
def test_gauss_newton_recovers_an_exact_warp_and_its_exposure(device, depth_mode):
    """Iterating ``normal_equations`` + ``solve_step`` on a textured plane seen from a camera 2.7 cm /
    1.5 deg away, 1.2x brighter - 0.05, recovers that pose and exposure (measured: 0.13 mm / 0.002 deg
    with the projective depth residual, 0.11 mm / 0.002 deg point to plane with the estimated noise scales
    (``geometric_equations``, ``solve_scales``), 2.4 mm / 0.055 deg without depth, whose translation trades
    against the rotation; gain 1.18: bilinear resampling softens the texture by ~1 %); with (g, b) held at
    (1, 0) the exposure change throws the pose off by 23 mm (projective) / 12 mm (point to plane) / 140 mm."""
    T_true = se3_exp(np.array([0.02, -0.015, 0.01, 0.01, 0.02, -0.015]))
    K, images = _textured_plane(T_true, 1.2, -0.05)
    T, affine, _ = _gauss_newton(device, K, images, depth_mode, 8)
    dt, dr = _relative_error(T, T_true)
    start = _relative_error(np.eye(4), T_true)
    assert start[0] > 0.025 and start[1] > 1.4
    limits = (5e-4, 0.01) if depth_mode else (5e-3, 0.1)
    assert dt < limits[0] and dr < limits[1], (dt, dr)
    assert abs(affine[0] - 1.2) < 0.03 and abs(affine[1] + 0.05) < 0.015, affine
    T_fixed, affine_fixed, _ = _gauss_newton(device, K, images, depth_mode, 8, brightness=False)
    assert np.array_equal(affine_fixed, [1.0, 0.0])
    assert _relative_error(T_fixed, T_true)[0] > 5 * max(dt, 2e-3)


# ---- the geometric term: point to plane against the reference's depth ----------------------------------
GEO_SHAPE = (48, 64)
GEO_K = (50.0, 50.0, 31.5, 23.5)
GEO_T_REL = se3_exp(1.07 * np.array([0.006, -0.004, 0.008, 0.012, -0.009, 0.015]))  # no pixel near a tie


def _kinect_sigma(z):
    """The depth noise model: sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 m (Kinect v1, Nguyen et al. 2012)."""
    return 0.0012 + 0.0019 * (z - 0.4) ** 2


def _point(x: float, y: float, z: float, K) -> np.ndarray:
    fx, fy, cx, cy = K
    return np.array([z * (x - cx) / fx, z * (y - cy) / fy, z])


def _edge_weight(depth: np.ndarray, x: int, y: int, K, noise: float) -> float:
    """1 / (1 + (s / (EDGE_SLOPE + noise f / D))^2), s = |grad D| f / D from central differences; 0 on the
    border, without depth or next to a pixel without it."""
    h, w = depth.shape
    if not (1 <= x <= w - 2 and 1 <= y <= h - 2):
        return 0.0
    d = float(depth[y, x])
    left, right, up, down = (float(depth[y + dy, x + dx]) for dy, dx in ((0, -1), (0, 1), (-1, 0), (1, 0)))
    if d <= 0 or min(left, right, up, down) <= 0:
        return 0.0
    slope2 = (0.5 * (right - left) * K[0] / d) ** 2 + (0.5 * (down - up) * K[1] / d) ** 2
    limit = dk.EDGE_SLOPE + noise * 0.5 * (K[0] + K[1]) / d
    return 1.0 / (1.0 + slope2 / limit**2)


def _plane(depth: np.ndarray, x: int, y: int, K) -> tuple[np.ndarray, np.ndarray]:
    """The reference's point at pixel (x, y) and its unit normal, (P(x+1) - P(x-1)) x (P(y+1) - P(y-1))."""
    P = lambda u, v: _point(u, v, float(depth[v, u]), K)  # noqa: E731
    n = np.cross(P(x + 1, y) - P(x - 1, y), P(x, y + 1) - P(x, y - 1))
    return P(x, y), n / np.linalg.norm(n)


def _point_to_plane_reference(ref_depth, depth, K, T_rel):
    """Per frame pixel, float64: the residual n . (T^-1 q - p), its Jacobian (-m, m x q, 0, 0) (m = R n),
    sigma(z), the pair's weight (0: none) and the reference pixel it is associated with; and the smallest
    margin of a discontinuous test among the pixels (association rounding, depth gap)."""
    h, w = depth.shape
    R, t = T_rel[:3, :3], T_rel[:3, 3]
    out = {
        "r": np.zeros((h, w)),
        "J": np.zeros((h, w, dk.N_PARAMS)),
        "sigma": np.zeros((h, w)),
        "weight": np.zeros((h, w)),
        "pixel": np.full((h, w, 2), -1),
        "gaps": 0,
    }
    margins = []
    for y in range(h):
        for x in range(w):
            z = float(depth[y, x])
            if z <= 0:
                continue
            sigma = _kinect_sigma(z)
            w_frame = _edge_weight(depth, x, y, K, sigma)
            if w_frame == 0:
                continue
            q = _point(x, y, z, K)
            pf = R.T @ (q - t)
            u, v = K[0] * pf[0] / pf[2] + K[2], K[1] * pf[1] / pf[2] + K[3]
            xr, yr = int(np.floor(u + 0.5)), int(np.floor(v + 0.5))
            margins += [abs(u + 0.5 - round(u + 0.5)), abs(v + 0.5 - round(v + 0.5))]
            w_ref = _edge_weight(ref_depth, xr, yr, K, 0.0)
            if w_ref == 0:
                continue
            p, n = _plane(ref_depth, xr, yr, K)
            margins.append(abs(abs(pf[2] - p[2]) / p[2] - dk.MAX_DEPTH_GAP))
            if abs(pf[2] - p[2]) > dk.MAX_DEPTH_GAP * p[2]:
                out["gaps"] += 1
                continue
            m = R @ n
            out["r"][y, x] = n @ (pf - p)
            out["J"][y, x, :6] = np.concatenate([-m, np.cross(m, q)])
            out["sigma"][y, x] = sigma
            out["weight"][y, x] = w_frame * w_ref
            out["pixel"][y, x] = xr, yr
    out["margin"] = min(margins)
    return out


def _geometric_inputs():
    """Reference depth (a curved surface, a box in front: depth edges, holes, an uncovered strip) and the
    frame's: the surface seen about a pixel aside, with Kinect-like noise growing with the depth squared,
    missing pixels and a patch, and an occluder nearer by a quarter."""
    h, w = GEO_SHAPE
    rng = np.random.default_rng(7)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)

    def surface(dx, dy):
        X, Y = x + dx, y + dy
        z = 2.0 + 0.25 * np.sin(X / 7.0) * np.cos(Y / 6.0) + 0.008 * X
        return np.where((Y >= 12) & (Y < 26) & (X >= 36) & (X < 52), 1.3 + 0.004 * Y, z)

    ref_depth = surface(0.0, 0.0)
    ref_depth[[5, 30, 40], [10, 20, 50]] = 0.0
    ref_depth[:, :3] = 0.0  # the map does not cover it
    depth = surface(0.6, -0.4)
    depth += rng.normal(size=depth.shape) * 1.5e-3 * depth**2
    depth[30:38, 8:18] *= 0.75  # an occluder
    depth[rng.uniform(size=depth.shape) < 0.03] = 0.0
    depth[40:44, 30:36] = 0.0
    return ref_depth.astype(np.float32), depth.astype(np.float32)


@wp.kernel
def _point_to_plane_pixels(
    ref_depth: wp.array2d(dtype=wp.float32),
    depth: wp.array2d(dtype=wp.float32),
    intrinsics: wp.vec4,
    T: wp.array(dtype=wp.mat44d),
    r_out: wp.array2d(dtype=wp.float32),
    J_out: wp.array2d(dtype=dk.vec8),
    sigma_out: wp.array2d(dtype=wp.float32),
    weight_out: wp.array2d(dtype=wp.float32),
):
    y, x = wp.tid()
    r, J, sigma, weight = dk.point_to_plane(ref_depth, depth, x, y, intrinsics, T[0])
    r_out[y, x] = r
    J_out[y, x] = J
    sigma_out[y, x] = sigma
    weight_out[y, x] = weight


def _kernel_point_to_plane(device, ref_depth, depth, K, T_rel) -> dict:
    shape = depth.shape
    out = {
        "r": wp.zeros(shape, dtype=wp.float32, device=device),
        "J": wp.zeros(shape, dtype=dk.vec8, device=device),
        "sigma": wp.zeros(shape, dtype=wp.float32, device=device),
        "weight": wp.zeros(shape, dtype=wp.float32, device=device),
    }
    wp.launch(
        _point_to_plane_pixels,
        dim=shape,
        inputs=[wp.array(ref_depth, device=device), wp.array(depth, device=device), wp.vec4(*K)]
        + [wp.array([T_rel], dtype=wp.mat44d, device=device)],
        outputs=list(out.values()),
        device=device,
    )
    return {k: v.numpy().astype(np.float64) for k, v in out.items()}


def test_point_to_plane_residual_and_its_jacobian_against_finite_differences(device):
    """``point_to_plane`` on every frame pixel: the same pixels used, residuals, sigma(z) and weights as the
    NumPy reference, and its Jacobian equal to central differences (float64) of the reference's residual
    under the left twist T_rel -> Exp(xi) T_rel, the association held (as Gauss-Newton holds it)."""
    ref_depth, depth = _geometric_inputs()
    ref = _point_to_plane_reference(ref_depth, depth, GEO_K, GEO_T_REL)
    got = _kernel_point_to_plane(device, ref_depth, depth, GEO_K, GEO_T_REL)
    used = ref["weight"] > 0
    # every branch: pixels without depth or at an edge (weight 0), down-weighted slopes, occlusions, and
    # no pixel within float32 rounding of the association's rounding or the gap threshold
    assert 500 < used.sum() < 0.9 * depth.size and ref["gaps"] > 5, (used.sum(), ref["gaps"])
    assert ref["weight"][used].max() > 0.95 and ref["weight"][used].min() < 0.3
    assert ref["margin"] > 1e-4, ref["margin"]
    np.testing.assert_array_equal(got["weight"] > 0, used)
    np.testing.assert_allclose(got["weight"][used], ref["weight"][used], rtol=1e-5)
    np.testing.assert_allclose(got["sigma"][used], ref["sigma"][used], rtol=1e-6)
    np.testing.assert_allclose(got["r"][used], ref["r"][used], rtol=0, atol=2e-6)
    # float32: the normal from differences of neighbouring points (8 cm apart at 2 m) keeps ~2e-6 of it
    np.testing.assert_allclose(got["J"][used], ref["J"][used], rtol=0, atol=1e-5)

    # central differences of r(xi) = n . ((Exp(xi) T)^-1 q - p), p and n of the associated pixel
    eps = 1e-6
    ys, xs = np.nonzero(used)
    fd = np.zeros((len(ys), 6))
    for k in range(6):
        for sign in (1.0, -1.0):
            T = invert_pose(se3_exp(sign * eps * np.eye(6)[k]) @ GEO_T_REL)
            for i, (y, x) in enumerate(zip(ys, xs, strict=True)):
                q = _point(x, y, float(depth[y, x]), GEO_K)
                p, n = _plane(ref_depth, *ref["pixel"][y, x], GEO_K)
                fd[i, k] += sign * (n @ (T[:3, :3] @ q + T[:3, 3] - p)) / (2 * eps)
    J = got["J"][ys, xs, :6]
    assert np.abs(fd).max() > 1.0
    np.testing.assert_allclose(J, fd, rtol=0, atol=2e-5)
    # the check can fail: the rotation part with the wrong sign (q x m), or the right update's Jacobian
    assert np.abs(np.concatenate([J[:, :3], -J[:, 3:]], axis=1) - fd).max() > 0.1
    assert np.all(got["J"][..., 6:] == 0)  # (g, b) do not enter the geometric residual


def _geometric_reference_sums(ref: dict, scale_g: float) -> tuple[np.ndarray, np.ndarray, int]:
    """``geometric_equations``' sums in float64 from the reference's residuals: each r / (sigma(z) s) under
    Huber's IRLS weight times the pair's weight; their sums of absolute contributions; the Huber count."""
    sums, scale = np.zeros(dk.N_COLUMNS), np.zeros(dk.N_COLUMNS)
    upper = np.triu_indices(dk.N_PARAMS)
    huber = 0
    for y, x in zip(*np.nonzero(ref["weight"] > 0), strict=True):
        sigma = ref["sigma"][y, x] * scale_g
        r, J, weight = ref["r"][y, x], ref["J"][y, x], ref["weight"][y, x]
        e = r / sigma
        huber += abs(e) > dk.HUBER
        wt = weight * (1.0 if abs(e) <= dk.HUBER else dk.HUBER / abs(e)) / sigma**2
        terms = np.concatenate([wt * np.outer(J, J)[upper], wt * J * r, [weight * _huber(e), 1.0]])
        sums += terms
        scale += np.abs(terms)
    return sums, scale, huber


def test_geometric_equations_match_numpy(device):
    """``geometric_equations``: the normal-equation sums (J^T W J upper triangle, J^T W r, cost, count) added
    to the given sums, and the histogram of |r| / sigma(z) (row TERM_GEOMETRIC), against NumPy from the
    reference residuals; the geometric scale read from the scales (at 2, about a third of the residuals
    lie beyond Huber's threshold)."""
    ref_depth, depth = _geometric_inputs()
    ref = _point_to_plane_reference(ref_depth, depth, GEO_K, GEO_T_REL)
    scale_g = 2.0
    expected, scale, huber = _geometric_reference_sums(ref, scale_g)
    used = ref["weight"] > 0
    assert 0.05 * used.sum() < huber < 0.6 * used.sum(), (huber, used.sum())
    start = np.linspace(1.0, 2.0, dk.N_COLUMNS)  # added to what is there (the colour's sums)
    sums = wp.array(start, dtype=wp.float64, device=device)
    histogram = wp.zeros((N_TERMS, dk.HIST_BINS), dtype=wp.int32, device=device)
    h, w = depth.shape
    wp.launch_tiled(
        dk.geometric_equations,
        dim=[(h * w + dk.BLOCK - 1) // dk.BLOCK],
        inputs=[wp.array(ref_depth, device=device), wp.array(depth, device=device), wp.vec4(*GEO_K)]
        + [wp.array([GEO_T_REL], dtype=wp.mat44d, device=device)]
        + [wp.array([0.123, scale_g], dtype=wp.float32, device=device)],
        outputs=[sums, histogram],
        block_dim=dk.BLOCK,
        device=device,
    )
    got = sums.numpy() - start
    assert got[dk.S_COUNT] == used.sum()
    np.testing.assert_array_less(np.abs(got - expected)[: dk.S_COUNT], 1e-4 * scale[: dk.S_COUNT] + 1e-12)
    counts = histogram.numpy()
    assert not counts[TERM_COLOUR].any()
    _assert_same_histogram(counts[TERM_GEOMETRIC], _histogram(ref["r"][used] / ref["sigma"][used]))
    # the comparison can fail: without the edge weights, or at scale 1, the sums differ
    plain = dict(ref, weight=used.astype(float))
    for other in (_geometric_reference_sums(plain, scale_g)[0], _geometric_reference_sums(ref, 1.0)[0]):
        assert np.any(np.abs(got - other)[: dk.S_COUNT] > 1e-2 * scale[: dk.S_COUNT])


def test_solve_scales_is_the_median_absolute_residual(device):
    """``solve_scales``: each term's scale is 1.4826 x the median |r| of its histogram (log-uniform within the
    median's bin: within 3 % of NumPy's median on the samples), at least its floor; a term with fewer than
    MIN_PIXELS residuals keeps its scale."""
    rng = np.random.default_rng(3)
    colour = rng.normal(0, 0.03, 5000)
    colour[:800] = rng.uniform(-1, 1, 800)  # outliers: the median stays put
    geometric = rng.normal(0, 0.7, 3000)
    cases = [
        (colour, geometric, [1.4826 * np.median(np.abs(colour)), 1.4826 * np.median(np.abs(geometric))]),
        (colour * 1e-3, geometric * 1e-3, [dk.SIGMA_COLOUR_MIN, dk.GEOMETRIC_SCALE_MIN]),  # the floors
        (colour[: dk.MIN_PIXELS - 1], geometric, [0.5, 1.4826 * np.median(np.abs(geometric))]),  # too few: kept
    ]
    for c, g, expected in cases:
        histogram = wp.array(np.stack([_histogram(c), _histogram(g)]).astype(np.int32), device=device)
        scales = wp.array([0.5, 3.0], dtype=wp.float32, device=device)
        wp.launch(dk.solve_scales, dim=N_TERMS, inputs=[histogram], outputs=[scales], device=device)
        np.testing.assert_allclose(scales.numpy(), expected, rtol=0.03)
    assert 1.4826 * np.median(np.abs(colour)) < 0.04  # the outliers did not count (their std is 0.58)


# ---- the tracker's direct stage on a map built from ground truth ------------------------------------
# test_tracking.py's scene (helpers_maps.room_scene): room0 at 96x54 (fx = 48), a map of discs on the
# ground-truth depth of frames 0, 4, 8, the frames observed as the map's renders at the true poses.
@pytest.fixture(scope="module")
def scene(device):
    return room_scene(device)


def _track(device, scene, cfg, mode, rgb=None, frame=2, seeds=(0, 1)) -> list[np.ndarray]:
    """``Tracker(cfg)``'s poses of frame ``frame`` (observed, or ``rgb``) from starts 2 cm / 2 deg off."""
    observed, depth = scene["observe"](frame)
    rgb = observed if rgb is None else rgb
    tracker = Tracker(cfg, scene["camera"], device, mode=mode)
    poses = []
    for seed in seeds:
        T0 = perturbed(scene["poses"][frame], 0.02, 2.0, seed)
        result = tracker.track(rgb, depth if mode == "rgbd" else None, scene["map"], T0)
        assert not result.lost, result.reason
        poses.append(result.T_WC)
    return poses


def _errors(scene, poses, frame=2) -> np.ndarray:
    """(translation m, rotation deg) of each pose against the truth."""
    return np.array([pose_error(T, scene["poses"][frame]) for T in poses])


@pytest.mark.parametrize("mode", ["rgbd", "mono"])
def test_direct_stage_lands_near_the_true_pose(device, scene, mode):
    """``tracking.direct_levels=2`` with one Adam step at lr 1e-4 (which hardly moves the pose, so this is
    the direct stage alone) from 2 cm / 2 deg off: measured 4.6-5.3 mm / 0.04-0.05 deg in RGB-D (6.6-7.2 mm /
    0.09-0.10 deg with ``tracking.geometric`` off, the projective depth residual); monocular
    0.26-0.32 deg but 22-24 mm, no better than the start (at 96x54 its translation trades against the
    rotation).  The same step without the direct stage stays at the start (20 mm / 1.98 deg).  The
    remaining error is the reference's: a render at the start pose resampled, not the frame's render
    (an exact warp converges: test_gauss_newton_recovers_an_exact_warp_and_its_exposure)."""
    direct = _errors(scene, _track(device, scene, TrackingConfig(direct_levels=2, iters=1, lr=1e-4), mode))
    plain = _errors(scene, _track(device, scene, TrackingConfig(direct_levels=0, iters=1, lr=1e-4), mode))
    assert np.all(plain[:, 0] > 0.018) and np.all(plain[:, 1] > 1.9), plain
    if mode == "rgbd":
        assert np.all(direct[:, 0] < 0.01) and np.all(direct[:, 1] < 0.2), direct
        assert np.all(direct[:, 0] < 0.5 * plain[:, 0]) and np.all(direct[:, 1] < 0.1 * plain[:, 1])
    else:
        assert np.all(direct[:, 1] < 0.5) and np.all(direct[:, 1] < 0.25 * plain[:, 1]), direct
        assert np.all(direct[:, 0] < 0.035), direct  # does not run away


@pytest.mark.parametrize("mode", ["rgbd", "mono"])
@pytest.mark.slow
def test_direct_stage_then_adam_steps_reach_sub_millimetre(device, scene, mode):
    """The direct stage, then 15 Adam steps at lr 1e-3, from 2 cm / 2 deg off: measured 0.06-0.09 mm /
    0.001-0.002 deg (RGB-D; 0.10-0.22 mm with ``tracking.geometric`` off), 1.0-1.5 mm / 0.011-0.017 deg
    (mono); the 15 steps alone end 46-73 mm off."""
    direct = _errors(scene, _track(device, scene, TrackingConfig(direct_levels=2, iters=15, lr=1e-3), mode))
    limits = (5e-4, 0.02) if mode == "rgbd" else (3e-3, 0.05)
    assert np.all(direct[:, 0] < limits[0]) and np.all(direct[:, 1] < limits[1]), direct
    if mode == "rgbd":
        plain = _errors(scene, _track(device, scene, TrackingConfig(direct_levels=0, iters=15, lr=1e-3), mode))
        assert np.all(plain[:, 0] > 0.01), plain


def test_direct_stage_absorbs_an_exposure_change(device, scene):
    """A frame 1.25x brighter - 0.04 (Eq. 3): the direct stage alone (RGB-D, as above) still lands within
    1 cm / 0.2 deg, and within 0.14 mm / 0.004 deg (measured; 1.1 mm / 0.03 deg with ``tracking.geometric``
    off) of where it lands on the unchanged frame; its (g, b) take the change (without them the pose
    suffers: the exact-warp test)."""
    cfg = TrackingConfig(direct_levels=2, iters=1, lr=1e-4)
    observed, _ = scene["observe"](2)
    brighter = np.clip(1.25 * observed - 0.04, 0, 1).astype(np.float32)
    assert np.mean(brighter == 1.0) < 0.01  # hardly any saturated pixel
    same = _track(device, scene, cfg, "rgbd")
    changed = _track(device, scene, cfg, "rgbd", brighter)
    errors = _errors(scene, changed)
    assert np.all(errors[:, 0] < 0.01) and np.all(errors[:, 1] < 0.2), errors
    for a, b in zip(same, changed, strict=True):
        dt, dr = pose_error(a, b)
        assert dt < 2e-3 and dr < 0.06, (dt, dr)


def test_direct_levels_must_fit_the_image(device, scene):
    """``tracking.direct_levels``: every pyramid level keeps DIRECT_MIN_PX (8) pixels a side, else
    ValueError naming the setting and the first level too small (96x54: level 3 is 12x6); 3 levels fit
    (level 2 is 24x13), 0 is off."""
    with pytest.raises(ValueError, match=r"tracking\.direct_levels = 5: level 3 .* is 12x6"):
        Tracker(TrackingConfig(direct_levels=5), scene["camera"], device)
    with pytest.raises(ValueError, match=r"tracking\.direct_levels = 4: level 3"):
        Tracker(TrackingConfig(direct_levels=4), scene["camera"], device)
    for levels in (0, 3):
        Tracker(TrackingConfig(direct_levels=levels), scene["camera"], device)
