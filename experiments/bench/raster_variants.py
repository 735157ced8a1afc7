"""Compilation variants of the tiled compositing kernels: per-kernel GPU times and register, spill and
shared-memory use, on the workload of raster.py.  One variant per process, since compile options are
fixed when a module loads (give each variant its own WARP_CACHE_PATH):

    python experiments/bench/raster_variants.py [--no-fast-math] [--min-blocks N] [--sizes 300000 1000000]

``--no-fast-math``: the rasterize module compiled without fast math (approximate exp and division, its
default, as gsplat builds with -use_fast_math); ``--min-blocks N``: ``__launch_bounds__(256, N)`` on the
tiled kernels, which caps their registers so that N blocks fit on an SM (0: as in the module).
"""

from __future__ import annotations

import argparse
import ctypes
import json

import numpy as np
import warp as wp
from raster import CAMERA, room_scene

import rgs_warp.kernels.rasterize as rasterize
from rgs_warp.render import Renderer
from rgs_warp.types import GaussianMap

ITERS = 10
TILED = (rasterize.rasterize_tiles, rasterize.rasterize_tiles_backward, rasterize.rasterize_tiles_pose_backward)
# CUfunction_attribute values (cuda.h)
ATTRIBUTES = {"registers": 4, "local_bytes": 3, "static_shared_bytes": 1}


def resources(kernel, device) -> dict:
    """Registers per thread, local memory (spills) and static shared memory of a loaded CUDA kernel."""
    try:
        cuda = ctypes.CDLL("libcuda.so.1")
        function = kernel.module.get_kernel_hooks(kernel, device).forward
        function = function if isinstance(function, ctypes.c_void_p) else ctypes.c_void_p(int(function))
        out = {}
        for name, attribute in ATTRIBUTES.items():
            value = ctypes.c_int(0)
            cuda.cuFuncGetAttribute(ctypes.byref(value), attribute, function)
            out[name] = value.value
        return out
    except Exception as e:  # noqa: BLE001 - internal Warp API: report rather than fail the run
        return {"error": repr(e)}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--no-fast-math", action="store_true")
    parser.add_argument("--min-blocks", type=int, default=0)
    parser.add_argument("--sizes", type=int, nargs="+", default=[300_000, 1_000_000])
    args = parser.parse_args()
    wp.init()
    device = wp.get_device("cuda:0")
    if args.no_fast_math:
        wp.set_module_options({"fast_math": False}, module=rasterize)
    if args.min_blocks:
        for kernel in TILED:
            kernel.options["launch_bounds"] = (256, args.min_blocks)
    rng = np.random.default_rng(1)
    g_color = wp.array(rng.normal(size=(CAMERA.height, CAMERA.width, 3)).astype(np.float32), dtype=wp.vec3)
    g_depth = wp.array(rng.normal(size=(CAMERA.height, CAMERA.width)).astype(np.float32))
    report = {"variant": {"fast_math": not args.no_fast_math, "min_blocks": args.min_blocks}, "rows": []}
    for n in args.sizes:
        s = room_scene(n)
        gmap = GaussianMap.from_numpy(s["means"], s["quats_xyzw"], s["log_scales"], s["opacity_logits"], s["sh"])
        renderer = Renderer(device)
        T = np.eye(4)
        row = {"n": n}
        for label, pose_only in (("forward_backward", False), ("forward_pose_backward", True)):
            for _ in range(3):
                renderer.forward(gmap, CAMERA, T, pose_jacobians=pose_only)
                renderer.backward(g_color, g_depth, pose_only=pose_only, with_pose=False)
            with wp.ScopedTimer(label, print=False, synchronize=True, cuda_filter=wp.TIMING_KERNEL) as timer:
                for _ in range(ITERS):
                    renderer.forward(gmap, CAMERA, T, pose_jacobians=pose_only)
                    renderer.backward(g_color, g_depth, pose_only=pose_only, with_pose=False)
            times: dict[str, float] = {}
            for r in timer.timing_results:
                name = r.name.split()[-1].rsplit("_", 1)[0]
                times[name] = times.get(name, 0.0) + r.elapsed / ITERS
            row[label] = times
        rendered = renderer.forward(gmap, CAMERA, T)
        row["color_mean"] = float(rendered.color.numpy().mean())
        report["rows"].append(row)
    report["resources"] = {k.key: resources(k, device) for k in TILED}
    print(json.dumps(report))


if __name__ == "__main__":
    main()
