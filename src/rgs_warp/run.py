"""A run of the SLAM system on a dataset, and the command line ``python -m rgs_warp.slam``: ``run``
tracks every frame with ``SLAM``, saves what it tracked (also when stopped), and evaluates it
(``evaluate_run``: ATE, photometric metrics on held-out frames, mesh metrics) into the run folder's
report and figures.
"""

from __future__ import annotations

import json
import sys
import time
from datetime import datetime
from pathlib import Path

import numpy as np
import warp as wp
from tqdm import tqdm

from rgs_warp.config import Config, ConfigError, help_text, load_config, resolve_device, save_config
from rgs_warp.datasets import DatasetError, open_dataset
from rgs_warp.eval import (
    LPIPS,
    ate_keyframes_and_all,
    compensate_exposure,
    eval_frame_indices,
    photometric_metrics,
    plot_trajectory_topview,
    psnr,
    write_report,
)
from rgs_warp.slam import SLAM

USAGE = """usage: python -m rgs_warp.slam [group=option ...] [key=value ...]

examples:
  python -m rgs_warp.slam                                  # generated synthetic room (CPU-sized)
  python -m rgs_warp.slam method=baseline                  # the same with the dense initialization baseline
  python -m rgs_warp.slam dataset=replica/office0 data_root=/data tracking.iters=40
  python -m rgs_warp.slam dataset=7scenes/redkitchen dataset.path=../shared/data/7scenes-redkitchen
"""


def make_run_dir(cfg: Config) -> Path:
    name = cfg.run_name or f"{cfg.dataset.type}-{cfg.dataset.name}-{datetime.now():%Y%m%d-%H%M%S}"
    run_dir = Path(cfg.output_dir) / name
    run_dir.mkdir(parents=True, exist_ok=True)
    return run_dir


def dataset_summary(ds) -> dict:
    c = ds.camera
    return {
        "dataset": repr(ds),
        "frames": len(ds),
        "resolution": [c.width, c.height],
        "intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy},
    }


def ground_truth_mesh(cfg: Config, ds) -> Path | None:
    """The sequence's ground-truth mesh when there is one: the synthetic scenes' ``mesh.ply``, or
    Replica's ``<scene>_mesh.ply`` next to the scene folder (the NICE-SLAM layout)."""
    path = getattr(ds, "mesh_path", None)
    if path is not None and Path(path).is_file():
        return Path(path)
    if cfg.dataset.type == "replica":
        folder = cfg.dataset_path()
        candidate = folder.parent / f"{folder.name}_mesh.ply"
        if candidate.is_file():
            return candidate
    return None


def peak_memory_mib(device) -> float | None:
    device = wp.get_device(device)
    if not device.is_cuda or not wp.is_mempool_enabled(device):
        return None
    return wp.get_mempool_used_mem_high(device) / 2**20


def run(cfg: Config, run_dir: Path | None = None, progress: bool = True) -> tuple[Path, dict]:
    """Run SLAM on the configured sequence and evaluate it; returns (run folder, metrics).

    The folder gets: ``config.yaml``, ``dataset.json``, ``trajectory.txt`` (TUM, readable by evo),
    ``map.ply`` (3DGS layout), ``keyframes.npz``, ``metrics.json`` + ``metrics.md``,
    ``trajectory_topview.png``, ``renders/*.png`` (render | ground truth side by side),
    ``log.jsonl`` (one line per frame) and ``convergence.json`` + ``convergence.png`` (``SLAM.convergence``:
    window PSNR against the cumulative mapping iterations).  If the run stops early (error, Ctrl-C),
    what was tracked so far is still saved, and the error is re-raised.
    """
    device = resolve_device(cfg.device)
    ds = open_dataset(cfg, device=device)
    run_dir = run_dir or make_run_dir(cfg)
    run_dir.mkdir(parents=True, exist_ok=True)
    save_config(cfg, run_dir / "config.yaml")
    (run_dir / "dataset.json").write_text(json.dumps(dataset_summary(ds), indent=2))
    first = ds[0]
    slam = SLAM(cfg, ds.camera, device=device, T_first_WC=first.pose_gt)
    gt_poses, frame_losses, lost = [], [], []  # lost: (frame, reason) of each frame whose tracking was lost
    tracked = 0  # frames tracked or lost (the first frame and the monocular bootstrap's waiting ones are not)
    t_start = time.perf_counter()
    bar = tqdm(total=len(ds), desc=f"{cfg.dataset.type}/{cfg.dataset.name}", unit="frame", disable=not progress)
    log = (run_dir / "log.jsonl").open("w", encoding="utf-8", buffering=1)  # a line per frame, readable while it runs
    try:
        for frame in ds:
            result = slam.process(frame.rgb, frame.depth if cfg.mode == "rgbd" else None, frame.timestamp)
            gt_poses.append(frame.pose_gt)
            entry = {
                "frame": result.index,
                "keyframe": result.keyframe,
                "reason": result.keyframe_reason,
                "seconds": round(result.seconds, 4),
                "gaussians": len(slam.map),
            }
            if result.tracking is not None:
                entry.update(loss=result.tracking.loss, lost=result.tracking.lost, gain=result.tracking.gain)
                frame_losses.append(result.tracking.loss)
            tracked += result.tracking is not None or result.lost
            if result.lost:  # tracking lost, or the frame's input unusable (then not tracked)
                entry.update(lost=True, lost_reason=result.lost_reason)
                lost.append((result.index, result.lost_reason))
            for key in ("nonfinite_rgb", "nonfinite_depth"):
                if getattr(result, key):
                    entry[key] = getattr(result, key)
            if result.keyframe:
                entry.update(seeded=result.seeded, pruned=result.pruned, merged=result.merged)
                if result.mapping is not None and result.mapping.iters:
                    entry["mapping_l1"] = result.mapping.final_l1
                if cfg.method == "baseline" and result.mapping is not None:
                    entry.update(cloned=result.mapping.cloned, split=result.mapping.split)
            elif result.seeded:  # frame fill: seeds waiting for the next keyframe
                entry["seeded"] = result.seeded
            log.write(json.dumps(entry) + "\n")
            elapsed = time.perf_counter() - t_start
            bar.set_postfix(
                fps=f"{(result.index + 1) / elapsed:.2f}",
                kf=len(slam.keyframe_indices),
                gaussians=len(slam.map),
                loss=f"{frame_losses[-1]:.4f}" if frame_losses else "-",
                lost=len(lost),
            )
            bar.update(1)
    finally:
        bar.close()
        log.close()
        slam.finish()
        slam.save(run_dir)
        write_convergence(run_dir, slam.convergence, title=f"{cfg.dataset.type}/{cfg.dataset.name} ({cfg.method})")
    wall = time.perf_counter() - t_start
    metrics = evaluate_run(cfg, ds, slam, gt_poses, run_dir, wall, tracking_section(tracked, lost))
    return run_dir, metrics


def tracking_section(tracked: int, lost: list[tuple[int, str]]) -> dict:
    """The report's ``tracking`` section: how many of the ``tracked`` frames were lost (``lost``: frame
    index and the tracker's reason of each) and the first of them."""
    section: dict = {"tracked_frames": tracked, "lost_frames": len(lost)}
    if lost:
        section["first_lost_frame"], section["first_lost_reason"] = lost[0]
    else:
        section["first_lost_frame"] = section["first_lost_reason"] = None
        section["first_lost_frame_na_reason"] = section["first_lost_reason_na_reason"] = "never lost"
    return section


def write_convergence(run_dir: Path, points: list[dict], title: str) -> None:
    """``convergence.json`` (the points of ``SLAM.convergence``) and ``convergence.png``: the window's
    PSNR against the cumulative mapping iterations (initialization samples joined by a line, one
    marker per keyframe's mapping after it) with the number of Gaussians on a second axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (run_dir / "convergence.json").write_text(json.dumps(points, indent=1) + "\n", encoding="utf-8")
    fig, ax = plt.subplots(figsize=(7.0, 4.0), dpi=150)
    count_ax = ax.twinx()
    for phase, style in (("init", "-o"), ("keyframe", "s")):
        shown = [p for p in points if p["phase"] == phase and p["psnr_db"] is not None]
        label = "initialization window" if phase == "init" else "window after a keyframe's mapping"
        ax.plot([p["iteration"] for p in shown], [p["psnr_db"] for p in shown], style, markersize=3, label=label)
    count_ax.plot([p["iteration"] for p in points], [p["gaussians"] for p in points], color="gray", linewidth=0.8)
    count_ax.set_ylabel("Gaussians", color="gray")
    ax.set_xlabel("mapping iterations (cumulative)")
    ax.set_ylabel("mean window PSNR (dB)")
    ax.set_title(title)
    ax.grid(True, linewidth=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(run_dir / "convergence.png")
    plt.close(fig)


def evaluate_run(
    cfg: Config, ds, slam: SLAM, gt_poses: list, run_dir: Path, wall_s: float, tracking: dict | None = None
) -> dict:
    """Metrics of a finished run (supplement §3) written with ``write_report``; ``tracking``: the
    section of ``tracking_section``."""
    _, est = slam.trajectory()
    n = len(est)
    metrics: dict = {
        "dataset": f"{cfg.dataset.type}/{cfg.dataset.name}",
        "method": cfg.method,
        "mode": cfg.mode,
        "device": str(slam.device),
        "frames": n,
        "keyframes": len(slam.keyframe_indices),
        "gaussians": len(slam.map),
        "fps": n / wall_s if wall_s > 0 else None,
        "tracking_fps": (n - 1) / slam.stats["tracking_s"] if slam.stats["tracking_s"] > 0 else None,
        "wall_s": wall_s,
    }
    mem = peak_memory_mib(slam.device)
    metrics["peak_memory_mib"] = mem
    if mem is None:
        metrics["peak_memory_mib_na_reason"] = "measured on CUDA devices only (Warp's memory pool)"
    if metrics["tracking_fps"] is None:
        metrics["tracking_fps_na_reason"] = "a single frame"
    metrics["time_s"] = {k: v for k, v in slam.stats.items() if k.endswith("_s")}
    if tracking is not None:
        metrics["tracking"] = tracking
    has_gt = all(p is not None for p in gt_poses) and n >= 3
    if has_gt:
        gt = np.array(gt_poses)
        align = "sim3" if cfg.mode == "mono" else "se3"
        metrics["ate"] = ate_keyframes_and_all(est, gt, np.array(slam.keyframe_indices), align=align)
        for section in metrics["ate"].values():
            section.pop("align_T", None)
        plot_trajectory_topview(est, gt, run_dir / "trajectory_topview.png", title=metrics["dataset"], align=align)
    else:
        metrics["ate"] = None
        metrics["ate_na_reason"] = "no ground-truth poses" if n >= 3 else "fewer than 3 frames"
        if n >= 2:
            plot_trajectory_topview(est, None, run_dir / "trajectory_topview.png", title=metrics["dataset"])
    # photometric metrics: every eval.every-th frame, keyframes excluded (§3), rendered at the estimate
    idx = eval_frame_indices(n, slam.keyframe_indices, cfg.eval.every)
    renders, refs, alphas, depths, ref_depths = [], [], [], [], []
    for i in idx:
        frame = ds[int(i)]
        res = slam.render(est[i])
        renders.append(np.clip(res.color.numpy(), 0.0, 1.0))
        refs.append(frame.rgb)
        alphas.append(res.alpha.numpy().copy())
        if frame.depth is not None and cfg.mode == "rgbd":  # monocular depth has the map's own scale
            alpha = alphas[-1]
            depths.append(np.where(alpha > 0.5, res.depth.numpy() / np.maximum(alpha, 1e-6), 0.0))
            ref_depths.append(frame.depth)
    if renders:
        lpips = LPIPS(cfg.eval.lpips_alexnet_path or None, cfg.eval.lpips_linear_path or None)
        metrics["photometric"] = photometric_metrics(
            renders, refs, lpips, depths if depths else None, ref_depths if ref_depths else None, alphas
        )
        metrics["photometric"].update(keyframe_fit(ds, slam, est))
        save_side_by_side(run_dir / "renders", [int(i) for i in idx], renders, refs, alphas)
    else:
        metrics["photometric"] = None
        metrics["photometric_na_reason"] = "no non-keyframe frame to score"
    metrics.update(mesh_section(cfg, ds, slam, est))
    write_report(run_dir, metrics, title=f"rgs_warp {metrics['dataset']} ({cfg.method}, {cfg.mode})")
    return metrics


def mesh_section(cfg: Config, ds, slam: SLAM, est: np.ndarray) -> dict:
    """Acc / Comp / Comp.Ratio of the TSDF fusion of rendered depth along the keyframe trajectory."""
    mesh_path = ground_truth_mesh(cfg, ds)
    if mesh_path is None:
        return {"mesh": None, "mesh_na_reason": "no ground-truth mesh for this sequence"}
    if cfg.mode != "rgbd":
        return {"mesh": None, "mesh_na_reason": "monocular run (scale-free map)"}
    try:
        import open3d as o3d

        from rgs_warp.eval import mesh_metrics, tsdf_fuse
    except ImportError as e:
        return {"mesh": None, "mesh_na_reason": f"open3d not importable ({e})"}
    depths, poses = [], []
    for i in slam.keyframe_indices:
        res = slam.render(est[i])
        alpha = res.alpha.numpy()
        depths.append(np.where(alpha > 0.5, res.depth.numpy() / np.maximum(alpha, 1e-6), 0.0).astype(np.float32))
        poses.append(est[i])
    rec = tsdf_fuse(depths, poses, slam.camera)
    gt = o3d.io.read_triangle_mesh(str(mesh_path))
    return {"mesh": mesh_metrics(rec, gt)}


def keyframe_fit(ds, slam: SLAM, est: np.ndarray) -> dict:
    """How well the map fits what it was trained on: the mean PSNR of the renders at every keyframe's
    pose against its frame, raw and exposure-compensated (``keyframe_psnr_db``,
    ``keyframe_psnr_compensated_db``)."""
    raw, compensated = [], []
    for i in slam.keyframe_indices:
        res = slam.render(est[i])
        render, ref = np.clip(res.color.numpy(), 0.0, 1.0), ds[int(i)].rgb
        raw.append(psnr(render, ref))
        compensated.append(psnr(compensate_exposure(render, ref, res.alpha.numpy()), ref))
    return {"keyframe_psnr_db": float(np.mean(raw)), "keyframe_psnr_compensated_db": float(np.mean(compensated))}


def save_side_by_side(
    folder: Path, indices: list[int], renders: list, refs: list, alphas: list, count: int = 4
) -> None:
    """A few scored frames as PNG, evenly over the run: render | ground truth | error, the error being
    |render at the frame's exposure - frame| (``compensate_exposure``), x4 in grey levels."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    picks = np.unique(np.linspace(0, len(indices) - 1, min(count, len(indices))).round().astype(int))
    for k in picks:
        error = np.abs(compensate_exposure(renders[k], refs[k], alphas[k]) - refs[k]).mean(axis=2, keepdims=True)
        row = np.concatenate([renders[k], refs[k], np.repeat(np.clip(4.0 * error, 0.0, 1.0), 3, axis=2)], axis=1)
        image = (np.clip(row, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        cv2.imwrite(str(folder / f"frame{indices[k]:05d}_render_gt_error.png"), image[..., ::-1])


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if any(a in ("-h", "--help") for a in argv):
        print(USAGE)
        print(help_text())
        return 0
    try:
        cfg = load_config(argv)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    try:
        run_dir, metrics = run(cfg)
    except DatasetError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    ate = (metrics.get("ate") or {}).get("all_frames", {})
    photo = metrics.get("photometric") or {}
    print(f"run dir   {run_dir}")
    print(
        f"frames {metrics['frames']}, keyframes {metrics['keyframes']}, Gaussians {metrics['gaussians']}, "
        f"{metrics['fps']:.2f} frames/s"
    )
    if ate:
        print(f"ATE RMSE  {ate['rmse_cm']:.2f} cm (all frames)")
    if photo:
        print(f"PSNR      {photo['psnr_db']:.2f} dB, SSIM {photo['ssim']:.3f}")
    print(f"report    {run_dir / 'metrics.md'}")
    tracking = metrics.get("tracking") or {}
    if tracking.get("lost_frames"):
        print(
            f"warning: tracking was lost in {tracking['lost_frames']} of {tracking['tracked_frames']} tracked frames, "
            f"first at frame {tracking['first_lost_frame']} ({tracking['first_lost_reason']}); poses from there on "
            f"are unreliable (each frame's entry in {run_dir / 'log.jsonl'} says why)",
            file=sys.stderr,
        )
    return 0
