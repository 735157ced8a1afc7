"""The GaussianMap's own kernel: stream compaction of its columns for ``GaussianMap.remove``."""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def compact_rows(
    # in: a column viewed as (rows, entries per row), removal flags and their exclusive prefix sum
    src: wp.array2d(dtype=Any),
    remove: wp.array(dtype=wp.int32),
    removed_before: wp.array(dtype=wp.int32),
    # out: the kept rows, in order (row i moves to i - removed_before[i])
    dst_out: wp.array2d(dtype=Any),
):
    i, k = wp.tid()
    if remove[i] == 0:
        dst_out[i - removed_before[i], k] = src[i, k]


# the column types of the map (parameters, optimiser moments, statistics), compiled ahead of use
for _dtype in (wp.float32, wp.int32, wp.vec3, wp.quat):
    wp.overload(compact_rows, {"src": wp.array2d(dtype=_dtype), "dst_out": wp.array2d(dtype=_dtype)})
