"""Frame check (``rgs_warp.frame_check``) of frames given as device arrays: the counts of colour pixels
that are not finite or outside [0, 1], and of depth values that are not finite, negative or valid,
reduced on the device so that a clean frame costs one small read."""

import warp as wp

from rgs_warp.kernels.math import REDUCE_BLOCK, block_sum, reduce_blocks

wp.set_module_options({"enable_backward": False})

# columns of counts_out
C_RGB_NONFINITE = 0  # pixels with a channel that is not finite
C_RGB_OUT_OF_RANGE = 1  # pixels with a finite channel outside [-tol, 1 + tol]
C_DEPTH_NONFINITE = 2
C_DEPTH_NEGATIVE = 3
C_DEPTH_VALID = 4  # finite and > 0
N_COUNTS = 5


@wp.func
def _channel_finite(v: wp.vec3):
    return wp.isfinite(v[0]) and wp.isfinite(v[1]) and wp.isfinite(v[2])


@wp.func
def _channel_in_range(v: wp.vec3, tol: float):
    lo = wp.min(wp.min(v[0], v[1]), v[2])
    hi = wp.max(wp.max(v[0], v[1]), v[2])
    return lo >= -tol and hi <= 1.0 + tol


vec5i = wp.types.vector(length=N_COUNTS, dtype=wp.int32)


@wp.kernel
def _frame_counts_blocks(
    # in: the frame (depth read only when has_depth)
    rgb: wp.array2d(dtype=wp.vec3),
    depth: wp.array2d(dtype=wp.float32),
    has_depth: int,
    tol: float,
    # out: the C_* counts (zeroed beforehand)
    counts_out: wp.array(dtype=wp.int32),
):
    # one thread per pixel, the counts summed over the block and added with one atomic per block and
    # count, as the co-visibility counts
    block, lane = wp.tid()
    i = block * REDUCE_BLOCK + lane
    width = rgb.shape[1]
    c = vec5i()
    if i < rgb.shape[0] * width:
        y = i // width
        x = i - y * width
        v = rgb[y, x]
        if not _channel_finite(v):
            c[C_RGB_NONFINITE] = 1
        elif not _channel_in_range(v, tol):
            c[C_RGB_OUT_OF_RANGE] = 1
        if has_depth != 0:
            d = depth[y, x]
            if not wp.isfinite(d):
                c[C_DEPTH_NONFINITE] = 1
            elif d < 0.0:
                c[C_DEPTH_NEGATIVE] = 1
            elif d > 0.0:
                c[C_DEPTH_VALID] = 1
    total = block_sum(c)
    if lane == 0:
        for k in range(N_COUNTS):
            wp.atomic_add(counts_out, k, total[k])


def frame_counts(rgb: wp.array2d, depth: wp.array2d, has_depth: bool, tol: float, counts_out: wp.array) -> None:
    """Writes the ``C_*`` counts of ``rgb`` (vec3) and, with ``has_depth``, ``depth`` (float32, the same
    shape; any float32 array otherwise) into ``counts_out`` (``N_COUNTS`` int32 entries)."""
    if counts_out.shape[0] != N_COUNTS:
        raise ValueError(f"counts_out needs {N_COUNTS} entries, got {counts_out.shape[0]}")
    counts_out.zero_()
    wp.launch_tiled(
        _frame_counts_blocks,
        dim=[reduce_blocks(rgb.shape[0] * rgb.shape[1])],
        inputs=[rgb, depth, int(has_depth), float(tol)],
        outputs=[counts_out],
        block_dim=REDUCE_BLOCK,
        device=rgb.device,
    )
