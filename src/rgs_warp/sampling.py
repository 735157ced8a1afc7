"""Sampling by prioritised dart throwing (``kernels/sampling.py`` explains the scheme and its
guarantees): blue-noise thinning of matches in image space (supplement §4.4, the DenseMatcher's) and
Poisson-disk subsampling of seeds in world space (§4.5, the Seeder's), and the stream compaction of
a 0/1 mask.

Both samplers are rounds looping on a device counter of undecided points: on CUDA the loop is a CUDA
graph conditional while-node (``loop_until_zero``), so the rounds run without a host round trip.
"""

from __future__ import annotations

import warp as wp

from rgs_warp.graph_cache import GraphCache, launch_key
from rgs_warp.kernels.sampling import (
    mask_indices,
    poisson_accept,
    poisson_init,
    poisson_reject,
    thinning_accept,
    thinning_init,
    thinning_reject,
)

# Confidence levels of the dart priority: finer levels follow the confidence more closely but allow
# longer chains of rounds (a chain climbs at most one level per round); 32 levels resolve Eq. 12's
# confidence to 0.03, below the spread of its inputs.
CONFIDENCE_LEVELS = 32


def loop_until_zero(condition: wp.array, body, graphs: GraphCache | None = None, key=None) -> None:
    """Run ``body()`` while ``condition[0] != 0`` (the body updates it) without a host round trip
    on CUDA: the loop is captured as a CUDA graph with a conditional while-node and launched once.
    ``wp.capture_while`` alone reads the condition back to the host before every round when no
    capture is active.  With ``graphs`` the loop's graph is kept under ``key`` (which must hold every
    address and scalar the body bakes in) and replayed by later calls instead of captured again.
    Inside an enclosing capture, or where the driver lacks conditional nodes (CUDA < 12.4), the loop is
    recorded / run as ``wp.capture_while`` does; on the CPU the condition is read from host memory at
    no cost."""
    if graphs is None:
        graphs = GraphCache(condition.device, size=1)  # captured for this call only
    if not graphs.run_while(key, condition, body):
        wp.capture_while(condition, body)


def _throw_darts(
    accept,
    accept_inputs: list,
    reject,
    reject_inputs: list,
    dim,
    state: wp.array,
    counters: wp.array,
    graphs: GraphCache | None = None,
):
    """Rounds of the ``accept`` then the ``reject`` launch over ``dim`` (``kernels/sampling.py``) until
    no point of ``state`` is undecided: ``reject`` counts the undecided ones into ``counters[0]``,
    the loop's condition, and the rounds into ``counters[1]``.  ``graphs``: the loop's graph is kept
    there (by its kernels, size and arguments) and replayed by a call with the same ones."""
    device = state.device
    counters.fill_(1)

    def one_round():
        counters[:1].zero_()
        wp.launch(accept, dim=dim, inputs=accept_inputs, outputs=[state], device=device)
        wp.launch(reject, dim=dim, inputs=reject_inputs, outputs=[state, counters], device=device)

    counters[1:2].zero_()
    key = (accept.key, reject.key, str(dim)) + launch_key([*accept_inputs, *reject_inputs, state, counters])
    # the loop condition is counters[0]: capture_while needs a one-element array (CUDA checks its size)
    loop_until_zero(counters[:1], one_round, graphs, key)


def poisson_disk_subsample(
    points: wp.array,
    radius: wp.array,
    confidence: wp.array,
    candidate: wp.array | None = None,
    cell_size: float | None = None,
    grid: wp.HashGrid | None = None,
    keep_out: wp.array | None = None,
    counters: wp.array | None = None,
    radius_max: wp.array | None = None,
    levels: int = CONFIDENCE_LEVELS,
    graphs: GraphCache | None = None,
) -> wp.array:
    """Poisson-disk subset of world points, higher confidence winning conflicts.

    points: (N,) ``wp.vec3``; radius: (N,) float32 per-point disk radius (e.g. the pixel footprint
    ``k * depth / focal``); confidence: (N,) float32 in [0, 1]; candidate: optional (N,) int32,
    0 excludes a point.  Two points conflict when closer than the larger of their radii.
    Returns keep (N,) int32, 1 for kept points: no kept pair conflicts, every candidate lies within
    max(its radius, the kept point's radius) of a kept point.

    ``cell_size`` sets the hash grid's cells (performance only; default: the largest radius, read
    back once).  ``grid`` (a ``wp.HashGrid``), ``keep_out``, ``counters`` ((2,) int32) and
    ``radius_max`` ((1,) float32) let a stage reuse its buffers; ``counters[1]`` holds the number
    of rounds afterwards.  ``graphs``: where the rounds' loop graph is kept for the next call with the
    same buffers (``GraphCache``; the grid's address stays as it is rebuilt).
    """
    device = points.device
    n = points.shape[0]
    if keep_out is None:
        keep_out = wp.empty(n, dtype=wp.int32, device=device)
    if n == 0:
        return keep_out
    if counters is None:
        counters = wp.zeros(2, dtype=wp.int32, device=device)
    if radius_max is None:
        radius_max = wp.zeros(1, dtype=wp.float32, device=device)
    if candidate is None:
        candidate = wp.ones(n, dtype=wp.int32, device=device)
    if grid is None:
        grid = wp.HashGrid(128, 128, 128, device=device)
    radius_max.zero_()
    wp.launch(poisson_init, dim=n, inputs=[radius, candidate], outputs=[keep_out, radius_max], device=device)
    if cell_size is None:
        cell_size = float(radius_max.numpy()[0]) or 1.0
    grid.build(points, cell_size)
    _throw_darts(
        poisson_accept,
        [grid.id, points, radius, confidence, levels, radius_max],
        poisson_reject,
        [grid.id, points, radius, radius_max],
        n,
        keep_out,
        counters,
        graphs,
    )
    return keep_out


def thin_blue_noise(
    confidence: wp.array,
    spacing_px: float,
    keep_out: wp.array | None = None,
    counters: wp.array | None = None,
    levels: int = CONFIDENCE_LEVELS,
) -> wp.array:
    """Blue-noise subset of the pixels of a confidence image, the most confident preferred.

    confidence: (H, W) float32 (Eq. 12; 0 = no match); spacing_px: minimum distance in pixels
    between kept pixels.  Returns keep (H, W) int32, 1 for kept pixels: no kept pair closer than
    ``spacing_px``, every pixel of positive confidence within ``spacing_px`` of a kept one.
    ``counters``: optional (2,) int32 scratch; ``counters[1]`` holds the number of rounds afterwards.
    """
    device = confidence.device
    if keep_out is None:
        keep_out = wp.empty(confidence.shape, dtype=wp.int32, device=device)
    if counters is None:
        counters = wp.zeros(2, dtype=wp.int32, device=device)
    wp.launch(thinning_init, dim=confidence.shape, inputs=[confidence], outputs=[keep_out], device=device)
    spacing_px = float(spacing_px)
    _throw_darts(
        thinning_accept,
        [confidence, spacing_px, levels],
        thinning_reject,
        [spacing_px],
        confidence.shape,
        keep_out,
        counters,
    )
    return keep_out


def compact_mask(
    keep: wp.array, indices_out: wp.array | None = None, count_out: wp.array | None = None, offsets=None
) -> tuple[wp.array, wp.array]:
    """Indices (int32, ascending, flat for 2-d masks) of the 1s of a 0/1 int32 mask and their count
    (a 1-element device array), without a host round trip; ``indices_out`` holds at least as many
    entries as the mask, ``offsets`` is optional scratch of the mask's size."""
    flat = keep.flatten()
    n = flat.shape[0]
    device = keep.device
    if indices_out is None:
        indices_out = wp.empty(n, dtype=wp.int32, device=device)
    if count_out is None:
        count_out = wp.zeros(1, dtype=wp.int32, device=device)
    if offsets is None:
        offsets = wp.empty(n, dtype=wp.int32, device=device)
    wp.utils.array_scan(flat, offsets, inclusive=False)
    wp.launch(mask_indices, dim=n, inputs=[flat, offsets], outputs=[indices_out, count_out], device=device)
    return indices_out, count_out
