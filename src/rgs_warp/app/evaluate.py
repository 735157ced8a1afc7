"""The evaluation at the end of a run (supplement §3): ATE, photometric metrics on held-out frames,
the keyframes' fit, SplaTAM's protocol, mesh metrics, the convergence plot and the renders, into the
run's report."""

from __future__ import annotations

import importlib.util
import json
import time
from pathlib import Path

import numpy as np

from rgs_warp.app.export import fuse_keyframes
from rgs_warp.app.memory import run_peak_memory
from rgs_warp.app.report import plot_trajectory_topview, write_frame_scores, write_report
from rgs_warp.app.rundir import ground_truth_mesh, read_frames
from rgs_warp.config import Config
from rgs_warp.eval import (
    LPIPS,
    ate_keyframes_and_all,
    cached_alexnet_path,
    compensate_exposure,
    eval_frame_indices,
    frame_scores,
    mean_scores,
    mesh_metrics,
    metric_device,
    photometric_metrics,
)
from rgs_warp.slam import SLAM

# what the evaluation at the end of a run imports, and the pip name that provides it
EVALUATION_IMPORTS = {"torch": "torch", "pytorch_msssim": "pytorch-msssim"}

# SplaTAM's protocol scores every 5th frame, the keyframes included (its Table 1-3 PSNR / SSIM / LPIPS)
SPLATAM_EVERY = 5

# metrics.md's line under the photometric table: what each PSNR means
PSNR_LEGEND = (
    "PSNR raw: the render as is; compensated: one gain and bias fitted to the frame (MonoGS's protocol); "
    "tracked exposure: rendered at the SLAM's own gain/bias estimate, the primary number (both clip(g render + b), "
    "clipped after the exposure as a camera clips); "
    "keyframe: the fit to trained views; row photometric: every eval.every-th frame, trained views left out; "
    "row every_5th_with_keyframes: every 5th frame, keyframes included (SplaTAM's protocol)."
)
FINAL_LEGEND = (
    "After the last frame: mapping.final_share x the run's iterations (live, mapping.catch_up: at least up to an "
    "offline run's count) over every view on the device; iters_planned > iters: Ctrl-C ended it; keyframe PSNR: "
    "the mean over every keyframe, before and after."
)


def check_evaluation_imports() -> None:
    """Refuse to start a run whose evaluation could not import what it needs (a run of minutes
    would otherwise end in a ModuleNotFoundError); an ``ImportError`` naming what to install."""
    missing = [pip for module, pip in EVALUATION_IMPORTS.items() if importlib.util.find_spec(module) is None]
    if missing:
        raise ImportError(
            f"the evaluation at the end of a run needs {', '.join(missing)}, which is not installed: "
            f"pip install {' '.join(missing)} (nothing was run)"
        )


def tracking_section(
    tracked: int, lost: list[tuple[int, str]], settled: list[int] | None = None, iters: int | None = None
) -> dict:
    """The report's ``tracking`` section: how many of the ``tracked`` frames were lost (``lost``: frame
    index and the tracker's reason of each) and the first of them; with ``settled`` (each tracked
    frame's ``settled_iters``) their median and 90th percentile against the ``iters`` steps taken."""
    section: dict = {"tracked_frames": tracked, "lost_frames": len(lost)}
    if settled:
        section["settled_iters_p50"] = float(np.percentile(settled, 50))
        section["settled_iters_p90"] = float(np.percentile(settled, 90))
        section["iters"] = iters
    if lost:
        section["first_lost_frame"], section["first_lost_reason"] = lost[0]
    else:
        section["first_lost_frame"] = section["first_lost_reason"] = None
        section["first_lost_frame_na_reason"] = section["first_lost_reason_na_reason"] = "never lost"
    return section


def write_convergence(run_dir: Path, points: list[dict], title: str) -> None:
    """``convergence.json`` (the points of ``SLAM.convergence``) and ``convergence.png``: the window's
    PSNR against the cumulative mapping iterations (initialization samples joined by a line, one
    marker per keyframe's mapping after it, and the keyframes' mean after the final refinement) with the
    number of Gaussians on a second axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (run_dir / "convergence.json").write_text(json.dumps(points, indent=1) + "\n", encoding="utf-8")
    fig, ax = plt.subplots(figsize=(7.0, 4.0), dpi=150)
    count_ax = ax.twinx()
    labels = {
        "init": ("-o", "initialization window"),
        "keyframe": ("s", "window after a keyframe's mapping"),
        "final": ("D", "every keyframe after the final refinement"),
    }
    for phase, (style, label) in labels.items():
        shown = [p for p in points if p["phase"] == phase and p["psnr_db"] is not None]
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
    cfg: Config,
    ds,
    slam: SLAM,
    gt_poses: list,
    run_dir: Path,
    wall_s: float,
    tracking: dict | None = None,
    kernels: dict | None = None,
    peak_floor_mib: float | None = 0.0,
    exposures: list | None = None,
    loop_s: dict | None = None,
    save=None,
    playback: dict | None = None,
) -> dict:
    """Metrics of a finished run (supplement §3) written with ``write_report``; ``tracking``: the
    section of ``tracking_section``; ``kernels``: ``KernelLoads.summary()`` (the seconds the run spent
    compiling Warp kernels, part of ``wall_s``); ``peak_floor_mib``: ``start_peak_memory``'s floor;
    ``exposures``: each frame's tracked (gain, bias) (``RunState.exposures``), for the scores at the
    tracked exposure; ``loop_s``: more seconds for ``time_s`` (the frame loop's waits); ``save``: the
    run's final save (``FinalSave``), written meanwhile: waited for (its ``SaveError`` raised) before the report, its
    seconds ``time_s.save_s``; ``playback``: ``Playback.summary()`` of a run played at
    ``dataset.playback_fps``.  ``time_s.evaluation_s``: this evaluation's seconds, up to the report (the
    final save's wait not included)."""
    t_start = time.perf_counter()
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
    metrics["peak_memory_mib"], reason = run_peak_memory(slam.device, peak_floor_mib)
    if reason:
        metrics["peak_memory_mib_na_reason"] = reason
    if metrics["tracking_fps"] is None:
        metrics["tracking_fps_na_reason"] = "a single frame"
    metrics["time_s"] = {k: v for k, v in slam.stats.items() if k.endswith("_s")}
    metrics["mapping_iterations"] = slam.mapper.total_iters
    # the mapping budget (mapping.rate_fps) and how it was spent: iterations by kind, a frame and a keyframe
    its = slam.mapping_iterations
    metrics["mapping_budget"] = {
        "rate_fps": cfg.mapping.rate_fps,
        "iterations_per_frame_budget": slam.budget.per_frame,
        "iterations": dict(its),
        "iterations_per_frame": (its["keyframe"] + its["refine"]) / max(1, len(slam.poses)),
        "iterations_per_keyframe": its["keyframe"] / max(1, slam.budget.keyframes),
    }
    # renders of the mapping renderer (mapping, seeding) found to have dropped intersections
    metrics["mapping_renders_overflowed"] = slam.renderer.overflowed_renders
    # mapping steps run eagerly, captured and replayed (mapping.graph), replays that overflowed
    metrics["mapping_graph_steps"] = dict(slam.mapper.graph_counts)
    metrics["mapping"] = "asynchronous" if cfg.mapping.asynchronous else "synchronous"
    # tracked frames that wanted a frame fill, and those that got none (mapping.fill_queue, asynchronous)
    metrics["frame_fills"] = dict(slam.frame_fills)
    if playback is not None:
        metrics["playback"] = playback
    turns = slam.mapping_jobs.turn_seconds()
    if turns is not None:  # asynchronous: seconds tracking and the mapping worker each held the device's turn
        metrics["device_turns_s"] = turns
    if slam.keyframe_latency_s:  # asynchronous: from a keyframe's tracking to its map published
        lat = np.array(slam.keyframe_latency_s)
        metrics["keyframe_to_map_s"] = {
            "count": len(lat),
            "p50": float(np.median(lat)),
            "p99": float(np.percentile(lat, 99)),
            "max": float(lat.max()),
        }
    if kernels is not None:
        metrics["kernels"] = kernels
    if slam.final_refinement is not None:  # mapping.final_share: reported apart from the run's mapping
        metrics["final_refinement"] = slam.final_refinement
    if tracking is not None:
        metrics["tracking"] = tracking
    has_gt = all(p is not None for p in gt_poses) and n >= 3
    if has_gt:
        gt = np.array(gt_poses)
        align = "sim3" if cfg.mode == "mono" else "se3"
        metrics["ate"] = ate_keyframes_and_all(est, gt, np.array(slam.keyframe_indices), align=align)
        for section in metrics["ate"].values():
            if isinstance(section, dict):
                section.pop("align_T", None)
        plot_trajectory_topview(est, gt, run_dir / "trajectory_topview.png", title=metrics["dataset"], align=align)
    else:
        metrics["ate"] = None
        metrics["ate_na_reason"] = "no ground-truth poses" if n >= 3 else "fewer than 3 frames"
        if n >= 2:
            plot_trajectory_topview(est, None, run_dir / "trajectory_topview.png", title=metrics["dataset"])
    # photometric metrics: every eval.every-th frame, trained views excluded (§3), rendered at the estimate
    idx = eval_frame_indices(n, trained_frames(slam), cfg.eval.every)
    renders, refs, alphas, depths, ref_depths = [], [], [], [], []
    for i, frame in zip(idx, read_frames(ds, idx), strict=True):
        res = slam.render(est[i])
        renders.append(res.color.numpy().copy())  # as rendered: frame_scores clips after the exposure
        refs.append(frame.rgb)
        alphas.append(res.alpha.numpy().copy())
        if frame.depth is not None and cfg.mode == "rgbd":  # monocular depth has the map's own scale
            alpha = alphas[-1]
            depths.append(np.where(alpha > 0.5, res.depth.numpy() / np.maximum(alpha, 1e-6), 0.0))
            ref_depths.append(frame.depth)
    if renders:
        alexnet = cfg.eval.lpips_alexnet_path or cached_alexnet_path()
        on = metric_device(slam.device)
        lpips = LPIPS(alexnet, cfg.eval.lpips_linear_path or None, device=on or "cpu")
        tracked = None
        if exposures is not None and len(exposures) >= n:
            tracked = [tuple(e or (1.0, 0.0)) for e in exposures[:n]]
        rows: list = []
        metrics["photometric"] = photometric_metrics(
            renders,
            refs,
            lpips,
            depths if depths else None,
            ref_depths if ref_depths else None,
            alphas,
            on,
            None if tracked is None else [tracked[i] for i in idx],
            frame_scores_out=rows,
        )
        # SplaTAM's every 5th frame is among the held-out ones where eval.every divides 5
        protocol = SPLATAM_EVERY % cfg.eval.every == 0
        fit, fit_rows = keyframe_fit(ds, slam, est, on, tracked, lpips, SPLATAM_EVERY if protocol else None)
        metrics["photometric"].update(fit)
        scored = list(zip((int(i) for i in idx), rows, strict=True))
        if protocol:
            splatam = [row for i, row in scored + fit_rows if i % SPLATAM_EVERY == 0]
            metrics["photometric"]["every_5th_with_keyframes"] = mean_scores(splatam, lpips.reason)
        else:
            metrics["photometric"]["every_5th_with_keyframes"] = None
            metrics["photometric"]["every_5th_with_keyframes_na_reason"] = (
                f"eval.every={cfg.eval.every} does not score every {SPLATAM_EVERY}th frame"
            )
        save_side_by_side(run_dir / "renders", [int(i) for i in idx], renders, refs, alphas)
        title = f"{metrics['dataset']}: PSNR of every scored frame and keyframe"
        is_keyframe = set(slam.keyframe_indices)
        keyframes = [(i, row) for i, row in fit_rows if i in is_keyframe]
        views = [(i, row) for i, row in fit_rows if i not in is_keyframe]  # frames kept as views, on the grid
        write_frame_scores(
            run_dir / "frame_scores.csv",
            run_dir / "frame_scores.png",
            psnrs(scored),
            psnrs(keyframes),
            title,
            psnrs(views),
        )
    else:
        metrics["photometric"] = None
        metrics["photometric_na_reason"] = "no non-keyframe frame to score"
    metrics.update(mesh_section(cfg, ds, slam, run_dir))
    metrics["time_s"].update(loop_s or {})
    metrics["time_s"]["evaluation_s"] = time.perf_counter() - t_start
    if save is not None:
        save.write()
        metrics["time_s"]["save_s"] = save.seconds
    title = f"rgs_warp {metrics['dataset']} ({cfg.method}, {cfg.mode})"
    write_report(run_dir, metrics, title=title, notes={"photometric": PSNR_LEGEND, "final_refinement": FINAL_LEGEND})
    return metrics


def mesh_section(cfg: Config, ds, slam: SLAM, run_dir: Path) -> dict:
    """Acc / Comp / Comp.Ratio of the TSDF fusion of rendered depth and colour at the keyframes
    (``rgs_warp.app.export.fuse_keyframes``); with ``export.mesh`` that mesh is also ``mesh.ply``."""
    mesh_path = ground_truth_mesh(cfg, ds)
    if cfg.mode != "rgbd":
        return {"mesh": None, "mesh_na_reason": "monocular run (scale-free map)"}
    if mesh_path is None and not cfg.export.mesh:
        return {"mesh": None, "mesh_na_reason": "no ground-truth mesh for this sequence"}
    try:
        from rgs_warp.eval.reconstruction import require_open3d

        o3d = require_open3d()
    except ImportError as e:
        return {"mesh": None, "mesh_na_reason": f"open3d not importable ({e})"}
    rec = fuse_keyframes(slam, voxel_m=cfg.export.voxel_m)
    if cfg.export.mesh:
        o3d.io.write_triangle_mesh(str(run_dir / "mesh.ply"), rec, write_vertex_colors=True)
    if mesh_path is None:
        return {"mesh": None, "mesh_na_reason": "no ground-truth mesh for this sequence"}
    return {"mesh": mesh_metrics(rec, o3d.io.read_triangle_mesh(str(mesh_path)))}


def trained_frames(slam: SLAM) -> list[int]:
    """The frames mapping trained on, sorted: left out of the held-out scores and scored by ``keyframe_fit``.
    The keyframes and the frames between them kept as views (``mapping.frame_views``)."""
    views = slam.frame_views.frame_ids if slam.frame_views is not None else []
    return sorted({int(i) for i in slam.keyframe_indices} | {int(i) for i in views})


def keyframe_fit(
    ds,
    slam: SLAM,
    est: np.ndarray,
    device: str | None = None,
    tracked: list | None = None,
    lpips_model: LPIPS | None = None,
    every: int | None = None,
) -> tuple[dict, list]:
    """How well the map fits what it was trained on (``trained_frames``): the keyframes' mean PSNR of the
    renders at their poses against their frames, raw, exposure-compensated and at the tracked exposure
    (``keyframe_psnr_db``, ``keyframe_psnr_compensated_db``, ``keyframe_psnr_tracked_exposure_db``), and
    (index, ``frame_scores`` row) of each keyframe and of each trained frame on the ``every``-th grid: PSNRs
    only, but every ``every``-th frame's in full (SSIMs, LPIPS with ``lpips_model``) for SplaTAM's protocol.
    ``tracked``: each frame's tracked (gain, bias), None without; ``device``: the torch device of the scores."""
    rows = []
    keyframes = {int(i) for i in slam.keyframe_indices}
    # the frames kept as views count only in SplaTAM's protocol (a stream keeps no other frame for the evaluation)
    frames = [i for i in trained_frames(slam) if i in keyframes or (every is not None and i % every == 0)]
    for i, frame in zip(frames, read_frames(ds, frames), strict=True):
        res = slam.render(est[i])
        render = res.color.numpy()  # as rendered, scored before the next render
        at = None if tracked is None else tracked[i]
        full = every is not None and i % every == 0
        row = frame_scores(render, frame.rgb, res.alpha.numpy(), at, device, lpips_model, psnr_only=not full)
        rows.append((i, row))

    def mean(key: str) -> float:
        return float(np.mean([row[key] for i, row in rows if i in keyframes]))

    fit = {"keyframe_psnr_db": mean("psnr"), "keyframe_psnr_compensated_db": mean("psnr_compensated")}
    fit["keyframe_psnr_tracked_exposure_db"] = None if tracked is None else mean("psnr_tracked")
    if tracked is None:
        fit["keyframe_psnr_tracked_exposure_db_na_reason"] = "no tracked exposures given"
    return fit, rows


def psnrs(rows: list) -> list[tuple[int, float, float, float | None]]:
    """(frame, raw, compensated, at the tracked exposure or None) PSNRs of (frame, ``frame_scores`` row)s."""
    return [(i, row["psnr"], row["psnr_compensated"], row.get("psnr_tracked")) for i, row in rows]


def error_image(render: np.ndarray, ref: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """|render at the frame's exposure - frame| (``compensate_exposure``), x4 in grey levels (H x W x 3)."""
    error = np.abs(compensate_exposure(render, ref, alpha) - ref).mean(axis=2, keepdims=True)
    return np.repeat(np.clip(4.0 * error, 0.0, 1.0), 3, axis=2)


def save_side_by_side(
    folder: Path, indices: list[int], renders: list, refs: list, alphas: list, count: int = 4
) -> None:
    """A few scored frames as PNG, evenly over the run: render | ground truth | error, the error being
    |render at the frame's exposure - frame| (``compensate_exposure``), x4 in grey levels."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    picks = np.unique(np.linspace(0, len(indices) - 1, min(count, len(indices))).round().astype(int))
    for k in picks:
        row = np.concatenate([renders[k], refs[k], error_image(renders[k], refs[k], alphas[k])], axis=1)
        image = (np.clip(row, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        cv2.imwrite(str(folder / f"frame{indices[k]:05d}_render_gt_error.png"), image[..., ::-1])
