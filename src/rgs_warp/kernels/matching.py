"""Dense matching kernels (supplement §4.4): epipolar-constrained descriptor search with sub-pixel
refinement, descriptor sampling for the backward search, the score and confidence of Eq. 11-12,
and the aggregation across neighbours.

Coordinates: image pixels follow ``types.py`` (pixel centres at integers); feature pixel (i, j) of
stride s is centred at image coordinates (s*j + (s-1)/2, s*i + (s-1)/2).  Searches run on the
feature grid; positions they return are in image pixels.
"""

import warp as wp

from rgs_warp.config import MAX_PATCH_RADIUS
from rgs_warp.kernels.math import bilerp, bilinear_corner, grey_level, grey_sample, sample_depth

wp.set_module_options({"enable_backward": False})

# Similarity of a query without a match (its segment leaves the image, or it was skipped).
NO_MATCH = wp.constant(-2.0)
MIN_Z_M = wp.constant(0.05)  # points closer than this to a camera are not searched for
# A ZNCC query patch, read once per query (``query_patch``): patch radii up to MAX_PATCH_RADIUS
patch_values = wp.types.vector(length=(2 * MAX_PATCH_RADIUS + 1) ** 2, dtype=wp.float32)


@wp.func
def to_grid(u: float, stride: int) -> float:
    return (u - 0.5 * float(stride - 1)) / float(stride)


@wp.func
def to_image(g: float, stride: int) -> float:
    return g * float(stride) + 0.5 * float(stride - 1)


@wp.func
def similarity(
    query: wp.array2d(dtype=wp.float32), row: int, target: wp.array3d(dtype=wp.float32), y: int, x: int
) -> float:
    """Eq. 10: inner product of L2-normalised descriptors."""
    s = float(0.0)
    for k in range(query.shape[1]):
        s += query[row, k] * target[y, x, k]
    return s


@wp.func
def parabola_peak(s_minus: float, s0: float, s_plus: float) -> float:
    """Offset in [-0.5, 0.5] of the vertex of the parabola through (-1, s-), (0, s0), (1, s+)."""
    curvature = s_minus - 2.0 * s0 + s_plus
    if curvature >= 0.0:
        return 0.0
    return wp.clamp(0.5 * (s_minus - s_plus) / curvature, -0.5, 0.5)


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
def query_patch(grey: wp.array2d(dtype=wp.float32), q: wp.vec2, radius: int):
    """The (2r+1)^2 grey patch at q (bilinear, row by row; r <= MAX_PATCH_RADIUS), its sum and n
    times its variance: what ``patch_zncc`` needs of the query, read once for all its shifts."""
    a = patch_values()
    sa = float(0.0)
    saa = float(0.0)
    k = int(0)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            v = grey_sample(grey, q[0] + float(dx), q[1] + float(dy))
            a[k] = v
            sa += v
            saa += v * v
            k += 1
    n = float((2 * radius + 1) * (2 * radius + 1))
    return a, sa, saa - sa * sa / n


@wp.func
def patch_zncc(
    a: patch_values,
    sa: float,
    va: float,
    target_grey: wp.array2d(dtype=wp.float32),
    t: wp.vec2,
    radius: int,
) -> float:
    """Zero-mean normalised cross-correlation of the query patch (``query_patch``: values ``a``,
    sum ``sa``, n times its variance ``va``) with the grey (2r+1)^2 patch at t (bilinear); NO_MATCH
    when either patch is flat (below 1e-4 grey-level variance: JPEG noise)."""
    sb = float(0.0)
    sbb = float(0.0)
    sab = float(0.0)
    k = int(0)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            b = grey_sample(target_grey, t[0] + float(dx), t[1] + float(dy))
            sb += b
            sbb += b * b
            sab += a[k] * b
            k += 1
    n = float((2 * radius + 1) * (2 * radius + 1))
    vb = sbb - sb * sb / n
    if va < 1e-4 * n or vb < 1e-4 * n:
        return NO_MATCH
    return (sab - sa * sb / n) / wp.sqrt(va * vb)


@wp.func
def project(K: wp.vec4, X: wp.vec3) -> wp.vec2:
    return wp.vec2(K[0] * X[0] / X[2] + K[2], K[1] * X[1] / X[2] + K[3])


@wp.func
def refine_zncc(
    query_grey: wp.array2d(dtype=wp.float32),
    q: wp.vec2,
    target_grey: wp.array2d(dtype=wp.float32),
    coarse: wp.vec2,
    refine_radius: int,
    patch_radius: int,
) -> wp.vec2:
    """Image-resolution refinement of a match around ``coarse`` by patch ZNCC (see epipolar_search)
    on the grey images (``grey_image``)."""
    a, sa, va = query_patch(query_grey, q, patch_radius)
    if va < 1e-4 * float((2 * patch_radius + 1) * (2 * patch_radius + 1)):
        return coarse  # a flat query patch: no shift correlates
    best = float(NO_MATCH)
    bx = int(0)
    by = int(0)
    for dy in range(-refine_radius, refine_radius + 1):
        for dx in range(-refine_radius, refine_radius + 1):
            c = patch_zncc(a, sa, va, target_grey, coarse + wp.vec2(float(dx), float(dy)), patch_radius)
            if c > best:
                best = c
                bx = dx
                by = dy
    if best <= NO_MATCH:
        return coarse
    off_x = float(0.0)
    off_y = float(0.0)
    r = patch_radius
    if wp.abs(bx) < refine_radius:
        left = patch_zncc(a, sa, va, target_grey, coarse + wp.vec2(float(bx - 1), float(by)), r)
        right = patch_zncc(a, sa, va, target_grey, coarse + wp.vec2(float(bx + 1), float(by)), r)
        off_x = parabola_peak(left, best, right)
    if wp.abs(by) < refine_radius:
        up = patch_zncc(a, sa, va, target_grey, coarse + wp.vec2(float(bx), float(by - 1)), r)
        down = patch_zncc(a, sa, va, target_grey, coarse + wp.vec2(float(bx), float(by + 1)), r)
        off_y = parabola_peak(up, best, down)
    return coarse + wp.vec2(float(bx) + off_x, float(by) + off_y)


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


# ---- the monocular two-view bootstrap: an unconstrained search in a window (no pose is known yet, so
# there is no epipolar line to search along) and the selection of distinctive, mutually consistent
# matches ------------------------------------------------------------------------------------------
@wp.func
def search_bounds(uv: wp.vec2, stride: int, offset: wp.vec2, radius: int, Hf: int, Wf: int):
    """The window of ``window_search``: the cell of image point ``uv`` moved by ``offset`` (feature
    px), clamped to the grid, and the rows / columns within +/- ``radius`` of it: (cx, cy, x0, x1, y0,
    y1)."""
    cx = wp.clamp(int(wp.round(to_grid(uv[0], stride) + offset[0])), 0, Wf - 1)
    cy = wp.clamp(int(wp.round(to_grid(uv[1], stride) + offset[1])), 0, Hf - 1)
    return (
        cx,
        cy,
        wp.max(cx - radius, 0),
        wp.min(cx + radius, Wf - 1),
        wp.max(cy - radius, 0),
        wp.min(cy + radius, Hf - 1),
    )


@wp.func
def textureless(query_desc: wp.array2d(dtype=wp.float32), i: int) -> bool:
    """A (near) zero descriptor: the classic backbone zeroes those of textureless cells."""
    energy = float(0.0)
    for k in range(query_desc.shape[1]):
        energy += query_desc[i, k] * query_desc[i, k]
    return energy < 0.25


@wp.func
def best_in_rows(
    query_desc: wp.array2d(dtype=wp.float32),
    i: int,
    target_desc: wp.array3d(dtype=wp.float32),
    y0: int,
    y1: int,
    x0: int,
    x1: int,
    cx: int,
    cy: int,
):
    """The most similar cell in rows y0..y1, columns x0..x1, the first in row-major order on ties:
    (similarity, x, y); (NO_MATCH, cx, cy) for no rows."""
    best = float(NO_MATCH)
    bx = int(cx)
    by = int(cy)
    for y in range(y0, y1 + 1):
        for x in range(x0, x1 + 1):
            s = similarity(query_desc, i, target_desc, y, x)
            if s > best:
                best = s
                bx = x
                by = y
    return best, bx, by


@wp.func
def second_in_rows(
    query_desc: wp.array2d(dtype=wp.float32),
    i: int,
    target_desc: wp.array3d(dtype=wp.float32),
    y0: int,
    y1: int,
    x0: int,
    x1: int,
    bx: int,
    by: int,
    exclusion: int,
) -> float:
    """The best similarity in rows y0..y1, columns x0..x1 outside +/- ``exclusion`` cells of (bx, by)."""
    second = float(NO_MATCH)
    for y in range(y0, y1 + 1):
        for x in range(x0, x1 + 1):
            if wp.max(wp.abs(x - bx), wp.abs(y - by)) > exclusion:
                second = wp.max(second, similarity(query_desc, i, target_desc, y, x))
    return second


@wp.func
def refined_match(
    query_desc: wp.array2d(dtype=wp.float32),
    i: int,
    uv: wp.vec2,
    query_grey: wp.array2d(dtype=wp.float32),
    target_desc: wp.array3d(dtype=wp.float32),
    target_grey: wp.array2d(dtype=wp.float32),
    stride: int,
    best: float,
    bx: int,
    by: int,
    refine_radius: int,
    patch_radius: int,
) -> wp.vec2:
    """The best cell (bx, by) to sub-pixel: a parabola of the similarity in x and y (none on a grid
    border), then, with ``refine_radius`` > 0, patch ZNCC at image resolution (``refine_zncc``)."""
    Hf = target_desc.shape[0]
    Wf = target_desc.shape[1]
    off_x = float(0.0)
    off_y = float(0.0)
    if bx > 0 and bx < Wf - 1:
        left = similarity(query_desc, i, target_desc, by, bx - 1)
        right = similarity(query_desc, i, target_desc, by, bx + 1)
        off_x = parabola_peak(left, best, right)
    if by > 0 and by < Hf - 1:
        up = similarity(query_desc, i, target_desc, by - 1, bx)
        down = similarity(query_desc, i, target_desc, by + 1, bx)
        off_y = parabola_peak(up, best, down)
    match = wp.vec2(to_image(float(bx) + off_x, stride), to_image(float(by) + off_y, stride))
    if refine_radius > 0:
        match = refine_zncc(query_grey, uv, target_grey, match, refine_radius, patch_radius)
    return match


@wp.kernel
def window_search(
    # in:
    query_desc: wp.array2d(dtype=wp.float32),
    query_uv: wp.array(dtype=wp.vec2),
    query_grey: wp.array2d(dtype=wp.float32),
    target_desc: wp.array3d(dtype=wp.float32),
    target_grey: wp.array2d(dtype=wp.float32),
    stride: int,
    offset: wp.vec2,
    radius: int,
    exclusion: int,
    refine_radius: int,
    patch_radius: int,
    # out:
    match_uv_out: wp.array(dtype=wp.vec2),
    sim_out: wp.array(dtype=wp.float32),
    second_sim_out: wp.array(dtype=wp.float32),
):
    """For query i (descriptor row i, at image point query_uv[i]), the most similar target cell
    (Eq. 10) within +/- ``radius`` feature px of the query's own cell moved by ``offset`` (feature
    px: the expected image motion), and, when ``exclusion`` >= 0, the best similarity outside
    +/- ``exclusion`` cells of it (the second best for the ratio test: the cells next to the best
    see almost the same patch, so they say nothing about ambiguity).  The match is refined
    to sub-pixel (``refined_match``).  Writes the match (image px), its similarity and the second
    best (NO_MATCH where the window holds nothing outside the exclusion, or it was not sought); a
    query whose descriptor is (near) zero gets no match (similarity NO_MATCH, the match at the
    query's position).  ``window_search_rows`` + ``window_search_finish`` do the same with the
    window's rows spread over threads (a window as large as the image)."""
    i = wp.tid()
    match_uv_out[i] = query_uv[i]
    sim_out[i] = NO_MATCH
    second_sim_out[i] = NO_MATCH
    if textureless(query_desc, i):
        return
    uv = query_uv[i]
    cx, cy, x0, x1, y0, y1 = search_bounds(uv, stride, offset, radius, target_desc.shape[0], target_desc.shape[1])
    best, bx, by = best_in_rows(query_desc, i, target_desc, y0, y1, x0, x1, cx, cy)
    second = float(NO_MATCH)
    if exclusion >= 0:
        second = second_in_rows(query_desc, i, target_desc, y0, y1, x0, x1, bx, by, exclusion)
    match_uv_out[i] = refined_match(
        query_desc, i, uv, query_grey, target_desc, target_grey, stride, best, bx, by, refine_radius, patch_radius
    )
    sim_out[i] = best
    second_sim_out[i] = second


@wp.func
def band_rows(y0: int, y1: int, band: int, n_bands: int):
    """Rows of band ``band`` of ``n_bands`` contiguous bands of y0..y1 (empty: first > last)."""
    per = (y1 - y0 + n_bands) // n_bands
    lo = y0 + band * per
    return lo, wp.min(lo + per - 1, y1)


@wp.kernel
def window_search_rows(
    # in:
    query_desc: wp.array2d(dtype=wp.float32),
    query_uv: wp.array(dtype=wp.vec2),
    target_desc: wp.array3d(dtype=wp.float32),
    stride: int,
    offset: wp.vec2,
    radius: int,
    exclusion: int,
    # in (second pass) / out (first pass): the best cell of each query, (x, y), and its similarity
    best_xy: wp.array(dtype=wp.vec2i),
    # out: per query and band, the best similarity and its cell (first pass) or the second best
    # (second pass, ``exclusion`` >= 0 and ``best_xy`` given)
    band_sim: wp.array2d(dtype=wp.float32),
    band_xy: wp.array2d(dtype=wp.vec2i),
    second_pass: int,
):
    """``window_search``'s two scans of query i's window, its rows split into ``band_sim.shape[1]``
    bands, one thread each: the first pass finds each band's best cell, the second (after
    ``window_search_best`` reduced them into ``best_xy``) each band's best outside the exclusion."""
    i, b = wp.tid()
    n_bands = band_sim.shape[1]
    band_sim[i, b] = NO_MATCH
    if textureless(query_desc, i):
        return
    cx, cy, x0, x1, y0, y1 = search_bounds(
        query_uv[i], stride, offset, radius, target_desc.shape[0], target_desc.shape[1]
    )
    lo, hi = band_rows(y0, y1, b, n_bands)
    if second_pass == 0:
        best, bx, by = best_in_rows(query_desc, i, target_desc, lo, hi, x0, x1, cx, cy)
        band_sim[i, b] = best
        band_xy[i, b] = wp.vec2i(bx, by)
    else:
        xy = best_xy[i]
        band_sim[i, b] = second_in_rows(query_desc, i, target_desc, lo, hi, x0, x1, xy[0], xy[1], exclusion)


@wp.kernel
def window_search_best(
    # in:
    query_uv: wp.array(dtype=wp.vec2),
    target_desc: wp.array3d(dtype=wp.float32),
    stride: int,
    offset: wp.vec2,
    radius: int,
    band_sim: wp.array2d(dtype=wp.float32),
    band_xy: wp.array2d(dtype=wp.vec2i),
    # out:
    best_xy: wp.array(dtype=wp.vec2i),
    sim_out: wp.array(dtype=wp.float32),
):
    """The first pass's bands reduced in row order (the first best on ties, as one scan finds it)."""
    i = wp.tid()
    cx, cy, x0, x1, y0, y1 = search_bounds(
        query_uv[i], stride, offset, radius, target_desc.shape[0], target_desc.shape[1]
    )
    best = float(NO_MATCH)
    xy = wp.vec2i(cx, cy)
    for b in range(band_sim.shape[1]):
        if band_sim[i, b] > best:
            best = band_sim[i, b]
            xy = band_xy[i, b]
    best_xy[i] = xy
    sim_out[i] = best


@wp.kernel
def window_search_finish(
    # in:
    query_desc: wp.array2d(dtype=wp.float32),
    query_uv: wp.array(dtype=wp.vec2),
    query_grey: wp.array2d(dtype=wp.float32),
    target_desc: wp.array3d(dtype=wp.float32),
    target_grey: wp.array2d(dtype=wp.float32),
    stride: int,
    best_xy: wp.array(dtype=wp.vec2i),
    band_sim: wp.array2d(dtype=wp.float32),
    exclusion: int,
    refine_radius: int,
    patch_radius: int,
    # in: the best similarity (``window_search_best``); out: as window_search's
    sim_out: wp.array(dtype=wp.float32),
    # out:
    match_uv_out: wp.array(dtype=wp.vec2),
    second_sim_out: wp.array(dtype=wp.float32),
):
    """``window_search``'s outputs from the banded passes: the second best over the second pass's
    bands, the match refined (``refined_match``)."""
    i = wp.tid()
    uv = query_uv[i]
    match_uv_out[i] = uv
    second_sim_out[i] = NO_MATCH
    if textureless(query_desc, i):
        sim_out[i] = NO_MATCH
        return
    second = float(NO_MATCH)
    if exclusion >= 0:
        for b in range(band_sim.shape[1]):
            second = wp.max(second, band_sim[i, b])
    xy = best_xy[i]
    match_uv_out[i] = refined_match(
        query_desc,
        i,
        uv,
        query_grey,
        target_desc,
        target_grey,
        stride,
        sim_out[i],
        xy[0],
        xy[1],
        refine_radius,
        patch_radius,
    )
    second_sim_out[i] = second


@wp.func
def descriptor_distance(sim: float) -> float:
    """Euclidean distance of two unit descriptors of inner product ``sim``."""
    return wp.sqrt(wp.max(2.0 - 2.0 * sim, 0.0))


@wp.kernel
def select_matches(
    # in:
    ref_uv: wp.array(dtype=wp.vec2),
    fwd_uv: wp.array(dtype=wp.vec2),
    fwd_sim: wp.array(dtype=wp.float32),
    fwd_second_sim: wp.array(dtype=wp.float32),
    bwd_uv: wp.array(dtype=wp.vec2),
    min_similarity: float,
    max_ratio: float,
    max_fb_px: float,
    # out:
    fb_err_out: wp.array(dtype=wp.float32),
    valid_out: wp.array(dtype=wp.int32),
):
    """A forward match is kept when it is similar enough, distinctive (Lowe's ratio of descriptor
    distances, best / second best, below ``max_ratio``) and mutual: the backward search from it
    lands within ``max_fb_px`` image px of the query."""
    i = wp.tid()
    fb_err = wp.length(bwd_uv[i] - ref_uv[i])
    fb_err_out[i] = fb_err
    sim = fwd_sim[i]
    distinct = descriptor_distance(sim) < max_ratio * descriptor_distance(fwd_second_sim[i])
    valid_out[i] = wp.where(sim >= min_similarity and distinct and fb_err <= max_fb_px, 1, 0)
