"""Kernels of the mapper (supplement §4.5): the window loss's image gradients (L1 with robust per-pixel
weights, exposure (g, b) of the keyframe, depth L1), the regularizer of the Gaussians (elongation,
saturated opacity, drift from the EMA position), the per-Gaussian statistics m_i, v_i and the EMA of
Eq. 15, and the window's exposure-corrected squared error (convergence curves).

Reductions sum ``REDUCE_BLOCK`` pixels in a block tile and add one float64 atomic per block and column,
so nothing is read back to the host inside the mapping loop.
"""

import warp as wp

from rgs_warp.kernels.math import REDUCE_BLOCK, block_sum

wp.set_module_options({"enable_backward": False})

# Loss columns (one row per iteration).
L_LOSS = 0  # weighted L1 + depth term, divided by the pixel count (SSIM is added on the host side)
L_ABS = 1  # sum over pixels of the unweighted mean |I - g I_hat - b| over channels
L_PIXELS = 2  # pixels counted
L_DEPTH = 3  # sum |D_hat - D| over pixels with observed depth
L_DEPTH_PIXELS = 4
L_COLUMNS = 5


@wp.kernel
def mapping_loss(
    # in: observed keyframe (depth ignored unless use_depth) and the render
    observed: wp.array2d(dtype=wp.vec3),
    observed_depth: wp.array2d(dtype=wp.float32),
    rendered: wp.array2d(dtype=wp.vec3),
    rendered_depth: wp.array2d(dtype=wp.float32),
    # in: exposures (g, b) of Eq. 3 of the window's keyframes and this view's position, robust scale,
    # depth weight
    exposure: wp.array(dtype=wp.vec2),
    view: int,
    robust_scale: float,
    use_depth: int,
    depth_weight: float,
    l1_weight: float,
    row: int,
    # the row is row + counter[0] (the mapping step counter, kernels.tracking.advance_step)
    counter: wp.array(dtype=wp.int32),
    # out: x = g I_hat + b (SSIM's input), dL/dx of the L1 part, dL/dD_hat, loss sums of row `row`
    x_out: wp.array2d(dtype=wp.vec3),
    grad_x_out: wp.array2d(dtype=wp.vec3),
    d_depth_out: wp.array2d(dtype=wp.float32),
    loss_out: wp.array2d(dtype=wp.float64),
):
    # L = 1/N sum_x [ l1 w_r(x) |I - x|_1 + lambda_d |D_hat - D| ] with x = g I_hat + b.  w_r is a
    # Cauchy weight 1 / (1 + (r / c)^2) of the pixel's mean absolute residual r, held constant in the
    # gradient (one IRLS step per iteration): outliers (specularities, moving objects, wrong seeds)
    # pull with at most ~c / 2 instead of their full residual.  The depth is the un-normalised
    # rendered depth sum_i w_i z_i: matching it also drives the opacity of observed surfaces to 1.
    block, lane = wp.tid()
    row = row + counter[0]
    i = block * REDUCE_BLOCK + lane
    height = observed.shape[0]
    width = observed.shape[1]
    s = wp.vec4(0.0)
    d_ab = wp.vec2(0.0)
    if i < height * width:
        y = i // width
        x = i - y * width
        inv_n = 1.0 / float(height * width)
        xv = exposure[view][0] * rendered[y, x] + wp.vec3(exposure[view][1])
        x_out[y, x] = xv
        r = observed[y, x] - xv
        mean_abs = (wp.abs(r[0]) + wp.abs(r[1]) + wp.abs(r[2])) / 3.0
        w = float(1.0)
        if robust_scale > 0.0:
            q = mean_abs / robust_scale
            w = 1.0 / (1.0 + q * q)
        k = -inv_n * l1_weight * w
        grad_x_out[y, x] = k * wp.vec3(wp.sign(r[0]), wp.sign(r[1]), wp.sign(r[2]))
        loss = l1_weight * w * 3.0 * mean_abs * inv_n
        d_depth = float(0.0)
        if use_depth != 0:
            d_obs = observed_depth[y, x]
            if d_obs > 0.0:
                e = rendered_depth[y, x] - d_obs
                loss += depth_weight * wp.abs(e) * inv_n
                d_depth = inv_n * depth_weight * wp.sign(e)
                d_ab = wp.vec2(wp.abs(e), 1.0)
        d_depth_out[y, x] = d_depth
        s = wp.vec4(loss, mean_abs, 1.0, 0.0)
    total = block_sum(s)
    total_d = block_sum(d_ab)
    if lane == 0:
        wp.atomic_add(loss_out, row, L_LOSS, wp.float64(total[0]))
        wp.atomic_add(loss_out, row, L_ABS, wp.float64(total[1]))
        wp.atomic_add(loss_out, row, L_PIXELS, wp.float64(total[2]))
        wp.atomic_add(loss_out, row, L_DEPTH, wp.float64(total_d[0]))
        wp.atomic_add(loss_out, row, L_DEPTH_PIXELS, wp.float64(total_d[1]))


@wp.kernel
def scale_image_grad(
    # in: dL/dx of x = g I_hat + b, the window's exposures and this view's position
    grad_x: wp.array2d(dtype=wp.vec3),
    exposure: wp.array(dtype=wp.vec2),
    view: int,
    # out: dL/dI_hat
    d_color_out: wp.array2d(dtype=wp.vec3),
):
    y, x = wp.tid()
    d_color_out[y, x] = exposure[view][0] * grad_x[y, x]


@wp.kernel
def regularize(
    # in: parameters, EMA positions
    means: wp.array(dtype=wp.vec3),
    log_scales: wp.array(dtype=wp.vec3),
    opacity_logits: wp.array(dtype=wp.float32),
    ema_means: wp.array(dtype=wp.vec3),
    # in: coefficients
    w_elongation: float,
    max_log_ratio: float,
    w_opacity: float,
    max_abs_logit: float,
    w_anchor: float,
    # in/out: gradients (added to)
    grad_means: wp.array(dtype=wp.vec3),
    grad_log_scales: wp.array(dtype=wp.vec3),
    grad_opacity: wp.array(dtype=wp.float32),
):
    # R = w_e relu(l_max - l_mid - log r)^2 + w_o relu(|logit| - o_max)^2 + w_a |mu - mu_ema|^2:
    # - elongation: a needle (largest scale r times the middle one) streaks across the image when
    #   seen from the side; flat discs (two equal large scales, a small axial one) are the surfel
    #   shape the seeds start with and are left alone;
    # - degenerate transmittance: a saturated sigmoid (opacity ~0 or ~1) has no gradient left, the
    #   Gaussian freezes as a hole or as an opaque occluder; the logit is kept within +-o_max;
    # - anchor: new Gaussians stay near the EMA of their own trajectory (Eq. 15) while their
    #   neighbours are still settling, instead of drifting with the first few noisy gradients.
    i = wp.tid()
    ls = log_scales[i]
    # indices of the largest and middle scale
    a = int(0)
    if ls[1] > ls[a]:
        a = 1
    if ls[2] > ls[a]:
        a = 2
    b = (a + 1) % 3
    c = (a + 2) % 3
    if ls[c] > ls[b]:
        b = c
    excess = ls[a] - ls[b] - max_log_ratio
    if excess > 0.0:
        g = grad_log_scales[i]
        g[a] = g[a] + 2.0 * w_elongation * excess
        g[b] = g[b] - 2.0 * w_elongation * excess
        grad_log_scales[i] = g
    o = opacity_logits[i]
    over = wp.abs(o) - max_abs_logit
    if over > 0.0:
        grad_opacity[i] = grad_opacity[i] + 2.0 * w_opacity * over * wp.sign(o)
    grad_means[i] = grad_means[i] + 2.0 * w_anchor * (means[i] - ema_means[i])


@wp.kernel
def update_statistics(
    # in: the render's radii (> 0: inside the view), the opacity gradient accumulated up to and before
    # this view's backward (a change: the Gaussian contributed to a pixel of this view)
    radii: wp.array(dtype=wp.vec2i),
    grad_opacity: wp.array(dtype=wp.float32),
    grad_opacity_before: wp.array(dtype=wp.float32),
    # in/out: m_i (observation count), v_i (cumulative visibility)
    obs_count: wp.array(dtype=wp.int32),
    vis_count: wp.array(dtype=wp.float32),
):
    i = wp.tid()
    if radii[i][0] > 0:
        obs_count[i] = obs_count[i] + 1
        if grad_opacity[i] != grad_opacity_before[i]:
            vis_count[i] = vis_count[i] + 1.0


@wp.kernel
def update_ema(
    # in: positions after the step, smoothing factor eta of Eq. 15
    means: wp.array(dtype=wp.vec3),
    eta: float,
    # in/out: EMA positions
    ema_means: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    ema_means[i] = (1.0 - eta) * ema_means[i] + eta * means[i]


@wp.kernel
def exposed_squared_error(
    # in: keyframe image, render of the map at its pose, the window's exposures (Eq. 3), the view's
    # position in the window (its exposure and its entry of the sums)
    observed: wp.array2d(dtype=wp.vec3),
    rendered: wp.array2d(dtype=wp.vec3),
    exposure: wp.array(dtype=wp.vec2),
    row: int,
    # out: sum over pixels and channels of (clip(g I_hat + b, 0, 1) - I)^2, added to entry `row`
    sums_out: wp.array(dtype=wp.float64),
):
    block, lane = wp.tid()
    i = block * REDUCE_BLOCK + lane
    width = observed.shape[1]
    e = float(0.0)
    if i < observed.shape[0] * width:
        y = i // width
        x = i - y * width
        c = exposure[row][0] * rendered[y, x] + wp.vec3(exposure[row][1])
        r = wp.vec3(wp.clamp(c[0], 0.0, 1.0), wp.clamp(c[1], 0.0, 1.0), wp.clamp(c[2], 0.0, 1.0)) - observed[y, x]
        e = wp.dot(r, r)
    total = block_sum(e)
    if lane == 0:
        wp.atomic_add(sums_out, row, wp.float64(total))


@wp.kernel
def count_overflow(
    # in: the intersections a render needed (Renderer.intersection_count_array), its capacity
    needed: wp.array(dtype=wp.int32),
    capacity: int,
    # out: renders that needed more than their capacity (a replayed graph's dropped intersections)
    overflows_out: wp.array(dtype=wp.int32),
):
    if needed[0] > capacity:
        overflows_out[0] = overflows_out[0] + 1
