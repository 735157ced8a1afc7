"""How much of each monocular keyframe the map covers, and how right its depth is (issue 22).

    python experiments/bench/mono_coverage.py [--size 320x180] [--path-frames 300] [--frames 90]
        [--fit 48] [--out results.json] [override ...]

Runs the monocular SLAM (``mode=mono``, synchronous, on the CPU unless ``device=`` says otherwise)
frame by frame over the first ``--frames`` frames of the synthetic office
(``dataset=synthetic/office0_replica_size``, its path sampled with ``--path-frames`` frames, generated
at ``--size`` into ``$RGS_CACHE`` on first use).  At each keyframe, right after its
mapping, the map is rendered at the keyframe's estimated pose: coverage = the share of pixels with
accumulated opacity above 0.5; depth error = |s d / alpha - d_true| / d_true over those pixels,
with one scale s fitted at the bootstrap keyframe (the median ratio of true to rendered depth).

After the run: the position error at every tenth frame with the trajectory Sim(3)-fitted to the
ground truth on frames 0..``--fit`` (how far the later frames drift from a start that was right),
the Sim(3) ATE of all frames (``rgs_warp.eval.ate``), lost frames and the run time.  Prints a line
per keyframe and a summary; ``--out`` writes it all as JSON.  The override ``mode=rgbd`` gives the
RGB-D reference on the same frames (with their depth).  Results: experiments/results/mono.md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from rgs_warp.config import load_config, save_config
from rgs_warp.datasets import open_dataset
from rgs_warp.eval.ate import ate, umeyama_alignment
from rgs_warp.render import Renderer
from rgs_warp.slam import SLAM


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="320x180")
    ap.add_argument("--path-frames", type=int, default=300)
    ap.add_argument("--frames", type=int, default=90)
    ap.add_argument("--fit", type=int, default=48, help="last frame of the Sim(3) fit of the position errors")
    ap.add_argument("--out", default=None)
    ap.add_argument(
        "--snapshot",
        default=None,
        help="folder of the SLAM saved (with its state) right after the bootstrap: written by the first run, "
        "resumed from by the next ones with their own overrides (the bootstrap does not depend on them)",
    )
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.split("x"))
    office = ["dataset=synthetic/office0_replica_size", f"dataset.width={w}", f"dataset.height={h}"]
    office += [f"dataset.n_frames={args.path_frames}", f"dataset.max_frames={args.frames}"]
    cfg = load_config([*office, "mode=mono", "device=cpu", *args.overrides])
    ds = open_dataset(cfg, device="cpu")
    camera, frames_in = ds.camera, [ds[i] for i in range(args.frames)]
    rgb, depth = [f.rgb for f in frames_in], [f.depth for f in frames_in]
    gt = np.array([f.pose_gt for f in frames_in])
    snapshot = Path(args.snapshot) if args.snapshot else None
    keyframes, lost, scale, frames, t_slam = [], [], None, [], 0.0
    if snapshot is not None and (snapshot / "state.npz").is_file():
        folder = Path(tempfile.mkdtemp(prefix="mono_coverage_"))
        shutil.copytree(snapshot, folder, dirs_exist_ok=True)
        save_config(cfg, folder / "config.yaml")  # this run's overrides
        slam = SLAM.load(folder)
        shutil.rmtree(folder)
        before = json.loads((snapshot / "bench.json").read_text())
        keyframes, lost, scale, frames, t_slam = (before[k] for k in ("keyframes", "lost", "scale", "frames", "t_slam"))
        print(f"resumed from {snapshot} at frame {len(slam.poses)}", flush=True)
    else:
        slam = SLAM(cfg, camera, T_first_WC=gt[0])
    renderer = Renderer(slam.device)  # the bench's own: the SLAM's renderers keep their buffers
    t_run = time.perf_counter()
    for i in range(len(slam.poses), args.frames):
        t0 = time.perf_counter()
        r = slam.process(rgb[i], depth[i] if cfg.mode == "rgbd" else None)
        t_slam += time.perf_counter() - t0
        if r.lost:
            lost.append(i)
        res = renderer.forward(slam.map, camera, r.T_WC)
        alpha, d = res.alpha.numpy().copy(), res.depth.numpy().copy()
        covered = alpha > 0.5
        frames.append({"frame": i, "coverage": float(covered.mean()), "seeded": r.seeded, "keyframe": r.keyframe})
        if r.seeded and not r.keyframe:
            print(f"frame {i}: {r.seeded} seeds, the map covers {100 * covered.mean():.1f} % of it", flush=True)
        if not r.keyframe:
            continue
        d_map = np.where(covered, d / np.maximum(alpha, 1e-6), 0.0)
        if scale is None:  # the bootstrap keyframe sets the gauge
            scale = float(np.median(depth[i][covered] / d_map[covered]))
        rel = np.abs(scale * d_map[covered] - depth[i][covered]) / depth[i][covered]
        position_cm = 100 * float(np.linalg.norm(r.T_WC[:3, 3] - gt[i][:3, 3]))
        row = {
            "frame": i,
            "coverage": float(covered.mean()),
            "depth_err_median": float(np.median(rel)) if rel.size else None,
            "depth_err_p90": float(np.percentile(rel, 90)) if rel.size else None,
            "seeded": r.seeded,
            "gaussians": len(slam.map),
            "reason": r.keyframe_reason,
        }
        keyframes.append(row)
        if snapshot is not None and not (snapshot / "state.npz").is_file() and slam.bootstrap is None:
            slam.save(snapshot, state=True)
            state = {"keyframes": keyframes, "lost": lost, "scale": scale, "frames": frames, "t_slam": t_slam}
            (snapshot / "bench.json").write_text(json.dumps(state) + "\n")
        print(
            f"keyframe {i}: covered {100 * row['coverage']:.1f} %, depth err median "
            f"{100 * (row['depth_err_median'] or 0):.1f} % p90 {100 * (row['depth_err_p90'] or 0):.1f} %, "
            f"seeded {r.seeded}, {len(slam.map)} Gaussians ({row['reason']}); raw position {position_cm:.2f} cm",
            flush=True,
        )
    seconds = time.perf_counter() - t_run
    _, est = slam.trajectory()
    n = len(est)
    R, t, s = umeyama_alignment(est[: args.fit + 1, :3, 3], gt[: args.fit + 1, :3, 3], with_scale=True)
    fitted = s * est[:, :3, 3] @ R.T + t
    err_cm = 100 * np.linalg.norm(fitted - gt[:n, :3, 3], axis=1)
    sim3 = ate(est, gt[:n], "sim3")
    summary = {
        "size": args.size,
        "path_frames": args.path_frames,
        "frames": args.frames,
        "overrides": args.overrides,
        "keyframes": keyframes,
        "position_err_cm": {int(k): float(err_cm[k]) for k in range(0, n, 10)},
        "fit_frames": args.fit,
        "fit_scale": s,
        "sim3_ate_rmse_cm": sim3["rmse_cm"],
        "sim3_align_scale": sim3["align_scale"],
        "lost_frames": lost,
        "frame_coverage": frames,
        "seconds": seconds,
        "slam_seconds": t_slam,
        "stats": {k: float(v) for k, v in slam.stats.items()},
    }
    errors = {k: round(v, 2) for k, v in summary["position_err_cm"].items()}
    print(f"position error (cm, fit on 0..{args.fit}):", errors)
    print(
        f"SUMMARY sim3 ATE {sim3['rmse_cm']:.2f} cm (scale {sim3['align_scale']:.3f}), lost {len(lost)} {lost}, "
        f"{len(keyframes)} keyframes, {seconds:.0f} s ({t_slam:.0f} s in process), stats {summary['stats']}",
        flush=True,
    )
    if args.out:
        Path(args.out).write_text(json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    main()
