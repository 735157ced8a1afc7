"""Every module that defines Warp kernels compiles for the GPU (sm_90) with NVRTC, without a GPU:
CUDA-only compile errors (shared memory, tile sizes, intrinsics) would otherwise first show on a lent
H100.  The modules are found by scanning the package's sources for ``@wp.kernel``, so a kernel moved
to another file stays covered; generic kernels compile through the overloads their module declares."""

import importlib
import re
from pathlib import Path

import pytest
import warp as wp

import rgs_warp

PACKAGE_DIR = Path(rgs_warp.__file__).resolve().parent
KERNEL_DECORATOR = re.compile(r"^\s*@(?:wp|warp)\.kernel\b", re.MULTILINE)


def _kernel_modules() -> list[str]:
    names = []
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        if KERNEL_DECORATOR.search(path.read_text(encoding="utf-8")):
            parts = path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts
            names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


MODULES = _kernel_modules()


def test_scan_finds_kernel_modules():
    # The scan itself can fail silently (a changed decorator spelling, a moved package): modules known
    # to hold kernels, in and outside rgs_warp.kernels, must be among those it found.
    for name in ("rgs_warp.kernels.rasterize", "rgs_warp.kernels.map_ops", "rgs_warp.datasets.synthetic.render"):
        assert name in MODULES


@pytest.mark.parametrize("name", MODULES)
def test_module_compiles_for_sm90(name):
    module = importlib.import_module(name)
    kernels = wp.get_module(name).kernels
    assert kernels, f"{name} has @wp.kernel in its source but registered no Warp kernel"
    undeclared = [key for key, k in kernels.items() if k.is_generic and not k.overloads]
    assert not undeclared, f"generic kernels without wp.overload declarations (not compiled ahead): {undeclared}"
    # Into Warp's kernel cache: the binary is named by the hash of the module's code, so an unchanged
    # module is not compiled again, any change is, and a failed compile leaves no binary behind.
    files = wp.compile_aot_module(module, arch=90)
    assert files and all(f.stat().st_size > 0 for f in files)
