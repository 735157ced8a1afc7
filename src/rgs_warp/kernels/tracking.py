"""Kernels of the tracker (supplement §4.2): frame preparation, per-pixel weights (Eq. 6-8), the
brightness gain (Eq. 3), the tracking loss (Eq. 5 + depth L1) with its image gradients
for the renderer's backward, and Adam on the pose twist with the left-multiplicative SE(3) update.

Per-iteration quantities go to one row of a float64 history array (columns ``H_*``) so that an
iteration never reads anything back to the host: the tracker reads the whole history once per frame.
Reductions sum 256 pixels in a block tile, then add one float64 atomic per block and column.
"""

import warp as wp

from rgs_warp.kernels.math import (
    REDUCE_BLOCK,
    TERM_COLOUR,
    TERM_GEOMETRIC,
    block_sum,
    depth_sigma,
    rigid_inverse_f32,
    se3_exp,
    vec6,
)

wp.set_module_options({"enable_backward": False})


# History columns (one row per iteration).
H_SX = 0  # the gain's sums over pixels x channels, weighted (brightness_sums): sum w * rendered
H_SY = 1  # sum w * observed
H_VALID = 2  # pixels with accumulated opacity >= tau_alpha
H_GAIN = 3  # g of Eq. 3 used in this iteration
H_BIAS = 4  # b of Eq. 3 (0: the gain model)
H_LOSS = 5  # Eq. 5 + depth term, divided by the pixel count
H_PHOTO = 6  # sum_x w(x) |I - g I_hat - b|_1
H_WEIGHT = 7  # sum_x w(x)
H_DEPTH = 8  # sum of the rendered depth sum_i w_i z_i (pivot of the twist, see adam_pose_step)
H_ALPHA = 9  # sum of the accumulated opacity
H_CONSISTENCY = 10  # mean over the 6 twist coordinates of Adam's |m_hat| / sqrt(v_hat), in [0, 1]
H_COLUMNS = 11

# Below this accumulated opacity the alpha-normalised depth D_hat / alpha is not formed (its weight
# w_alpha = alpha / tau_alpha is negligible there anyway).
ALPHA_DEPTH_MIN = 1.0e-3

vec5 = wp.types.vector(length=5, dtype=wp.float32)


@wp.kernel
def downsample_rgbd(
    # in: full-resolution frame (depth (1, 1) when the frame has none)
    rgb: wp.array2d(dtype=wp.vec3),
    depth: wp.array2d(dtype=wp.float32),
    factor: int,
    has_depth: int,
    max_rel_spread: float,
    # out: frame at 1 / factor resolution
    rgb_out: wp.array2d(dtype=wp.vec3),
    depth_out: wp.array2d(dtype=wp.float32),
):
    # Block means, as the datasets' downscale_rgb / downscale_depth (docs/decisions.md): the depth of
    # a block straddling a depth edge (spread above max_rel_spread of its mean) becomes invalid.
    y, x = wp.tid()
    c = wp.vec3(0.0)
    total = float(0.0)
    count = int(0)
    lo = float(1.0e30)
    hi = float(-1.0e30)
    for dy in range(factor):
        for dx in range(factor):
            c += rgb[y * factor + dy, x * factor + dx]
            if has_depth != 0:
                d = depth[y * factor + dy, x * factor + dx]
                if d > 0.0:
                    total += d
                    count += 1
                    lo = wp.min(lo, d)
                    hi = wp.max(hi, d)
    rgb_out[y, x] = c / float(factor * factor)
    mean = float(0.0)
    if count > 0:
        mean = total / float(count)
        if hi - lo > max_rel_spread * mean:
            mean = 0.0
    depth_out[y, x] = mean


@wp.kernel
def gradient_weight(
    # in: observed image
    rgb: wp.array2d(dtype=wp.vec3),
    tau_grad: float,
    # out: w_grad of Eq. 8
    w_grad_out: wp.array2d(dtype=wp.float32),
):
    # |grad I| of the luminance (channel mean) by central differences, one-sided at the border.
    # tau_grad <= 0 switches the weight off (w = 1), for ablations.
    y, x = wp.tid()
    h = rgb.shape[0]
    w = rgb.shape[1]
    x0 = wp.max(x - 1, 0)
    x1 = wp.min(x + 1, w - 1)
    y0 = wp.max(y - 1, 0)
    y1 = wp.min(y + 1, h - 1)
    one3 = wp.vec3(1.0 / 3.0)
    gx = float(0.0)
    gy = float(0.0)
    if x1 > x0:
        gx = wp.dot(rgb[y, x1] - rgb[y, x0], one3) / float(x1 - x0)
    if y1 > y0:
        gy = wp.dot(rgb[y1, x] - rgb[y0, x], one3) / float(y1 - y0)
    weight = float(1.0)
    if tau_grad > 0.0:
        weight = wp.clamp(wp.sqrt(gx * gx + gy * gy) / tau_grad, 0.0, 1.0)
    w_grad_out[y, x] = weight


@wp.func
def alpha_weight(alpha: float, tau_alpha: float):
    """w_alpha of Eq. 7."""
    return wp.clamp(alpha / tau_alpha, 0.0, 1.0)


@wp.kernel
def brightness_sums(
    # in: observed and rendered images
    observed: wp.array2d(dtype=wp.vec3),
    rendered: wp.array2d(dtype=wp.vec3),
    rendered_depth: wp.array2d(dtype=wp.float32),
    alpha: wp.array2d(dtype=wp.float32),
    tau_alpha: float,
    min_alpha: float,
    max_residual: float,
    row: int,
    # the row is row + counter[0] (see advance_step)
    counter: wp.array(dtype=wp.int32),
    # out: columns H_SX, H_SY, H_VALID, H_DEPTH, H_ALPHA of history row `row` (zeroed beforehand; the
    # row before it, when row > 0, holds the previous step's gain)
    history_out: wp.array2d(dtype=wp.float64),
):
    # The gain's sums over the pixels the map covers fully (alpha >= min_alpha) and channels:
    # pixels it does not cover say nothing about the exposure, and partly covered ones render darker
    # by their opacity (over the black background), which would read as a gain > 1; dividing the
    # opacity out instead is biased the other way, since the mapper brightens thin regions to match
    # the keyframes, and either bias is fed back by the mapper frame after frame (GPU office runs:
    # g 1 -> 1.2 -> 20 monocular, 1 -> 0.8 with the division; experiments/results/slam.md).  min_alpha
    # <= 0 falls back to the w_alpha weights of Eq. 7.  w_grad is left out on purpose, flat areas
    # constrain the gain as well as edges do.  From the second step of a frame on, pixels whose mean
    # |I - g I_hat| per channel under the previous step's gain exceeds max_residual (> 0) are left out
    # too: where the map is wrong (content not yet mapped, a floater) the render says nothing about the
    # exposure either.
    block, lane = wp.tid()
    row = row + counter[0]
    i = block * REDUCE_BLOCK + lane
    width = observed.shape[1]
    s = vec5()
    if i < observed.shape[0] * width:
        y = i // width
        x = i - y * width
        a = alpha[y, x]
        w = alpha_weight(a, tau_alpha)
        if min_alpha > 0.0:
            w = wp.where(a >= min_alpha, 1.0, 0.0)
        xr = rendered[y, x]
        yo = observed[y, x]
        if max_residual > 0.0 and row > 0:
            g = float(history_out[row - 1, H_GAIN])
            r = (wp.abs(yo[0] - g * xr[0]) + wp.abs(yo[1] - g * xr[1]) + wp.abs(yo[2] - g * xr[2])) / 3.0
            w = wp.where(r > max_residual, 0.0, w)
        s = vec5(
            w * (xr[0] + xr[1] + xr[2]),
            w * (yo[0] + yo[1] + yo[2]),
            wp.where(a >= tau_alpha, 1.0, 0.0),
            rendered_depth[y, x],
            a,
        )
    total = block_sum(s)
    if lane == 0:
        for c in range(3):
            wp.atomic_add(history_out, row, H_SX + c, wp.float64(total[c]))
        wp.atomic_add(history_out, row, H_DEPTH, wp.float64(total[3]))
        wp.atomic_add(history_out, row, H_ALPHA, wp.float64(total[4]))


@wp.kernel
def solve_brightness(
    # in: history row
    row: int,
    counter: wp.array(dtype=wp.int32),  # the row is row + counter[0] (see advance_step)
    # out: columns H_GAIN, H_BIAS of history row `row`, from its H_SX, H_SY sums
    history_out: wp.array2d(dtype=wp.float64),
):
    # g = Sy / Sx, b = 0: the ratio of the weighted means, which blur and small misalignments leave
    # (nearly) unbiased; auto-exposure is a gain in linear light and, through the sRGB power law, nearly a
    # gain on the stored values too.  Eq. 4's least squares of y on x is biased towards g < 1 when the
    # render x has errors of its own (regression dilution), and the mapper feeds that back (g 1 -> 0.83
    # over 150 frames without any exposure change; docs/decisions.md, "Brightness").
    row = row + counter[0]
    g = wp.float64(1.0)
    if history_out[row, H_SX] > wp.float64(0.0):
        g = history_out[row, H_SY] / history_out[row, H_SX]
    history_out[row, H_GAIN] = g
    history_out[row, H_BIAS] = wp.float64(0.0)


@wp.func
def depth_slope_weight(depth: wp.array2d(dtype=wp.float32), x: int, y: int, d: float, tau: float):
    """1 / (1 + |grad D| / (tau D)): down-weights the depth residual where the observed depth changes
    fast across pixels (slanted surfaces, near edges).  There a splat map's depth is biased towards
    the camera by up to about one pixel's depth step (front-to-back compositing lets the nearer of
    overlapping splats win; measured in experiments/results/tracking.md), while the photometric term
    is not.  |grad D| from central differences of the valid neighbours (metres per pixel); tau <= 0:
    weight 1."""
    if tau <= 0.0:
        return 1.0
    h = depth.shape[0]
    w = depth.shape[1]
    gx = float(0.0)
    gy = float(0.0)
    if x > 0 and x < w - 1:
        l = depth[y, x - 1]
        r = depth[y, x + 1]
        if l > 0.0 and r > 0.0:
            gx = 0.5 * (r - l)
    if y > 0 and y < h - 1:
        u = depth[y - 1, x]
        v = depth[y + 1, x]
        if u > 0.0 and v > 0.0:
            gy = 0.5 * (v - u)
    return 1.0 / (1.0 + wp.sqrt(gx * gx + gy * gy) / (tau * d))


@wp.kernel
def tracking_loss(
    # in: observed frame (depth ignored unless use_depth), w_grad of Eq. 8
    observed: wp.array2d(dtype=wp.vec3),
    observed_depth: wp.array2d(dtype=wp.float32),
    w_grad: wp.array2d(dtype=wp.float32),
    # in: rendered images
    rendered: wp.array2d(dtype=wp.vec3),
    rendered_depth: wp.array2d(dtype=wp.float32),
    alpha: wp.array2d(dtype=wp.float32),
    # in: parameters; (g, b) read from history row `row`
    tau_alpha: float,
    use_depth: int,
    depth_weight: float,
    depth_slope_tau: float,
    per_opacity: int,
    noise_weighted: int,
    scales: wp.array(dtype=wp.float32),  # noise_weighted: the direct alignment's noise scales (math.TERM_*)
    row: int,
    counter: wp.array(dtype=wp.int32),  # the row is row + counter[0] (see advance_step)
    # out: loss gradients w.r.t. the rendered images; H_LOSS, H_PHOTO, H_WEIGHT of row `row`
    d_color_out: wp.array2d(dtype=wp.vec3),
    d_depth_out: wp.array2d(dtype=wp.float32),
    d_alpha_out: wp.array2d(dtype=wp.float32),
    history_out: wp.array2d(dtype=wp.float64),
):
    # L = 1/N sum_x [ w(x) |I - g I_hat - b|_1 + lambda_d w_alpha(x) |D_hat / alpha - D| ] (Eq. 5-8; the
    # depth term on pixels with observed depth).  The weights and (g, b) are held constant in the
    # gradient: they are re-evaluated every iteration, and differentiating w_alpha would reward
    # moving the map out of view.  The rendered depth is sum_i w_i z_i (not normalised), so it is
    # divided by alpha here: otherwise partly covered pixels would pull towards the camera.
    # per_opacity != 0: the colour term compares the frame with the rendered colour / alpha too (the
    # map's colour where it covers the pixel only in part; the render itself is darkened by the
    # background there, and without depth that darkening at the edge of the map pulls the pose:
    # experiments/results/mono.md), differentiated through alpha as well.
    # noise_weighted != 0 (tracking.geometric, RGB-D): the gradients are those of the loss with each term in
    # units of its noise instead, the colour L1 divided by sigma_I and the depth L1 by sigma(z) s in place of
    # lambda_d (the direct alignment's estimates, ``scales``), so that the steps keep the balance its
    # Gauss-Newton had (with the hand-set lambda_d they pulled its pose back to their own optimum); the
    # loss written to the history stays the one above, which the keyframe selector compares across frames.
    block, lane = wp.tid()
    row = row + counter[0]
    i = block * REDUCE_BLOCK + lane
    height = observed.shape[0]
    width = observed.shape[1]
    s = wp.vec3(0.0)
    if i < height * width:
        y = i // width
        x = i - y * width
        inv_n = 1.0 / float(height * width)
        g = float(history_out[row, H_GAIN])
        b = float(history_out[row, H_BIAS])
        a = alpha[y, x]
        w_a = alpha_weight(a, tau_alpha)
        w = w_a * w_grad[y, x]
        c = rendered[y, x]
        inv_a = float(1.0)
        if per_opacity != 0 and a > ALPHA_DEPTH_MIN:
            inv_a = 1.0 / a
        r = observed[y, x] - (g * inv_a * c + wp.vec3(b))
        photo = w * (wp.abs(r[0]) + wp.abs(r[1]) + wp.abs(r[2]))
        sign_r = wp.vec3(wp.sign(r[0]), wp.sign(r[1]), wp.sign(r[2]))
        k_colour = float(1.0)
        if noise_weighted != 0:
            k_colour = 1.0 / scales[TERM_COLOUR]
        d_color_out[y, x] = (-inv_n * k_colour * w * g * inv_a) * sign_r
        loss = photo
        d_depth = float(0.0)
        d_alpha = float(0.0)
        if inv_a != 1.0:
            d_alpha = inv_n * k_colour * w * g * inv_a * inv_a * wp.dot(sign_r, c)
        if use_depth != 0:
            d_obs = observed_depth[y, x]
            if d_obs > 0.0 and a > ALPHA_DEPTH_MIN:
                d_hat = rendered_depth[y, x]
                e = d_hat / a - d_obs
                w_slope = depth_slope_weight(observed_depth, x, y, d_obs, depth_slope_tau)
                w_d = depth_weight * w_a * w_slope
                loss += w_d * wp.abs(e)
                k_depth = w_d
                if noise_weighted != 0:
                    k_depth = w_a * w_slope / (depth_sigma(d_obs) * scales[TERM_GEOMETRIC])
                k = inv_n * k_depth * wp.sign(e) / a
                d_depth = k
                d_alpha -= k * d_hat / a
        d_depth_out[y, x] = d_depth
        d_alpha_out[y, x] = d_alpha
        s = wp.vec3(loss * inv_n, photo, w)
    total = block_sum(s)
    if lane == 0:
        wp.atomic_add(history_out, row, H_LOSS, wp.float64(total[0]))
        wp.atomic_add(history_out, row, H_PHOTO, wp.float64(total[1]))
        wp.atomic_add(history_out, row, H_WEIGHT, wp.float64(total[2]))


@wp.kernel
def adam_pose_step(
    # in: twist gradient of the loss (renderer's pose backward), schedule and Adam constants
    grad: wp.array(dtype=wp.float32),
    row: int,
    iters: int,
    lr: float,
    beta1: float,
    beta2: float,
    eps: float,
    counter: wp.array(dtype=wp.int32),  # the step is row + counter[0] (see advance_step)
    # in/out: reads H_DEPTH, H_ALPHA, writes H_CONSISTENCY of history row `row`
    history: wp.array2d(dtype=wp.float64),
    # in/out: Adam moments (6 each) of the twist about the pivot, camera-from-world pose
    m: wp.array(dtype=wp.float32),
    v: wp.array(dtype=wp.float32),
    T_CW: wp.array(dtype=wp.mat44d),
    # out: the pose for the renderer (camera-to-world, float32); the updated T_CW at index `row`
    T_WC_out: wp.array(dtype=wp.mat44),
    pose_history_out: wp.array(dtype=wp.mat44d),
):
    row = row + counter[0]
    # Cosine schedule centred on lr: lr_k = lr (1 + cos(pi k / K)), from 2 lr at k = 0 down to ~0 at
    # k = K - 1; its mean over the K steps is lr (experiments/results/tracking.md).
    lr_k = lr * (1.0 + wp.cos(wp.pi * float(row) / float(iters)))
    n_steps = float(row + 1)
    c1 = 1.0 - wp.pow(beta1, n_steps)
    c2 = 1.0 - wp.pow(beta2, n_steps)
    # The twist is taken about a pivot p on the optical axis at the mean rendered depth rather than
    # about the camera centre: xi' = (rho', phi') with T_CW <- P^-1 Exp(xi') P T_CW, P: X -> X - p.
    # Both describe the same left update (rho = rho' + p x phi' to first order), but about the camera
    # centre a small rotation and a sideways translation shift the image almost alike, a long valley
    # in which Adam's per-coordinate steps zig-zag; about the scene's centre they separate.
    # Gradient: g_rho' = g_rho, g_phi' = g_phi + g_rho x p.
    p = wp.vec3(0.0)
    if history[row, H_ALPHA] > wp.float64(0.0):
        p = wp.vec3(0.0, 0.0, float(history[row, H_DEPTH] / history[row, H_ALPHA]))
    g_rho = wp.vec3(grad[0], grad[1], grad[2])
    g_phi = wp.vec3(grad[3], grad[4], grad[5]) + wp.cross(g_rho, p)
    g = vec6(g_rho[0], g_rho[1], g_rho[2], g_phi[0], g_phi[1], g_phi[2])
    step = vec6()
    consistency = float(0.0)
    for k in range(6):
        gk = g[k]
        mk = beta1 * m[k] + (1.0 - beta1) * gk
        vk = beta2 * v[k] + (1.0 - beta2) * gk * gk
        m[k] = mk
        v[k] = vk
        # ~1 while the gradient keeps its sign (still travelling), ~0 where it flips (at the minimum)
        ratio = (mk / c1) / (wp.sqrt(vk / c2) + eps)
        consistency += wp.abs(ratio) / 6.0
        step[k] = -lr_k * ratio
    history[row, H_CONSISTENCY] = wp.float64(consistency)
    rho = wp.vec3d(wp.float64(step[0]), wp.float64(step[1]), wp.float64(step[2]))
    phi = wp.vec3d(wp.float64(step[3]), wp.float64(step[4]), wp.float64(step[5]))
    E = se3_exp(rho, phi)
    # P^-1 E P: same rotation, translation t + p - R p
    pd = wp.vec3d(wp.float64(p[0]), wp.float64(p[1]), wp.float64(p[2]))
    R = wp.mat33d(E[0, 0], E[0, 1], E[0, 2], E[1, 0], E[1, 1], E[1, 2], E[2, 0], E[2, 1], E[2, 2])
    t = wp.vec3d(E[0, 3], E[1, 3], E[2, 3]) + pd - R @ pd
    E[0, 3] = t[0]
    E[1, 3] = t[1]
    E[2, 3] = t[2]
    T = E @ T_CW[0]
    T_CW[0] = T
    T_WC_out[0] = rigid_inverse_f32(T)
    pose_history_out[row] = T


@wp.kernel
def advance_step(counter: wp.array(dtype=wp.int32)):
    """The step counter of a frame's steps on the device: the kernels of a step read their history row
    (and the learning rate's step) as ``row + counter[0]``.  Eagerly the host passes each step's row and a
    counter at 0; a captured graph of one step passes row 0 and this counter, which the step's last
    launch advances, so the one graph replays every step (a capture of one step, not of all of them)."""
    counter[0] = counter[0] + 1
