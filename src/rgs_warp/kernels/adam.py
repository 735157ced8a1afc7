"""Fused Adam on flat float32 views of the GaussianMap fields, with global gradient-norm clipping
whose scale is computed on the device (no host read-back between the norm and the update)."""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def clip_scale_from_sq_norms(
    # in:
    sq_norms: wp.array(dtype=wp.float32),
    max_norm: float,
    # out: [scale, norm]
    clip_out: wp.array(dtype=wp.float32),
):
    total = float(0.0)
    for i in range(sq_norms.shape[0]):
        total += sq_norms[i]
    norm = wp.sqrt(total)
    clip_out[0] = wp.min(1.0, max_norm / (norm + 1e-6))
    clip_out[1] = norm


@wp.kernel
def adam_step(
    # in:
    grad: wp.array(dtype=wp.float32),
    clip: wp.array(dtype=wp.float32),
    lr_t: float,  # lr * sqrt(1 - b2^t) / (1 - b1^t): bias correction folded into the step size
    # entries i with (i mod row_width) >= row_lead step with lr_rest_t instead (the SH rows: the first
    # 3 floats are the DC colour, the rest the higher bands); row_lead = row_width: one rate
    row_width: int,
    row_lead: int,
    lr_rest_t: float,
    beta1: float,
    beta2: float,
    eps: float,
    # in/out:
    param: wp.array(dtype=wp.float32),
    m: wp.array(dtype=wp.float32),
    v: wp.array(dtype=wp.float32),
):
    i = wp.tid()
    g = grad[i] * clip[0]
    mi = beta1 * m[i] + (1.0 - beta1) * g
    vi = beta2 * v[i] + (1.0 - beta2) * g * g
    m[i] = mi
    v[i] = vi
    lr = lr_t
    if i % row_width >= row_lead:
        lr = lr_rest_t
    param[i] = param[i] - lr * mi / (wp.sqrt(vi) + eps)
