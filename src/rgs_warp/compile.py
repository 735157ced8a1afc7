"""Compile rgs_warp's Warp kernels before a run needs them.

    python -m rgs_warp.compile                      # every kernel module for this machine's GPU, in parallel
    python -m rgs_warp.compile --arch 80,86,89,90   # for those GPUs, without one (a Docker build, a head node)

Warp compiles a module the first time one of its kernels launches on a device and keeps the binary in
its kernel cache (``WARP_CACHE_PATH``), named by the hash of the module's code: an unchanged module is
never compiled again, a changed one always is.  Compiled one after another as a run reaches them,
rgs_warp's kernel modules take about 28 s of NVRTC (2-core machine; they were a fresh H100 machine's first
run's 5.0 against 7.8 frames/s).  A run on a GPU therefore compiles them all at its start, in parallel
(``preload``); this command does the same ahead of time, or, with ``--arch``, for GPUs this machine
does not have: the binaries go into the kernel cache that the GPU machine reads (a shared
``WARP_CACHE_PATH``, or a Docker image's).  A GPU whose driver is at least as new as Warp's CUDA
toolkit loads PTX, an older driver CUBIN: ``--arch`` writes both unless ``--format`` says one.
"""

from __future__ import annotations

import importlib
import os
import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import warp as wp

PACKAGE_DIR = Path(__file__).resolve().parent
KERNEL_DECORATOR = re.compile(r"^\s*@(?:wp|warp)\.kernel\b", re.MULTILINE)
FORMATS = ("cubin", "ptx")


def kernel_modules() -> list[str]:
    """The names of rgs_warp's modules that define Warp kernels, found by scanning the package's sources
    for ``@wp.kernel`` (a kernel moved to another file stays covered)."""
    names = []
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        if KERNEL_DECORATOR.search(path.read_text(encoding="utf-8")):
            parts = path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts
            names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


def _workers(workers: int | None) -> int:
    return max(1, workers if workers is not None else (os.cpu_count() or 1))


def preload(device: str, workers: int | None = None) -> None:
    """Load every kernel module on CUDA ``device``, compiling those not in the kernel cache, ``workers``
    at a time (default: one per CPU core).  Every launch of rgs_warp uses its module's default block
    size (256 threads, ``REDUCE_BLOCK``, ``PROJECT_BLOCK`` and 16x16 tiles alike; 128 in
    ``kernels.direct``, set as that module's default), the one variant this loads.  No-op on the CPU,
    whose tiled kernels need a second variant of their modules."""
    device = wp.get_device(device)
    if not device.is_cuda:
        return
    # Warp takes a GPU's primary context, and sets the stream its native code issues work on, at first
    # use (on a one-GPU machine: with two, its peer-access check at init takes them).  Taken inside
    # force_load's threads, the native stream stayed the legacy one while Python's device.stream was
    # Warp's own, and every run's first CUDA graph capture failed (CUDA error 906,
    # tests/test_compile_preload.py).  So this thread takes it before them.
    _ = device.context
    modules = [wp.get_module(importlib.import_module(name).__name__) for name in kernel_modules()]
    wp.force_load(device=device, modules=modules, max_workers=_workers(workers))


def compile_module(name: str, arch: int, fmt: str = "cubin") -> list[Path]:
    """Compile kernel module ``name`` for GPU architecture ``arch`` (e.g. 90 for sm_90) as ``fmt``
    ("cubin" or "ptx") into the kernel cache, without a GPU; the files written (or found there)."""
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, got {fmt!r}")
    module = importlib.import_module(name)
    return list(wp.compile_aot_module(module, arch=arch, use_ptx=fmt == "ptx"))


def compile_for_archs(
    archs: list[int], formats: tuple[str, ...] = FORMATS, workers: int | None = None, modules: list[str] | None = None
) -> list[Path]:
    """``compile_module`` for every kernel module (or ``modules``), architecture and format, ``workers``
    at a time; the files in the kernel cache."""
    names = kernel_modules() if modules is None else modules
    for name in names:  # imports first: a module's hash covers every kernel defined in it
        importlib.import_module(name)
    jobs = [(name, arch, fmt) for name in names for arch in archs for fmt in formats]
    with ThreadPoolExecutor(_workers(workers)) as pool:
        return [f for files in pool.map(lambda job: compile_module(*job), jobs) for f in files]


if __name__ == "__main__":
    from rgs_warp.app.compile import main

    raise SystemExit(main())
