"""The mapper's maintenance pass (supplement §4.5): pruning flags and the merging of duplicate Gaussians.

Pruning is one pass over the map writing a 0/1 removal flag and counting the first reason that
applies, in the order of ``PRUNE_*`` below.

Merging runs in three launches over one view:

1. ``merge_footprints`` projects every Gaussian (EWA, as the renderer does) and embeds its
   footprint as the point (u, v, ln(z) * depth_embed) with depth_embed = max_footprint_px /
   max_depth_rel, so that the two tolerances (centres within max_footprint_px pixels, depths within
   a ratio of exp(max_depth_rel)) both become "within max_footprint_px" in the embedding and one
   ``wp.HashGrid`` query of radius sqrt(2) * max_footprint_px finds every candidate partner.
2. ``merge_best_partner``: among the candidates that also pass the size and colour tests, each
   Gaussian picks the partner of the smallest edge key (score, min index, max index); the key is
   symmetric in the pair and a strict total order, so the globally smallest edge of every cluster is
   picked from both ends and every pass merges at least one pair per cluster.
3. ``merge_pairs``: a pair (i, j) merges only when each is the other's pick (mutual best partners),
   and the lower index i writes the merged Gaussian into its own row and flags j.  A Gaussian has
   one pick, so it belongs to at most one mutual pair: no Gaussian merges twice in a pass, and
   every row is written by at most one thread, which no other thread reads (race-free).
"""

import warp as wp

from rgs_warp.kernels.math import (
    COV2D_DILATION,
    SH_C0,
    CameraParams,
    exp3,
    hash_lattice,
    projection_jacobian,
    quat_to_rot,
)

wp.set_module_options({"enable_backward": False})

# Layout of the prune statistics: the total, then one count per reason (the first reason that applies).
PRUNE_TOTAL = wp.constant(0)
PRUNE_INVALID = wp.constant(1)
PRUNE_OPACITY = wp.constant(2)
PRUNE_SCALE = wp.constant(3)
PRUNE_HIDDEN = wp.constant(4)
PRUNE_STATS = 5
# Embedded positions of the Gaussians without a footprint in the merge view (``far_point``): far from
# every image point, FAR_SPACING apart on the hash lattice.
FAR = wp.constant(-1.0e6)
FAR_SPACING = wp.constant(3.3)
# Smallest variance of a merged axis (a scale of 1e-12 m): keeps the log finite for degenerate inputs.
MIN_VARIANCE = wp.constant(wp.float64(1.0e-24))


@wp.func
def gaussian_is_valid(
    means: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    opacity_logits: wp.array(dtype=wp.float32),
    sh: wp.array2d(dtype=wp.vec3),
    i: int,
):
    """All parameters finite and the rotation normalisable."""
    q = rotations[i]
    ok = wp.isfinite(means[i]) and wp.isfinite(q) and wp.isfinite(log_scales[i]) and wp.isfinite(opacity_logits[i])
    ok = ok and wp.dot(q, q) > 0.0
    for k in range(sh.shape[1]):
        ok = ok and wp.isfinite(sh[i, k])
    return ok


@wp.func
def sigmoid(x: wp.float32):
    return 1.0 / (1.0 + wp.exp(-x))


@wp.kernel
def prune_flags(
    # Gaussian map:
    means: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    opacity_logits: wp.array(dtype=wp.float32),
    sh: wp.array2d(dtype=wp.vec3),
    # Observation statistics (read only when has_visibility != 0):
    obs_count: wp.array(dtype=wp.int32),
    vis_count: wp.array(dtype=wp.float32),
    has_visibility: int,
    # Bounds:
    opacity_min: float,
    max_extent_m: float,
    min_obs: int,
    min_visibility_ratio: float,
    # Out: removal flags, and per-reason counts (zeroed by the caller)
    remove_out: wp.array(dtype=wp.int32),
    stats_out: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    reason = -1
    if not gaussian_is_valid(means, rotations, log_scales, opacity_logits, sh, i):
        reason = PRUNE_INVALID
    elif sigmoid(opacity_logits[i]) < opacity_min:
        reason = PRUNE_OPACITY
    else:
        s = exp3(log_scales[i])
        # sqrt(tr Sigma) = |s|, the root of the summed axis variances (rotation-invariant)
        if wp.length(s) > max_extent_m:
            reason = PRUNE_SCALE
        elif has_visibility != 0:
            # seen in min_obs views but contributing to (almost) no pixel: hidden behind surfaces
            m = obs_count[i]
            if m >= min_obs and vis_count[i] < min_visibility_ratio * float(m):
                reason = PRUNE_HIDDEN
    if reason >= 0:
        remove_out[i] = 1
        wp.atomic_add(stats_out, PRUNE_TOTAL, 1)
        wp.atomic_add(stats_out, reason, 1)
    else:
        remove_out[i] = 0


@wp.func
def far_point(i: int):
    """Where Gaussian ``i`` sits in the merge embedding when it has no footprint: out of every query's
    reach, on the hash lattice (``kernels/math.hash_lattice``)."""
    return wp.vec3(FAR) - FAR_SPACING * hash_lattice(i)


@wp.kernel
def merge_footprints(
    # Gaussian map:
    means: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    opacity_logits: wp.array(dtype=wp.float32),
    sh: wp.array2d(dtype=wp.vec3),
    # Rows already flagged for removal take no part:
    remove: wp.array(dtype=wp.int32),
    # View (camera-from-world rotation W, translation t) and intrinsics:
    W: wp.mat33,
    t: wp.vec3,
    cam: CameraParams,
    depth_embed: float,
    # Out: embedded footprint centre (u, v, ln z * depth_embed), 2D covariance (a, b, c), 1 if it has a footprint
    point_out: wp.array(dtype=wp.vec3),
    cov2d_out: wp.array(dtype=wp.vec3),
    valid_out: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    point_out[i] = far_point(i)
    cov2d_out[i] = wp.vec3(0.0)
    valid_out[i] = 0
    if remove[i] != 0 or not gaussian_is_valid(means, rotations, log_scales, opacity_logits, sh, i):
        return
    X = W @ means[i] + t
    z = X[2]
    if z < cam.near:
        return
    u = cam.fx * X[0] / z + cam.cx
    v = cam.fy * X[1] / z + cam.cy
    if u < -0.5 or u > float(cam.width) - 0.5 or v < -0.5 or v > float(cam.height) - 0.5:
        return
    M = quat_to_rot(wp.normalize(rotations[i])) @ wp.diag(exp3(log_scales[i]))
    J = projection_jacobian(X, cam) @ W
    cov2d = J @ M @ wp.transpose(M) @ wp.transpose(J)
    # the footprint as rendered, low-pass dilation included
    point_out[i] = wp.vec3(u, v, wp.log(z) * depth_embed)
    cov2d_out[i] = wp.vec3(cov2d[0, 0] + COV2D_DILATION, cov2d[0, 1], cov2d[1, 1] + COV2D_DILATION)
    valid_out[i] = 1


@wp.func
def sym2_norm(c: wp.vec3):
    """Frobenius norm of the symmetric 2x2 matrix [[a, b], [b, c]] stored as (a, b, c)."""
    return wp.sqrt(c[0] * c[0] + 2.0 * c[1] * c[1] + c[2] * c[2])


@wp.kernel
def merge_best_partner(
    # In: hash grid over the embedded footprints, the footprints and the map's SH
    grid: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    cov2d: wp.array(dtype=wp.vec3),
    valid: wp.array(dtype=wp.int32),
    sh: wp.array2d(dtype=wp.vec3),
    # Tolerances:
    max_footprint_px: float,
    max_size_rel: float,
    max_color_diff: float,
    # Out: the chosen partner, -1 for none
    best_out: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    best_out[i] = -1
    if valid[i] == 0:
        return
    p = points[i]
    ci = cov2d[i]
    ni = sym2_norm(ci)
    dc_i = sh[i, 0]
    best = int(-1)
    best_score = float(0.0)
    best_lo = int(0)
    best_hi = int(0)
    for j in wp.hash_grid_query(grid, p, max_footprint_px * 1.4142136):
        if j == i or valid[j] == 0:
            continue
        d = points[j] - p
        d_px = wp.sqrt(d[0] * d[0] + d[1] * d[1])
        d_depth = wp.abs(d[2])
        if d_px > max_footprint_px or d_depth > max_footprint_px:
            continue
        size_rel = sym2_norm(cov2d[j] - ci) / (0.5 * (ni + sym2_norm(cov2d[j])))
        if size_rel > max_size_rel:
            continue
        # colour difference of the SH DC band in colour units (colour = SH_C0 * dc + 0.5), worst channel
        dc = dc_i - sh[j, 0]
        d_color = SH_C0 * wp.max(wp.max(wp.abs(dc[0]), wp.abs(dc[1])), wp.abs(dc[2]))
        if d_color > max_color_diff:
            continue
        # every term is symmetric in (i, j), so both ends compute the same score
        score = d_px / max_footprint_px + d_depth / max_footprint_px + size_rel / max_size_rel
        score = score + d_color / max_color_diff
        lo = wp.min(i, j)
        hi = wp.max(i, j)
        better = best < 0 or score < best_score
        if score == best_score:
            better = better or lo < best_lo or (lo == best_lo and hi < best_hi)
        if better:
            best = j
            best_score = score
            best_lo = lo
            best_hi = hi
    best_out[i] = best


@wp.func
def covariance64(q: wp.quat, log_s: wp.vec3):
    """Sigma = R S^2 R^T in float64 (thin discs have variances 1e4 apart: float32 would lose the small one)."""
    qn = wp.normalize(q)
    R = wp.quat_to_matrix(wp.quatd(wp.float64(qn[0]), wp.float64(qn[1]), wp.float64(qn[2]), wp.float64(qn[3])))
    s = exp3(log_s)
    S = wp.diag(wp.vec3d(wp.float64(s[0]), wp.float64(s[1]), wp.float64(s[2])))
    M = R @ S
    return M @ wp.transpose(M)


@wp.kernel
def merge_pairs(
    # In: partners
    best: wp.array(dtype=wp.int32),
    max_merged_opacity: float,
    # Gaussian map (in and out: the survivor's row)
    means: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    opacity_logits: wp.array(dtype=wp.float32),
    sh: wp.array2d(dtype=wp.vec3),
    # Out: removal flags (the merged-away row), number of merges
    remove_out: wp.array(dtype=wp.int32),
    merged_out: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    j = best[i]
    if j <= i or best[j] != i:
        return
    means[i] = 0.5 * (means[i] + means[j])
    for k in range(sh.shape[1]):
        sh[i, k] = 0.5 * (sh[i, k] + sh[j, k])

    # average covariance, decomposed back into rotation and scales
    cov = wp.float64(0.5) * (covariance64(rotations[i], log_scales[i]) + covariance64(rotations[j], log_scales[j]))
    Q, var = wp.eig3(cov)
    if wp.determinant(Q) < wp.float64(0.0):
        Q = Q @ wp.diag(wp.vec3d(wp.float64(-1.0), wp.float64(1.0), wp.float64(1.0)))
    qd = wp.quat_from_matrix(Q)
    rotations[i] = wp.normalize(wp.quat(wp.float32(qd[0]), wp.float32(qd[1]), wp.float32(qd[2]), wp.float32(qd[3])))
    log_scales[i] = wp.vec3(
        wp.float32(wp.float64(0.5) * wp.log(wp.max(var[0], MIN_VARIANCE))),
        wp.float32(wp.float64(0.5) * wp.log(wp.max(var[1], MIN_VARIANCE))),
        wp.float32(wp.float64(0.5) * wp.log(wp.max(var[2], MIN_VARIANCE))),
    )

    # Two splats over one footprint composite to coverage 1 - (1 - a)(1 - b): keep that coverage,
    # capped at max_merged_opacity, but never below the more opaque of the two (compared as logits,
    # which stay finite where sigmoid rounds to 1).
    li = opacity_logits[i]
    lj = opacity_logits[j]
    union = 1.0 - (1.0 - sigmoid(li)) * (1.0 - sigmoid(lj))
    o = wp.min(union, max_merged_opacity)
    opacity_logits[i] = wp.max(wp.log(o / (1.0 - o)), wp.max(li, lj))

    remove_out[j] = 1
    wp.atomic_add(merged_out, 0, 1)
