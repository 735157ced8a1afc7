"""Bulk operations on GaussianMap fields: stream compaction for in-place removal."""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def scatter_kept(
    # in: field rows, removal flags and their exclusive prefix sum
    src: wp.array(dtype=Any),
    remove: wp.array(dtype=wp.int32),
    removed_before: wp.array(dtype=wp.int32),
    # out: compacted rows (row i moves to i - removed_before[i])
    dst_out: wp.array(dtype=Any),
):
    i = wp.tid()
    if remove[i] == 0:
        dst_out[i - removed_before[i]] = src[i]


@wp.kernel
def scatter_kept_rows(
    # in: 2D field (rows of SH coefficients), removal flags and their exclusive prefix sum
    src: wp.array2d(dtype=Any),
    remove: wp.array(dtype=wp.int32),
    removed_before: wp.array(dtype=wp.int32),
    # out: compacted rows
    dst_out: wp.array2d(dtype=Any),
):
    i, k = wp.tid()
    if remove[i] == 0:
        dst_out[i - removed_before[i], k] = src[i, k]


# The element types the package launches these with (GaussianMap fields, MapAdam's float32 moment
# rows, per-Gaussian statistics), declared so that the module compiles ahead of time like every
# other (tests/test_cuda_compile.py); any other type still compiles at its first launch.
for _dtype in (wp.float32, wp.int32, wp.vec3, wp.quat):
    wp.overload(scatter_kept, {"src": wp.array(dtype=_dtype), "dst_out": wp.array(dtype=_dtype)})
for _dtype in (wp.float32, wp.vec3):
    wp.overload(scatter_kept_rows, {"src": wp.array2d(dtype=_dtype), "dst_out": wp.array2d(dtype=_dtype)})
