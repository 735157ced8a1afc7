"""Co-visibility counting (supplement §4.3, Eq. 9): pixel visibility masks from accumulated opacity
and their intersection / union counts, reduced on the device."""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def _visibility_iou_rows(
    # in:
    alpha: wp.array2d(dtype=wp.float32),
    last_mask: wp.array2d(dtype=wp.uint8),
    alpha_threshold: wp.float32,
    # out:
    mask_out: wp.array2d(dtype=wp.uint8),
    counts_out: wp.array(dtype=wp.int32),
):
    # One thread per row, one atomic pair per row: a few hundred atomics per image instead of one
    # per pixel, and no host round trip before the decision's single 8-byte read.
    y = wp.tid()
    inter = int(0)
    union = int(0)
    visible = int(0)
    for x in range(alpha.shape[1]):
        vis = alpha[y, x] > alpha_threshold
        mask_out[y, x] = wp.uint8(1) if vis else wp.uint8(0)
        prev = last_mask[y, x] != wp.uint8(0)
        if vis and prev:
            inter += 1
        if vis or prev:
            union += 1
        if vis:
            visible += 1
    wp.atomic_add(counts_out, 0, inter)
    wp.atomic_add(counts_out, 1, union)
    wp.atomic_add(counts_out, 2, visible)


def visibility_iou(
    alpha: wp.array2d, last_mask: wp.array2d, alpha_threshold: float, mask_out: wp.array2d, counts_out: wp.array
) -> None:
    """Writes ``mask_out = alpha > alpha_threshold`` and ``counts_out = [|V ∩ V_last|, |V ∪ V_last|, |V|]``
    (``counts_out`` holds 3 entries)."""
    if counts_out.shape[0] != 3:
        raise ValueError(f"counts_out needs 3 entries, got {counts_out.shape[0]}")
    counts_out.zero_()
    wp.launch(
        _visibility_iou_rows,
        dim=alpha.shape[0],
        inputs=[alpha, last_mask, float(alpha_threshold)],
        outputs=[mask_out, counts_out],
        device=alpha.device,
    )
