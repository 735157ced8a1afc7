"""Test set-up: Warp on its CPU device, tile kernels correct on CPU, kernel cache inside the checkout."""

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"

os.environ.setdefault("WARP_CACHE_PATH", str(ROOT / ".cache" / "warp"))
os.environ.setdefault("RGS_CACHE", str(ROOT / ".cache" / "rgs_warp"))

import warp as wp  # noqa: E402

wp.config.enable_cpu_blocks = True  # tile kernels give wrong results on CPU without it (DESIGN.md)
wp.init()


MAX_WORKERS = 8  # python -m pytest -n logical: a worker per CPU, at most this many (each loads Warp and torch)


def pytest_xdist_auto_num_workers(config):
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return min(cpus, MAX_WORKERS)


@pytest.fixture(scope="session")
def device():
    # CI runs on the CPU; RGS_TEST_DEVICE=cuda:0 runs the same tests on a GPU (CUDA-only bugs such
    # as a capture_while condition of the wrong size pass on the CPU).
    return os.environ.get("RGS_TEST_DEVICE", "cpu")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared real data not found at {SHARED_DATA}")
    return SHARED_DATA
