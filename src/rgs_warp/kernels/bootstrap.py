"""Monocular two-view bootstrap kernels: the unconstrained descriptor search in a window (no pose
is known yet, so there is no epipolar line to search along) and the selection of distinctive,
mutually consistent matches.

Coordinates follow ``kernels/matching.py``: image pixels with centres at integers, feature pixel
(i, j) of stride s centred at image coordinates (s*j + (s-1)/2, s*i + (s-1)/2).
"""

import warp as wp

from rgs_warp.kernels.matching import NO_MATCH, parabola_peak, refine_zncc, similarity, to_grid, to_image

wp.set_module_options({"enable_backward": False})


@wp.kernel
def window_search(
    # in:
    query_desc: wp.array2d(dtype=wp.float32),
    query_uv: wp.array(dtype=wp.vec2),
    query_rgb: wp.array2d(dtype=wp.vec3),
    target_desc: wp.array3d(dtype=wp.float32),
    target_rgb: wp.array2d(dtype=wp.vec3),
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
    to sub-pixel by a parabola fit of the similarity in x and y (none on a grid border), then, with
    ``refine_radius`` > 0, at image resolution by patch ZNCC (``refine_zncc``, as the epipolar
    search does).  Writes the match (image px), its similarity and the second best (NO_MATCH where
    the window holds nothing outside the exclusion, or it was not sought); a query whose descriptor
    is (near) zero gets no match (similarity NO_MATCH, the match at the query's position)."""
    i = wp.tid()
    match_uv_out[i] = query_uv[i]
    sim_out[i] = NO_MATCH
    second_sim_out[i] = NO_MATCH
    energy = float(0.0)
    for k in range(query_desc.shape[1]):
        energy += query_desc[i, k] * query_desc[i, k]
    if energy < 0.25:  # a textureless query (the classic backbone zeroes those): nothing to find
        return
    Hf = target_desc.shape[0]
    Wf = target_desc.shape[1]
    uv = query_uv[i]
    cx = wp.clamp(int(wp.round(to_grid(uv[0], stride) + offset[0])), 0, Wf - 1)
    cy = wp.clamp(int(wp.round(to_grid(uv[1], stride) + offset[1])), 0, Hf - 1)
    x0 = wp.max(cx - radius, 0)
    x1 = wp.min(cx + radius, Wf - 1)
    y0 = wp.max(cy - radius, 0)
    y1 = wp.min(cy + radius, Hf - 1)
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
    second = float(NO_MATCH)
    if exclusion >= 0:
        for y in range(y0, y1 + 1):
            for x in range(x0, x1 + 1):
                if wp.max(wp.abs(x - bx), wp.abs(y - by)) > exclusion:
                    second = wp.max(second, similarity(query_desc, i, target_desc, y, x))
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
        match = refine_zncc(query_rgb, uv, target_rgb, match, refine_radius, patch_radius)
    match_uv_out[i] = match
    sim_out[i] = best
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
