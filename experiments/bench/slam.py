"""Whole-system benchmark: ``rgs_warp.app.runner.run`` on GPU-sized sequences, one table.

    python experiments/bench/slam.py [--out DIR] [--case NAME:override,override ...]

Default cases: the synthetic office at Replica size, RGB-D and monocular.  Every case writes its
run folder under DIR/runs; DIR/slam.json holds all metrics and DIR/runs.tar.gz the small files of
each run (metrics, log, config, trajectory, top-view plot; not the map, renders or keyframes).

``--diagnose`` adds, per case, the PSNR of the
keyframes at their refined poses (the fit to what the map was trained on), the PSNR of the scored
frames after re-tracking them against the final map from their estimated poses (how much of the
held-out loss is the pose's misregistration to the final map, not the map), and the pose change of
that re-tracking; and writes
DIR/mesh_inputs.tar.gz (half-resolution rendered depth of every keyframe as uint16 mm, poses, camera,
and the dataset's ground-truth mesh) so that the mesh metrics can be computed where open3d is
installed: ``python experiments/bench/mesh_from_inputs.py DIR/mesh_inputs.tar.gz``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tarfile
from pathlib import Path

import numpy as np

from rgs_warp import SLAM
from rgs_warp.app.report import git_commit
from rgs_warp.app.runner import run
from rgs_warp.config import load_config
from rgs_warp.types import Camera

DEFAULT_CASES = [
    "office_rgbd:dataset=synthetic/office0_replica_size",
    "office_mono:dataset=synthetic/office0_replica_size,mode=mono",
]


def case_configs(cases: list[str], common: str, out: Path):
    """(name, overrides, Config) of each ``name:override,override`` case, with the ``common``
    overrides (comma separated) and its run folder ``out/runs/<name>``."""
    shared = [o for o in common.split(",") if o]
    for case in cases:
        name, _, overrides = case.partition(":")
        folder = [f"output_dir={out / 'runs'}", f"run_name={name}"]
        yield name, overrides, load_config([o for o in overrides.split(",") if o] + shared + folder)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=os.environ.get("OUT", "bench_out"))
    ap.add_argument("--case", action="append", help="name:override,override (repeatable)")
    ap.add_argument("--common", default="", help="overrides applied to every case, comma separated")
    ap.add_argument("--diagnose", action="store_true", help="PSNR at ground-truth poses, mesh inputs")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for name, _, cfg in case_configs(args.case or DEFAULT_CASES, args.common, out):
        try:
            run_dir, metrics = run(cfg, progress=sys.stderr.isatty())
            if args.diagnose:
                metrics["diagnosis"] = diagnose(cfg, run_dir, out / "mesh_inputs" / name)
            results[name] = metrics
        except Exception as e:  # record and go on with the next case
            results[name] = {"error": f"{type(e).__name__}: {e}"}
            print(f"{name}: FAILED {e}", file=sys.stderr)
        (out / "slam.json").write_text(json.dumps({"commit": git_commit(), "results": results}, indent=2, default=str))
    header = f"{'case':<16} {'frames':>6} {'kf':>4} {'gaussians':>9} {'ATE cm':>7} {'PSNR':>6} {'SSIM':>6}"
    header += f" {'fps':>6} {'trk fps':>7} {'MiB':>6}"
    print(header)
    for name, m in results.items():
        if "error" in m:
            print(f"{name:<16} {m['error']}")
            continue
        ate = ((m.get("ate") or {}).get("all_frames") or {}).get("rmse_cm", float("nan"))
        ph = m.get("photometric") or {}
        print(
            f"{name:<16} {m['frames']:>6} {m['keyframes']:>4} {m['gaussians']:>9} {ate:>7.2f} "
            f"{ph.get('psnr_db', float('nan')):>6.2f} {ph.get('ssim', float('nan')):>6.3f} {m['fps']:>6.2f} "
            f"{(m.get('tracking_fps') or float('nan')):>7.2f} {(m.get('peak_memory_mib') or float('nan')):>6.0f}"
        )
    if args.diagnose:
        for name, m in results.items():
            d = m.get("diagnosis")
            if d:
                print(
                    f"{name:<16} PSNR at estimated poses {d['psnr_est_pose_db']:.2f}, "
                    f"re-tracked {d['psnr_retracked_db']:.2f} (moved {d['retrack_shift_cm']:.2f} cm), "
                    f"keyframes {d['psnr_keyframes_db']:.2f} dB; uncovered {100 * d['uncovered_fraction']:.2f} % "
                    f"of pixels with {100 * d['uncovered_error_share']:.1f} % of the error, covered pixels "
                    f"{d['psnr_covered_db']:.2f} dB, worst frame {d['worst_frame']} {d['worst_psnr_db']:.2f} dB"
                )
        with tarfile.open(out / "mesh_inputs.tar.gz", "w:gz") as tar:
            tar.add(out / "mesh_inputs", arcname="mesh_inputs")
    with tarfile.open(out / "runs.tar.gz", "w:gz") as tar:
        for p in sorted((out / "runs").rglob("*")):
            small = p.name in ("trajectory_topview.png", "trajectory.txt", "config.yaml")
            if p.is_file() and (p.suffix in (".md", ".json", ".jsonl") or small):
                tar.add(p, arcname=str(p.relative_to(out)))
    return 0


def diagnose(cfg, run_dir: Path, mesh_dir: Path) -> dict:
    """PSNR of the scored frames at their estimated poses and of the keyframes at their refined poses
    (the map's fit to what it was trained on); half-resolution keyframe depth renders + the
    ground-truth mesh into ``mesh_dir``.  (Rendering at the true poses measured the drift between
    the map's frame and the truth, not the map: the alignment from positions alone mis-rotates a
    nearly straight path; dropped.)"""
    import shutil

    from rgs_warp.datasets import open_dataset
    from rgs_warp.eval import eval_frame_indices, psnr

    slam = SLAM.load(run_dir)
    ds = open_dataset(cfg, device=str(slam.device))
    _, est = slam.trajectory()
    idx = eval_frame_indices(len(est), slam.keyframe_indices, cfg.eval.every)

    def score(indices, poses) -> float:
        values = []
        for i, T in zip(indices, poses, strict=True):
            image = np.clip(slam.render(T).color.numpy(), 0.0, 1.0)
            values.append(psnr(image, ds[int(i)].rgb))
        return float(np.mean(values)) if values else float("nan")

    # where the held-out error sits: pixels the map does not cover (alpha < 0.5), and the rest
    uncovered, err_uncovered, psnr_covered, worst = [], [], [], (np.inf, None)
    for i in idx:
        res = slam.render(est[i])
        ref = ds[int(i)].rgb
        err = np.mean((np.clip(res.color.numpy(), 0.0, 1.0) - ref) ** 2, axis=-1)
        low = res.alpha.numpy() < 0.5
        uncovered.append(float(low.mean()))
        err_uncovered.append(float(err[low].sum() / max(err.sum(), 1e-20)))
        covered_mse = float(err[~low].mean()) if (~low).any() else float("nan")
        psnr_covered.append(-10.0 * np.log10(max(covered_mse, 1e-20)))
        p = -10.0 * np.log10(max(float(err.mean()), 1e-20))
        if p < worst[0]:
            worst = (p, int(i), err)
    if worst[1] is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        mesh_dir.mkdir(parents=True, exist_ok=True)
        fig, ax = plt.subplots(figsize=(8, 4.6))
        im = ax.imshow(np.sqrt(worst[2]), cmap="magma", vmin=0.0, vmax=0.3)
        ax.set_title(f"{cfg.run_name}: RMS colour error of frame {worst[1]} ({worst[0]:.1f} dB)")
        ax.axis("off")
        fig.colorbar(im, ax=ax, fraction=0.03)
        fig.savefig(mesh_dir.parent.parent / f"error_{cfg.run_name}.png", dpi=80, bbox_inches="tight")
        plt.close(fig)

    retracked = []
    for i in idx:
        frame = ds[int(i)]
        slam.tracker.reset(est[i])
        retracked.append(slam.tracker.track(frame.rgb, frame.depth, slam.map, T_init_WC=est[i]).T_WC)
    retracked = np.array(retracked).reshape(-1, 4, 4)
    shift = np.linalg.norm(retracked[:, :3, 3] - est[idx][:, :3, 3], axis=1) if len(idx) else np.zeros(0)
    kf = slam.keyframe_indices
    out = {
        "psnr_est_pose_db": score(idx, est[idx]),
        "psnr_retracked_db": score(idx, retracked),
        "retrack_shift_cm": float(np.median(shift) * 100.0) if len(shift) else float("nan"),
        "psnr_keyframes_db": score(kf, est[kf]),
        "uncovered_fraction": float(np.mean(uncovered)) if uncovered else float("nan"),
        "uncovered_error_share": float(np.mean(err_uncovered)) if err_uncovered else float("nan"),
        "psnr_covered_db": float(np.mean(psnr_covered)) if psnr_covered else float("nan"),
        "worst_frame": worst[1],
        "worst_psnr_db": float(worst[0]),
    }
    c = slam.camera
    half = Camera(c.fx / 2, c.fy / 2, (c.cx + 0.5) / 2 - 0.5, (c.cy + 0.5) / 2 - 0.5, c.width // 2, c.height // 2)
    depths = []
    for i in kf:
        res = slam.render(est[i], camera=half)
        alpha = res.alpha.numpy()
        d = np.where(alpha > 0.5, res.depth.numpy() / np.maximum(alpha, 1e-6), 0.0)
        depths.append(np.clip(np.round(d * 1000.0), 0, 65535).astype(np.uint16))
    mesh_dir.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        mesh_dir / "keyframe_depth.npz",
        depth_mm=np.stack(depths),
        poses=est[kf],
        camera=np.array([half.fx, half.fy, half.cx, half.cy, half.width, half.height]),
    )
    mesh = getattr(ds, "mesh_path", None)
    if mesh is not None and Path(mesh).is_file() and Path(mesh).stat().st_size < 12 * 2**20:
        shutil.copy(mesh, mesh_dir / "mesh_gt.ply")
    return out


if __name__ == "__main__":
    sys.exit(main())
