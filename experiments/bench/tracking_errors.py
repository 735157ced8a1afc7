"""Where a run's tracking error is: per-frame pose errors against ground truth beside candidate causes.

    python experiments/bench/tracking_errors.py RUN_DIR --data DATA_PATH --out DIR [--figure PNG]

RUN_DIR holds ``trajectory.txt`` (TUM: timestamp tx ty tz qx qy qz qw, camera-to-world) and
``log.jsonl`` (one line per frame, in the run's frame order); its ``config.yaml``, when present, gives
the dataset section (loader, selection, 7-Scenes registration), else ``--dataset`` (default
``7scenes/redkitchen``) does; ``--set dataset.KEY=VALUE`` changes either.  The frames are read with
the package's loader, so the ground truth and the depth are what the run saw (7-Scenes: depth
registered to the colour camera, poses moved to it).  Estimated poses are matched to frames by
timestamp.

Per frame:
  * absolute error: the estimate SE(3)-aligned onto the ground truth as the ATE does
    (``rgs_warp.eval.ate``, positions only), translation (cm) and rotation (deg); also the error of
    the estimate anchored at the first frame's true pose (no fitted alignment: the accumulated drift);
  * relative error of the step from the previous frame, (gt_{i-1}^-1 gt_i)^-1 (est_{i-1}^-1 est_i):
    translation (mm) and rotation (deg);
  * the steps per camera axis against the true ones (least-squares ratio; a noisy ground truth pulls it
    below 1), the correlation of translation and rotation errors along the image's weak direction, and the
    aligned error slower than 10 frames;
  * candidate causes: true camera speed (mm and deg a frame), blur (variance of the Laplacian of the
    grey image, 0-255 scale: low is blurred), brightness change (mean grey level), valid-depth fraction
    and median depth, tracked gain and |ln gain| jump, tracking loss, valid_ratio, settled
    iterations, keyframe flag and frames since the last keyframe (``log.jsonl``).

Then: Spearman rank correlations of the relative errors with each cause; each cause's mean on the
worst ``--worst`` fraction of steps (by relative translation error) against the rest; whether the
absolute error is a few jumps or a spread drift (the ATE of the trajectory that takes the true steps
except the worst 5 % of estimated steps, and of the one that takes all estimated steps but those);
and the ATE that each ``--window``-frame stretch's estimated steps alone produce (true steps
elsewhere), which locates the stretches that carry the error.

With ``--reference FILE``: the estimate and the dataset's ground truth scored against a second reference
of the same frames, in the pose files of Brachmann et al., "On the Limits of Pseudo Ground Truth in Visual
Camera Re-localisation" (ICCV 2021; github.com/tsattler/visloc_pseudo_gt_limitations, ``pgt/sfm/7scenes/``:
Colmap's poses of the colour images, independent of the depth and of KinectFusion), one line a frame,
``seq-NN/frame-NNNNNN.color.png qw qx qy qz tx ty tz [f]`` (world-to-camera), the lines of
``--reference-sequence`` matched to the frames by their file's number (7-Scenes: timestamp x 30 Hz):
SE(3) and Sim(3) ATE, and the ratio of each trajectory's rotations since the first frame (rotation
vectors, per camera axis) to the reference's; the three trajectories side by side in DIR/reference.png.

Writes DIR/per_frame.csv, DIR/summary.json, DIR/summary.txt (also printed) and the figure
(``--figure``, default DIR/tracking_errors.png); with ``--show F1,F2,...`` also DIR/frames.png, those frames
with their errors.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import re
import sys
from pathlib import Path

import numpy as np


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps (N,), camera-to-world poses (N, 4, 4)) of a TUM trajectory file."""
    from scipy.spatial.transform import Rotation

    d = np.loadtxt(path, comments="#", ndmin=2)
    if d.shape[1] != 8:
        raise SystemExit(f"{path}: expected 8 columns (timestamp tx ty tz qx qy qz qw), got {d.shape[1]}")
    T = np.tile(np.eye(4), (len(d), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(d[:, 4:8]).as_matrix()
    T[:, :3, 3] = d[:, 1:4]
    return d[:, 0], T


def read_reference(path: Path, sequence: str) -> dict[int, np.ndarray]:
    """Camera-to-world poses by frame number from a pose file of world-to-camera quaternion and translation
    lines (``--reference``), the lines of ``sequence`` only."""
    from scipy.spatial.transform import Rotation

    if not path.is_file():
        raise SystemExit(f"{path}: no such file (--reference)")
    poses = {}
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        parts = line.split()
        if not parts or not parts[0].startswith(sequence + "/"):
            continue
        match = re.search(r"frame-(\d+)", parts[0])
        if match is None or len(parts) < 8:
            raise SystemExit(f"{path}:{number}: expected 'seq-NN/frame-NNNNNN.color.png qw qx qy qz tx ty tz [f]'")
        qw, qx, qy, qz, tx, ty, tz = map(float, parts[1:8])
        R_cw = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()
        T = np.eye(4)
        T[:3, :3] = R_cw.T
        T[:3, 3] = -R_cw.T @ np.array([tx, ty, tz])
        poses[int(match.group(1))] = T
    if not poses:
        raise SystemExit(f"{path}: no line of sequence {sequence!r}")
    return poses


def rotation_ratio(T: np.ndarray, ref: np.ndarray) -> list[float]:
    """Per camera axis, the least-squares ratio of ``T``'s rotation vectors since its first pose to ``ref``'s."""
    from scipy.spatial.transform import Rotation

    a = Rotation.from_matrix(np.swapaxes(T[:1, :3, :3], 1, 2) @ T[:, :3, :3]).as_rotvec()
    b = Rotation.from_matrix(np.swapaxes(ref[:1, :3, :3], 1, 2) @ ref[:, :3, :3]).as_rotvec()
    return [float(a[:, k] @ b[:, k] / (b[:, k] @ b[:, k])) for k in range(3)]


def against_reference(est: np.ndarray, gt: np.ndarray, indices: np.ndarray, path: Path, sequence: str) -> dict:
    """The estimate and the ground truth scored against the reference (``--reference``) on their common frames."""
    from rgs_warp.eval.ate import ate

    poses = read_reference(path, sequence)
    keep = np.array([int(i) in poses for i in indices])
    if keep.sum() < 3:
        raise SystemExit(f"{path}: only {int(keep.sum())} of the run's frames in sequence {sequence!r}")
    ref = np.array([poses[int(i)] for i in indices[keep]])
    out = {"file": str(path), "sequence": sequence, "frames": int(keep.sum()), "poses": ref, "used": keep}
    for name, T in (("estimate", est[keep]), ("ground_truth", gt[keep])):
        sim3 = ate(T, ref, "sim3")
        out[name] = {
            "ate_cm": ate(T, ref, "se3")["rmse_cm"],
            "ate_sim3_cm": sim3["rmse_cm"],
            "sim3_scale": sim3["align_scale"],
            "rotation_ratio_xyz": rotation_ratio(T, ref),
        }
    return out


def read_log(path: Path) -> list[dict]:
    if not path.is_file():
        print(f"note: {path} missing: no tracking columns", file=sys.stderr)
        return []
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]


def angle_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angle (deg) of (..., 3, 3) rotation matrices."""
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def open_frames(run_dir: Path, data: str | None, dataset: str, sets: list[str]):
    """The package's loader for the run's dataset (config.yaml's dataset section if the run has one)."""
    import yaml

    from rgs_warp.config import DatasetConfig, load_config
    from rgs_warp.datasets import open_dataset

    overrides = []
    saved = run_dir / "config.yaml"
    if saved.is_file():
        section = (yaml.safe_load(saved.read_text(encoding="utf-8")) or {}).get("dataset") or {}
        known = {f.name for f in dataclasses.fields(DatasetConfig)}
        overrides += [f"dataset.{k}={json.dumps(v)}" for k, v in section.items() if k in known]
    else:
        overrides.append(f"dataset={dataset}")
    if data:
        overrides.append(f"dataset.path={Path(data).expanduser().resolve()}")
    cfg = load_config(overrides + list(sets))
    return open_dataset(cfg, device="cpu")


def frame_measures(frame) -> dict:
    """Blur, brightness and depth coverage of one loaded frame."""
    import cv2

    rgb = np.asarray(frame.rgb, dtype=np.float32)
    if rgb.max() <= 1.0 + 1e-6:
        rgb = rgb * 255.0
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    depth = np.asarray(frame.depth, dtype=np.float32) if frame.depth is not None else None
    valid = depth > 0 if depth is not None else None
    return {
        "blur_lapvar": float(cv2.Laplacian(grey, cv2.CV_32F, ksize=3).var()),
        "brightness": float(grey.mean()),
        "depth_valid": float(valid.mean()) if valid is not None else np.nan,
        "depth_median_m": float(np.median(depth[valid])) if valid is not None and valid.any() else np.nan,
    }


def compose(gt: np.ndarray, steps_gt: np.ndarray, err: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Poses from gt[0] by the true steps, with step i's error err[i] applied where use[i]."""
    T = np.empty_like(gt)
    T[0] = gt[0]
    for i in range(len(steps_gt)):
        T[i + 1] = T[i] @ (steps_gt[i] @ err[i] if use[i] else steps_gt[i])
    return T


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    from scipy.stats import spearmanr

    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 5 or np.ptp(x[ok]) == 0 or np.ptp(y[ok]) == 0:
        return float("nan")
    return float(spearmanr(x[ok], y[ok]).statistic)


def runs_of(frames: np.ndarray, gap: int) -> list[tuple[int, int, int]]:
    """Sorted frame numbers grouped into (first, last, count) where consecutive ones are <= gap apart."""
    out: list[list[int]] = []
    for f in np.sort(frames):
        if out and f - out[-1][1] <= gap:
            out[-1][1] = int(f)
            out[-1][2] += 1
        else:
            out.append([int(f), int(f), 1])
    return [tuple(r) for r in out]


CAUSES = [  # (column, label in the table and figure)
    ("speed_mm", "true speed (mm/frame)"),
    ("speed_deg", "true turn (deg/frame)"),
    ("blur_lapvar", "sharpness (Laplacian var.)"),
    ("brightness_jump", "|brightness step| (grey)"),
    ("depth_valid", "valid depth fraction"),
    ("depth_median_m", "median depth (m)"),
    ("gain", "tracked gain"),
    ("gain_jump", "|ln gain jump|"),
    ("loss", "tracking loss"),
    ("valid_ratio", "valid_ratio"),
    ("settled_iters", "settled iterations"),
    ("short_mismatch", "one-sided short step"),
    ("keyframe", "keyframe (0/1)"),
    ("since_keyframe", "frames since keyframe"),
]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_dir", type=Path, help="run folder: trajectory.txt, log.jsonl (config.yaml if any)")
    ap.add_argument("--data", help="the sequence folder (dataset.path)")
    ap.add_argument("--dataset", default="7scenes/redkitchen", help="dataset group when the run has no config.yaml")
    ap.add_argument("--set", action="append", default=[], help="config override key=value (repeatable)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--figure", type=Path, help="figure path (default OUT/tracking_errors.png)")
    ap.add_argument("--worst", type=float, default=0.10, help="fraction of steps called worst (default 0.10)")
    ap.add_argument("--window", type=int, default=25, help="frames a stretch for the ATE contributions")
    ap.add_argument("--title", default="", help="figure title (default: the run folder)")
    ap.add_argument("--reference", type=Path, help="a second reference's pose file (see above)")
    ap.add_argument("--reference-sequence", default="seq-01", help="its lines of this sequence (default seq-01)")
    ap.add_argument("--show", help="frames (comma-separated) shown with their errors in DIR/frames.png")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    figure = args.figure or args.out / "tracking_errors.png"

    from rgs_warp.eval.ate import ate

    ts, est_all = read_tum(args.run_dir / "trajectory.txt")
    log = read_log(args.run_dir / "log.jsonl")
    ds = open_frames(args.run_dir, args.data, args.dataset, args.set)

    # one pass over the dataset: match each frame to an estimated pose by timestamp
    order = np.argsort(ts)
    rows, gt, est = [], [], []
    show = {int(v) for v in args.show.split(",")} if args.show else set()
    shown = {}  # frame -> its colour image, for --show
    last = None  # the previous frame read: a stream that repeats it exactly was stale (its pair lags the other)
    for pos in range(len(ds)):
        frame, previous, last = ds[pos], last, ds[pos]
        j = int(np.searchsorted(ts[order], frame.timestamp))
        cands = [order[k] for k in (j - 1, j) if 0 <= k < len(order)]
        best = min(cands, key=lambda k: abs(ts[k] - frame.timestamp)) if cands else None
        if best is None or abs(ts[best] - frame.timestamp) > 1e-3 or frame.pose_gt is None:
            continue
        entry = log[pos] if pos < len(log) else {}
        rows.append({"frame": pos, "index": frame.index, "timestamp": frame.timestamp} | frame_measures(frame))
        rows[-1] |= {
            "colour_repeats": float(previous is not None and np.array_equal(frame.rgb, previous.rgb)),
            "depth_repeats": float(
                previous is not None and frame.depth is not None and np.array_equal(frame.depth, previous.depth)
            ),
        }
        rows[-1] |= {
            "keyframe": float(bool(entry.get("keyframe", False))),
            "gain": float(entry.get("gain", np.nan)),
            "loss": float(entry.get("loss", np.nan)),
            "valid_ratio": float(entry.get("valid_ratio", np.nan)),
            "settled_iters": float(entry.get("settled_iters", np.nan)),
            "lost": float(bool(entry.get("lost", False))),
        }
        gt.append(frame.pose_gt)
        est.append(est_all[best])
        if pos in show:
            shown[pos] = np.asarray(frame.rgb, dtype=np.float32)
    n = len(rows)
    if n < 3:
        raise SystemExit(f"only {n} frames matched between {args.run_dir / 'trajectory.txt'} and the dataset")
    gt, est = np.asarray(gt, dtype=np.float64), np.asarray(est, dtype=np.float64)
    col = {k: np.array([r[k] for r in rows], dtype=np.float64) for k in rows[0]}
    frames = col["frame"].astype(int)

    # absolute error, SE(3)-aligned as the ATE
    res = ate(est, gt, "se3")
    est_a = res["align_T"] @ est
    col["abs_cm"] = 100.0 * np.linalg.norm(est_a[:, :3, 3] - gt[:, :3, 3], axis=1)
    col["abs_deg"] = angle_deg(np.swapaxes(gt[:, :3, :3], 1, 2) @ est_a[:, :3, :3])
    # anchored at the first true pose: the drift accumulated since the start
    est_0 = gt[0] @ np.linalg.inv(est[0]) @ est
    col["drift_cm"] = 100.0 * np.linalg.norm(est_0[:, :3, 3] - gt[:, :3, 3], axis=1)
    col["drift_deg"] = angle_deg(np.swapaxes(gt[:, :3, :3], 1, 2) @ est_0[:, :3, :3])

    # relative error of each step (frame i-1 -> i, attributed to frame i); a gap in the frames is a step too
    inv = np.linalg.inv
    step_gt = inv(gt[:-1]) @ gt[1:]
    step_est = inv(est[:-1]) @ est[1:]
    err = inv(step_gt) @ step_est
    nan1 = np.array([np.nan])
    col["rel_mm"] = np.r_[nan1, 1000.0 * np.linalg.norm(err[:, :3, 3], axis=1)]
    col["rel_deg"] = np.r_[nan1, angle_deg(err[:, :3, :3])]
    col["speed_mm"] = np.r_[nan1, 1000.0 * np.linalg.norm(step_gt[:, :3, 3], axis=1)]
    col["speed_deg"] = np.r_[nan1, angle_deg(step_gt[:, :3, :3])]
    col["brightness_jump"] = np.r_[nan1, np.abs(np.diff(col["brightness"]))]
    col["gain_jump"] = np.r_[nan1, np.abs(np.diff(np.log(col["gain"])))]

    # uneven frame spacing: a step far shorter than its neighbours (a near-repeated frame); a step where
    # only one of the ground truth and the estimate has one is a timing disagreement between them
    def short_steps(T):
        d = 1000.0 * np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
        out = np.zeros(len(d), bool)
        for i in range(len(d)):
            around = np.median(np.r_[d[max(0, i - 2) : i], d[i + 1 : i + 3]])
            out[i] = around > 3.0 and d[i] < 0.3 * around
        return out

    short_gt, short_est = short_steps(gt), short_steps(est)
    col["short_mismatch"] = np.r_[nan1, (short_gt ^ short_est).astype(np.float64)]
    since, last = np.zeros(n), None
    for i in range(n):
        last = frames[i] if col["keyframe"][i] else last
        since[i] = np.nan if last is None else frames[i] - last
    col["since_keyframe"] = since

    # jitter: second differences of the positions (mm), estimate against ground truth
    def acc_mm(T):
        p = T[:, :3, 3]
        return 1000.0 * np.linalg.norm(p[2:] - 2.0 * p[1:-1] + p[:-2], axis=1)

    # drift or jumps: the worst 5 % of steps alone, and everything but them
    steps = np.arange(1, n)
    k5 = max(1, int(round(0.05 * len(steps))))
    jumps = {}
    for name, key in (("translation", "rel_mm"), ("rotation", "rel_deg")):
        worst = np.zeros(len(steps), bool)
        worst[np.argsort(-col[key][1:])[:k5]] = True
        jumps[name] = {
            "steps": int(k5),
            "share_of_summed_error": float(col[key][1:][worst].sum() / col[key][1:].sum()),
            "ate_only_these_cm": ate(compose(gt, step_gt, err, worst), gt, "se3")["rmse_cm"],
            "ate_all_but_these_cm": ate(compose(gt, step_gt, err, ~worst), gt, "se3")["rmse_cm"],
        }

    # the steps' errors split at the camera centre: their rotations alone, their translations alone
    every = np.ones(len(steps), bool)
    err_r, err_t = err.copy(), np.tile(np.eye(4), (len(err), 1, 1))
    err_r[:, :3, 3] = 0.0
    err_t[:, :3, 3] = err[:, :3, 3]
    split = {
        "rotation_only_cm": ate(compose(gt, step_gt, err_r, every), gt, "se3")["rmse_cm"],
        "translation_only_cm": ate(compose(gt, step_gt, err_t, every), gt, "se3")["rmse_cm"],
    }

    # the steps per camera axis (the frame before's): estimated against true, least squares; the
    # correlation of the translation errors with the rotation errors about the other image axis (a
    # sideways step taken for a turn about the scene lies along the image's weak direction); and the
    # share of the aligned position error slower than 10 frames (its moving average).  A noisy ground truth's
    # own step noise pulls the ratios below 1 (7-Scenes); on exact synthetic poses they are the estimate's bias
    from scipy.spatial.transform import Rotation

    t_gt, t_est = step_gt[:, :3, 3], step_est[:, :3, 3]
    r_gt = Rotation.from_matrix(step_gt[:, :3, :3]).as_rotvec()
    r_est = Rotation.from_matrix(step_est[:, :3, :3]).as_rotvec()
    e_t, e_r = t_est - t_gt, r_est - r_gt
    kernel = np.ones(10)
    within = np.convolve(np.ones(n), kernel, "same")
    slow = np.stack([np.convolve(est_a[:, a, 3] - gt[:, a, 3], kernel, "same") / within for a in range(3)], axis=1)
    step_axes = {
        "step_translation_ratio_xyz": [float(t_est[:, a] @ t_gt[:, a] / (t_gt[:, a] @ t_gt[:, a])) for a in range(3)],
        "step_rotation_ratio_xyz": [float(r_est[:, a] @ r_gt[:, a] / (r_gt[:, a] @ r_gt[:, a])) for a in range(3)],
        "corr_tx_ry": float(np.corrcoef(e_t[:, 0], e_r[:, 1])[0, 1]),
        "corr_ty_rx": float(np.corrcoef(e_t[:, 1], e_r[:, 0])[0, 1]),
        "slow_cm": float(100.0 * np.sqrt(np.mean(np.sum(slow**2, axis=1)))),
    }

    # stretches: the ATE that one window's estimated steps produce alone (true steps elsewhere), and the
    # ATE's growth across the window when the estimated steps run up to its end (true steps after it);
    # the growths add up to the ATE
    windows, before = [], 0.0
    for s in range(0, len(steps), args.window):
        use = np.zeros(len(steps), bool)
        use[s : s + args.window] = True
        upto = ate(compose(gt, step_gt, err, np.arange(len(steps)) < s + args.window), gt, "se3")["rmse_cm"]
        windows.append(
            {
                "first": int(frames[s + 1]),
                "last": int(frames[min(s + args.window, len(steps))]),
                "ate_alone_cm": ate(compose(gt, step_gt, err, use), gt, "se3")["rmse_cm"],
                "ate_up_to_last_cm": upto,
                "ate_growth_cm": upto - before,
                "rel_mm_mean": float(np.mean(col["rel_mm"][1:][use])),
                "rel_deg_mean": float(np.mean(col["rel_deg"][1:][use])),
                "abs_cm_mean": float(np.mean(col["abs_cm"][s + 1 : s + args.window + 1])),
            }
        )
        before = upto

    # the worst steps and the causes
    worst_k = max(1, int(round(args.worst * len(steps))))
    worst_idx = 1 + np.argsort(-col["rel_mm"][1:])[:worst_k]
    is_worst = np.zeros(n, bool)
    is_worst[worst_idx] = True
    rest = ~is_worst
    rest[0] = False
    table = []
    for key, label in CAUSES:
        x = col[key]
        table.append(
            {
                "cause": key,
                "label": label,
                "rho_rel_mm": spearman(x, col["rel_mm"]),
                "rho_rel_deg": spearman(x, col["rel_deg"]),
                "rho_abs_cm": spearman(x, col["abs_cm"]),
                "worst_mean": float(np.nanmean(x[is_worst])) if np.isfinite(x[is_worst]).any() else np.nan,
                "rest_mean": float(np.nanmean(x[rest])) if np.isfinite(x[rest]).any() else np.nan,
            }
        )

    sim3 = ate(est, gt, "sim3")
    colour_only = (col["colour_repeats"] > 0) & (col["depth_repeats"] == 0)
    depth_only = (col["depth_repeats"] > 0) & (col["colour_repeats"] == 0)
    both = (col["colour_repeats"] > 0) & (col["depth_repeats"] > 0)

    def at(mask: np.ndarray) -> dict:
        return {
            "frames": int(mask.sum()),
            "true_step_mm_median": float(np.median(col["speed_mm"][mask])) if mask.any() else None,
            "step_error_mm_mean": float(np.mean(col["rel_mm"][mask])) if mask.any() else None,
        }

    summary = {
        "run": str(args.run_dir),
        "frames": n,
        "ate_cm": {k: res[k] for k in ("rmse_cm", "mean_cm", "median_cm", "max_cm")},
        "ate_sim3_cm": sim3["rmse_cm"],
        "sim3_scale": sim3["align_scale"],
        # a frame whose colour (depth) repeats the previous frame's exactly: that stream was stale
        "repeated_streams": {"colour": at(colour_only), "depth": at(depth_only), "both": at(both)},
        "ate_max_frame": int(frames[np.argmax(col["abs_cm"])]),
        "alignment_rotation_deg": float(angle_deg(res["align_T"][:3, :3])),
        "abs_deg": {"mean": float(col["abs_deg"].mean()), "max": float(col["abs_deg"].max())},
        "drift_from_start": {
            "max_cm": float(col["drift_cm"].max()),
            "max_cm_frame": int(frames[np.argmax(col["drift_cm"])]),
            "final_cm": float(col["drift_cm"][-1]),
            "max_deg": float(col["drift_deg"].max()),
            "final_deg": float(col["drift_deg"][-1]),
        },
        "rel_mm": {p: float(np.percentile(col["rel_mm"][1:], q)) for p, q in (("p50", 50), ("p90", 90), ("p99", 99))}
        | {"max": float(np.max(col["rel_mm"][1:])), "max_frame": int(frames[1 + np.argmax(col["rel_mm"][1:])])},
        "rel_deg": {p: float(np.percentile(col["rel_deg"][1:], q)) for p, q in (("p50", 50), ("p90", 90), ("p99", 99))}
        | {"max": float(np.max(col["rel_deg"][1:])), "max_frame": int(frames[1 + np.argmax(col["rel_deg"][1:])])},
        "speed_mm_p50": float(np.median(col["speed_mm"][1:])),
        "speed_deg_p50": float(np.median(col["speed_deg"][1:])),
        "second_difference_mm_p50": {"est": float(np.median(acc_mm(est))), "gt": float(np.median(acc_mm(gt)))},
        "worst_5pct_steps": jumps,
        "step_error_split": split,
        "step_axes": step_axes,
        "short_steps": {
            "gt": int(short_gt.sum()),
            "est": int(short_est.sum()),
            "both": int((short_gt & short_est).sum()),
            "first_last_gt": [int(frames[1 + i]) for i in np.flatnonzero(short_gt)[[0, -1]]]
            if short_gt.any()
            else None,
            "one_sided_rel_mm_mean": float(np.mean(col["rel_mm"][1:][short_gt ^ short_est]))
            if (short_gt ^ short_est).any()
            else None,
            "other_rel_mm_mean": float(np.mean(col["rel_mm"][1:][~(short_gt ^ short_est)])),
        },
        "windows": windows,
        "worst_fraction": args.worst,
        "worst_steps": [int(frames[i]) for i in np.sort(worst_idx)],
        "worst_runs": runs_of(frames[worst_idx], gap=5),
        "causes": table,
        "lost_frames": int(col["lost"].sum()),
        "keyframes": [int(f) for f in frames[col["keyframe"] > 0]],
        "rotation_ratio_xyz": rotation_ratio(est, gt),
    }
    if args.reference:
        from rgs_warp.datasets.sevenscenes import KINECT_FPS  # 7-Scenes' timestamps: the file's number / fps

        numbers = np.rint(col["timestamp"] * KINECT_FPS).astype(int)
        reference = against_reference(est, gt, numbers, args.reference, args.reference_sequence)
        plot_reference(args.out / "reference.png", frames, est, gt, reference)
        summary["reference"] = {k: v for k, v in reference.items() if k not in ("poses", "used")}
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n", encoding="utf-8")

    names = [
        "frame", "index", "timestamp", "abs_cm", "abs_deg", "drift_cm", "drift_deg", "rel_mm", "rel_deg",
        "speed_mm", "speed_deg", "blur_lapvar", "brightness", "brightness_jump", "depth_valid", "depth_median_m",
        "gain", "gain_jump", "loss", "valid_ratio", "settled_iters", "short_mismatch", "keyframe", "since_keyframe",
        "lost", "colour_repeats", "depth_repeats",
    ]  # fmt: skip
    with (args.out / "per_frame.csv").open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(names)
        for i in range(n):
            w.writerow([f"{col[k][i]:.6g}" for k in names])

    text = format_summary(summary, args)
    (args.out / "summary.txt").write_text(text, encoding="utf-8")
    print(text, end="")
    plot(figure, col, frames, summary, args)
    written = [args.out / "per_frame.csv", args.out / "summary.json", args.out / "summary.txt", figure]
    written += [args.out / "reference.png"] if args.reference else []
    if show - shown.keys():
        print(f"note: --show: no matched frame {sorted(show - shown.keys())}", file=sys.stderr)
    if shown:
        plot_frames(args.out / "frames.png", shown, col, frames)
        written.append(args.out / "frames.png")
    print("wrote " + ", ".join(str(p) for p in written))
    return 0


def format_summary(s: dict, args) -> str:
    a, d, j = s["ate_cm"], s["drift_from_start"], s["worst_5pct_steps"]
    lines = [
        f"{s['run']}: {s['frames']} frames, {s['lost_frames']} lost, {len(s['keyframes'])} keyframes",
        f"ATE (SE(3)) rmse {a['rmse_cm']:.2f} cm, median {a['median_cm']:.2f}, max {a['max_cm']:.2f} at frame "
        f"{s['ate_max_frame']}; the alignment turns the estimate by {s['alignment_rotation_deg']:.2f} deg; aligned "
        f"rotation error mean {s['abs_deg']['mean']:.2f} deg, max {s['abs_deg']['max']:.2f}",
        f"ATE with Sim(3) alignment {s['ate_sim3_cm']:.2f} cm at scale {s['sim3_scale']:.4f}; rotations since the "
        f"first frame x {', '.join(f'{v:.3f}' for v in s['rotation_ratio_xyz'])} the ground truth's (camera x, y, z)",
        "frames repeating the previous one's (a stale stream): "
        + "; ".join(
            f"{k} {v['frames']}"
            + (
                f" (true step median {v['true_step_mm_median']:.1f} mm, step error mean "
                f"{v['step_error_mm_mean']:.1f} mm)"
                if v["frames"]
                else ""
            )
            for k, v in s["repeated_streams"].items()
        ),
        f"drift from the true first pose: max {d['max_cm']:.2f} cm (frame {d['max_cm_frame']}), final "
        f"{d['final_cm']:.2f} cm; rotation max {d['max_deg']:.2f} deg, final {d['final_deg']:.2f}",
        f"relative error a step: median {s['rel_mm']['p50']:.2f} mm / {s['rel_deg']['p50']:.3f} deg, p90 "
        f"{s['rel_mm']['p90']:.2f} / {s['rel_deg']['p90']:.3f}, p99 {s['rel_mm']['p99']:.2f} / "
        f"{s['rel_deg']['p99']:.3f}, max {s['rel_mm']['max']:.2f} mm (frame {s['rel_mm']['max_frame']}) / "
        f"{s['rel_deg']['max']:.3f} deg (frame {s['rel_deg']['max_frame']}); true motion median "
        f"{s['speed_mm_p50']:.2f} mm / {s['speed_deg_p50']:.3f} deg a frame",
        f"position second difference median: estimate {s['second_difference_mm_p50']['est']:.2f} mm, ground truth "
        f"{s['second_difference_mm_p50']['gt']:.2f} mm",
    ]
    if "reference" in s:
        r = s["reference"]
        for name in ("estimate", "ground_truth"):
            v = r[name]
            lines.append(
                f"{name.replace('_', ' ')} against {Path(r['file']).name} ({r['sequence']}, {r['frames']} frames): ATE "
                f"{v['ate_cm']:.2f} cm, Sim(3) {v['ate_sim3_cm']:.2f} cm at scale {v['sim3_scale']:.4f}; rotations x "
                f"{', '.join(f'{x:.3f}' for x in v['rotation_ratio_xyz'])} the reference's"
            )
    for name, v in j.items():
        lines.append(
            f"worst 5 % of steps by {name} ({v['steps']}): {100 * v['share_of_summed_error']:.0f} % of the summed "
            f"error; ATE with only their errors {v['ate_only_these_cm']:.2f} cm, with all errors but theirs "
            f"{v['ate_all_but_these_cm']:.2f} cm"
        )
    lines.append(
        f"ATE with only the steps' rotation errors {s['step_error_split']['rotation_only_cm']:.2f} cm, with only "
        f"their translation errors (at the camera centre) {s['step_error_split']['translation_only_cm']:.2f} cm"
    )
    x = s["step_axes"]
    lines.append(
        f"steps (camera axes x, y, z) x {', '.join(f'{v:.3f}' for v in x['step_translation_ratio_xyz'])} the true "
        f"ones' translation, x {', '.join(f'{v:.3f}' for v in x['step_rotation_ratio_xyz'])} their rotation; error "
        f"correlation x translation / y rotation {x['corr_tx_ry']:.2f}, y translation / x rotation "
        f"{x['corr_ty_rx']:.2f}; aligned error slower than 10 frames {x['slow_cm']:.2f} cm"
    )
    t = s["short_steps"]
    if t["first_last_gt"]:
        lines.append(
            f"short steps (a near-repeated frame): ground truth {t['gt']} (frames {t['first_last_gt'][0]}-"
            f"{t['first_last_gt'][1]}), estimate {t['est']}, {t['both']} at the same step; steps where only one "
            f"has it: {t['one_sided_rel_mm_mean']:.2f} mm mean error against {t['other_rel_mm_mean']:.2f}"
        )
    lines.append(
        f"{args.window}-frame stretches: ATE of the stretch's estimated steps alone (true steps elsewhere); ATE with "
        f"the estimated steps up to the stretch's end (true steps after), and its growth over the stretch:"
    )
    for w in s["windows"]:
        lines.append(
            f"  frames {w['first']:4d}-{w['last']:4d}: alone {w['ate_alone_cm']:5.2f} cm, up to "
            f"{w['ate_up_to_last_cm']:5.2f} ({w['ate_growth_cm']:+.2f}); steps {w['rel_mm_mean']:5.2f} mm / "
            f"{w['rel_deg_mean']:.3f} deg, aligned error {w['abs_cm_mean']:5.2f} cm"
        )
    runs = [f"{a0}-{b0} ({c0})" if a0 != b0 else f"{a0}" for a0, b0, c0 in s["worst_runs"]]
    lines.append(f"worst {100 * s['worst_fraction']:.0f} % of steps by translation: {', '.join(runs)}")
    head = ("rho rel mm", "rho rel deg", "rho abs cm", "worst", "rest")
    lines.append(f"{'cause':30s} {head[0]:>10s} {head[1]:>11s} {head[2]:>10s} {head[3]:>9s} {head[4]:>9s}")
    for r in s["causes"]:
        lines.append(
            f"{r['label']:30s} {r['rho_rel_mm']:10.2f} {r['rho_rel_deg']:11.2f} {r['rho_abs_cm']:10.2f} "
            f"{r['worst_mean']:9.3g} {r['rest_mean']:9.3g}"
        )
    return "\n".join(lines) + "\n"


def plot_frames(path: Path, shown: dict[int, np.ndarray], col: dict, frames: np.ndarray) -> None:
    """The ``--show`` frames side by side, each titled with its aligned error and its step's error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    where = {int(f): i for i, f in enumerate(frames)}
    fig, axes = plt.subplots(1, len(shown), figsize=(4.0 * len(shown), 3.0), squeeze=False)
    for ax, (f, rgb) in zip(axes[0], sorted(shown.items()), strict=True):
        i = where[f]
        ax.imshow(np.clip(rgb, 0.0, 1.0))  # the loaders' colour: float in [0, 1]
        ax.set_title(
            f"frame {f}: error {col['abs_cm'][i]:.2f} cm, step {col['rel_mm'][i]:.2f} mm / {col['rel_deg'][i]:.3f} deg",
            fontsize=8,
        )
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_reference(path: Path, frames: np.ndarray, est: np.ndarray, gt: np.ndarray, reference: dict) -> None:
    """The estimate, the ground truth and the reference (``against_reference``) side by side: their rotations since
    the first frame about the camera's x and y axes (pitch, yaw; rotation vectors in the first frame's camera), and
    the positions seen from above, each trajectory SE(3)-aligned onto the reference."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.spatial.transform import Rotation

    from rgs_warp.eval.ate import ate

    keep, ref = reference["used"], reference["poses"]
    frames = frames[keep]
    named = (
        ("estimate", est[keep], "C0", reference["estimate"]["ate_cm"]),
        ("ground truth", gt[keep], "C3", reference["ground_truth"]["ate_cm"]),
        (Path(reference["file"]).name, ref, "k", 0.0),
    )
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6), dpi=100, gridspec_kw={"width_ratios": [1.3, 1.3, 1]})
    for name, T, c, ate_cm in named:
        turn = np.degrees(Rotation.from_matrix(np.swapaxes(T[:1, :3, :3], 1, 2) @ T[:, :3, :3]).as_rotvec())
        label = name if T is ref else f"{name} ({ate_cm:.2f} cm from the reference)"
        for k, ax in enumerate(axes[:2]):
            ax.plot(frames, turn[:, k], color=c, lw=1.0, label=label)
        P = T[:, :3, 3] if T is ref else (ate(T, ref, "se3")["align_T"] @ T)[:, :3, 3]
        axes[2].plot(P[:, 0], P[:, 2], color=c, lw=1.0, label=name)
    for k, ax in enumerate(axes[:2]):
        ax.set_title(f"rotation since the first frame about the camera's {'xy'[k]} axis (deg)", fontsize=9)
        ax.set_xlabel("frame", fontsize=9)
        ax.tick_params(labelsize=8)
    axes[0].legend(fontsize=7, frameon=False)
    axes[2].set_title("positions from above (x, z; m), aligned onto the reference", fontsize=9)
    axes[2].set_aspect("equal", adjustable="datalim")
    axes[2].tick_params(labelsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot(path: Path, col: dict, frames: np.ndarray, s: dict, args) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(14, 10), dpi=100)
    gs = fig.add_gridspec(6, 2, width_ratios=[2.3, 1], hspace=0.12, wspace=0.14, left=0.05, right=0.985, top=0.95)
    kf = frames[col["keyframe"] > 0]
    worst = np.array(s["worst_steps"])
    panels = [
        ("error (cm)", [("abs_cm", "aligned (ATE)", "C0"), ("drift_cm", "from the true first pose", "C7")]),
        ("step error", [("rel_mm", "translation (mm)", "C3")]),
        ("true motion", [("speed_mm", "mm/frame", "C2")]),
        ("sharpness", [("blur_lapvar", "Laplacian variance", "C4")]),
        ("valid depth", [("depth_valid", "fraction", "C5")]),
        ("gain", [("gain", "tracked gain", "C1")]),
    ]
    twins = {1: ("rel_deg", "rotation (deg)", "C9"), 2: ("speed_deg", "deg/frame", "C8")}
    axes = []
    for i, (ylabel, series) in enumerate(panels):
        ax = fig.add_subplot(gs[i, 0], sharex=axes[0] if axes else None)
        axes.append(ax)
        for key, label, c in series:
            ax.plot(frames, col[key], color=c, lw=0.9, label=label)
        if i in twins:
            key, label, c = twins[i]
            ax2 = ax.twinx()
            ax2.plot(frames, col[key], color=c, lw=0.7, alpha=0.7, label=label)
            ax2.tick_params(labelsize=7)
            ax2.set_ylabel(label, fontsize=8, color=c)
        for f in kf:
            ax.axvline(f, color="0.6", lw=0.5, ls=":", zorder=0)
        if i == 1 and len(worst):
            ax.plot(worst, col["rel_mm"][np.searchsorted(frames, worst)], "v", ms=3, color="k", label="worst steps")
        ax.set_ylabel(ylabel, fontsize=9)
        ax.tick_params(labelsize=8)
        ax.legend(fontsize=7, loc="upper left", frameon=False, ncol=3)
        if i < len(panels) - 1:
            ax.tick_params(labelbottom=False)
    axes[-1].set_xlabel("frame (dotted: keyframes)", fontsize=9)
    axes[0].set_xlim(frames[0], frames[-1])

    # right: the stretches, then the table
    axw = fig.add_subplot(gs[0:2, 1])
    w = s["windows"]
    x0 = np.array([v["first"] for v in w], dtype=np.float64)
    axw.bar(x0, [v["ate_alone_cm"] for v in w], width=args.window * 0.45, align="edge", color="C0", label="alone")
    axw.bar(
        x0 + args.window * 0.45,
        [v["ate_growth_cm"] for v in w],
        width=args.window * 0.45,
        align="edge",
        color="C3",
        label="growth when run up to it",
    )
    axw.axhline(0.0, color="k", lw=0.6)
    axw.set_title(f"ATE (cm) from each {args.window}-frame stretch's estimated steps", fontsize=9)
    axw.legend(fontsize=7, frameon=False, loc="upper right")
    axw.tick_params(labelsize=8)
    axw.set_xlim(frames[0], frames[-1])
    axt = fig.add_subplot(gs[2:6, 1])
    axt.axis("off")

    def fmt(x):
        return "-" if not np.isfinite(x) else f"{x:.0f}" if abs(x) >= 100 else f"{x:.3g}"

    cells = [
        [r["label"], f"{r['rho_rel_mm']:+.2f}", f"{r['rho_rel_deg']:+.2f}", fmt(r["worst_mean"]), fmt(r["rest_mean"])]
        for r in s["causes"]
    ]
    tbl = axt.table(
        cellText=cells,
        colLabels=["cause", "rho mm", "rho deg", f"worst {100 * s['worst_fraction']:.0f}%", "rest"],
        colWidths=[0.42, 0.13, 0.13, 0.16, 0.16],
        cellLoc="right",
        loc="upper center",
    )
    tbl.auto_set_font_size(False)
    tbl.set_fontsize(8)
    tbl.scale(1.0, 1.25)
    for (_row, c), cell in tbl.get_celld().items():
        if c == 0:
            cell.set_text_props(ha="left")
            cell.PAD = 0.03
    j = s["worst_5pct_steps"]
    note = (
        "Spearman rho of each cause with the step error\n"
        f"(translation mm, rotation deg); cause means on the worst\n"
        f"{100 * s['worst_fraction']:.0f}% of steps (by mm) and on the rest.\n"
        f"The worst 5% of steps alone: ATE {j['translation']['ate_only_these_cm']:.2f} cm (by mm),\n"
        f"{j['rotation']['ate_only_these_cm']:.2f} cm (by deg); all steps but them: "
        f"{j['translation']['ate_all_but_these_cm']:.2f} / {j['rotation']['ate_all_but_these_cm']:.2f} cm;\n"
        f"all steps: {s['ate_cm']['rmse_cm']:.2f} cm."
    )
    axt.text(0.0, 0.02, note, fontsize=8, va="bottom", transform=axt.transAxes)
    a = s["ate_cm"]
    fig.suptitle(
        f"{args.title or args.run_dir}: ATE {a['rmse_cm']:.2f} cm over {s['frames']} frames", fontsize=11, y=0.985
    )
    fig.savefig(path, dpi=100)
    plt.close(fig)
    try:  # a palette PNG: a third of the size, the same look
        from PIL import Image

        with Image.open(path) as im:
            small = im.convert("RGB").quantize(colors=64, method=Image.Quantize.MEDIANCUT)
        small.save(path, optimize=True)
    except ImportError:
        pass


if __name__ == "__main__":
    sys.exit(main())
