"""Every module that defines Warp kernels compiles for the GPU (sm_90) with NVRTC, without a GPU:
CUDA-only compile errors (shared memory, tile sizes, intrinsics) would otherwise first show on a
GPU.  The modules are found by scanning the package's sources for ``@wp.kernel``, so a kernel moved
to another file stays covered; generic kernels compile through the overloads their module declares."""

import importlib

import pytest
import warp as wp

from rgs_warp.app.compile import main
from rgs_warp.compile import compile_module, kernel_modules

MODULES = kernel_modules()


def test_scan_finds_kernel_modules():
    # The scan itself can fail silently (a changed decorator spelling, a moved package): modules known
    # to hold kernels, in and outside rgs_warp.kernels, must be among those it found.
    for name in ("rgs_warp.kernels.rasterize", "rgs_warp.kernels.map_ops", "rgs_warp.datasets.synthetic.render"):
        assert name in MODULES


@pytest.mark.parametrize("name", MODULES)
def test_module_compiles_for_sm90(name):
    kernels = wp.get_module(importlib.import_module(name).__name__).kernels
    assert kernels, f"{name} has @wp.kernel in its source but registered no Warp kernel"
    undeclared = [key for key, k in kernels.items() if k.is_generic and not k.overloads]
    assert not undeclared, f"generic kernels without wp.overload declarations (not compiled ahead): {undeclared}"
    # Into Warp's kernel cache: the binary is named by the hash of the module's code, so an unchanged
    # module is not compiled again, any change is, and a failed compile leaves no binary behind.
    files = compile_module(name, arch=90)
    assert files and all(f.stat().st_size > 0 and f.name.endswith(".sm90.cubin") for f in files)


def test_compile_command_for_an_arch_without_a_gpu(capsys):
    # what a Docker build or a cluster's head node runs: every module for sm_90 into the kernel cache
    # (found there once the tests above compiled it), as both formats a driver may ask for
    assert main(["--arch", "90", "--format", "cubin"]) == 0
    assert f"{len(MODULES)} binaries for sm_90 (cubin)" in capsys.readouterr().out
    ptx = compile_module("rgs_warp.kernels.adam", arch=90, fmt="ptx")
    assert ptx and ptx[0].name.endswith(".sm90.ptx") and b".target sm_90" in ptx[0].read_bytes()


def test_compile_command_says_what_is_wrong(capsys):
    assert main(["--arch", "sm90"]) == 2
    assert "--arch takes numbers" in capsys.readouterr().err
    assert main(["--arch", "90", "--format", "elf"]) == 2
    assert "--format takes" in capsys.readouterr().err
    if not wp.is_cuda_available():
        assert main([]) == 2
        assert "no CUDA GPU" in capsys.readouterr().err
