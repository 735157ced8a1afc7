"""What a run shows while it goes: one progress bar whose description names the phase (generating the
scene, compiling kernels, tracking, evaluating), and the seconds Warp spent compiling kernels.

Warp compiles a kernel module on its first launch on a device and caches the result
(``WARP_CACHE_PATH``); on a fresh cache the first run of ``python -m rgs_warp.slam`` on 2 CPU cores
spends about a minute doing so (README, quick start).  ``watch_kernel_loads`` wraps Warp's module
loading for the length of a run to report each module as it loads; Warp has no public hook for it,
so where its ``Module.load`` is not where we expect, nothing is reported and the run is unchanged.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import warp as wp
from tqdm import tqdm


def quiet_warp() -> None:
    """Warp's own lines off (its banner at start-up, a line per kernel module loaded): the commands say what
    happens (the progress bar names the modules as they compile); its warnings stay."""
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)


@dataclass
class KernelLoads:
    """The kernel modules loaded while ``watch_kernel_loads`` watched: ``compiled`` (name, start, end;
    ``time.perf_counter`` seconds) of those built (not in the kernel cache), ``cached`` those read from it.
    The seconds are wall time, the span the loads covered: a run's preload compiles modules in parallel
    threads, whose summed seconds (74 s on a fresh H100 with 16 workers) would overstate the wait many times."""

    compiled: list[tuple[str, float, float]] = field(default_factory=list)
    cached: list[tuple[str, float, float]] = field(default_factory=list)

    @property
    def compile_s(self) -> float:
        return _covered_s(self.compiled)

    @property
    def load_s(self) -> float:
        return _covered_s(self.compiled + self.cached)

    def summary(self) -> dict:
        return {
            "compiled_modules": len(self.compiled),
            "compile_s": round(self.compile_s, 2),
            "cached_modules": len(self.cached),
            "load_s": round(self.load_s, 2),
        }


def _covered_s(loads: list[tuple[str, float, float]]) -> float:
    """Seconds covered by the union of the loads' (start, end) intervals."""
    total, reach = 0.0, float("-inf")
    for _, start, end in sorted(loads, key=lambda load: load[1]):
        if end > reach:
            total += end - max(start, reach)
            reach = end
    return total


def _module_class():
    try:
        from warp._src.context import Module
    except ImportError:
        return None
    return Module if callable(getattr(Module, "load", None)) else None


@contextmanager
def watch_kernel_loads(on_load: Callable[[str, bool], None] | None = None) -> Iterator[KernelLoads]:
    """Within the block, every kernel module that Warp loads (on its first launch on a device) is
    recorded in the yielded ``KernelLoads``; ``on_load(name, cached)`` is called before each load
    (``cached``: the compiled module is in the kernel cache) and ``on_load("", True)`` after it."""
    loads = KernelLoads()
    module_class = _module_class()
    if module_class is None:
        yield loads
        return
    original = module_class.load

    def load(self, device, block_dim=None, *args, **kwargs):
        dev = wp.get_device(device)
        active = block_dim if block_dim is not None else self.options["block_dim"]
        if (dev.context, active) in self.execs:  # loaded before: Warp returns it at once
            return original(self, device, block_dim, *args, **kwargs)
        try:
            ident = self.get_module_identifier(active)
            cached = os.path.isdir(os.path.join(wp.config.kernel_cache_dir, ident))
        except Exception:  # noqa: BLE001 (only what the bar says depends on it)
            cached = False
        if on_load is not None:
            on_load(self.name, cached)
        t0 = time.perf_counter()
        try:
            return original(self, device, block_dim, *args, **kwargs)
        finally:
            (loads.cached if cached else loads.compiled).append((self.name, t0, time.perf_counter()))
            if on_load is not None:
                on_load("", True)

    module_class.load = load
    try:
        yield loads
    finally:
        module_class.load = original


class RunProgress:
    """The run's progress bar: frames done of ``total`` (None: a stream of unknown length) and the
    phase in its description, e.g. ``synthetic/room0 [compiling kernels: rasterize]``.  It shows
    nothing during its first ``quiet_s`` seconds, so a run that fails at start-up prints only its
    error."""

    def __init__(self, name: str, enabled: bool = True, quiet_s: float = 1.0):
        self.name = name
        self.bar = tqdm(total=None, desc=name, unit="frame", disable=not enabled, dynamic_ncols=True, delay=quiet_s)
        self._shown_after = time.monotonic() + quiet_s
        self.current = ""
        self._compiling = ""

    def phase(self, text: str) -> None:
        """The phase the run is in now (shown until the next ``phase``)."""
        self.current = text
        self._show()

    def kernel_load(self, module: str, cached: bool) -> None:
        """``watch_kernel_loads``'s callback: names the module while it loads, then the phase again."""
        short = module.rsplit(".", 1)[-1]
        self._compiling = f"{'loading' if cached else 'compiling'} kernels: {short}" if module else ""
        self._show()

    def _show(self) -> None:
        text = self._compiling or self.current
        refresh = time.monotonic() >= self._shown_after
        self.bar.set_description_str(f"{self.name} [{text}]" if text else self.name, refresh=refresh)

    def start_frames(self, total: int | None, initial: int = 0) -> None:
        self.bar.reset(total=total)
        self.bar.update(initial)
        self.phase("tracking")

    def set_postfix(self, **values) -> None:
        self.bar.set_postfix(**values)

    def update(self, frames: int = 1) -> None:
        self.bar.update(frames)

    def write(self, message: str, file=None) -> None:
        """A line above the bar (``file``: default stdout)."""
        self.bar.write(message, file=file)

    def close(self) -> None:
        """The bar's last state on a line of its own, once it has been shown (tqdm leaves the line open, and an
        error after it on the same line, when the frames began within its quiet time)."""
        if time.monotonic() >= self._shown_after:
            self.bar.delay = 0
        self.bar.close()
