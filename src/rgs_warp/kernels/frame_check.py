"""Frame check (``rgs_warp.frame_check``) of frames given as device arrays: the counts of colour pixels
that are not finite or outside [0, 1], and of depth values that are not finite, negative or valid,
reduced on the device so that a clean frame costs one small read."""

import warp as wp

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


@wp.kernel
def _frame_counts_rows(
    # in: the frame (depth read only when has_depth)
    rgb: wp.array2d(dtype=wp.vec3),
    depth: wp.array2d(dtype=wp.float32),
    has_depth: int,
    tol: float,
    # out: the C_* counts (zeroed beforehand)
    counts_out: wp.array(dtype=wp.int32),
):
    # one thread per row and one atomic per row and count, as the co-visibility counts
    y = wp.tid()
    nonfinite = int(0)
    out_of_range = int(0)
    d_nonfinite = int(0)
    d_negative = int(0)
    d_valid = int(0)
    for x in range(rgb.shape[1]):
        c = rgb[y, x]
        if not _channel_finite(c):
            nonfinite += 1
        elif not _channel_in_range(c, tol):
            out_of_range += 1
        if has_depth != 0:
            d = depth[y, x]
            if not wp.isfinite(d):
                d_nonfinite += 1
            elif d < 0.0:
                d_negative += 1
            elif d > 0.0:
                d_valid += 1
    wp.atomic_add(counts_out, C_RGB_NONFINITE, nonfinite)
    wp.atomic_add(counts_out, C_RGB_OUT_OF_RANGE, out_of_range)
    wp.atomic_add(counts_out, C_DEPTH_NONFINITE, d_nonfinite)
    wp.atomic_add(counts_out, C_DEPTH_NEGATIVE, d_negative)
    wp.atomic_add(counts_out, C_DEPTH_VALID, d_valid)


def frame_counts(rgb: wp.array2d, depth: wp.array2d, has_depth: bool, tol: float, counts_out: wp.array) -> None:
    """Writes the ``C_*`` counts of ``rgb`` (vec3) and, with ``has_depth``, ``depth`` (float32, the same
    shape; any float32 array otherwise) into ``counts_out`` (``N_COUNTS`` int32 entries)."""
    if counts_out.shape[0] != N_COUNTS:
        raise ValueError(f"counts_out needs {N_COUNTS} entries, got {counts_out.shape[0]}")
    counts_out.zero_()
    wp.launch(
        _frame_counts_rows,
        dim=rgb.shape[0],
        inputs=[rgb, depth, int(has_depth), float(tol)],
        outputs=[counts_out],
        device=rgb.device,
    )
