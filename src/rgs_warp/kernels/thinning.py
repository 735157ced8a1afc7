"""Blue-noise thinning of dense matches in image space (supplement §4.4), before triangulation.

The same prioritised dart throwing as the world-space Poisson disk (``kernels/poisson.py``, whose
priority and states it shares), on the pixel grid: pixels with positive confidence are candidates,
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

from rgs_warp.kernels.poisson import KEPT, REJECTED, UNDECIDED, dart_priority

wp.set_module_options({"enable_backward": False})


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
