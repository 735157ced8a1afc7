"""One-shot dense initialization on a synthetic scene: DenseMatcher -> Triangulator ->
PointSeeder at one keyframe with its neighbours, ground-truth poses; reports match accuracy against the
true correspondences, triangulated depth error, seeds, and the PSNR of the seeded map (no
optimisation) rendering the reference keyframe.

    PYTHONPATH=src python experiments/bench/dense_init.py --width 1200 --height 680 --frames 100 --ids 50,47,53
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import warp as wp

from rgs_warp.app.report import git_commit
from rgs_warp.config import MatchingConfig, SeedingConfig, TriangulationConfig
from rgs_warp.datasets import SyntheticDataset
from rgs_warp.eval import psnr
from rgs_warp.geometry import invert_pose
from rgs_warp.keyframes import KeyframeBuffer
from rgs_warp.matching import DenseMatcher
from rgs_warp.render import Renderer
from rgs_warp.seeding import PointSeeder
from rgs_warp.triangulation import Triangulator
from rgs_warp.types import GaussianMap


def true_correspondences(ref_uv, depth, cam, T_ref, T_nb):
    """Where the reference pixels land in a neighbour according to the true depth and poses."""
    z = depth[np.round(ref_uv[:, 1]).astype(int), np.round(ref_uv[:, 0]).astype(int)]
    x = np.stack([(ref_uv[:, 0] - cam.cx) / cam.fx * z, (ref_uv[:, 1] - cam.cy) / cam.fy * z, z], 1)
    T = invert_pose(T_nb) @ T_ref
    y = x @ T[:3, :3].T + T[:3, 3]
    return np.stack([cam.fx * y[:, 0] / y[:, 2] + cam.cx, cam.fy * y[:, 1] / y[:, 2] + cam.cy], 1), z


def run(args) -> dict:
    device = args.device or ("cuda:0" if wp.is_cuda_available() else "cpu")
    ids = [int(v) for v in args.ids.split(",")]
    ds = SyntheticDataset(
        args.scene,
        width=args.width,
        height=args.height,
        n_frames=args.frames,
        exposure_drift=True,
        device=device,
        prefetch=0,
    )
    cam = ds.camera
    exposure = np.loadtxt(ds.root / "exposure.txt")
    frames = {i: ds[i] for i in ids}
    buf = KeyframeBuffer(max(len(ids), 2), cam.width, cam.height, device)
    slots = {i: buf.add(i, frames[i].pose_gt, frames[i].rgb, frames[i].depth, exposure=exposure[i]) for i in ids}
    matcher = DenseMatcher(MatchingConfig(thin_spacing=args.thin_spacing), cam, device)
    triangulator = Triangulator(TriangulationConfig(), device)
    # Seed spacing = the thinning spacing in image pixels, so the splats close into a surface.
    seeder = PointSeeder(SeedingConfig(poisson_radius_px=args.thin_spacing * matcher.stride), cam, device)
    gmap = GaussianMap(1024, 2, device)
    ref_slot, nb_slots = slots[ids[0]], [slots[i] for i in ids[1:]]

    def chain():
        m = matcher.match(ref_slot, buf, neighbours=nb_slots)
        pts = triangulator.triangulate(m.P, m.ref_uv, m.match_uv, m.confidence)
        return m, pts

    chain()  # warm-up: kernel compilation
    wp.synchronize()
    t0 = time.perf_counter()
    m, pts = chain()
    added = seeder.seed(pts, m.aggregated, buf, [ref_slot, *m.neighbours], gmap)
    wp.synchronize()
    seconds = time.perf_counter() - t0

    graph = capture_chain(chain, seeder, buf, ref_slot, gmap, added) if wp.get_device(device).is_cuda else None

    ref = frames[ids[0]]
    ref_uv, match_uv, conf = m.ref_uv.numpy(), m.match_uv.numpy(), m.confidence.numpy()
    match_stats = []
    for k, slot in enumerate(m.neighbours):
        uv_true, z = true_correspondences(ref_uv, ref.depth, cam, ref.pose_gt, buf.poses[slot])
        sel = (conf[:, k] > 0.5) & (z > 0)
        err = np.linalg.norm(match_uv[sel, k] - uv_true[sel], axis=1)
        match_stats.append(
            {
                "frame": int(buf.frame_ids[slot]),
                "confident": int(sel.sum()),
                "median_px": float(np.median(err)),
                "within_2px": float(np.mean(err < 2.0)),
            }
        )
    X, valid = pts.X.numpy(), pts.valid.numpy().astype(bool)
    T = ref.pose_gt
    z_est = (X - T[:3, 3]) @ T[:3, 2]
    z_true = ref.depth[np.round(ref_uv[:, 1]).astype(int), np.round(ref_uv[:, 0]).astype(int)]
    ok = valid & (z_true > 0)
    rel = (z_est[ok] - z_true[ok]) / z_true[ok]
    out = Renderer(device).forward(gmap, cam, T)
    g, b = exposure[ids[0]]
    image = np.clip(g * out.color.numpy() + b, 0.0, 1.0)
    covered = out.alpha.numpy() > 0.5
    commit = git_commit()
    return {
        "scene": args.scene,
        "resolution": [cam.width, cam.height],
        "frames": args.frames,
        "keyframes": ids,
        "device": str(wp.get_device(device)),
        "commit": commit or "unknown",
        "feature_grid": list(m.grid),
        "kept_after_thinning": int(m.kept_count.numpy()[0]),
        "matches": match_stats,
        "triangulated": int(valid.sum()),
        "parallax_median_deg": float(np.median(pts.parallax_deg.numpy()[valid])),
        "depth_error_median_pct": float(100 * np.median(np.abs(rel))),
        "depth_error_signed_median_pct": float(100 * np.median(rel)),
        "depth_error_p90_pct": float(100 * np.percentile(np.abs(rel), 90)),
        "gaussians_added": int(added),
        "coverage_alpha_gt_0.5": float(covered.mean()),
        "psnr_covered_db": float(psnr(image[covered], ref.rgb[covered])) if covered.any() else None,
        "psnr_whole_db": float(psnr(image, ref.rgb)),
        "chain_seconds": seconds,
        "graph": graph,
    }


def capture_chain(chain, seeder, buf, ref_slot, gmap, added_eager, repeats=20) -> dict:
    """The whole chain (match -> triangulate -> seed, without the final count read) captured in one
    CUDA graph: the capture fails if anything inside synchronises with the host.  Replays seed into
    the same rows again; the result must equal the eager one."""
    means_eager = gmap.means.numpy()[len(gmap) - added_eager : len(gmap)].copy()
    row_end = len(gmap)
    gmap.count = row_end - added_eager  # seed the same rows again
    gmap.reserve(row_end + 4 * added_eager + 1024)  # no reallocation inside the capture

    def body():
        m, pts = chain()
        return seeder.enqueue(pts, m.aggregated, buf, [ref_slot, *m.neighbours], gmap)

    try:
        with wp.ScopedCapture() as cap:
            row0 = body()
    except Exception as exc:  # report why, the eager numbers stand
        gmap.count = row_end
        return {"captured": False, "error": f"{type(exc).__name__}: {exc}"}
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        wp.capture_launch(cap.graph)
        wp.synchronize()
        times.append(time.perf_counter() - t0)
    added = seeder.collect(gmap, row0)
    means = gmap.means.numpy()[row0 : row0 + added]
    return {
        "captured": True,
        "added": int(added),
        "same_as_eager": bool(added == added_eager and np.array_equal(means, means_eager)),
        "replay_ms_median": 1e3 * float(np.median(times)),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="room0")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=180)
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--ids", default="50,47,53", help="reference keyframe first, then its neighbours")
    p.add_argument("--thin-spacing", type=float, default=1.0, help="feature px between kept matches")
    p.add_argument("--device", default=None)
    p.add_argument("--out", default=os.environ.get("OUT", "."))
    args = p.parse_args()
    result = run(args)
    print(json.dumps(result, indent=2))
    name = f"dense_init_{args.scene}_{args.width}x{args.height}.json"
    Path(args.out).mkdir(parents=True, exist_ok=True)
    (Path(args.out) / name).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
