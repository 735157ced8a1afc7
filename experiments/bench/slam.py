"""Whole-system benchmark (issue 7): ``rgs_warp.slam.run`` on GPU-sized sequences, one table.

    python experiments/bench/slam.py [--out DIR] [--case NAME:override,override ...]

Default cases: the synthetic office at Replica size, RGB-D and monocular.  Every case writes its
run folder under DIR/runs; DIR/slam.json holds all metrics and DIR/runs.tar.gz the small files of
each run (metrics, log, top-view plot; not the map, renders or keyframes).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
from pathlib import Path

from rgs_warp.config import load_config
from rgs_warp.slam import run

DEFAULT_CASES = [
    "office_rgbd:dataset=synthetic/office0_replica_size",
    "office_mono:dataset=synthetic/office0_replica_size,mode=mono",
]


def commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    except OSError:
        return "unknown"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=os.environ.get("OUT", "bench_out"))
    ap.add_argument("--case", action="append", help="name:override,override (repeatable)")
    ap.add_argument("--common", default="", help="overrides applied to every case, comma separated")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    common = [o for o in args.common.split(",") if o]
    for case in args.case or DEFAULT_CASES:
        name, _, overrides = case.partition(":")
        cfg = load_config(
            [o for o in overrides.split(",") if o] + common + [f"output_dir={out / 'runs'}", f"run_name={name}"]
        )
        try:
            run_dir, metrics = run(cfg, progress=sys.stderr.isatty())
            results[name] = metrics
        except Exception as e:  # record and go on with the next case
            results[name] = {"error": f"{type(e).__name__}: {e}"}
            print(f"{name}: FAILED {e}", file=sys.stderr)
        (out / "slam.json").write_text(json.dumps({"commit": commit(), "results": results}, indent=2, default=str))
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
    with tarfile.open(out / "runs.tar.gz", "w:gz") as tar:
        for p in sorted((out / "runs").rglob("*")):
            if p.is_file() and (p.suffix in (".md", ".json", ".jsonl") or p.name == "trajectory_topview.png"):
                tar.add(p, arcname=str(p.relative_to(out)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
