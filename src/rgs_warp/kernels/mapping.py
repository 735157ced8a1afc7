"""Kernels of the mapper (supplement §4.5): the window loss's image gradients (L1 with robust per-pixel
weights, exposure (g, b) of the keyframe, depth L1), the regularizer of the Gaussians (elongation,
saturated opacity, drift from the EMA position), the per-Gaussian statistics m_i, v_i and the EMA of
Eq. 15, Adam on the keyframe poses, and the depth seeds of the first keyframe.

Reductions follow ``kernels/tracking.py``: 256 pixels summed in a block tile, one float64 atomic per
block and column, so nothing is read back to the host inside the mapping loop.
"""

import warp as wp

from rgs_warp.kernels.tracking import REDUCE_BLOCK, rigid_inverse_f32, se3_exp

wp.set_module_options({"enable_backward": False})

# Loss columns (one row per iteration).
L_LOSS = 0  # weighted L1 + depth term, divided by the pixel count (SSIM is added on the host side)
L_ABS = 1  # sum over pixels of the unweighted mean |I - g I_hat - b| over channels
L_PIXELS = 2  # pixels counted
L_DEPTH = 3  # sum |D_hat - D| over pixels with observed depth
L_DEPTH_PIXELS = 4
L_COLUMNS = 5

vec6 = wp.types.vector(length=6, dtype=wp.float32)


@wp.kernel
def mapping_loss(
    # in: observed keyframe (depth ignored unless use_depth) and the render
    observed: wp.array2d(dtype=wp.vec3),
    observed_depth: wp.array2d(dtype=wp.float32),
    rendered: wp.array2d(dtype=wp.vec3),
    rendered_depth: wp.array2d(dtype=wp.float32),
    # in: exposure of the keyframe (Eq. 3), robust scale, depth weight
    gain: float,
    bias: float,
    robust_scale: float,
    use_depth: int,
    depth_weight: float,
    l1_weight: float,
    row: int,
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
    i = block * REDUCE_BLOCK + lane
    height = observed.shape[0]
    width = observed.shape[1]
    s = wp.vec4(0.0)
    d_ab = wp.vec2(0.0)
    if i < height * width:
        y = i // width
        x = i - y * width
        inv_n = 1.0 / float(height * width)
        xv = gain * rendered[y, x] + wp.vec3(bias)
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
    total = wp.tile_extract(wp.tile_sum(wp.tile(s, preserve_type=True)), 0)
    total_d = wp.tile_extract(wp.tile_sum(wp.tile(d_ab, preserve_type=True)), 0)
    if lane == 0:
        wp.atomic_add(loss_out, row, L_LOSS, wp.float64(total[0]))
        wp.atomic_add(loss_out, row, L_ABS, wp.float64(total[1]))
        wp.atomic_add(loss_out, row, L_PIXELS, wp.float64(total[2]))
        wp.atomic_add(loss_out, row, L_DEPTH, wp.float64(total_d[0]))
        wp.atomic_add(loss_out, row, L_DEPTH_PIXELS, wp.float64(total_d[1]))


@wp.kernel
def scale_image_grad(
    # in: dL/dx of x = g I_hat + b
    grad_x: wp.array2d(dtype=wp.vec3),
    gain: float,
    # out: dL/dI_hat
    d_color_out: wp.array2d(dtype=wp.vec3),
):
    y, x = wp.tid()
    d_color_out[y, x] = gain * grad_x[y, x]


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
def init_statistics(
    # in:
    means: wp.array(dtype=wp.vec3),
    start: int,
    # out: fresh rows start + tid
    obs_count: wp.array(dtype=wp.int32),
    vis_count: wp.array(dtype=wp.float32),
    ema_means: wp.array(dtype=wp.vec3),
):
    i = start + wp.tid()
    obs_count[i] = 0
    vis_count[i] = 0.0
    ema_means[i] = means[i]


@wp.kernel
def adam_keyframe_pose_step(
    # in: twist gradient of this iteration's render, slot in the window, schedule
    grad: wp.array(dtype=wp.float32),
    k: int,
    lr: float,
    beta1: float,
    beta2: float,
    eps: float,
    # in/out: per-window-slot Adam moments (6 floats each), step counts and camera-from-world poses
    m: wp.array2d(dtype=wp.float32),
    v: wp.array2d(dtype=wp.float32),
    steps: wp.array(dtype=wp.int32),
    T_CW: wp.array(dtype=wp.mat44d),
    # out: the renderer's camera-to-world pose of slot k
    T_WC_out: wp.array(dtype=wp.mat44),
):
    # Same left update as the tracker (T_CW <- Exp(xi) T_CW), about the camera centre: the mapping
    # steps are small corrections of a tracked pose, not a search.
    n = steps[k] + 1
    steps[k] = n
    c1 = 1.0 - wp.pow(beta1, float(n))
    c2 = 1.0 - wp.pow(beta2, float(n))
    step = vec6()
    for j in range(6):
        g = grad[j]
        mj = beta1 * m[k, j] + (1.0 - beta1) * g
        vj = beta2 * v[k, j] + (1.0 - beta2) * g * g
        m[k, j] = mj
        v[k, j] = vj
        step[j] = -lr * (mj / c1) / (wp.sqrt(vj / c2) + eps)
    rho = wp.vec3d(wp.float64(step[0]), wp.float64(step[1]), wp.float64(step[2]))
    phi = wp.vec3d(wp.float64(step[3]), wp.float64(step[4]), wp.float64(step[5]))
    T = se3_exp(rho, phi) @ T_CW[k]
    T_CW[k] = T
    T_WC_out[k] = rigid_inverse_f32(T)


@wp.kernel
def depth_points(
    # in: keyframe depth (metres, 0 = invalid), pinhole intrinsics, camera-to-world pose
    depth: wp.array2d(dtype=wp.float32),
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    T_WC: wp.mat44d,
    stride: int,
    max_rel_jump: float,
    residual_px: float,
    parallax_deg: float,
    # in: the map's accumulated opacity at this keyframe (empty map: zeros) and the coverage bound
    alpha: wp.array2d(dtype=wp.float32),
    max_alpha: float,
    # out: one point per grid cell (the Triangulator's output layout, single view)
    X_out: wp.array(dtype=wp.vec3d),
    residual_out: wp.array(dtype=wp.float64),
    parallax_out: wp.array(dtype=wp.float64),
    support_out: wp.array(dtype=wp.int32),
    valid_out: wp.array(dtype=wp.int32),
):
    # RGB-D seeds: the pixel at the centre of each stride x stride cell, back-projected with its
    # measured depth, where the map does not cover the view yet (alpha < max_alpha) and the depth is
    # not on a discontinuity (neighbours at +-stride within max_rel_jump after a linear fit, i.e.
    # the second difference): a point straddling an edge would float between two surfaces.
    gy, gx = wp.tid()
    i = gy * (depth.shape[1] // stride) + gx
    u = gx * stride + stride // 2
    v = gy * stride + stride // 2
    z = depth[v, u]
    ok = z > 0.0 and alpha[v, u] < max_alpha
    if ok and u >= stride and u + stride < depth.shape[1] and v >= stride and v + stride < depth.shape[0]:
        zl = depth[v, u - stride]
        zr = depth[v, u + stride]
        zu = depth[v - stride, u]
        zd = depth[v + stride, u]
        ok = zl > 0.0 and zr > 0.0 and zu > 0.0 and zd > 0.0
        if ok:
            ok = wp.abs(zl + zr - 2.0 * z) < max_rel_jump * z and wp.abs(zu + zd - 2.0 * z) < max_rel_jump * z
    zd64 = wp.float64(z)
    pc = wp.vec4d(
        (wp.float64(u) - wp.float64(cx)) / wp.float64(fx) * zd64,
        (wp.float64(v) - wp.float64(cy)) / wp.float64(fy) * zd64,
        zd64,
        wp.float64(1.0),
    )
    pw = T_WC @ pc
    X_out[i] = wp.vec3d(pw[0], pw[1], pw[2])
    residual_out[i] = wp.float64(residual_px)
    parallax_out[i] = wp.float64(parallax_deg)
    support_out[i] = 1
    valid_out[i] = wp.where(ok, 1, 0)


@wp.func
def reference_pixel(coordinate: wp.float64, size: int):
    """The pixel index of an image coordinate (pixel centres at integers), clamped into the image."""
    return wp.clamp(int(wp.round(float(coordinate))), 0, size - 1)


@wp.func
def camera_depth(X: wp.vec3d, T_CW: wp.mat44d):
    """z of the world point X in the camera T_CW (metres, float32)."""
    return float((T_CW @ wp.vec4d(X[0], X[1], X[2], wp.float64(1.0)))[2])


@wp.kernel
def mask_covered_points(
    # in: reference-view pixels of the triangulated points and the map's render at the reference
    ref_uv: wp.array(dtype=wp.vec2d),
    alpha: wp.array2d(dtype=wp.float32),
    rendered_depth: wp.array2d(dtype=wp.float32),
    X: wp.array(dtype=wp.vec3d),
    T_CW: wp.mat44d,
    max_alpha: float,
    depth_rel_tol: float,
    # in/out: validity of each point
    valid: wp.array(dtype=wp.int32),
):
    # A new keyframe's seeds go where the map is missing: pixels it does not cover yet, or where the
    # map's surface (alpha-normalised depth) is off the triangulated point by more than depth_rel_tol.
    # Elsewhere the map already explains the keyframe and a seed would only double the density.
    i = wp.tid()
    if valid[i] == 0:
        return
    u = reference_pixel(ref_uv[i][0], alpha.shape[1])
    v = reference_pixel(ref_uv[i][1], alpha.shape[0])
    a = alpha[v, u]
    if a < max_alpha:
        return
    z = camera_depth(X[i], T_CW)
    d_map = rendered_depth[v, u] / a
    if wp.abs(d_map - z) > depth_rel_tol * z:
        return
    valid[i] = 0


@wp.kernel
def map_depth_ratio(
    # in: reference-view pixels of the triangulated points and the map's render at the reference
    ref_uv: wp.array(dtype=wp.vec2d),
    alpha: wp.array2d(dtype=wp.float32),
    rendered_depth: wp.array2d(dtype=wp.float32),
    X: wp.array(dtype=wp.vec3d),
    valid: wp.array(dtype=wp.int32),
    T_CW: wp.mat44d,
    min_alpha: float,
    # out: the map's depth over the point's (alpha-normalised, reference view); 0 where the map does
    # not cover the point's pixel or the point is invalid or behind the camera
    ratio: wp.array(dtype=wp.float32),
):
    # Monocular: the scale of a keyframe's triangulated points against the map it extends.
    i = wp.tid()
    ratio[i] = 0.0
    if valid[i] == 0:
        return
    u = reference_pixel(ref_uv[i][0], alpha.shape[1])
    v = reference_pixel(ref_uv[i][1], alpha.shape[0])
    a = alpha[v, u]
    z = camera_depth(X[i], T_CW)
    if a < min_alpha or z <= 0.0:
        return
    ratio[i] = rendered_depth[v, u] / a / z


@wp.kernel
def reject_depth_inconsistent_points(
    # in: reference-view pixels of the triangulated points and the reference keyframe's measured depth
    ref_uv: wp.array(dtype=wp.vec2d),
    measured_depth: wp.array2d(dtype=wp.float32),
    X: wp.array(dtype=wp.vec3d),
    T_CW: wp.mat44d,
    depth_rel_tol: float,
    # in/out: validity of each point
    valid: wp.array(dtype=wp.int32),
):
    # RGB-D: a triangulated point whose depth in the reference view is off the sensor's by more than
    # depth_rel_tol is a wrong match (or a low-parallax triangulation) and would seed a floater; the
    # measured-depth fill covers its pixel instead.  Pixels without a measurement keep their points.
    i = wp.tid()
    if valid[i] == 0:
        return
    u = reference_pixel(ref_uv[i][0], measured_depth.shape[1])
    v = reference_pixel(ref_uv[i][1], measured_depth.shape[0])
    d = measured_depth[v, u]
    if d <= 0.0:
        return
    if wp.abs(camera_depth(X[i], T_CW) - d) > depth_rel_tol * d:
        valid[i] = 0


@wp.kernel
def union_alpha(
    # in: accumulated opacities of two maps rendered at the same pose
    alpha_a: wp.array2d(dtype=wp.float32),
    alpha_b: wp.array2d(dtype=wp.float32),
    # out: the opacity of both together, 1 - (1 - a)(1 - b) (order-independent)
    alpha_out: wp.array2d(dtype=wp.float32),
):
    y, x = wp.tid()
    alpha_out[y, x] = 1.0 - (1.0 - alpha_a[y, x]) * (1.0 - alpha_b[y, x])
