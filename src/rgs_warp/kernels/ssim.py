"""Differentiable SSIM (Wang et al. 2004): 11x11 Gaussian window, sigma 1.5, K1 = 0.01, K2 = 0.03,
over the valid region (windows fully inside the image), per channel. Separable: a horizontal then a
vertical pass for the five local moments; the backward runs the adjoint passes in reverse order.

Forward moments: mu_x, mu_y, E[x^2], E[y^2], E[xy]; with var_x = E[x^2] - mu_x^2 and
cov = E[xy] - mu_x mu_y, S = N1 N2 / (D1 D2) where N1 = 2 mu_x mu_y + C1, N2 = 2 cov + C2,
D1 = mu_x^2 + mu_y^2 + C1, D2 = var_x + var_y + C2. The gradient w.r.t. x at pixel p is
sum_q w(q - p) [dS/dmu_x(q) + 2 x(p) dS/dE[x^2](q) + y(p) dS/dE[xy](q)], i.e. the adjoint blur of
three per-pixel partial maps.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

SSIM_RADIUS = 5  # 11x11 window
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


@wp.kernel
def ssim_moments_h(
    # in:
    x: wp.array2d(dtype=wp.vec3),
    y: wp.array2d(dtype=wp.vec3),
    window: wp.array(dtype=wp.float32),
    # out: (H, W - 10)
    mu_x_out: wp.array2d(dtype=wp.vec3),
    mu_y_out: wp.array2d(dtype=wp.vec3),
    xx_out: wp.array2d(dtype=wp.vec3),
    yy_out: wp.array2d(dtype=wp.vec3),
    xy_out: wp.array2d(dtype=wp.vec3),
):
    i, j = wp.tid()
    mx = wp.vec3(0.0)
    my = wp.vec3(0.0)
    sxx = wp.vec3(0.0)
    syy = wp.vec3(0.0)
    sxy = wp.vec3(0.0)
    for k in range(2 * SSIM_RADIUS + 1):
        w = window[k]
        a = x[i, j + k]
        b = y[i, j + k]
        mx += w * a
        my += w * b
        sxx += w * wp.cw_mul(a, a)
        syy += w * wp.cw_mul(b, b)
        sxy += w * wp.cw_mul(a, b)
    mu_x_out[i, j] = mx
    mu_y_out[i, j] = my
    xx_out[i, j] = sxx
    yy_out[i, j] = syy
    xy_out[i, j] = sxy


@wp.func
def _ssim_channel(mx: float, my: float, exx: float, eyy: float, exy: float) -> wp.vec4:
    """(S, dS/dmu_x, dS/dE[x^2], dS/dE[xy]) for one channel; no division by N2, which can vanish."""
    n1 = 2.0 * mx * my + SSIM_C1
    n2 = 2.0 * (exy - mx * my) + SSIM_C2
    d1 = mx * mx + my * my + SSIM_C1
    d2 = (exx - mx * mx) + (eyy - my * my) + SSIM_C2
    inv = 1.0 / (d1 * d2)
    s = n1 * n2 * inv
    ds_dmx = 2.0 * my * n2 * inv - 2.0 * mx * s / d1 - 2.0 * my * n1 * inv + 2.0 * mx * s / d2
    return wp.vec4(s, ds_dmx, -s / d2, 2.0 * n1 * inv)


@wp.kernel
def ssim_map_v(
    # in: horizontal moments (H, W - 10)
    mu_x_h: wp.array2d(dtype=wp.vec3),
    mu_y_h: wp.array2d(dtype=wp.vec3),
    xx_h: wp.array2d(dtype=wp.vec3),
    yy_h: wp.array2d(dtype=wp.vec3),
    xy_h: wp.array2d(dtype=wp.vec3),
    window: wp.array(dtype=wp.float32),
    dloss_dssim: float,  # d loss / d S(q, c), the same for every valid pixel and channel
    # out: (H - 10, W - 10)
    ssim_out: wp.array2d(dtype=wp.vec3),
    d_mu_x_out: wp.array2d(dtype=wp.vec3),
    d_xx_out: wp.array2d(dtype=wp.vec3),
    d_xy_out: wp.array2d(dtype=wp.vec3),
):
    i, j = wp.tid()
    mx = wp.vec3(0.0)
    my = wp.vec3(0.0)
    exx = wp.vec3(0.0)
    eyy = wp.vec3(0.0)
    exy = wp.vec3(0.0)
    for k in range(2 * SSIM_RADIUS + 1):
        w = window[k]
        mx += w * mu_x_h[i + k, j]
        my += w * mu_y_h[i + k, j]
        exx += w * xx_h[i + k, j]
        eyy += w * yy_h[i + k, j]
        exy += w * xy_h[i + k, j]
    s = wp.vec3(0.0)
    a = wp.vec3(0.0)
    b = wp.vec3(0.0)
    c = wp.vec3(0.0)
    for ch in range(3):
        r = _ssim_channel(mx[ch], my[ch], exx[ch], eyy[ch], exy[ch])
        s[ch] = r[0]
        a[ch] = dloss_dssim * r[1]
        b[ch] = dloss_dssim * r[2]
        c[ch] = dloss_dssim * r[3]
    ssim_out[i, j] = s
    d_mu_x_out[i, j] = a
    d_xx_out[i, j] = b
    d_xy_out[i, j] = c


@wp.kernel
def ssim_adjoint_v(
    # in: partial maps (H - 10, W - 10)
    d_mu_x: wp.array2d(dtype=wp.vec3),
    d_xx: wp.array2d(dtype=wp.vec3),
    d_xy: wp.array2d(dtype=wp.vec3),
    window: wp.array(dtype=wp.float32),
    # out: (H, W - 10)
    d_mu_x_out: wp.array2d(dtype=wp.vec3),
    d_xx_out: wp.array2d(dtype=wp.vec3),
    d_xy_out: wp.array2d(dtype=wp.vec3),
):
    # Adjoint of out[i] = sum_k w[k] in[i + k]: in_grad[r] = sum_k w[k] out_grad[r - k].
    r, j = wp.tid()
    a = wp.vec3(0.0)
    b = wp.vec3(0.0)
    c = wp.vec3(0.0)
    for k in range(2 * SSIM_RADIUS + 1):
        i = r - k
        if i >= 0 and i < d_mu_x.shape[0]:
            w = window[k]
            a += w * d_mu_x[i, j]
            b += w * d_xx[i, j]
            c += w * d_xy[i, j]
    d_mu_x_out[r, j] = a
    d_xx_out[r, j] = b
    d_xy_out[r, j] = c


@wp.kernel
def ssim_adjoint_h(
    # in: vertical adjoints (H, W - 10)
    d_mu_x: wp.array2d(dtype=wp.vec3),
    d_xx: wp.array2d(dtype=wp.vec3),
    d_xy: wp.array2d(dtype=wp.vec3),
    x: wp.array2d(dtype=wp.vec3),
    y: wp.array2d(dtype=wp.vec3),
    window: wp.array(dtype=wp.float32),
    # out: (H, W), accumulated into
    grad_x_out: wp.array2d(dtype=wp.vec3),
):
    i, r = wp.tid()
    a = wp.vec3(0.0)
    b = wp.vec3(0.0)
    c = wp.vec3(0.0)
    for k in range(2 * SSIM_RADIUS + 1):
        j = r - k
        if j >= 0 and j < d_mu_x.shape[1]:
            w = window[k]
            a += w * d_mu_x[i, j]
            b += w * d_xx[i, j]
            c += w * d_xy[i, j]
    grad_x_out[i, r] = grad_x_out[i, r] + a + 2.0 * wp.cw_mul(x[i, r], b) + wp.cw_mul(y[i, r], c)
