"""Adam over the GaussianMap's parameters in two launches a step: the squared gradient norms of the
five parameters (one block sum per 256 Gaussians), then one thread per Gaussian that updates all its
parameters and moments, scaled by the global gradient-norm clip computed on the device in between (no
host read-back between the norm and the update)."""

import warp as wp

from rgs_warp.kernels.math import REDUCE_BLOCK, block_sum

wp.set_module_options({"enable_backward": False})

# per-parameter squared gradient norms, in GaussianMap.PARAMETERS' order
N_PARAMETERS = 5
vec5 = wp.types.vector(length=N_PARAMETERS, dtype=wp.float32)
# learning rates of the fused step: the five parameters', then the higher SH bands'
vec6 = wp.types.vector(length=6, dtype=wp.float32)
LR_SH_REST = wp.constant(5)


@wp.kernel
def grad_sq_norms(
    # in: the gradients of the first n Gaussians
    g_means: wp.array(dtype=wp.vec3),
    g_rotations: wp.array(dtype=wp.quat),
    g_log_scales: wp.array(dtype=wp.vec3),
    g_opacity_logits: wp.array(dtype=wp.float32),
    g_sh: wp.array2d(dtype=wp.vec3),
    n: int,
    # out: the five squared norms (zeroed beforehand)
    sq_out: wp.array(dtype=wp.float32),
):
    block, lane = wp.tid()
    i = block * REDUCE_BLOCK + lane
    s = vec5()
    if i < n:
        s[0] = wp.length_sq(g_means[i])
        q = g_rotations[i]
        s[1] = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]
        s[2] = wp.length_sq(g_log_scales[i])
        o = g_opacity_logits[i]
        s[3] = o * o
        for k in range(g_sh.shape[1]):
            s[4] += wp.length_sq(g_sh[i, k])
    total = block_sum(s)
    if lane == 0:
        for k in range(N_PARAMETERS):
            wp.atomic_add(sq_out, k, total[k])


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


@wp.func
def adam_entry(p: float, g: float, m: float, v: float, lr: float, beta1: float, beta2: float, eps: float):
    """One entry's step: (new parameter, first moment, second moment); ``lr`` has the bias correction
    folded in."""
    mi = beta1 * m + (1.0 - beta1) * g
    vi = beta2 * v + (1.0 - beta2) * g * g
    return p - lr * mi / (wp.sqrt(vi) + eps), mi, vi


@wp.func
def adam_vec3(p: wp.vec3, g: wp.vec3, m: wp.vec3, v: wp.vec3, lr: float, beta1: float, beta2: float, eps: float):
    po = wp.vec3()
    mo = wp.vec3()
    vo = wp.vec3()
    for c in range(3):
        pc, mc, vc = adam_entry(p[c], g[c], m[c], v[c], lr, beta1, beta2, eps)
        po[c] = pc
        mo[c] = mc
        vo[c] = vc
    return po, mo, vo


@wp.kernel
def adam_gaussians(
    # in: gradients (scaled by clip[0]), learning rates (lr x sqrt(1 - b2^t) / (1 - b1^t), LR_* order)
    g_means: wp.array(dtype=wp.vec3),
    g_rotations: wp.array(dtype=wp.quat),
    g_log_scales: wp.array(dtype=wp.vec3),
    g_opacity_logits: wp.array(dtype=wp.float32),
    g_sh: wp.array2d(dtype=wp.vec3),
    clip: wp.array(dtype=wp.float32),
    lr: vec6,
    beta1: float,
    beta2: float,
    eps: float,
    # in/out: the parameters, then their first and second moments (the map's adam_m / adam_v columns)
    means: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    opacity_logits: wp.array(dtype=wp.float32),
    sh: wp.array2d(dtype=wp.vec3),
    m_means: wp.array(dtype=wp.vec3),
    m_rotations: wp.array(dtype=wp.quat),
    m_log_scales: wp.array(dtype=wp.vec3),
    m_opacity_logits: wp.array(dtype=wp.float32),
    m_sh: wp.array2d(dtype=wp.vec3),
    v_means: wp.array(dtype=wp.vec3),
    v_rotations: wp.array(dtype=wp.quat),
    v_log_scales: wp.array(dtype=wp.vec3),
    v_opacity_logits: wp.array(dtype=wp.float32),
    v_sh: wp.array2d(dtype=wp.vec3),
):
    i = wp.tid()
    c = clip[0]
    p3, m3, v3 = adam_vec3(means[i], c * g_means[i], m_means[i], v_means[i], lr[0], beta1, beta2, eps)
    means[i] = p3
    m_means[i] = m3
    v_means[i] = v3
    q = rotations[i]
    gq = g_rotations[i]
    mq = m_rotations[i]
    vq = v_rotations[i]
    for k in range(4):
        pk, mk, vk = adam_entry(q[k], c * gq[k], mq[k], vq[k], lr[1], beta1, beta2, eps)
        q[k] = pk
        mq[k] = mk
        vq[k] = vk
    rotations[i] = q
    m_rotations[i] = mq
    v_rotations[i] = vq
    p3, m3, v3 = adam_vec3(
        log_scales[i], c * g_log_scales[i], m_log_scales[i], v_log_scales[i], lr[2], beta1, beta2, eps
    )
    log_scales[i] = p3
    m_log_scales[i] = m3
    v_log_scales[i] = v3
    po, mo, vo = adam_entry(
        opacity_logits[i], c * g_opacity_logits[i], m_opacity_logits[i], v_opacity_logits[i], lr[3], beta1, beta2, eps
    )
    opacity_logits[i] = po
    m_opacity_logits[i] = mo
    v_opacity_logits[i] = vo
    for k in range(sh.shape[1]):
        rate = wp.where(k == 0, lr[4], lr[LR_SH_REST])
        p3, m3, v3 = adam_vec3(sh[i, k], c * g_sh[i, k], m_sh[i, k], v_sh[i, k], rate, beta1, beta2, eps)
        sh[i, k] = p3
        m_sh[i, k] = m3
        v_sh[i, k] = v3
