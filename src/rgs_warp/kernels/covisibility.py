"""Co-visibility counting (supplement §4.3, Eq. 9): pixel visibility masks from accumulated opacity
and their intersection / union counts, and the reprojected variant (``reprojected_iou``): one thread
per pixel, the counts summed per block on the device."""

import warp as wp

from rgs_warp.kernels.math import REDUCE_BLOCK, block_sum, reduce_blocks

wp.set_module_options({"enable_backward": False})


@wp.kernel
def _visibility_iou_blocks(
    # in:
    alpha: wp.array2d(dtype=wp.float32),
    last_mask: wp.array2d(dtype=wp.uint8),
    alpha_threshold: wp.float32,
    # out:
    mask_out: wp.array2d(dtype=wp.uint8),
    counts_out: wp.array(dtype=wp.int32),
):
    # One thread per pixel, the counts summed over the block and added with one atomic per block
    # and count: no host round trip before the decision's single 12-byte read.
    block, lane = wp.tid()
    i = block * REDUCE_BLOCK + lane
    width = alpha.shape[1]
    c = wp.vec3i(0, 0, 0)
    if i < alpha.shape[0] * width:
        y = i // width
        x = i - y * width
        vis = alpha[y, x] > alpha_threshold
        mask_out[y, x] = wp.uint8(1) if vis else wp.uint8(0)
        prev = last_mask[y, x] != wp.uint8(0)
        c = wp.vec3i(wp.where(vis and prev, 1, 0), wp.where(vis or prev, 1, 0), wp.where(vis, 1, 0))
    total = block_sum(c)
    if lane == 0:
        for k in range(3):
            wp.atomic_add(counts_out, k, total[k])


def visibility_iou(
    alpha: wp.array2d, last_mask: wp.array2d, alpha_threshold: float, mask_out: wp.array2d, counts_out: wp.array
) -> None:
    """Writes ``mask_out = alpha > alpha_threshold`` and ``counts_out = [|V ∩ V_last|, |V ∪ V_last|, |V|]``
    (``counts_out`` holds 3 entries)."""
    if counts_out.shape[0] != 3:
        raise ValueError(f"counts_out needs 3 entries, got {counts_out.shape[0]}")
    counts_out.zero_()
    wp.launch_tiled(
        _visibility_iou_blocks,
        dim=[reduce_blocks(alpha.shape[0] * alpha.shape[1])],
        inputs=[alpha, last_mask, float(alpha_threshold)],
        outputs=[mask_out, counts_out],
        block_dim=REDUCE_BLOCK,
        device=alpha.device,
    )


@wp.kernel
def _reprojected_iou_blocks(
    # in: the frame's render (accumulated opacity, expected depth not normalised by it)
    alpha: wp.array2d(dtype=wp.float32),
    depth: wp.array2d(dtype=wp.float32),
    # in: the reference keyframe's mask and depth (normalised), from an earlier call's outputs
    last_mask: wp.array2d(dtype=wp.uint8),
    last_depth: wp.array2d(dtype=wp.float32),
    alpha_threshold: wp.float32,
    # in: the frame's camera in the reference's (X_ref = R X + t), intrinsics, relative depth tolerance
    R: wp.mat33,
    t: wp.vec3,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    depth_tol: float,
    # out:
    mask_out: wp.array2d(dtype=wp.uint8),
    depth_out: wp.array2d(dtype=wp.float32),
    counts_out: wp.array(dtype=wp.int32),
):
    block, lane = wp.tid()
    i = block * REDUCE_BLOCK + lane
    height = alpha.shape[0]
    width = alpha.shape[1]
    c = wp.vec3i(0, 0, 0)  # shared, visible, visible in the reference
    if i < height * width:
        y = i // width
        x = i - y * width
        if last_mask[y, x] != wp.uint8(0):
            c[2] = 1
        a = alpha[y, x]
        z = float(0.0)
        if a > alpha_threshold:
            c[1] = 1
            z = depth[y, x] / a
            X = wp.vec3((float(x) - cx) / fx * z, (float(y) - cy) / fy * z, z)
            Xr = R * X + t
            if Xr[2] > 1.0e-6:
                # pixel centres at integer coordinates, as the rasterizer's
                u = int(wp.floor(fx * Xr[0] / Xr[2] + cx + 0.5))
                v = int(wp.floor(fy * Xr[1] / Xr[2] + cy + 0.5))
                if u >= 0 and u < width and v >= 0 and v < height:
                    if last_mask[v, u] != wp.uint8(0):
                        zr = last_depth[v, u]
                        if wp.abs(Xr[2] - zr) <= depth_tol * zr:
                            c[0] = 1
        mask_out[y, x] = wp.uint8(1) if a > alpha_threshold else wp.uint8(0)
        depth_out[y, x] = z
    total = block_sum(c)
    if lane == 0:
        for k in range(3):
            wp.atomic_add(counts_out, k, total[k])


def reprojected_iou(
    alpha: wp.array2d,
    depth: wp.array2d,
    last_mask: wp.array2d,
    last_depth: wp.array2d,
    alpha_threshold: float,
    T_ref_cur,
    intrinsics: tuple[float, float, float, float],
    depth_tol: float,
    mask_out: wp.array2d,
    depth_out: wp.array2d,
    counts_out: wp.array,
) -> None:
    """Co-visibility of the surface two views see (not of their pixel grids).  Writes ``mask_out =
    alpha > alpha_threshold``, ``depth_out`` its depth (``depth / alpha``; 0 where not visible) and
    ``counts_out = [S, |V|, |V_ref|]``: S counts the visible pixels whose point (lifted with that depth,
    moved by ``T_ref_cur``, the 4x4 transform from this camera to the reference's) lands on a visible
    pixel of the reference whose depth agrees within ``depth_tol`` (relative).  IoU = S / (|V| +
    |V_ref| - S): 1 for the same view, falling as the surface in view changes."""
    if counts_out.shape[0] != 3:
        raise ValueError(f"counts_out needs 3 entries, got {counts_out.shape[0]}")
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    counts_out.zero_()
    wp.launch_tiled(
        _reprojected_iou_blocks,
        dim=[reduce_blocks(alpha.shape[0] * alpha.shape[1])],
        inputs=[
            alpha,
            depth,
            last_mask,
            last_depth,
            float(alpha_threshold),
            wp.mat33(*[float(v) for v in T_ref_cur[:3, :3].ravel()]),
            wp.vec3(*[float(v) for v in T_ref_cur[:3, 3]]),
            fx,
            fy,
            cx,
            cy,
            float(depth_tol),
        ],
        outputs=[mask_out, depth_out, counts_out],
        block_dim=REDUCE_BLOCK,
        device=alpha.device,
    )
