"""The command line's CPU-sized run of a synthetic scene."""

from __future__ import annotations

from rgs_warp.config import Config

# The command line's run of a synthetic scene on the CPU when the user set no size (README, quick start):
# the full default takes over half an hour on 2 cores; these sizes finish in under 3 minutes there, fresh
# caches included, and still track and map (experiments/results/perf.md, "The CPU-sized first run")
CPU_SIZED = {
    "dataset.width": 120,
    "dataset.height": 68,
    "dataset.max_frames": 25,
    "mapping.init_iters": 100,
    "mapping.iters_per_frame": 4,
    "mapping.views_per_iter": 0,
    "mapping.window": 3,
}
# Keys that size a run: when the command line sets any of them, none of CPU_SIZED is applied
CPU_SIZE_KEYS = (
    *CPU_SIZED,
    *("dataset.n_frames", "dataset.stride", "dataset.start", "dataset.downscale", "tracking.iters"),
    *("tracking.downscale", "mapping.init_window", "mapping.rate_fps"),
)


def cpu_sized_overrides(cfg: Config, overrides, device: str) -> tuple[list[str], str]:
    """The ``key=value`` overrides that make the command line's run CPU-sized, and the message that
    says so, or ``([], "")``: only when ``device`` (resolved) is the CPU, the dataset is a synthetic
    scene (``cfg``, loaded from ``overrides``), ``cpu_sized`` is on and ``overrides`` set none of
    ``CPU_SIZE_KEYS``."""
    given = {item.split("=", 1)[0].strip() for item in overrides if "=" in item}
    if not device.startswith("cpu") or cfg.dataset.type != "synthetic" or not cfg.cpu_sized:
        return [], ""
    if given & set(CPU_SIZE_KEYS):
        return [], ""
    extra = [f"{k}={v}" for k, v in CPU_SIZED.items()]
    d, m, q = cfg.dataset, cfg.mapping, CPU_SIZED
    message = (
        f"No GPU ({device}): a CPU-sized run of synthetic/{d.name}: {q['dataset.width']}x{q['dataset.height']} "
        f"pixels, the first {q['dataset.max_frames']} of {d.n_frames} frames, "
        f"{q['mapping.init_iters']} initial and {q['mapping.iters_per_frame']} mapping iterations a frame "
        f"over {q['mapping.window']} keyframes (under 3 minutes on 2 cores).\n"
        f"The full run ({d.width}x{d.height}, {d.n_frames} frames, {m.init_iters} initial mapping iterations and "
        f"the budget of mapping.rate_fps={m.rate_fps:g}; "
        f"over half an hour on 2 cores): add cpu_sized=false, or set any size yourself, e.g. "
        f"dataset.max_frames=40 (the rest then keeps its defaults)."
    )
    return extra, message
