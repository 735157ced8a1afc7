"""Captured graphs of a stage's fixed launch sequences, replayed instead of launched again.

A stage that runs the same launches on the same arrays call after call (a frame fill's 64 depth
extrapolation steps, a Poisson-disk sampling's loop of rounds) pays Warp's Python launch cost for each
of them every time: about 1.3 ms of a 1200x680 frame fill on an H100 machine for the extrapolation
alone.  ``GraphCache.run`` captures the launches once per key and replays the graph after.  The key
must hold everything the launches bake in: array addresses, sizes, scalar arguments (``launch_key``
builds one from launch arguments); the arrays' contents may change between replays.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Sequence

import warp as wp

__all__ = ["GraphCache", "launch_key"]


def launch_key(args: Sequence) -> tuple:
    """A hashable key of launch arguments: an array by its address, shape and type, a scalar by value."""
    out = []
    for a in args:
        if isinstance(a, wp.array):
            out.append(("array", a.ptr, a.shape, a.dtype))
        elif isinstance(a, (int, float, bool, str)):
            out.append(a)
        else:
            out.append((type(a).__name__, repr(a)))
    return tuple(out)


class GraphCache:
    """At most ``size`` captured graphs on ``device``, by key (the least recently captured goes first).
    ``enabled`` (default: on CUDA devices): off, ``run`` just calls the body.  Warp's CPU graphs let the
    tests capture on the CPU; the conditional loops of ``run_while`` need CUDA and run eagerly elsewhere."""

    def __init__(self, device, size: int = 8, enabled: bool | None = None):
        self.device = wp.get_device(device)
        self.size = size
        self.enabled = self.device.is_cuda if enabled is None else bool(enabled)
        self._graphs: dict[Hashable, object] = {}
        self.counts = {"captured": 0, "replayed": 0}

    def run(self, key: Hashable, body: Callable[[], None]) -> None:
        """``body()``'s launches: replayed from the graph captured under ``key``, or captured now."""
        if not self.enabled or self.device.is_capturing:
            body()
            return
        graph = self._graphs.get(key)
        if graph is None:
            with wp.ScopedCapture(device=self.device) as capture:
                body()
            graph = self._keep(key, capture.graph)
        else:
            self.counts["replayed"] += 1
        wp.capture_launch(graph)

    def run_while(self, key: Hashable, condition: wp.array, body: Callable[[], None]) -> bool:
        """``body()`` while ``condition[0] != 0`` as one graph with a conditional while-node (captured
        under ``key`` once, replayed after); False, nothing run, where that is not available (not CUDA,
        or a driver without conditional nodes): the caller loops itself."""
        dev = self.device
        if not (self.enabled and dev.is_cuda and not dev.is_capturing and wp.is_conditional_graph_supported()):
            return False
        graph = self._graphs.get(key)
        if graph is None:
            with wp.ScopedCapture(device=dev) as capture:
                wp.capture_while(condition, body)
            graph = self._keep(key, capture.graph)
        else:
            self.counts["replayed"] += 1
        wp.capture_launch(graph)
        return True

    def __len__(self) -> int:
        return len(self._graphs)

    def _keep(self, key: Hashable, graph):
        while len(self._graphs) >= self.size:
            self._graphs.pop(next(iter(self._graphs)))
        self._graphs[key] = graph
        self.counts["captured"] += 1
        return graph
