"""Kernels of the monocular two-view bootstrap's matching: an unconstrained descriptor search in a
window (no pose is known yet, so there is no epipolar line to search along), the same with the
window's rows spread over threads for windows as large as the image, and the selection of
distinctive, mutually consistent matches.  Coordinates as in kernels/matching.py.
"""

import warp as wp

from rgs_warp.kernels.math import NO_MATCH, parabola_peak, refine_zncc, similarity, to_grid, to_image

wp.set_module_options({"enable_backward": False})


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
