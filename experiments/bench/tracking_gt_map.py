"""Tracking against a map built from ground truth, on the CPU or a GPU (``--device``).

Scene room0 at a small resolution, n_frames=200 (~1.9 cm / 1.9 deg between frames).  The map holds flat
discs on the ground-truth depth of every 10th frame of the tracked segment, rendered with a 1.5x wider
field of view (tests/helpers_maps.py), optionally with colours refitted to those frames.  Two kinds of
observations are tracked, frame by frame from the true first pose with the constant-velocity prediction:

* ``rendered``: the map's own render at the true pose (tracker-only error: gradient, optimiser, motion
  model, gain model), with the dataset's exposure walk applied when drift is on;
* ``raw``: the ray-traced synthetic frames (adds the error of a map that does not reproduce them exactly).

For each: ATE with the exposure drift off and on.  With
``--keyframes`` instead: the lead's KeyframeSelector and KeyframeBuffer along the whole path, the map
growing by each keyframe (rho, buffer contents).  Results go to
``<out>/tracking_<observations>.json``; ``<out>/tracking.md`` summarises every such file there.

    PYTHONPATH=src python experiments/bench/tracking_gt_map.py --observations rendered --map-stride 2 --refine-iters 0
    PYTHONPATH=src python experiments/bench/tracking_gt_map.py --observations raw
    PYTHONPATH=src python experiments/bench/tracking_gt_map.py --keyframes
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))  # helpers_maps: the map-from-ground-truth builder


def machine(device: str = "cpu") -> str:
    if device.startswith("cuda"):
        return f"{wp.get_device(device).name} (Warp {device})"
    try:
        model = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if "model name" in line)
    except (OSError, StopIteration):
        model = platform.processor() or "unknown CPU"
    return f"{model}, {os.cpu_count()} logical cores (Warp cpu device, single-threaded kernels)"


def build_map(seq, camera, frame_ids, stride: int, refine_iters: int, device, refit: str = "colours"):
    from helpers_maps import map_from_rgbd, refine_colours
    from rgs_warp.datasets.synthetic.textures import linear_to_srgb
    from rgs_warp.types import Camera

    w, h = round(1.5 * camera.width), round(1.5 * camera.height)
    wide = Camera(camera.fx, camera.fy, (w - 1) / 2, (h - 1) / 2, w, h)
    frames = []
    for i in frame_ids:
        rgb, depth = seq.renderer.render(wide, seq.poses[i : i + 1], seq.poses[i], n_ss=2, seed=i)
        frames.append((np.clip(linear_to_srgb(rgb), 0, 1).astype(np.float32), depth, seq.poses[i]))
    gmap = map_from_rgbd(frames, wide, stride=stride, sigma_per_spacing=0.4 if stride == 1 else 0.5, device=device)
    if refine_iters and refit == "colours":
        refine_colours(gmap, [(f[0], f[2]) for f in frames], wide, iters=refine_iters)
    elif refine_iters:
        refit_with_mapper(gmap, wide, frames, refine_iters, device)
    return gmap


def refit_with_mapper(gmap, camera, frames, iters: int, device) -> None:
    """Fit the whole map (all Gaussian parameters, poses fixed at the truth) to its ground-truth
    frames with the Mapper's loss, on the device: what mapping would do with perfect poses."""
    from rgs_warp.config import MappingConfig
    from rgs_warp.keyframes import KeyframeBuffer
    from rgs_warp.mapping import Mapper

    buf = KeyframeBuffer(max(len(frames), 2), camera.width, camera.height, device)
    slots = [buf.add(k, T, rgb, depth) for k, (rgb, depth, T) in enumerate(frames)]
    mapper = Mapper(MappingConfig(), camera, gmap, device, mode="rgbd")
    result = mapper.optimize(buf, slots, iters)
    print(f"map refit: {iters} iterations, L1 {result.l1_history[0]:.4f} -> {result.final_l1:.4f}", flush=True)


def run_sequence(seq, camera, gmap, n, kind, drift, device, overrides=None):
    from rgs_warp.config import TrackingConfig
    from rgs_warp.eval import ate
    from rgs_warp.render import Renderer
    from rgs_warp.tracking import Tracker, pose_error

    renderer = Renderer(device)
    tcfg = TrackingConfig(**(overrides or {}))
    tracker = Tracker(tcfg, camera, device, mode="rgbd")
    tracker.reset(seq.poses[0])
    estimates = [seq.poses[0]]
    rows = []
    t0 = time.perf_counter()
    for i in range(1, n):
        if kind == "raw":
            rgb, depth = seq.render(i)
        else:
            res = renderer.forward(gmap, camera, seq.poses[i])
            alpha = res.alpha.numpy()
            depth = np.where(alpha > 0.5, res.depth.numpy() / np.maximum(alpha, 1e-6), 0.0).astype(np.float32)
            gain, bias = seq.exposure[i]
            rgb = np.clip(gain * res.color.numpy() + bias, 0, 1).astype(np.float32)
        r = tracker.track(rgb, depth, gmap)
        estimates.append(r.T_WC)
        dt, dr = pose_error(r.T_WC, seq.poses[i])
        rows.append(
            {"frame": i, "err_mm": 1e3 * dt, "err_deg": dr, "gain": r.gain, "bias": r.bias, "loss": r.loss}
            | {"true_gain": float(seq.exposure[i][0]), "true_bias": float(seq.exposure[i][1])}
            | {"converged": r.converged, "lost": r.lost, "valid_ratio": r.valid_ratio}
        )
    seconds = (time.perf_counter() - t0) / (n - 1)
    est, gt = np.array(estimates), seq.poses[:n]
    return {
        "observations": kind,
        "tracking": overrides or {},
        "exposure_drift": drift,
        "ate_rmse_cm": ate(est, gt, align="none")["rmse_cm"],
        "ate_rmse_cm_se3": ate(est, gt, align="se3")["rmse_cm"],
        "max_err_mm": max(r["err_mm"] for r in rows),
        "max_err_deg": max(r["err_deg"] for r in rows),
        "converged": sum(r["converged"] for r in rows),
        "lost": sum(r["lost"] for r in rows),
        "seconds_per_frame": seconds,
        "frames": rows,
    }


def parse_overrides(text: str) -> dict:
    """'depth_weight=0.3,iters=60' -> {'depth_weight': 0.3, 'iters': 60} (numbers parsed, else str)."""
    out = {}
    for item in filter(None, text.split(",")):
        key, value = item.split("=", 1)
        try:
            out[key] = int(value)
        except ValueError:
            try:
                out[key] = float(value)
            except ValueError:
                out[key] = value
    return out


def keyframe_statistics(seq, camera, device) -> dict:
    """The lead's KeyframeSelector along the whole ground-truth path, with the map growing as a SLAM
    map does: each accepted keyframe adds discs on its ground-truth depth (one every 2 pixels), and
    every frame's visibility mask comes from the alpha render of the map built so far."""
    from helpers_maps import map_from_rgbd
    from rgs_warp.config import KeyframeConfig
    from rgs_warp.keyframes import KeyframeBuffer, KeyframeSelector
    from rgs_warp.render import Renderer

    cfg = KeyframeConfig()
    selector = KeyframeSelector(cfg, camera, device)
    buffer = KeyframeBuffer(cfg.buffer_size, camera.width, camera.height, device)
    renderer = Renderer(device)
    gmap = None
    decisions = []
    for i, T_WC in enumerate(seq.poses):
        rgb, depth = seq.render(i)
        if gmap is None:
            alpha = depth_r = wp.zeros((camera.height, camera.width), dtype=wp.float32, device=device)
        else:
            res = renderer.forward(gmap, camera, T_WC)
            alpha, depth_r = res.alpha, res.depth
        d = selector.should_add(alpha, T_WC, depth=depth_r)
        decisions.append({"frame": i, "keyframe": d.is_keyframe, "iou": d.iou, "reason": d.reason})
        if d.is_keyframe:
            selector.accept(T_WC)
            buffer.add(i, T_WC, rgb, depth)
            new = map_from_rgbd([(rgb, depth, T_WC)], camera, stride=2, sigma_per_spacing=0.5, device=device)
            if gmap is None:
                gmap = new
            else:
                fields = new.to_numpy()
                gmap.append(
                    fields["means"], fields["rotations"], fields["log_scales"], fields["opacity_logits"], fields["sh"]
                )
    kf = [d["frame"] for d in decisions if d["keyframe"]]
    return {
        "config": asdict(cfg),
        "frames": len(decisions),
        "keyframe_frames": kf,
        "rho": len(kf) / len(decisions),
        "buffer_frame_ids_oldest_first": [int(buffer.frame_ids[s]) for s in buffer.slots()],
        "map_gaussians": len(gmap),
        "reasons": {r: sum(d["reason"].startswith(r) for d in decisions) for r in ("IoU", "overlap", "motion")},
        "iou": [round(d["iou"], 4) for d in decisions],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--observations", nargs="+", default=["rendered", "raw"], choices=["rendered", "raw"])
    parser.add_argument("--keyframes", action="store_true", help="keyframe statistics along the whole path instead")
    parser.add_argument("--no-ablation", action="store_true", help="only the no-drift run (raw frames are slow)")
    parser.add_argument("--frames", type=int, default=50)
    parser.add_argument("--width", type=int, default=96)
    parser.add_argument("--height", type=int, default=54)
    parser.add_argument("--map-stride", type=int, default=1, help="one disc every stride pixels")
    parser.add_argument("--map-every", type=int, default=10, help="map frames: every n-th frame of the segment")
    parser.add_argument("--refine-iters", type=int, default=15, help="colour refit of the map (0: off)")
    parser.add_argument(
        "--refit",
        default="colours",
        choices=["colours", "mapper"],
        help="colour-only Adam (host) or the Mapper (device)",
    )
    parser.add_argument("--scene", default="room0")
    parser.add_argument(
        "--tracking",
        nargs="*",
        default=[""],
        help="TrackingConfig variants, each 'key=value,key=value' ('' = defaults); every variant is run",
    )
    parser.add_argument("--tag", default="", help="suffix of the result file name (e.g. gpu)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", default=os.environ.get("OUT", "bench_out"))
    args = parser.parse_args()
    os.environ.setdefault("WARP_CACHE_PATH", str(ROOT / ".cache" / "warp"))
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    from rgs_warp.app.report import git_commit
    from rgs_warp.datasets.synthetic import SequenceRenderer, SyntheticConfig

    device = args.device
    t_start = time.perf_counter()
    cfg = SyntheticConfig(scene=args.scene, width=args.width, height=args.height, n_frames=200, exposure_drift=True)
    seqs = {True: SequenceRenderer(cfg, device=device)}  # same path, with and without the exposure walk
    seqs[False] = SequenceRenderer(replace(cfg, exposure_drift=0.0), device=device)
    camera = cfg.camera
    map_ids = [] if args.keyframes else list(range(0, args.frames, args.map_every))
    gmap = (
        build_map(seqs[False], camera, map_ids, args.map_stride, args.refine_iters, device, args.refit)
        if map_ids
        else None
    )
    print(f"map: {len(gmap or [])} Gaussians from frames {map_ids} ({time.perf_counter() - t_start:.0f} s)", flush=True)
    report = {
        "machine": machine(device),
        "commit": git_commit(),
        "warp": wp.config.version,
        "scene": asdict(cfg) | {"camera": asdict(camera)},
        "map": {"gaussians": len(gmap or []), "frames": map_ids, "stride": args.map_stride}
        | {"refit": args.refit, "refit_iters": args.refine_iters},
        "runs": [],
    }
    if args.keyframes:
        report["keyframes"] = keyframe_statistics(seqs[False], camera, device)
        args.observations = ["keyframes"]
    else:
        for kind in args.observations:
            configs = (False,) if args.no_ablation else (False, True)
            variants = [parse_overrides(v) for v in args.tracking]
            for drift, overrides in [(c, v) for v in variants for c in configs]:
                run = run_sequence(seqs[drift], camera, gmap, args.frames, kind, drift, device, overrides)
                report["runs"].append(run)
                print(
                    f"{kind:8s} {overrides} drift={drift!s:5s} "
                    f"ATE {run['ate_rmse_cm']:.3f} cm "
                    f"(se3 {run['ate_rmse_cm_se3']:.3f}), max {run['max_err_mm']:.2f} mm / "
                    f"{run['max_err_deg']:.3f} deg, converged {run['converged']}, lost {run['lost']}, "
                    f"{run['seconds_per_frame']:.1f} s/frame",
                    flush=True,
                )
    report["total_seconds"] = time.perf_counter() - t_start
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name = "tracking_" + "_".join(args.observations) + (f"_{args.tag}" if args.tag else "") + ".json"
    (out / name).write_text(json.dumps(report, indent=1, default=float))
    reports = [json.loads(p.read_text()) for p in sorted(out.glob("tracking_*.json"))]
    (out / "tracking.md").write_text("# Tracker\n\n" + "\n".join(markdown(r) for r in reports))
    print(markdown(report))


def markdown(report: dict) -> str:
    cam = report["scene"]["camera"]
    head = (
        f"Machine: {report['machine']}; commit {report['commit']}; warp-lang {report['warp']}; "
        f"total {report['total_seconds'] / 60:.1f} min. Scene {report['scene']['scene']}, "
        f"{cam['width']}x{cam['height']} "
        f"(fx {cam['fx']:g}), {report['scene']['n_frames']}-frame path."
    )
    if "keyframes" in report:
        k = report["keyframes"]
        c = k["config"]
        return "\n".join(
            [
                "## Keyframe selection along the synthetic path",
                "",
                head,
                f"KeyframeSelector defaults (IoU < {c['iou_threshold']} of alpha > {c['alpha_threshold']} masks, "
                f"compared {c['covisibility']}, AND "
                f"motion > {c['min_translation_m']} m or {c['min_rotation_deg']} deg), ground-truth poses, the map "
                f"growing by each keyframe's discs ({k['map_gaussians']:,} Gaussians at the end).",
                "",
                f"- rho = {k['rho']:.3f}: {len(k['keyframe_frames'])} keyframes in {k['frames']} frames: "
                f"{k['keyframe_frames']}",
                f"- decisions: {k['reasons']} (IoU = accepted, overlap = IoU too high, motion = below the bounds)",
                f"- buffer (capacity {c['buffer_size']}, FIFO) at the end: frames {k['buffer_frame_ids_oldest_first']}",
                f"- IoU median {np.median(k['iou'][1:]):.3f}, min {min(k['iou'][1:]):.3f}",
                "",
            ]
        )
    kinds = ", ".join(sorted({r["observations"] for r in report["runs"]}))
    m = report["map"]
    iters = m.get("refit_iters", m.get("colour_refit_iters", 0))
    refit = (
        f"all parameters refitted by the Mapper to those frames at their true poses, {iters} iterations"
        if m.get("refit") == "mapper"
        else f"colours refitted {iters} iterations"
    )
    lines = [
        f"## Tracking against a map built from ground truth ({kinds} observations)",
        "",
        head,
        f"Map: {report['map']['gaussians']:,} Gaussians on the GT depth of frames {report['map']['frames']} "
        f"(1.5x wider view, one disc every {report['map']['stride']} pixels, {refit}). "
        "Tracker defaults (RGB-D, 30 iterations), start from the "
        "true first pose, then the constant-velocity prediction.",
        "",
        "| observations | tracking overrides | exposure drift | ATE RMSE (cm, no alignment) "
        "| ATE RMSE (cm, SE(3)) | max error (mm / deg) | converged | lost | s / frame |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in report["runs"]:
        lines.append(
            f"| {r['observations']} | {overrides_text(r.get('tracking'))} | {'on' if r['exposure_drift'] else 'off'} "
            f"| {r['ate_rmse_cm']:.3f} | {r['ate_rmse_cm_se3']:.3f} | {r['max_err_mm']:.2f} / {r['max_err_deg']:.3f} "
            f"| {r['converged']}/{len(r['frames'])} | {r['lost']} | {r['seconds_per_frame']:.1f} |"
        )
    by = {(r["observations"], r["exposure_drift"]): r["ate_rmse_cm"] for r in report["runs"] if not r.get("tracking")}
    lines.append("")
    for kind in ("rendered", "raw"):
        if (kind, False) in by and (kind, True) in by:
            lines.append(f"- {kind}: drift = {by[(kind, True)] / by[(kind, False)]:.2f}x the no-drift ATE.")
    return "\n".join(lines) + "\n"


def overrides_text(overrides) -> str:
    return ", ".join(f"{k}={v}" for k, v in (overrides or {}).items()) or "defaults"


if __name__ == "__main__":
    main()
