"""Rasterizer benchmark: rgs_warp vs gsplat 1.5.3 on the same GPU, same inputs, same process.

Workload: 1200x680, fx = fy = 600, cx = 599.5, cy = 339.5, identity pose; N Gaussians
with means uniform (by area) on the five visible walls of the box x in [-3, 3], y in [-1.5, 1.5],
z in [0.5, 4.5] seen from the origin down +z; scales uniform in [1, 2] cm, random unit quaternions,
opacity uniform in [0.5, 1], SH degree 2 coefficients ~ N(0, 0.1).  Colour + depth (sum w z:
gsplat's "RGB+D").  Steps: forward, forward + backward of every Gaussian parameter (the mapper's
step: neither library computes the view matrix's gradient), forward + pose-only backward (gsplat:
gradient of the view matrix only).  gsplat's forward runs under torch.no_grad(); gsplat runs both
packed=True (its default) and packed=False, and the faster one per step is the reference.

Three times per step:
* end-to-end: CUDA-event median of 30 eager launches after warm-up.  This includes host launch
  overhead wherever the host cannot stay ahead of the GPU, so it depends on the host CPU (recorded);
* GPU: the sum of kernel, memcpy and memset durations of one step (CUPTI via torch.profiler, the
  mean of 10 steps), for both libraries: what the step costs the GPU, without any host gaps;
* graph (rgs_warp only): CUDA-event median of replays of the step captured in a CUDA graph.  gsplat
  reads its intersection count back to the host inside ``rasterization``, so it cannot be captured
  (the attempt's error is recorded).

    python experiments/bench/raster.py [--sizes 100000 300000 1000000] [--out DIR] [--no-gsplat]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import warp as wp

from rgs_warp.app.report import git_commit
from rgs_warp.render import Renderer
from rgs_warp.types import Camera, GaussianMap

CAMERA = Camera(fx=600.0, fy=600.0, cx=599.5, cy=339.5, width=1200, height=680)
ITERS = 30
WARMUP = 5
PROFILE_ITERS = 10
STEPS = ("forward_ms", "forward_backward_ms", "forward_pose_backward_ms")


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


def host_cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return f"{line.split(':', 1)[1].strip()} ({os.cpu_count()} logical CPUs)"
    except OSError:
        pass
    return platform.processor() or "unknown"


def gpu_busy_ms(step, synchronize) -> tuple[float, dict[str, float]]:
    """Mean per-step sum of GPU activity durations (kernels, memcpy, memset) recorded by CUPTI through
    torch.profiler, whatever library launched them; and the per-kernel breakdown (ms per step)."""
    import torch
    from torch.profiler import ProfilerActivity, profile

    step()
    synchronize()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(PROFILE_ITERS):
            step()
        synchronize()
    # the chrome trace lists every device activity, also those no torch op launched (Warp's, CUB's)
    with tempfile.TemporaryDirectory() as tmp:
        trace = Path(tmp) / "trace.json"
        prof.export_chrome_trace(str(trace))
        events = json.loads(trace.read_text())["traceEvents"]
    by_name: dict[str, float] = {}
    for e in events:
        if e.get("ph") == "X" and e.get("cat") in ("kernel", "gpu_memcpy", "gpu_memset"):
            name = e["name"] if e["cat"] == "kernel" else e["cat"]
            by_name[name] = by_name.get(name, 0.0) + e["dur"] / 1e3 / PROFILE_ITERS
    del torch
    return sum(by_name.values()), by_name


def bench_rgs(scene: dict, grads_np: tuple, device) -> dict:
    gmap = GaussianMap.from_numpy(
        scene["means"], scene["quats_xyzw"], scene["log_scales"], scene["opacity_logits"], scene["sh"], device=device
    )
    renderer = Renderer(device)
    # the pose lives on the device, as the tracker's does, so a captured graph reads its current value
    T = wp.array([np.eye(4, dtype=np.float32)], dtype=wp.mat44, device=device)
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
        renderer.forward(gmap, CAMERA, T, pose_jacobians=False)

    def fwd_bwd():
        renderer.forward(gmap, CAMERA, T, pose_jacobians=False)
        renderer.backward(g_color, g_depth, with_pose=False)

    def fwd_pose():
        renderer.forward(gmap, CAMERA, T, pose_jacobians=True)
        renderer.backward(g_color, g_depth, pose_only=True)

    steps = dict(zip(STEPS, (fwd, fwd_bwd, fwd_pose), strict=True))
    out = {"end_to_end": {k: median_ms(step, timed) for k, step in steps.items()}}
    if device.is_cuda:
        out["gpu"], out["profile_ms"] = {}, {}
        for k, step in steps.items():
            out["gpu"][k], out["profile_ms"][k] = gpu_busy_ms(step, lambda: wp.synchronize_device(device))
        out["graph"] = {}
        for k, step in steps.items():
            step()  # eager: sizes the intersection buffers from this view's count
            try:
                with wp.ScopedCapture(device) as capture:
                    step()
            except Exception as e:  # noqa: BLE001 - record why, keep benchmarking
                out["graph"] = {"error": repr(e)}
                break
            out["graph"][k] = median_ms(lambda g=capture.graph: wp.capture_launch(g), timed)
            out["graph"][k.replace("_ms", "_overflowed")] = renderer.intersections_overflowed()
    result = renderer.forward(gmap, CAMERA, T)
    out["intersections"] = result.num_intersections
    out["intersection_capacity"] = result.intersection_capacity
    out["mean_alpha"] = float(result.alpha.numpy().mean())
    out["peak_mem_mb"] = wp.get_mempool_used_mem_high(device) / 2**20 if wp.is_mempool_enabled(device) else None
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
    # the pose-only compositing backward (Jacobians folded per thread) against the general path
    renderer = Renderer(device)
    renderer.forward(gmap, CAMERA, np.eye(4), pose_jacobians=True)
    pose_fast = renderer.backward(g_color, g_depth, pose_only=True)[1].numpy()
    out["pose_only_rel"] = float(np.linalg.norm(pose_fast - p1) / np.linalg.norm(p1))
    return out


def bench_gsplat(scene: dict, grads_np: tuple, packed: bool) -> dict:
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
            **params, Ks=K, width=CAMERA.width, height=CAMERA.height, sh_degree=2, render_mode="RGB+D", packed=packed
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

    def fwd():
        with torch.no_grad():
            run(full, False)

    full, pose = make(True), make(False)
    steps = dict(zip(STEPS, (fwd, lambda: run(full, True), lambda: run(pose, True)), strict=True))
    torch.cuda.reset_peak_memory_stats()
    out = {"end_to_end": {k: median_ms(step, timed) for k, step in steps.items()}, "gpu": {}}
    for k, step in steps.items():
        out["gpu"][k] = gpu_busy_ms(step, torch.cuda.synchronize)[0]
    out["peak_mem_mb"] = torch.cuda.max_memory_allocated() / 2**20
    return out


def gsplat_graph_attempt(scene: dict) -> str:
    """Try to capture gsplat's forward in a CUDA graph; returns the outcome."""
    import torch
    from gsplat import rasterization

    dev = torch.device("cuda")
    q = scene["quats_xyzw"]
    args = dict(
        means=torch.tensor(scene["means"], device=dev),
        quats=torch.tensor(np.concatenate([q[:, 3:], q[:, :3]], 1), device=dev),
        scales=torch.tensor(np.exp(scene["log_scales"]), device=dev),
        opacities=torch.tensor(1 / (1 + np.exp(-scene["opacity_logits"])), device=dev),
        colors=torch.tensor(scene["sh"], device=dev),
        viewmats=torch.eye(4, device=dev)[None],
        Ks=torch.tensor([[CAMERA.fx, 0.0, CAMERA.cx], [0.0, CAMERA.fy, CAMERA.cy], [0.0, 0.0, 1.0]], device=dev)[None],
        width=CAMERA.width,
        height=CAMERA.height,
        sh_degree=2,
    )
    graph = torch.cuda.CUDAGraph()
    try:
        with torch.no_grad(), torch.cuda.graph(graph):
            rasterization(**args)
    except Exception as e:  # noqa: BLE001 - the failure is the result
        return f"not capturable: {type(e).__name__}: {str(e).splitlines()[0][:200]}"
    return "captured"


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000, 300_000, 1_000_000])
    parser.add_argument("--out", default=os.environ.get("OUT", "bench_out"))
    parser.add_argument("--no-gsplat", action="store_true")
    args = parser.parse_args()
    wp.init()
    device = wp.get_device("cuda:0" if wp.get_cuda_device_count() else "cpu")
    commit = os.environ.get("RGS_COMMIT") or git_commit()
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
            variants = {f"packed={p}": bench_gsplat(scene, grads_np, p) for p in (True, False)}
            row["gsplat"] = variants
            # reference: the faster gsplat variant, per step and per kind of time
            row["gsplat_best"] = {
                kind: {k: min((v[kind][k], name) for name, v in variants.items()) for k in STEPS}
                for kind in ("end_to_end", "gpu")
            }
            row["ratio"] = {
                kind: {k: row["rgs_warp"][kind][k] / row["gsplat_best"][kind][k][0] for k in STEPS}
                for kind in ("end_to_end", "gpu")
            }
        print(json.dumps(row), f"({time.time() - t0:.1f} s)", flush=True)
        rows.append(row)
    report = {
        "gpu": device.name,
        "host_cpu": host_cpu(),
        "commit": commit,
        "warp": wp.config.version,
        "tiled_vs_pixel": check,
        "rows": rows,
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "raster.json").write_text(json.dumps(report, indent=2))
    if not args.no_gsplat:
        report["gsplat_cuda_graph"] = gsplat_graph_attempt(room_scene(args.sizes[0]))
        (out / "raster.json").write_text(json.dumps(report, indent=2))
    lines = [
        f"GPU: {device.name}; host: {report['host_cpu']}; commit {commit}; warp-lang {wp.config.version}",
        "",
        "| N | step | rgs e2e | rgs graph | rgs GPU | gsplat e2e | gsplat GPU | ratio e2e | ratio GPU | isect |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    nan = float("nan")
    for row in rows:
        r = row["rgs_warp"]
        best = row.get("gsplat_best", {})
        for k in STEPS:
            ge2e, gname = best.get("end_to_end", {}).get(k, (nan, ""))
            ggpu, gname_gpu = best.get("gpu", {}).get(k, (nan, ""))
            cells = [f"{row['n']:,}", k.removesuffix("_ms").replace("_", " ")]
            cells += [f"{r['end_to_end'][k]:.2f}", f"{r.get('graph', {}).get(k, nan):.2f}"]
            cells += [f"{r.get('gpu', {}).get(k, nan):.2f}", f"{ge2e:.2f} ({gname})", f"{ggpu:.2f} ({gname_gpu})"]
            cells += [f"{r['end_to_end'][k] / ge2e:.2f}", f"{r.get('gpu', {}).get(k, nan) / ggpu:.2f}"]
            cells += [f"{r['intersections']:,}"]
            lines.append("| " + " | ".join(cells) + " |")
    (out / "raster_table.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
