"""The GPU memory a run holds and its peak, from Warp's memory pool (None on the CPU)."""

from __future__ import annotations

import ctypes
import sys

import warp as wp


def memory_mib(device) -> float | None:
    """GPU memory the run holds now (Warp's memory pool), in MiB; None on the CPU."""
    device = wp.get_device(device)
    if not device.is_cuda or not wp.is_mempool_enabled(device):
        return None
    return wp.get_mempool_used_mem_current(device) / 2**20


def peak_memory_mib(device) -> float | None:
    """The high-water mark of Warp's memory pool in MiB (since ``start_peak_memory``); None on the CPU."""
    device = wp.get_device(device)
    if not device.is_cuda or not wp.is_mempool_enabled(device):
        return None
    return wp.get_mempool_used_mem_high(device) / 2**20


# CUmemPool_attribute CU_MEMPOOL_ATTR_USED_MEM_HIGH (cuda.h): set to 0, the mark restarts at the memory in use
_CU_MEMPOOL_ATTR_USED_MEM_HIGH = 8


def reset_mempool_high(ordinal: int) -> bool:
    """Reset the high-water mark of CUDA device ``ordinal``'s default memory pool (the pool Warp
    allocates from) through the CUDA driver; False where the driver or a call is missing or fails."""
    try:
        cuda = ctypes.CDLL("nvcuda.dll" if sys.platform == "win32" else "libcuda.so.1")
        dev, pool, zero = ctypes.c_int(), ctypes.c_void_p(), ctypes.c_uint64(0)
        return (
            cuda.cuDeviceGet(ctypes.byref(dev), ctypes.c_int(ordinal)) == 0
            and cuda.cuDeviceGetDefaultMemPool(ctypes.byref(pool), dev) == 0
            and cuda.cuMemPoolSetAttribute(pool, _CU_MEMPOOL_ATTR_USED_MEM_HIGH, ctypes.byref(zero)) == 0
        )
    except (OSError, AttributeError):
        return False


def start_peak_memory(device) -> float | None:
    """Start measuring a run's peak memory; returns the floor (MiB) a peak must exceed to be this run's
    (0 after a reset), None on the CPU.  The pool's high-water mark spans the process, and the suite
    runs several runs in one process (Ray reuses its workers too): without the reset every run after a
    bigger one reported that one's peak (4801 MiB for 7-Scenes runs of 2.3 GiB).  Where the
    driver cannot reset it, a run that stays under the mark it found has no peak of its own to report."""
    device = wp.get_device(device)
    if not device.is_cuda or not wp.is_mempool_enabled(device):
        return None
    reset_mempool_high(device.ordinal)
    high, current = wp.get_mempool_used_mem_high(device), wp.get_mempool_used_mem_current(device)
    return 0.0 if high <= current else high / 2**20


def run_peak_memory(device, floor_mib: float | None) -> tuple[float | None, str | None]:
    """(the run's peak memory in MiB, None) or (None, why it is n/a); ``floor_mib`` from ``start_peak_memory``."""
    mem = peak_memory_mib(device)
    if mem is None:
        return None, "measured on CUDA devices only (Warp's memory pool)"
    if floor_mib and mem <= floor_mib:
        return None, (
            f"an earlier run in this process left the memory pool's high-water mark at {floor_mib:.0f} MiB, "
            "above this run's peak, and the CUDA driver could not reset it"
        )
    return mem, None
