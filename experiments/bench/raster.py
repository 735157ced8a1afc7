"""Rasterizer benchmark: rgs_warp vs gsplat 1.5.3 on the same GPU, same inputs, same process.

Workload (issue 4): 1200x680, fx = fy = 600, cx = 599.5, cy = 339.5, identity pose; N Gaussians
with means uniform (by area) on the five visible walls of the box x in [-3, 3], y in [-1.5, 1.5],
z in [0.5, 4.5] seen from the origin down +z; scales uniform in [1, 2] cm, random unit quaternions,
opacity uniform in [0.5, 1], SH degree 2 coefficients ~ N(0, 0.1).  Colour + depth (sum w z:
gsplat's "RGB+D").  Times are CUDA-event medians of 30 after warm-up: forward, forward + backward
of every Gaussian parameter (rgs_warp also returns the pose twist gradient; gsplat's view matrix
gets none), forward + pose-only backward (gsplat: gradient of the view matrix only).  gsplat's
forward runs under torch.no_grad().

    python experiments/bench/raster.py [--sizes 100000 300000 1000000] [--out DIR] [--no-gsplat]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import time
from pathlib import Path

import numpy as np
import warp as wp

from rgs_warp.render import Renderer
from rgs_warp.types import Camera, GaussianMap

CAMERA = Camera(fx=600.0, fy=600.0, cx=599.5, cy=339.5, width=1200, height=680)
ITERS = 30
WARMUP = 5


def room_scene(n: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    # walls: back z = 4.5 (6 x 3), left/right x = -+3 (4 x 3), ceiling/floor y = -+1.5 (6 x 4)
    areas = np.array([18.0, 12.0, 12.0, 24.0, 24.0])
    wall = rng.choice(5, size=n, p=areas / areas.sum())
    p = np.stack([rng.uniform(-3, 3, n), rng.uniform(-1.5, 1.5, n), rng.uniform(0.5, 4.5, n)], axis=1)
    p[wall == 0, 2] = 4.5
    p[wall == 1, 0] = -3.0
    p[wall == 2, 0] = 3.0
    p[wall == 3, 1] = -1.5
    p[wall == 4, 1] = 1.5
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    opacity = rng.uniform(0.5, 1.0, n)
    return {
        "means": p.astype(np.float32),
        "quats_xyzw": q.astype(np.float32),
        "log_scales": np.log(rng.uniform(0.01, 0.02, (n, 3))).astype(np.float32),
        "opacity_logits": np.log(opacity / (1 - opacity)).astype(np.float32),
        "sh": rng.normal(0.0, 0.1, (n, 9, 3)).astype(np.float32),
    }


def median_ms(step, sync_event) -> float:
    for _ in range(WARMUP):
        step()
    times = []
    for _ in range(ITERS):
        times.append(sync_event(step))
    return float(np.median(times))


def bench_rgs(scene: dict, grads_np: tuple, device) -> dict:
    gmap = GaussianMap.from_numpy(
        scene["means"], scene["quats_xyzw"], scene["log_scales"], scene["opacity_logits"], scene["sh"], device=device
    )
    renderer = Renderer(device)
    T = np.eye(4)
    g_color = wp.array(grads_np[0], dtype=wp.vec3, device=device)
    g_depth = wp.array(grads_np[1], device=device)

    def timed(step):
        if not device.is_cuda:  # dry run of the script on a CPU machine
            t0 = time.perf_counter()
            step()
            return 1e3 * (time.perf_counter() - t0)
        e0, e1 = wp.Event(device, enable_timing=True), wp.Event(device, enable_timing=True)
        wp.record_event(e0)
        step()
        wp.record_event(e1)
        wp.synchronize_event(e1)
        return wp.get_event_elapsed_time(e0, e1)

    def fwd():
        renderer.forward(gmap, CAMERA, T)

    def fwd_bwd():
        renderer.forward(gmap, CAMERA, T)
        renderer.backward(g_color, g_depth)

    def fwd_pose():
        renderer.forward(gmap, CAMERA, T)
        renderer.backward(g_color, g_depth, pose_only=True)

    out = {"forward_ms": median_ms(fwd, timed)}
    out["forward_backward_ms"] = median_ms(fwd_bwd, timed)
    out["forward_pose_backward_ms"] = median_ms(fwd_pose, timed)
    result = renderer.forward(gmap, CAMERA, T)
    out["intersections"] = result.num_intersections
    out["mean_alpha"] = float(result.alpha.numpy().mean())
    out["peak_mem_mb"] = wp.get_mempool_used_mem_high(device) / 2**20 if wp.is_mempool_enabled(device) else None
    # per-kernel profile of one forward + full backward
    with wp.ScopedTimer("profile", print=False, synchronize=True, cuda_filter=wp.TIMING_ALL) as timer:
        fwd_bwd()
    profile: dict[str, float] = {}
    for r in timer.timing_results:
        profile[r.name] = profile.get(r.name, 0.0) + r.elapsed
    out["profile_ms"] = profile
    return out


def check_paths(scene: dict, grads_np: tuple, device) -> dict:
    """The tiled path (shared memory, warp shuffles: CUDA-only code) against the per-pixel path."""
    out = {}
    gmap = GaussianMap.from_numpy(
        scene["means"], scene["quats_xyzw"], scene["log_scales"], scene["opacity_logits"], scene["sh"], device=device
    )
    g_color = wp.array(grads_np[0], dtype=wp.vec3, device=device)
    g_depth = wp.array(grads_np[1], device=device)
    results = []
    for tiled in (True, False):
        renderer = Renderer(device, tiled=tiled)
        res = renderer.forward(gmap, CAMERA, np.eye(4))
        grads, pose = renderer.backward(g_color, g_depth)
        results.append((res.color.numpy(), res.depth.numpy(), grads.to_numpy(len(gmap)), pose.numpy()))
    (c0, d0, g0, p0), (c1, d1, g1, p1) = results
    out["color_max_abs"] = float(np.abs(c0 - c1).max())
    out["depth_max_abs"] = float(np.abs(d0 - d1).max())
    for name in g0:
        out[f"grad_{name}_rel"] = float(np.linalg.norm(g0[name] - g1[name]) / max(np.linalg.norm(g1[name]), 1e-30))
    out["pose_rel"] = float(np.linalg.norm(p0 - p1) / np.linalg.norm(p1))
    return out


def bench_gsplat(scene: dict, grads_np: tuple) -> dict:
    import torch
    from gsplat import rasterization

    dev = torch.device("cuda")
    q = scene["quats_xyzw"]

    def tensor(a, grad):
        return torch.tensor(a, device=dev, requires_grad=grad)

    # gsplat samples pixel centres at u + 0.5: shift its principal point so the images coincide
    K = torch.tensor(
        [[CAMERA.fx, 0.0, CAMERA.cx + 0.5], [0.0, CAMERA.fy, CAMERA.cy + 0.5], [0.0, 0.0, 1.0]], device=dev
    )[None]
    g = torch.cat([torch.tensor(grads_np[0], device=dev), torch.tensor(grads_np[1], device=dev)[..., None]], -1)

    def make(all_grads: bool):
        return dict(
            means=tensor(scene["means"], all_grads),
            quats=tensor(np.concatenate([q[:, 3:], q[:, :3]], 1), all_grads),
            scales=tensor(np.exp(scene["log_scales"]), all_grads),
            opacities=tensor(1 / (1 + np.exp(-scene["opacity_logits"])), all_grads),
            colors=tensor(scene["sh"], all_grads),
            viewmats=torch.eye(4, device=dev, requires_grad=not all_grads)[None],
        )

    def run(params, backward: bool):
        img, alpha, meta = rasterization(
            **params, Ks=K, width=CAMERA.width, height=CAMERA.height, sh_degree=2, render_mode="RGB+D"
        )
        if backward:
            (img[0] * g).sum().backward()

    def timed(step):
        e0, e1 = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        e0.record()
        step()
        e1.record()
        e1.synchronize()
        return e0.elapsed_time(e1)

    full, pose = make(True), make(False)
    torch.cuda.reset_peak_memory_stats()
    with torch.no_grad():
        out = {"forward_ms": median_ms(lambda: run(full, False), timed)}
    out["forward_backward_ms"] = median_ms(lambda: run(full, True), timed)
    out["forward_pose_backward_ms"] = median_ms(lambda: run(pose, True), timed)
    out["peak_mem_mb"] = torch.cuda.max_memory_allocated() / 2**20
    return out


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000, 300_000, 1_000_000])
    parser.add_argument("--out", default=os.environ.get("OUT", "experiments/results"))
    parser.add_argument("--no-gsplat", action="store_true")
    args = parser.parse_args()
    wp.config.enable_cpu_blocks = True  # only matters for a dry run on the CPU
    wp.init()
    device = wp.get_device("cuda:0" if wp.get_cuda_device_count() else "cpu")
    commit = os.environ.get("RGS_COMMIT")
    if commit is None:
        try:
            commit = subprocess.check_output(["git", "rev-parse", "--short", "HEAD"], text=True).strip()
        except (OSError, subprocess.CalledProcessError):
            commit = "unknown"
    rows = []
    rng = np.random.default_rng(1)
    grads_np = (
        rng.normal(size=(CAMERA.height, CAMERA.width, 3)).astype(np.float32),
        rng.normal(size=(CAMERA.height, CAMERA.width)).astype(np.float32),
    )
    check = check_paths(room_scene(args.sizes[0]), grads_np, device)
    print("tiled vs per-pixel:", json.dumps(check), flush=True)
    for n in args.sizes:
        scene = room_scene(n)
        t0 = time.time()
        row = {"n": n, "rgs_warp": bench_rgs(scene, grads_np, device)}
        if not args.no_gsplat:
            row["gsplat"] = bench_gsplat(scene, grads_np)
            row["ratio"] = {
                k: row["rgs_warp"][k] / row["gsplat"][k]
                for k in ("forward_ms", "forward_backward_ms", "forward_pose_backward_ms")
            }
        print(json.dumps(row), f"({time.time() - t0:.1f} s)", flush=True)
        rows.append(row)
    report = {"gpu": device.name, "commit": commit, "warp": wp.config.version, "tiled_vs_pixel": check, "rows": rows}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "raster.json").write_text(json.dumps(report, indent=2))
    lines = [
        f"GPU: {device.name}; commit {commit}; warp-lang {wp.config.version}; median of {ITERS} (ms)",
        "",
        "| N | rgs fwd | gsplat fwd | ratio | rgs fwd+bwd | gsplat fwd+bwd | ratio | rgs fwd+pose | gsplat fwd+pose"
        " | ratio | isect | rgs peak MB | gsplat peak MB |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        r, g, q = row["rgs_warp"], row.get("gsplat", {}), row.get("ratio", {})
        cells = [f"{row['n']:,}"]
        for k in ("forward_ms", "forward_backward_ms", "forward_pose_backward_ms"):
            cells += [f"{r[k]:.2f}", f"{g.get(k, float('nan')):.2f}", f"{q.get(k, float('nan')):.2f}"]
        cells += [f"{r['intersections']:,}", f"{r['peak_mem_mb'] or float('nan'):.0f}"]
        cells += [f"{g.get('peak_mem_mb', float('nan')):.0f}"]
        lines.append("| " + " | ".join(cells) + " |")
    (out / "raster_table.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
