"""Run-to-run spread of the whole system: each case of ``slam.py`` several times, as concurrent
processes on one GPU, one table of every run and of each case's spread.

    python experiments/bench/slam_repeats.py --out DIR --repeats 4 --jobs 8 \
        --case "kitchen:dataset=7scenes/redkitchen" \
        --case "kitchen_loss15:dataset=7scenes/redkitchen,keyframes.max_loss_ratio=1.5"

Repeat r of a case runs with ``seed=r`` (GPU atomics make even equal seeds differ: experiments/results/
slam.md, 7-Scenes).  Concurrent runs share the GPU, so their frames per second are not the system's
speed (use ``slam.py`` alone for that); ATE and PSNR are unaffected.  Writes DIR/repeats.json (every
run's metrics) and DIR/runs.tar.gz (the small files of every run: metrics, per-frame log, config,
trajectory).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import numpy as np

BENCH = Path(__file__).with_name("slam.py")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=os.environ.get("OUT", "bench_out"))
    ap.add_argument("--case", action="append", required=True, help="name:override,override (repeatable)")
    ap.add_argument("--common", default="", help="overrides applied to every case, comma separated")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--jobs", type=int, default=6, help="runs at once")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runs = []  # (case, repeat, name, overrides)
    for case in args.case:
        name, _, overrides = case.partition(":")
        for r in range(args.repeats):
            runs.append((name, r, f"{name}_r{r}", ",".join(o for o in (overrides, f"seed={r}") if o)))
    pending, active, t0 = list(runs), {}, time.perf_counter()
    # each run's share of the CPU cores for the evaluation's host code (torch, BLAS): with every run
    # spinning one thread per core, 6 runs on 16 cores did not finish their evaluations in 7 minutes
    # (4 runs at 4 threads each: 170 s for the whole batch)
    threads = str(max(1, (os.cpu_count() or 1) // args.jobs))
    env = dict(os.environ, **{k: threads for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")})
    while pending or active:
        while pending and len(active) < args.jobs:
            _, _, run_name, overrides = pending.pop(0)
            cmd = [sys.executable, str(BENCH), "--out", str(out / run_name), "--case", f"{run_name}:{overrides}"]
            if args.common:
                cmd += ["--common", args.common]
            log = (out / f"{run_name}.out").open("w")
            active[run_name] = (subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env), log)
        for run_name, (proc, log) in list(active.items()):
            if proc.poll() is not None:
                log.close()
                del active[run_name]
                print(f"[{time.perf_counter() - t0:6.0f} s] {run_name} exited {proc.returncode}", flush=True)
        time.sleep(1.0)

    results = {}
    for case, r, run_name, overrides in runs:
        f = out / run_name / "slam.json"
        m = json.loads(f.read_text())["results"].get(run_name, {}) if f.is_file() else {"error": "no slam.json"}
        results[run_name] = {"case": case, "repeat": r, "overrides": overrides, "metrics": m}
    (out / "repeats.json").write_text(json.dumps(results, indent=2, default=str))

    def ate(m):
        return ((m.get("ate") or {}).get("all_frames") or {}).get("rmse_cm", float("nan"))

    def ate_kf(m):
        return ((m.get("ate") or {}).get("keyframes") or {}).get("rmse_cm", float("nan"))

    print(
        f"{'run':<28} {'kf':>4} {'gaussians':>9} {'ATE cm':>7} {'kf ATE':>7} {'PSNR':>6} {'comp':>6} "
        f"{'kf comp':>7} {'fps':>6} {'lost':>4} {'lag ms':>7}"
    )
    nan = float("nan")
    by_case: dict[str, list] = {}
    for run_name, res in results.items():
        m = res["metrics"]
        if "error" in m:
            print(f"{run_name:<28} {m['error']}")
            continue
        ph = m.get("photometric") or {}
        psnr = ph.get("psnr_db", nan)
        print(
            f"{run_name:<28} {m['keyframes']:>4} {m['gaussians']:>9} {ate(m):>7.2f} {ate_kf(m):>7.2f} {psnr:>6.2f} "
            f"{ph.get('psnr_compensated_db', nan):>6.2f} {ph.get('keyframe_psnr_compensated_db') or nan:>7.2f} "
            f"{m.get('fps') or nan:>6.2f} {(m.get('tracking') or {}).get('lost_frames', 0):>4} "
            f"{(m.get('playback') or {}).get('lag_ms_last', nan):>7.0f}"  # dataset.playback_fps: the last frame's lag
        )
        by_case.setdefault(res["case"], []).append((ate(m), psnr))
    print(f"\n{'case':<24} {'runs':>4} {'ATE median':>10} {'ATE min':>8} {'ATE max':>8} {'PSNR mean':>9}")
    for case, vals in by_case.items():
        a = np.array([v[0] for v in vals])
        p = np.array([v[1] for v in vals])
        print(f"{case:<24} {len(a):>4} {np.median(a):>10.2f} {a.min():>8.2f} {a.max():>8.2f} {np.nanmean(p):>9.2f}")
    with tarfile.open(out / "runs.tar.gz", "w:gz") as tar:
        for _, r, run_name, _ in runs:
            for p in sorted((out / run_name / "runs").rglob("*")):
                small = p.name in ("trajectory_topview.png", "frame_scores.png", "trajectory.txt", "config.yaml")
                if p.is_file() and (p.suffix in (".md", ".json", ".jsonl") or small):
                    tar.add(p, arcname=str(p.relative_to(out)))
            if r == 0:  # what the map looks like: the run's last render | truth | error, as a small JPEG
                _add_last_render(tar, out, run_name)
            if (out / f"{run_name}.out").is_file():
                tar.add(out / f"{run_name}.out", arcname=f"{run_name}.out")
    return 0


def _add_last_render(tar: tarfile.TarFile, out: Path, run_name: str) -> None:
    """The run's last ``renders/*_render_gt_error.png`` (render | ground truth | error), at half
    resolution as JPEG: the full PNGs of a batch exceed what a device call brings back."""
    import cv2

    renders = sorted((out / run_name / "runs").rglob("renders/*_render_gt_error.png"))
    if not renders:
        return
    image = cv2.imread(str(renders[-1]))
    small = cv2.resize(image, (image.shape[1] // 2, image.shape[0] // 2), interpolation=cv2.INTER_AREA)
    path = out / f"{run_name}_{renders[-1].stem}.jpg"
    cv2.imwrite(str(path), small, [cv2.IMWRITE_JPEG_QUALITY, 88])
    tar.add(path, arcname=path.name)


if __name__ == "__main__":
    raise SystemExit(main())
