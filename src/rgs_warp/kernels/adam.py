"""Adam over the GaussianMap's parameters in three launches a step, each over the flat float32 entries
of all five parameters at once (entry i belongs to the parameter whose range of ``ends`` holds it: the
same coalesced access as one launch per parameter): the five squared gradient norms (one block sum
per 256 entries), the global gradient-norm clip computed on the device (no host read-back between the
norm and the update), then the update of every entry and its two moments."""

import warp as wp

from rgs_warp.kernels.math import REDUCE_BLOCK, block_sum

wp.set_module_options({"enable_backward": False})

# per-parameter squared gradient norms and entry ranges, in GaussianMap.PARAMETERS' order
N_PARAMETERS = 5
vec5 = wp.types.vector(length=N_PARAMETERS, dtype=wp.float32)
vec5i = wp.types.vector(length=N_PARAMETERS, dtype=wp.int32)
# learning rates of the step: the five parameters', then the higher SH bands'
vec6 = wp.types.vector(length=6, dtype=wp.float32)
LR_SH_REST = wp.constant(5)
# blocks of the norms' launch at most (each thread then strides over the entries)
NORM_BLOCKS = wp.constant(1024)


@wp.func
def parameter_of(i: int, ends: vec5i):
    """(parameter, entry within it) of flat entry ``i``; ``ends``: the cumulative entry counts."""
    f = int(0)
    start = int(0)
    for k in range(N_PARAMETERS - 1):
        if i >= ends[k]:
            f = k + 1
            start = ends[k]
    return f, i - start


@wp.func
def entry(
    a0: wp.array(dtype=wp.float32),
    a1: wp.array(dtype=wp.float32),
    a2: wp.array(dtype=wp.float32),
    a3: wp.array(dtype=wp.float32),
    a4: wp.array(dtype=wp.float32),
    f: int,
    j: int,
):
    if f == 0:
        return a0[j]
    if f == 1:
        return a1[j]
    if f == 2:
        return a2[j]
    if f == 3:
        return a3[j]
    return a4[j]


@wp.func
def set_entry(
    a0: wp.array(dtype=wp.float32),
    a1: wp.array(dtype=wp.float32),
    a2: wp.array(dtype=wp.float32),
    a3: wp.array(dtype=wp.float32),
    a4: wp.array(dtype=wp.float32),
    f: int,
    j: int,
    x: float,
):
    if f == 0:
        a0[j] = x
    elif f == 1:
        a1[j] = x
    elif f == 2:
        a2[j] = x
    elif f == 3:
        a3[j] = x
    else:
        a4[j] = x


@wp.kernel
def grad_sq_norms(
    # in: flat float32 views of the five gradients, their live entry ranges (cumulative)
    g0: wp.array(dtype=wp.float32),
    g1: wp.array(dtype=wp.float32),
    g2: wp.array(dtype=wp.float32),
    g3: wp.array(dtype=wp.float32),
    g4: wp.array(dtype=wp.float32),
    ends: vec5i,
    # out: the five squared norms (zeroed beforehand)
    sq_out: wp.array(dtype=wp.float32),
):
    # each thread strides over the entries (the launch has at most NORM_BLOCKS blocks), so the block
    # sums and atomics are a few thousand, not one per 256 entries (90k at 1M Gaussians)
    block, lane = wp.tid()
    stride = NORM_BLOCKS * REDUCE_BLOCK
    s = vec5()
    i = block * REDUCE_BLOCK + lane
    while i < ends[N_PARAMETERS - 1]:
        f, j = parameter_of(i, ends)
        g = entry(g0, g1, g2, g3, g4, f, j)
        s[f] += g * g
        i += stride
    total = block_sum(s)
    if lane == 0:
        for k in range(N_PARAMETERS):
            if total[k] != 0.0:
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


@wp.kernel
def adam_entries(
    # in: flat float32 views of the gradients (scaled by clip[0]), their live entry ranges (cumulative),
    # the learning rates (lr x sqrt(1 - b2^t) / (1 - b1^t); the SH entries past the first 3 of each row
    # of sh_width take LR_SH_REST)
    g0: wp.array(dtype=wp.float32),
    g1: wp.array(dtype=wp.float32),
    g2: wp.array(dtype=wp.float32),
    g3: wp.array(dtype=wp.float32),
    g4: wp.array(dtype=wp.float32),
    ends: vec5i,
    clip: wp.array(dtype=wp.float32),
    # the step's learning rates: row counter[0] of the schedule (a captured step reads its own)
    lr_schedule: wp.array(dtype=vec6),
    counter: wp.array(dtype=wp.int32),
    sh_width: int,
    beta1: float,
    beta2: float,
    eps: float,
    # in/out: flat views of the parameters, their first and second moments (the map's adam_m / adam_v)
    p0: wp.array(dtype=wp.float32),
    p1: wp.array(dtype=wp.float32),
    p2: wp.array(dtype=wp.float32),
    p3: wp.array(dtype=wp.float32),
    p4: wp.array(dtype=wp.float32),
    m0: wp.array(dtype=wp.float32),
    m1: wp.array(dtype=wp.float32),
    m2: wp.array(dtype=wp.float32),
    m3: wp.array(dtype=wp.float32),
    m4: wp.array(dtype=wp.float32),
    v0: wp.array(dtype=wp.float32),
    v1: wp.array(dtype=wp.float32),
    v2: wp.array(dtype=wp.float32),
    v3: wp.array(dtype=wp.float32),
    v4: wp.array(dtype=wp.float32),
):
    i = wp.tid()
    f, j = parameter_of(i, ends)
    g = entry(g0, g1, g2, g3, g4, f, j) * clip[0]
    m = beta1 * entry(m0, m1, m2, m3, m4, f, j) + (1.0 - beta1) * g
    v = beta2 * entry(v0, v1, v2, v3, v4, f, j) + (1.0 - beta2) * g * g
    rates = lr_schedule[counter[0]]
    rate = rates[f]
    if f == N_PARAMETERS - 1 and j % sh_width >= 3:
        rate = rates[LR_SH_REST]
    set_entry(m0, m1, m2, m3, m4, f, j, m)
    set_entry(v0, v1, v2, v3, v4, f, j, v)
    set_entry(p0, p1, p2, p3, p4, f, j, entry(p0, p1, p2, p3, p4, f, j) - rate * m / (wp.sqrt(v) + eps))
