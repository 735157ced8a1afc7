"""Dense matching kernels (supplement §4.4): epipolar-constrained descriptor search with sub-pixel
refinement, descriptor sampling for the backward search, the score and confidence of Eq. 11-12,
and the aggregation across neighbours.

Coordinates: image pixels follow ``types.py`` (pixel centres at integers); feature pixel (i, j) of
stride s is centred at image coordinates (s*j + (s-1)/2, s*i + (s-1)/2).  Searches run on the
feature grid; positions they return are in image pixels.  The descriptor similarity, the patch ZNCC
and the sub-pixel fits are shared with the bootstrap's window search (kernels/math.py).
"""

import warp as wp

from rgs_warp.kernels.math import (
    NO_MATCH,
    bilerp,
    bilinear_corner,
    grey_level,
    parabola_peak,
    refine_zncc,
    sample_depth,
    similarity,
    to_grid,
    to_image,
)

wp.set_module_options({"enable_backward": False})

MIN_Z_M = wp.constant(0.05)  # points closer than this to a camera are not searched for


@wp.kernel
def grey_image(
    # in:
    rgb: wp.array2d(dtype=wp.vec3),
    # out:
    grey_out: wp.array2d(dtype=wp.float32),
):
    """The grey level (``grey_level``) of every pixel: the ZNCC refinement's input."""
    y, x = wp.tid()
    grey_out[y, x] = grey_level(rgb[y, x])


@wp.func
def project(K: wp.vec4, X: wp.vec3) -> wp.vec2:
    return wp.vec2(K[0] * X[0] / X[2] + K[2], K[1] * X[1] / X[2] + K[3])


@wp.struct
class EpipolarSearch:
    """What an epipolar search (``epipolar_search_parts``, ``epipolar_search``) needs besides its
    images: the intrinsics (fx, fy, cx, cy), the query camera into the target camera (R_tq, t_tq),
    the descriptor stride, the depths searched without a query depth, the relative depth tolerance
    with one, the least half-length and the band of the segment (feature px), and its most samples."""

    K: wp.vec4
    R_tq: wp.mat33
    t_tq: wp.vec3
    stride: int
    depth_range: wp.vec2
    depth_rel_tol: float
    min_radius: float
    band: int
    max_steps: int


@wp.func
def epipolar_segment(uv: wp.vec2, query_depth: wp.array2d(dtype=wp.float32), Hf: int, Wf: int, e: EpipolarSearch):
    """The feature-grid segment that ``epipolar_search`` scans for the query at image point uv: its
    start g0, unit direction and normal, a point of the epipolar line, the parameter range's start
    t_lo, the number of samples and their spacing (0 samples: none to scan)."""
    K = e.K
    R_tq = e.R_tq
    t_tq = e.t_tq
    stride = e.stride
    depth_rel_tol = e.depth_rel_tol
    min_radius = e.min_radius
    ray = R_tq @ wp.vec3((uv[0] - K[2]) / K[0], (uv[1] - K[3]) / K[1], 1.0)
    d = sample_depth(query_depth, uv[0], uv[1], depth_rel_tol)
    d_near = e.depth_range[0]
    d_far = e.depth_range[1]
    if d > 0.0:
        d_near = d * (1.0 - depth_rel_tol)
        d_far = d * (1.0 + depth_rel_tol)
    none = wp.vec2(0.0, 0.0)
    # Keep the segment in front of the target camera: z(d) = d * ray.z + t.z >= MIN_Z_M.
    if ray[2] > 0.0:
        d_near = wp.max(d_near, (MIN_Z_M - t_tq[2]) / ray[2])
    elif ray[2] < 0.0:
        d_far = wp.min(d_far, (MIN_Z_M - t_tq[2]) / ray[2])
    elif t_tq[2] < MIN_Z_M:
        return none, none, none, none, 0.0, 0, 0.0
    if d_near >= d_far:
        return none, none, none, none, 0.0, 0, 0.0
    p_near = project(K, d_near * ray + t_tq)
    p_far = project(K, d_far * ray + t_tq)
    g0 = wp.vec2(to_grid(p_near[0], stride), to_grid(p_near[1], stride))
    g1 = wp.vec2(to_grid(p_far[0], stride), to_grid(p_far[1], stride))
    length = wp.length(g1 - g0)
    direction = wp.vec2(1.0, 0.0)
    if length > 1e-6:
        direction = (g1 - g0) / length
    normal = wp.vec2(-direction[1], direction[0])
    line_point = g0
    # Without parallax (or with a tight depth prior) the segment is short: search at least
    # +/- min_radius around its middle so the sub-pixel fit and the band have room.
    if length < 2.0 * min_radius:
        middle = 0.5 * (g0 + g1)
        g0 = middle - min_radius * direction
        length = 2.0 * min_radius
    # Clip the segment to the grid (widened by the band) by its parameter range.
    margin = float(e.band) + 0.5
    t_lo = float(0.0)
    t_hi = float(length)
    for axis in range(2):
        lo = -margin
        hi = float(Wf - 1) + margin
        if axis == 1:
            hi = float(Hf - 1) + margin
        if wp.abs(direction[axis]) > 1e-9:
            ta = (lo - g0[axis]) / direction[axis]
            tb = (hi - g0[axis]) / direction[axis]
            t_lo = wp.max(t_lo, wp.min(ta, tb))
            t_hi = wp.min(t_hi, wp.max(ta, tb))
        elif g0[axis] < lo or g0[axis] > hi:
            t_hi = -1.0
    if t_lo > t_hi:
        return none, none, none, none, 0.0, 0, 0.0
    n_steps = wp.min(int(wp.ceil(t_hi - t_lo)) + 1, e.max_steps)
    step = (t_hi - t_lo) / float(wp.max(n_steps - 1, 1))
    return g0, direction, normal, line_point, t_lo, n_steps, step


@wp.kernel
def epipolar_search_parts(
    # in:
    query_desc: wp.array2d(dtype=wp.float32),
    query_uv: wp.array(dtype=wp.vec2),
    query_sim: wp.array(dtype=wp.float32),
    query_depth: wp.array2d(dtype=wp.float32),
    target_desc: wp.array3d(dtype=wp.float32),
    search: EpipolarSearch,
    # out:
    part_sim_out: wp.array2d(dtype=wp.float32),
    part_cell_out: wp.array2d(dtype=wp.vec3i),
):
    """The descriptor scan of ``epipolar_search`` spread over P = part_sim_out.shape[1] threads a
    query: thread (i, p) scans the segment's samples p, p + P, p + 2P, ... (every band offset of
    each, in ``epipolar_search``'s order) and writes its best similarity and its cell (x, y, sample
    index; NO_MATCH where it has none), which ``epipolar_search`` reduces in sample order.  One
    thread a query left the GPU waiting on the few queries without depth, whose segments are up to
    ``max_steps`` long against a few samples with depth."""
    i, part = wp.tid()
    parts = part_sim_out.shape[1]
    part_sim_out[i, part] = NO_MATCH
    part_cell_out[i, part] = wp.vec3i(-1, -1, -1)
    if query_sim[i] <= NO_MATCH:
        return
    Hf = target_desc.shape[0]
    Wf = target_desc.shape[1]
    g0, direction, normal, line_point, t_lo, n_steps, step = epipolar_segment(query_uv[i], query_depth, Hf, Wf, search)
    band = search.band
    best = float(NO_MATCH)
    cell = wp.vec3i(-1, -1, -1)
    for s in range(part, n_steps, parts):
        p = g0 + (t_lo + float(s) * step) * direction
        for k in range(-band, band + 1):
            q = p + float(k) * normal
            x = int(wp.round(q[0]))
            y = int(wp.round(q[1]))
            if x >= 0 and y >= 0 and x < Wf and y < Hf:
                sim = similarity(query_desc, i, target_desc, y, x)
                if sim > best:
                    best = sim
                    cell = wp.vec3i(x, y, s)
    part_sim_out[i, part] = best
    part_cell_out[i, part] = cell


@wp.kernel
def epipolar_search(
    # in:
    query_desc: wp.array2d(dtype=wp.float32),
    query_uv: wp.array(dtype=wp.vec2),
    query_sim: wp.array(dtype=wp.float32),
    query_depth: wp.array2d(dtype=wp.float32),
    query_grey: wp.array2d(dtype=wp.float32),
    target_desc: wp.array3d(dtype=wp.float32),
    target_grey: wp.array2d(dtype=wp.float32),
    search: EpipolarSearch,
    refine_radius: int,
    patch_radius: int,
    part_sim: wp.array2d(dtype=wp.float32),
    part_cell: wp.array2d(dtype=wp.vec3i),
    # out:
    match_uv_out: wp.array(dtype=wp.vec2),
    sim_out: wp.array(dtype=wp.float32),
    epi_dist_out: wp.array(dtype=wp.float32),
):
    """For query i (descriptor row i at image point query_uv[i]; skipped when query_sim[i] is
    NO_MATCH), the best match in the target image along the epipolar segment of its ray between
    the depths the query's depth allows (d (1 -/+ depth_rel_tol), else depth_range), widened by
    ``band`` feature pixels either side (the first best in sample order, from the parts of
    ``epipolar_search_parts``, launched before with the same arguments), refined to sub-pixel by a
    parabola fit of the similarity in x and y, then at image resolution: the best patch ZNCC of the
    grey images over integer shifts within +/- refine_radius px, refined by a parabola fit of the
    ZNCC (where both patches are flat the descriptor estimate stays).  ``search`` (``EpipolarSearch``)
    maps query-camera points into the target camera and holds the segment's bounds.  Writes the match
    (image px), its similarity (Eq. 10, NO_MATCH if none) and its distance to the epipolar line
    (image px)."""
    i = wp.tid()
    match_uv_out[i] = wp.vec2(0.0, 0.0)
    sim_out[i] = NO_MATCH
    epi_dist_out[i] = 0.0
    if query_sim[i] <= NO_MATCH:
        return
    Hf = target_desc.shape[0]
    Wf = target_desc.shape[1]
    uv = query_uv[i]
    g0, direction, normal, line_point, t_lo, n_steps, step = epipolar_segment(uv, query_depth, Hf, Wf, search)
    stride = search.stride
    best = float(NO_MATCH)
    cell = wp.vec3i(-1, -1, -1)
    for part in range(part_sim.shape[1]):
        c = part_cell[i, part]
        sim = part_sim[i, part]
        if c[0] >= 0 and (sim > best or (sim == best and c[2] < cell[2])):
            best = sim
            cell = c
    bx = cell[0]
    by = cell[1]
    if bx < 0:
        return
    s_left = best
    s_right = best
    s_up = best
    s_down = best
    if bx > 0:
        s_left = similarity(query_desc, i, target_desc, by, bx - 1)
    if bx < Wf - 1:
        s_right = similarity(query_desc, i, target_desc, by, bx + 1)
    if by > 0:
        s_up = similarity(query_desc, i, target_desc, by - 1, bx)
    if by < Hf - 1:
        s_down = similarity(query_desc, i, target_desc, by + 1, bx)
    g = wp.vec2(float(bx) + parabola_peak(s_left, best, s_right), float(by) + parabola_peak(s_up, best, s_down))
    coarse = wp.vec2(to_image(g[0], stride), to_image(g[1], stride))
    fine = refine_zncc(query_grey, uv, target_grey, coarse, refine_radius, patch_radius)
    match_uv_out[i] = fine
    sim_out[i] = best
    g_fine = wp.vec2(to_grid(fine[0], stride), to_grid(fine[1], stride))
    epi_dist_out[i] = wp.abs(wp.dot(g_fine - line_point, normal)) * float(stride)  # image px


@wp.kernel
def sample_descriptors(
    # in:
    desc: wp.array3d(dtype=wp.float32),
    uv: wp.array(dtype=wp.vec2),
    stride: int,
    # out:
    sampled_out: wp.array2d(dtype=wp.float32),
):
    """Bilinear descriptor at image point uv[i] (grid borders clamped), renormalised: the query of
    the backward search starts from where the forward search landed, not from a rounded cell."""
    i = wp.tid()
    gx = to_grid(uv[i][0], stride)
    gy = to_grid(uv[i][1], stride)
    x0, y0, fx, fy = bilinear_corner(gx, gy, desc.shape[1], desc.shape[0])
    sq = float(0.0)
    for k in range(desc.shape[2]):
        v = bilerp(desc[y0, x0, k], desc[y0, x0 + 1, k], desc[y0 + 1, x0, k], desc[y0 + 1, x0 + 1, k], fx, fy)
        sampled_out[i, k] = v
        sq += v * v
    scale = wp.where(sq > 1e-12, 1.0 / wp.sqrt(wp.max(sq, 1e-12)), 0.0)
    for k in range(desc.shape[2]):
        sampled_out[i, k] = sampled_out[i, k] * scale


@wp.func
def match_confidence(
    sim: float,
    fb_err: float,
    epi_dist: float,
    weights: wp.vec3,
    sigma_fb: float,
    sigma_epi: float,
    gamma0: float,
    gamma1: float,
) -> float:
    """Eq. 11-12: kappa = clip((w_sim s + w_fb rho_fb + w_epi rho_epi - gamma0) / (gamma1 - gamma0), 0, 1),
    rho = exp(-e^2 / (2 sigma^2)) of the forward-backward error and the epipolar distance."""
    rho_fb = wp.exp(-0.5 * (fb_err / sigma_fb) * (fb_err / sigma_fb))
    rho_epi = wp.exp(-0.5 * (epi_dist / sigma_epi) * (epi_dist / sigma_epi))
    score = weights[0] * sim + weights[1] * rho_fb + weights[2] * rho_epi
    return wp.clamp((score - gamma0) / (gamma1 - gamma0), 0.0, 1.0)


@wp.kernel
def score_matches(
    # in:
    ref_uv: wp.array(dtype=wp.vec2),
    fwd_uv: wp.array(dtype=wp.vec2),
    fwd_sim: wp.array(dtype=wp.float32),
    fwd_epi_dist: wp.array(dtype=wp.float32),
    bwd_uv: wp.array(dtype=wp.vec2),
    bwd_sim: wp.array(dtype=wp.float32),
    column: int,
    weights: wp.vec3,
    sigma_fb: float,
    sigma_epi: float,
    gamma0: float,
    gamma1: float,
    # out:
    match_uv_out: wp.array2d(dtype=wp.vec2d),
    confidence_out: wp.array2d(dtype=wp.float32),
):
    """Column ``column`` (one neighbour) of the match and confidence tables.  The forward-backward
    error and the epipolar distance are in image pixels: matches are refined at image resolution,
    so their consistency is judged there whatever the backbone's grid."""
    i = wp.tid()
    m = fwd_uv[i]
    match_uv_out[i, column] = wp.vec2d(wp.float64(m[0]), wp.float64(m[1]))
    confidence_out[i, column] = 0.0
    if fwd_sim[i] <= NO_MATCH or bwd_sim[i] <= NO_MATCH:
        return
    fb_err = wp.length(bwd_uv[i] - ref_uv[i])
    confidence_out[i, column] = match_confidence(
        fwd_sim[i], fb_err, fwd_epi_dist[i], weights, sigma_fb, sigma_epi, gamma0, gamma1
    )


@wp.kernel
def aggregate_confidence(
    # in:
    confidence: wp.array2d(dtype=wp.float32),
    n_neighbours: int,
    # out:
    aggregated_out: wp.array(dtype=wp.float32),
):
    """kappa_bar(p): mean confidence over the neighbours, so agreement of more views counts more."""
    i = wp.tid()
    acc = float(0.0)
    for n in range(n_neighbours):
        acc += confidence[i, n]
    aggregated_out[i] = acc / float(n_neighbours)


@wp.kernel
def apply_thinning(
    # in:
    keep: wp.array(dtype=wp.int32),
    n_neighbours: int,
    # out:
    confidence_out: wp.array2d(dtype=wp.float32),
    aggregated_out: wp.array(dtype=wp.float32),
    kept_count_out: wp.array(dtype=wp.int32),
):
    """Zero the confidences of pixels the blue-noise thinning dropped; count the matched survivors."""
    i = wp.tid()
    if keep[i] == 1:
        if aggregated_out[i] > 0.0:
            wp.atomic_add(kept_count_out, 0, 1)
        return
    aggregated_out[i] = 0.0
    for n in range(n_neighbours):
        confidence_out[i, n] = 0.0
