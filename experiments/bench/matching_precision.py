"""Dense matching precision on the shared real data, per backbone.

For every reference pixel of the feature grid and every neighbour, the true correspondence is the
reference pixel back-projected with the ground-truth depth and projected into the neighbour with the
ground-truth poses; it is undefined (and the match not counted) where the reference depth is
missing or on a depth edge, or where the neighbour's depth says the point is occluded (more than
5 % + 2 cm in front).  Reported per backbone and search mode (``rgbd``: band around the depth
reprojection; ``mono``: the whole epipolar segment, depth unused): the number of matches with
confidence > 0.5 and a defined truth, the fraction of them within 2 px of the truth (precision),
the median error, and the matches left after the blue-noise thinning.

Data: Replica office0 frames 0-3 (reference 0, neighbours 1-3) and 7-Scenes redkitchen keyframes
20 frames apart (references 40, 80, ..., 440; neighbours chosen by ``select_neighbours`` among the
keyframes up to 40 frames away).

    python experiments/bench/matching_precision.py [--backbones classic xfeat dinov2] [--device cpu]
        [--set matching.key=value ...] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import warp as wp

from rgs_warp.app.report import git_commit
from rgs_warp.config import MatchingConfig, load_config
from rgs_warp.datasets import ReplicaDataset, SevenScenesDataset
from rgs_warp.geometry import invert_pose
from rgs_warp.keyframes import KeyframeBuffer
from rgs_warp.matching import DenseMatcher

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "data"
THRESHOLD_PX = 2.0
CONFIDENT = 0.5


def true_correspondences(ref_uv, depth_r, depth_n, T_r, T_n, camera) -> np.ndarray:
    """(N, 2) true positions in n of the reference pixels ref_uv (N, 2); NaN where undefined."""
    u, v = ref_uv[:, 0], ref_uv[:, 1]
    x0 = np.clip(np.floor(u).astype(int), 0, camera.width - 2)
    y0 = np.clip(np.floor(v).astype(int), 0, camera.height - 2)
    fx, fy = u - x0, v - y0
    quad = np.stack([depth_r[y0, x0], depth_r[y0, x0 + 1], depth_r[y0 + 1, x0], depth_r[y0 + 1, x0 + 1]], 1)
    d = (1 - fy) * ((1 - fx) * quad[:, 0] + fx * quad[:, 1]) + fy * ((1 - fx) * quad[:, 2] + fx * quad[:, 3])
    ok = (quad.min(1) > 0) & (quad.max(1) - quad.min(1) < 0.05 * quad.mean(1))
    Xc = np.stack([(u - camera.cx) / camera.fx * d, (v - camera.cy) / camera.fy * d, d], 1)
    T = invert_pose(T_n) @ T_r
    Xn = Xc @ T[:3, :3].T + T[:3, 3]
    z = Xn[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        un = camera.fx * Xn[:, 0] / z + camera.cx
        vn = camera.fy * Xn[:, 1] / z + camera.cy
    inside = ok & (z > 0.05) & (un >= 0) & (vn >= 0) & (un <= camera.width - 1) & (vn <= camera.height - 1)
    ui = np.clip(np.round(np.nan_to_num(un)).astype(int), 0, camera.width - 1)
    vi = np.clip(np.round(np.nan_to_num(vn)).astype(int), 0, camera.height - 1)
    dn = depth_n[vi, ui]
    visible = inside & ((dn <= 0) | (z < dn * 1.05 + 0.02))
    out = np.stack([un, vn], 1)
    out[~visible] = np.nan
    return out


def evaluate(matcher: DenseMatcher, buffer: KeyframeBuffer, ref_slot: int, neighbours, depth, use_depth: bool):
    """Errors (px) and confidences of the confident matches of one reference, before and after thinning."""
    result = {}
    for thin in (False, True):
        m = matcher.match(ref_slot, buffer, neighbours=neighbours, use_depth=use_depth, thin=thin)
        ref_uv = m.ref_uv.numpy().copy()
        match_uv = m.match_uv.numpy().copy()
        conf = m.confidence.numpy().copy()
        errs, confs = [], []
        for col, slot in enumerate(m.neighbours):
            truth = true_correspondences(
                ref_uv, depth[ref_slot], depth[slot], buffer.poses[ref_slot], buffer.poses[slot], matcher.camera
            )
            defined = np.isfinite(truth[:, 0])
            err = np.linalg.norm(match_uv[:, col] - truth, axis=1)
            errs.append(err[defined])
            confs.append(conf[defined, col])
        result[thin] = (np.concatenate(errs), np.concatenate(confs))
    return result


def summarise(runs) -> dict:
    out = {}
    for thin, key in ((False, "all"), (True, "thinned")):
        err = np.concatenate([r[thin][0] for r in runs])
        conf = np.concatenate([r[thin][1] for r in runs])
        good = conf > CONFIDENT
        n = int(good.sum())
        out[key] = {
            "confident": n,
            "precision": float((err[good] < THRESHOLD_PX).mean()) if n else None,
            "median_err_px": float(np.median(err[good])) if n else None,
            "any_match": int((conf > 0).sum()),
        }
    return out


def load_frames(ds, indices):
    return [ds[i] for i in indices]


def ground_truth_check(camera, frames, plan) -> float:
    """Fraction of OpenCV DIS optical flow (an independent matcher) within 2 px of the ground-truth
    correspondence, on an 8 px grid over the same reference/candidate pairs: where this is low,
    the 'truth' itself (depth not registered to colour, estimated poses) limits any precision."""
    import cv2

    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    hits = []
    for ref, candidates in plan:
        fr = frames[ref]
        ys, xs = np.mgrid[4 : camera.height - 4 : 8, 4 : camera.width - 4 : 8]
        uv = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
        for k in candidates:
            fn = frames[k]
            flow = dis.calc(*[(f.rgb.mean(2) * 255).astype(np.uint8) for f in (fr, fn)], None)
            truth = true_correspondences(uv, fr.depth, fn.depth, fr.pose_gt, fn.pose_gt, camera)
            defined = np.isfinite(truth[:, 0])
            err = np.linalg.norm(uv + flow[ys.ravel(), xs.ravel()] - truth, axis=1)[defined]
            hits.append(err < THRESHOLD_PX)
    return float(np.concatenate(hits).mean())


def run_sequence(cfg: MatchingConfig, device, camera, frames, plan, use_depth: bool) -> dict:
    """plan: list of (reference index into frames, candidate indices)."""
    matcher = DenseMatcher(cfg, camera, device)
    runs = []
    for ref, candidates in plan:
        members = [ref, *candidates]
        buffer = KeyframeBuffer(len(members), camera.width, camera.height, device)
        depth = {}
        for k in members:
            f = frames[k]
            slot = buffer.add(f.index, f.pose_gt, f.rgb, f.depth)
            depth[slot] = f.depth
        ref_slot = 0
        neighbours = matcher.select_neighbours(ref_slot, buffer) if len(candidates) > cfg.n_neighbours else None
        neighbours = neighbours or list(range(1, len(members)))
        runs.append(evaluate(matcher, buffer, ref_slot, neighbours, depth, use_depth))
    return summarise(runs)


def datasets():
    replica = ReplicaDataset(DATA / "replica-office0-sample" / "office0", prefetch=0)
    rep_frames = load_frames(replica, range(4))
    kitchen = SevenScenesDataset(DATA / "7scenes-redkitchen", prefetch=0)
    keyframes = list(range(0, len(kitchen), 20))
    kit_frames = dict(zip(keyframes, load_frames(kitchen, keyframes), strict=True))
    kit_plan = [
        (k, [j for j in keyframes if j != k and abs(j - k) <= 40]) for k in range(40, 441, 40) if k in kit_frames
    ]
    return {
        "replica-office0 (frames 0-3)": (replica.camera, {i: f for i, f in enumerate(rep_frames)}, [(0, [1, 2, 3])]),
        "7scenes-redkitchen (keyframes 20 apart)": (kitchen.camera, kit_frames, kit_plan),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backbones", nargs="+", default=["classic", "xfeat", "dinov2"])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--set", nargs="*", default=[], help="matching.key=value overrides")
    ap.add_argument("--modes", nargs="+", default=["rgbd", "mono"])
    ap.add_argument("--out", type=Path, default=Path(os.environ.get("OUT", "bench_out")))
    args = ap.parse_args()
    wp.init()
    data = datasets()
    results = {"commit": git_commit(), "device": str(wp.get_device(args.device)), "backbones": {}}
    results["ground_truth_check"] = {name: ground_truth_check(cam, fr, plan) for name, (cam, fr, plan) in data.items()}
    for name in args.backbones:
        cfg = load_config([f"matching.backbone={name}", *args.set]).matching
        entry = {"config": asdict(cfg), "datasets": {}}
        try:
            for dname, (camera, frames, plan) in data.items():
                entry["datasets"][dname] = {}
                for mode in args.modes:
                    t0 = time.perf_counter()
                    summary = run_sequence(cfg, args.device, camera, frames, plan, use_depth=mode == "rgbd")
                    summary["seconds"] = round(time.perf_counter() - t0, 1)
                    entry["datasets"][dname][mode] = summary
                    print(name, dname, mode, json.dumps(summary), flush=True)
        except (FileNotFoundError, ImportError, NotImplementedError) as e:
            entry = {"config": asdict(cfg), "n/a": str(e).split(". ")[0]}
            print(name, "n/a:", e, flush=True)
        results["backbones"][name] = entry
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "matching.json").write_text(json.dumps(results, indent=1))
    (args.out / "matching.md").write_text(markdown(results))


def markdown(results: dict) -> str:
    lines = [
        "# Dense matching precision",
        "",
        f"Commit `{results['commit']}`, device `{results['device']}`, by `experiments/bench/matching_precision.py` "
        "(protocol in its docstring). Precision = fraction of matches with confidence > 0.5 within 2 px of the "
        "ground-truth correspondence; 'confident' = their number (all neighbours, all references); 'after "
        "thinning' = the same after blue-noise thinning (what the Triangulator receives).",
        "",
        "Ground-truth check (fraction of OpenCV DIS optical flow within 2 px of the 'true' correspondence on "
        "the same pairs; low values mean the truth, not the matcher, limits the precision): "
        + ", ".join(f"{k}: {100 * v:.1f} %" for k, v in results["ground_truth_check"].items()),
        "",
        "| backbone | data | search | confident | precision | median err (px) | after thinning: confident "
        "| precision | time (s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, entry in results["backbones"].items():
        if "n/a" in entry:
            lines.append(f"| {name} | all | - | n/a: {entry['n/a']} | | | | | |")
            continue
        for dname, modes in entry["datasets"].items():
            for mode, s in modes.items():
                a, t = s["all"], s["thinned"]

                def pct(x):
                    return "-" if x is None else f"{100 * x:.1f} %"

                def px(x):
                    return "-" if x is None else f"{x:.2f}"

                lines.append(
                    f"| {name} | {dname} | {mode} | {a['confident']} | {pct(a['precision'])} | "
                    f"{px(a['median_err_px'])} | {t['confident']} | {pct(t['precision'])} | {s['seconds']} |"
                )
    lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
