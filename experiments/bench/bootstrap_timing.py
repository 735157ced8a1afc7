"""Where a monocular bootstrap attempt's time goes (``MonoBootstrap.try_init``), stage by stage.

    python experiments/bench/bootstrap_timing.py [dataset=synthetic/office0_replica_size ...]

Frame 0 against frames 3, 9 and 18 of the dataset (the GPU office at 1200x680 took 3.9 s an attempt
in session 14, 19 attempts before its map started); each stage is timed with ``wp.synchronize`` after
one warm-up attempt, median of 3.  Writes $OUT/bootstrap_timing.json (default OUT: bench_out).
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

from rgs_warp.bootstrap import MonoBootstrap, relative_pose
from rgs_warp.config import load_config
from rgs_warp.datasets import open_dataset


def main(argv: list[str]) -> None:
    overrides = argv or ["dataset=synthetic/office0_replica_size"]
    cfg = load_config([*overrides, "mode=mono"])
    wp.init()
    device = wp.get_device("cuda:0" if wp.is_cuda_available() else "cpu")
    ds = open_dataset(cfg, str(device))
    boot = MonoBootstrap(cfg.bootstrap, ds.camera, device, matching=cfg.matching)
    frames = {i: np.asarray(ds[i].rgb, dtype=np.float32) for i in (0, 3, 9, 18)}
    results = {"device": str(device), "name": device.name, "size": [ds.camera.width, ds.camera.height]}
    results["grid"] = list(boot.grid)

    def timed(fn, *args):
        wp.synchronize()
        t0 = time.perf_counter()
        out = fn(*args)
        wp.synchronize()
        return out, time.perf_counter() - t0

    for k in (3, 9, 18):
        boot.try_init(frames[0], frames[k])  # warm-up (compilation)
        rows = []
        for _ in range(3):
            row = {}
            _, row["try_init_s"] = timed(boot.try_init, frames[0], frames[k])
            row["rejection"] = boot.last_rejection
            (ref_uv, match_uv, valid), row["match_s"] = timed(boot.match, frames[0], frames[k])
            d0 = boot._rgb[0]
            _, row["describe_s"] = timed(boot.backbone.describe, d0, boot._desc[0])
            _, row["global_motion_s"] = timed(boot._global_motion, boot._desc[0], boot._desc[1])
            sel = np.flatnonzero(valid)
            row["selected"] = int(len(sel))
            K = ds.camera.K
            b = cfg.bootstrap
            _, row["relative_pose_s"] = timed(
                relative_pose, ref_uv[sel], match_uv[sel], K, b.ransac_threshold_px, b.ransac_confidence, b.ransac_iters
            )
            rows.append(row)
        med = {key: float(np.median([r[key] for r in rows])) for key in rows[0] if key.endswith("_s")}
        med.update(selected=rows[0]["selected"], rejection=rows[0]["rejection"])
        results[f"0-{k}"] = med
        print(k, json.dumps(med), flush=True)
    out = Path(os.environ.get("OUT", "bench_out"))
    out.mkdir(parents=True, exist_ok=True)
    (out / "bootstrap_timing.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main(sys.argv[1:])
