"""Adaptive density control of 3DGS (Kerbl et al. 2023, §5.2), the map growth of the dense
initialization baseline: screen-space gradient statistics, clone / split selection, writing the new
rows, pruning flags and the opacity reset (of the Gaussians seen since the statistics restarted).

Actions per Gaussian (``new_rows``): 0 = untouched, 1 = cloned (one exact copy appended),
2 = split (two children appended, the parent removed afterwards).
"""

import warp as wp

from rgs_warp.kernels.math import quat_to_rot, vec10

wp.set_module_options({"enable_backward": False})

CLONE = wp.constant(1)
SPLIT = wp.constant(2)


@wp.kernel
def accumulate_grad_stats(
    # in: screen-space gradients of the latest full backward and the projected radii
    grad2d: wp.array(dtype=vec10),
    radii: wp.array(dtype=wp.vec2i),
    # in: pixels -> NDC gradient factors (W / 2, H / 2)
    ndc_scale: wp.vec2,
    # in/out: running sum of |dL/d mean2d_ndc| and number of renders where the Gaussian was visible
    grad_norm_sum_out: wp.array(dtype=wp.float32),
    visible_count_out: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    if radii[i][0] > 0:
        g = grad2d[i]
        grad_norm_sum_out[i] += wp.length(wp.vec2(g[0] * ndc_scale[0], g[1] * ndc_scale[1]))
        visible_count_out[i] += 1


@wp.kernel
def classify_densify(
    # in: gradient statistics
    grad_norm_sum: wp.array(dtype=wp.float32),
    visible_count: wp.array(dtype=wp.int32),
    # in: Gaussian map
    log_scales: wp.array(dtype=wp.vec3),
    # in: thresholds (NDC gradient; world-space scale splitting clone from split)
    grad_threshold: float,
    clone_max_scale: float,
    # out: rows to append per Gaussian (0 / CLONE / SPLIT) and the totals [cloned, split]
    new_rows_out: wp.array(dtype=wp.int32),
    counts_out: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    action = int(0)
    seen = visible_count[i]
    if seen > 0:
        if grad_norm_sum[i] / float(seen) >= grad_threshold:
            s = log_scales[i]
            if wp.exp(wp.max(s[0], wp.max(s[1], s[2]))) <= clone_max_scale:
                action = CLONE
                wp.atomic_add(counts_out, 0, 1)
            else:
                action = SPLIT
                wp.atomic_add(counts_out, 1, 1)
    new_rows_out[i] = action


@wp.kernel
def write_densified(
    # in: what to append per Gaussian and where (exclusive scan of new_rows, relative to `base`)
    new_rows: wp.array(dtype=wp.int32),
    row_offset: wp.array(dtype=wp.int32),
    base: int,
    num_sh: int,
    # in: split children's scales = parent's / split_factor; sampling seed
    log_split_factor: float,
    seed: int,
    # in/out: Gaussian map (rows < base read, rows >= base written)
    means_out: wp.array(dtype=wp.vec3),
    rotations_out: wp.array(dtype=wp.quat),
    log_scales_out: wp.array(dtype=wp.vec3),
    opacity_logits_out: wp.array(dtype=wp.float32),
    sh_out: wp.array2d(dtype=wp.vec3),
):
    i = wp.tid()
    action = new_rows[i]
    if action == 0:
        return
    mean = means_out[i]
    q = rotations_out[i]
    log_s = log_scales_out[i]
    logit = opacity_logits_out[i]
    dst = base + row_offset[i]
    if action == CLONE:
        means_out[dst] = mean
        rotations_out[dst] = q
        log_scales_out[dst] = log_s
        opacity_logits_out[dst] = logit
        for k in range(num_sh):
            sh_out[dst, k] = sh_out[i, k]
        return
    # Split: children drawn from the parent's Gaussian N(mean, R S S^T R^T), scales shrunk by the
    # split factor (3DGS: 1.6 for two children, so that they roughly cover the parent's extent).
    state = wp.rand_init(seed, i)
    R = quat_to_rot(wp.normalize(q))
    s = wp.vec3(wp.exp(log_s[0]), wp.exp(log_s[1]), wp.exp(log_s[2]))
    child_log_s = log_s - wp.vec3(log_split_factor)
    for c in range(2):
        z = wp.vec3(wp.randn(state), wp.randn(state), wp.randn(state))
        means_out[dst + c] = mean + R @ wp.cw_mul(s, z)
        rotations_out[dst + c] = q
        log_scales_out[dst + c] = child_log_s
        opacity_logits_out[dst + c] = logit
        for k in range(num_sh):
            sh_out[dst + c, k] = sh_out[i, k]


@wp.kernel
def flag_pruned(
    # in: actions of the rows that existed before densification (split parents are removed)
    new_rows: wp.array(dtype=wp.int32),
    num_before: int,
    # in: Gaussian map
    opacity_logits: wp.array(dtype=wp.float32),
    log_scales: wp.array(dtype=wp.vec3),
    # in: pruning thresholds (logit of the culling opacity; world scale, <= 0 disables it)
    cull_logit: float,
    max_scale: float,
    # out: removal flags (nonzero = remove) over all rows, split parents included
    remove_out: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    drop = opacity_logits[i] < cull_logit
    if i < num_before:
        drop = drop or new_rows[i] == SPLIT
    if max_scale > 0.0:
        s = log_scales[i]
        drop = drop or wp.exp(wp.max(s[0], wp.max(s[1], s[2]))) > max_scale
    remove_out[i] = wp.where(drop, 1, 0)


@wp.kernel
def clamp_opacity_logits(
    # in: renders that saw each Gaussian since the statistics restarted (only those are reset)
    visible_count: wp.array(dtype=wp.int32),
    # in: largest logit kept (the logit of the reset opacity)
    max_logit: float,
    # in/out:
    opacity_logits_out: wp.array(dtype=wp.float32),
):
    i = wp.tid()
    if visible_count[i] > 0:
        opacity_logits_out[i] = wp.min(opacity_logits_out[i], max_logit)
