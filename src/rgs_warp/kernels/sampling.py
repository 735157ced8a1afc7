"""Sampling by prioritised dart throwing: the world-space Poisson disk of the Seeder and the
image-space blue-noise thinning of the DenseMatcher share the priority and the states below.

Parallel Poisson-disk subsampling of seeds in world space (supplement §4.5), by rounds of
prioritised dart throwing over a ``wp.HashGrid``.

Every candidate starts undecided.  A round has two launches: an undecided point whose conflicting
neighbours (distance below the larger of the two radii) that are not rejected all have a lower
priority is kept; then every undecided point with a kept conflicting neighbour is rejected.  The
globally highest undecided point is kept in every round, so the rounds end; the result is the
greedy maximal set in priority order, hence no kept pair conflicts and every input point lies
within its own or its kept neighbour's radius of a kept point.

Both launches read neighbours' states while other threads write theirs, and this is benign: in the
first only "undecided -> kept" transitions happen and both states block a lower-priority point
alike; in the second only "undecided -> rejected" ones, and the test reads "kept".

Priority: confidence quantised to ``levels`` steps, then a bijective hash of the index.  Ties in
raw index order would chain along the raster order of the seeds (a point waits for its lower-index
neighbour, which waits for its own ...), making the rounds grow with the extent of the scene; hashed
indices make each level a random order, for which this parallel greedy maximal independent set
needs O(log N) rounds w.h.p. (Blelloch, Fineman, Shun 2012; Fischer, Noever 2018), and quantising
the confidence bounds the chains of strictly increasing levels.  Deterministic: the same input
gives the same set.

States double as the keep mask: ``UNDECIDED = -1``, ``REJECTED = 0``, ``KEPT = 1``.

Blue-noise thinning of dense matches in image space (supplement §4.4), before triangulation: the
same prioritised dart throwing on the pixel grid: pixels with positive confidence are candidates,
two pixels conflict when closer than ``spacing_px``, and the neighbourhood is the pixel window
around each pixel, so no spatial index is needed.  The kept set is the greedy maximal set in order
of quantised confidence, ties broken by a hash of the pixel index: no two kept pixels closer than
the spacing, every candidate within the spacing of a kept one, the most confident pixel of every
neighbourhood kept, and in regions of uniform confidence a random maximal Poisson-disk pattern,
which is blue noise.  (A precomputed blue-noise threshold mask modulated by confidence would be
cheaper per pixel but guarantees no minimum distance, and its confidence preference is only
statistical.)
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

UNDECIDED = wp.constant(-1)
REJECTED = wp.constant(0)
KEPT = wp.constant(1)
# lowbias32 (C. Wellons' hash prospector): a bijection of 32-bit integers with good avalanche.
_HASH_M1 = wp.constant(wp.uint32(0x7FEB352D))
_HASH_M2 = wp.constant(wp.uint32(0x846CA68B))


@wp.func
def dart_priority(confidence: wp.float32, index: int, levels: int) -> wp.int64:
    """Confidence level in the high word, a bijective hash of the index in the low word."""
    x = wp.uint32(index)
    x = x ^ (x >> wp.uint32(16))
    x = x * _HASH_M1
    x = x ^ (x >> wp.uint32(15))
    x = x * _HASH_M2
    x = x ^ (x >> wp.uint32(16))
    level = wp.int64(wp.clamp(confidence, wp.float32(0.0), wp.float32(1.0)) * wp.float32(levels))
    return level * wp.int64(4294967296) + wp.int64(x)


@wp.kernel
def poisson_init(
    # in:
    radius: wp.array(dtype=wp.float32),
    candidate: wp.array(dtype=wp.int32),
    # out:
    state_out: wp.array(dtype=wp.int32),
    radius_max_out: wp.array(dtype=wp.float32),
):
    i = wp.tid()
    if candidate[i] != 0 and radius[i] > wp.float32(0.0):
        state_out[i] = UNDECIDED
        wp.atomic_max(radius_max_out, 0, radius[i])
    else:
        state_out[i] = REJECTED


@wp.kernel
def poisson_accept(
    # in:
    grid: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    radius: wp.array(dtype=wp.float32),
    confidence: wp.array(dtype=wp.float32),
    levels: int,
    radius_max: wp.array(dtype=wp.float32),
    # out (read and written):
    state_out: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    if state_out[i] != UNDECIDED:
        return
    p = points[i]
    r = radius[i]
    priority = dart_priority(confidence[i], i, levels)
    # A neighbour j conflicts within max(r_i, r_j), so the query must reach the largest radius.
    for j in wp.hash_grid_query(grid, p, wp.max(r, radius_max[0])):
        if j != i and state_out[j] != REJECTED:
            if wp.length(points[j] - p) < wp.max(r, radius[j]):
                if dart_priority(confidence[j], j, levels) > priority:
                    return
    state_out[i] = KEPT


@wp.kernel
def poisson_reject(
    # in:
    grid: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    radius: wp.array(dtype=wp.float32),
    radius_max: wp.array(dtype=wp.float32),
    # out (read and written):
    state_out: wp.array(dtype=wp.int32),
    undecided_rounds_out: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    if i == 0:
        wp.atomic_add(undecided_rounds_out, 1, 1)
    if state_out[i] != UNDECIDED:
        return
    p = points[i]
    r = radius[i]
    for j in wp.hash_grid_query(grid, p, wp.max(r, radius_max[0])):
        if state_out[j] == KEPT:
            if wp.length(points[j] - p) < wp.max(r, radius[j]):
                state_out[i] = REJECTED
                return
    wp.atomic_add(undecided_rounds_out, 0, 1)


@wp.kernel
def mask_indices(
    # in:
    keep: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    # out:
    indices_out: wp.array(dtype=wp.int32),
    count_out: wp.array(dtype=wp.int32),
):
    """Stream compaction of a 0/1 mask after an exclusive scan of it."""
    i = wp.tid()
    if keep[i] == 1:
        indices_out[offsets[i]] = i
    if i == keep.shape[0] - 1:
        count_out[0] = offsets[i] + keep[i]


# ---- image-space thinning -----------------------------------------------------------------------
@wp.kernel
def thinning_init(
    # in:
    confidence: wp.array2d(dtype=wp.float32),
    # out:
    state_out: wp.array2d(dtype=wp.int32),
):
    y, x = wp.tid()
    state_out[y, x] = wp.where(confidence[y, x] > wp.float32(0.0), UNDECIDED, REJECTED)


@wp.kernel
def thinning_accept(
    # in:
    confidence: wp.array2d(dtype=wp.float32),
    spacing_px: wp.float32,
    levels: int,
    # out (read and written):
    state_out: wp.array2d(dtype=wp.int32),
):
    y, x = wp.tid()
    if state_out[y, x] != UNDECIDED:
        return
    H = confidence.shape[0]
    W = confidence.shape[1]
    reach = int(wp.ceil(spacing_px)) - 1
    priority = dart_priority(confidence[y, x], y * W + x, levels)
    for yy in range(wp.max(y - reach, 0), wp.min(y + reach + 1, H)):
        for xx in range(wp.max(x - reach, 0), wp.min(x + reach + 1, W)):
            dy = wp.float32(yy - y)
            dx = wp.float32(xx - x)
            if dx * dx + dy * dy < spacing_px * spacing_px and (yy != y or xx != x):
                if state_out[yy, xx] != REJECTED:
                    if dart_priority(confidence[yy, xx], yy * W + xx, levels) > priority:
                        return
    state_out[y, x] = KEPT


@wp.kernel
def thinning_reject(
    # in:
    spacing_px: wp.float32,
    # out (read and written):
    state_out: wp.array2d(dtype=wp.int32),
    undecided_rounds_out: wp.array(dtype=wp.int32),
):
    y, x = wp.tid()
    if y == 0 and x == 0:
        wp.atomic_add(undecided_rounds_out, 1, 1)
    if state_out[y, x] != UNDECIDED:
        return
    H = state_out.shape[0]
    W = state_out.shape[1]
    reach = int(wp.ceil(spacing_px)) - 1
    for yy in range(wp.max(y - reach, 0), wp.min(y + reach + 1, H)):
        for xx in range(wp.max(x - reach, 0), wp.min(x + reach + 1, W)):
            dy = wp.float32(yy - y)
            dx = wp.float32(xx - x)
            if dx * dx + dy * dy < spacing_px * spacing_px and state_out[yy, xx] == KEPT:
                state_out[y, x] = REJECTED
                return
    wp.atomic_add(undecided_rounds_out, 0, 1)
