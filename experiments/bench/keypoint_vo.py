"""Measure the monocular keypoint odometry (``rgs_warp.keypoint_odometry``, issue 22) on the synthetic office
(or any sequence with poses: ``--dataset 7scenes/redkitchen --path ../shared/data/7scenes-redkitchen``).

The odometry itself is the package's ``KeypointOdometry`` (its parameters the config's ``keypoints``
section, overridable here as ``keypoints.KEY=VALUE``); this harness only gives it a start, runs it over
the frames causally and scores the poses (experiments/results/mono.md, "Keypoint front end with a local
bundle adjustment").

Start (the SLAM's monocular bootstrap stands in here):

- ``--init ess`` (default): frame 0 against the first frame whose essential-matrix two-view geometry
  (``findEssentialMat`` / ``recoverPose`` on KLT tracks from frame 0) gives a median triangulation angle of
  ``--boot-deg``; the scale is that baseline's (median depth 1).  No ground truth is used.
- ``--init gt``: frames 0 and ``--init-frame`` at their true poses (session 16's start).
- ``--init run --run DIR``: the monocular bootstrap of a SLAM run folder (its frames 0 and ``--init-frame``
  at that run's poses, from its trajectory.txt): the odometry alone from the start the SLAM gave it.

Both poses go to ``KeypointOdometry.start``, which keeps the first and the distance between them and
refines the second in its first BA (as the SLAM's bootstrap poses are treated).

Measures (printed as one JSON line, appended to ``--json`` with the positions): the Sim(3) ATE of the
online poses (as ``track`` returned them; a lost frame counts with the pose before it), the position
error after that fit at frames 51/90/96/102/120/150/200/250/299/400/499, the Sim(3) scale of each 50-frame
window relative to the whole fit (the scale drift), lost and rotation-only frames, keyframes, the
seconds of each local BA (timed around the package's ``_bundle_adjust``) and the frames per second.

    PYTHONPATH=src .venv/bin/python experiments/bench/keypoint_vo.py --width 640 --height 360 --frames 150
    ... keypoints.ba_window=0              # no local BA
    ... --init gt --init-frame 20          # start from the true poses of frames 0 and 20
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from rgs_warp import keypoint_odometry
from rgs_warp.config import load_config
from rgs_warp.datasets import open_dataset
from rgs_warp.eval.ate import ate, umeyama_alignment
from rgs_warp.io.trajectory import read_tum_trajectory
from rgs_warp.keypoint_odometry import KeypointOdometry, _grey

REPORT_FRAMES = (51, 90, 96, 102, 120, 150, 200, 250, 299, 400, 499)


def essential_start(frames, K: np.ndarray, width: int, height: int, boot_deg: float, log=print):
    """(k, T_WC of frame 0, T_WC of frame k): frame 0 against the first frame k whose essential matrix
    gives a median triangulation angle of boot_deg over its inliers, the baseline scaled to a median
    depth of 1.  KLT tracks from frame 0 with the odometry's default corners and KLT settings (the
    tracks its ``start`` follows too)."""
    scale = width / 640.0
    px = max(scale, 0.5)
    win = int(round(21 * max(scale, 1.0))) | 1
    klt = dict(
        winSize=(win, win),
        maxLevel=4 if scale > 1.5 else 3,
        criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
    )
    img0 = _grey(frames(0))
    p0 = cv2.goodFeaturesToTrack(img0, int(600 * px), 0.01, max(int(round(12 * scale)), 5), blockSize=3)
    p0 = cv2.cornerSubPix(img0, p0, (3, 3), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.01))
    p0 = p0.reshape(-1, 2).astype(np.float32)
    pts, alive, prev = p0.copy(), np.arange(len(p0)), img0
    i = 0
    while True:
        i += 1
        img = _grey(frames(i))
        p1, st, _ = cv2.calcOpticalFlowPyrLK(prev, img, pts, None, **klt)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(img, prev, p1, pts.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **klt)
        ok = (
            (st.ravel() == 1)
            & (st2.ravel() == 1)
            & (np.linalg.norm(back - pts, axis=1) < 0.5 * px)
            & (p1[:, 0] >= 4)
            & (p1[:, 0] < width - 4)
            & (p1[:, 1] >= 4)
            & (p1[:, 1] < height - 4)
        )
        pts, alive, prev = p1[ok], alive[ok], img
        u0, u1 = p0[alive].astype(np.float64), pts.astype(np.float64)
        if len(u1) < 50 or np.median(np.linalg.norm(u1 - u0, axis=1)) < 5 * px:
            continue
        E, m = cv2.findEssentialMat(u0, u1, K, cv2.RANSAC, 0.999, 1.0 * px)
        if E is None or E.shape != (3, 3):
            continue
        _, R, t, m2 = cv2.recoverPose(E, u0, u1, K, mask=m.copy())
        sel = m2.ravel() > 0
        if sel.sum() < 50:
            continue
        Xh = cv2.triangulatePoints(K @ np.eye(3, 4), K @ np.c_[R, t], u0[sel].T, u1[sel].T)
        X = (Xh[:3] / Xh[3]).T
        r0 = X / np.linalg.norm(X, axis=1, keepdims=True)
        r1 = X + R.T @ t.ravel()
        r1 /= np.linalg.norm(r1, axis=1, keepdims=True)
        angle = np.degrees(np.arccos(np.clip(np.sum(r0 * r1, axis=1), -1, 1)))
        if np.median(angle) >= boot_deg:
            T_CW = np.eye(4)
            T_CW[:3, :3], T_CW[:3, 3] = R, t.ravel() / np.median(X[:, 2])
            log(
                f"bootstrap: frames 0 and {i}, {int(sel.sum())} essential inliers, "
                f"median angle {np.median(angle):.2f} deg"
            )
            return i, np.eye(4), np.linalg.inv(T_CW)


def evaluate(est_WC: np.ndarray, gt: np.ndarray, first: int) -> dict:
    est, g = est_WC[first:], gt[first:]
    r = ate(est, g, "sim3")
    R, t, s = umeyama_alignment(est[:, :3, 3], g[:, :3, 3], True)
    e = 100 * np.linalg.norm(s * est[:, :3, 3] @ R.T + t - g[:, :3, 3], axis=1)
    at = {f: round(float(e[f - first]), 2) for f in REPORT_FRAMES if first <= f < first + len(e)}
    windows = []
    for w0 in range(0, len(est) + first, 50):
        lo, hi = max(w0, first), min(w0 + 50, first + len(est))
        if hi - lo >= 10:
            _, _, sw = umeyama_alignment(est[lo - first : hi - first, :3, 3], g[lo - first : hi - first, :3, 3], True)
            windows.append((lo, hi - 1, round(sw / s, 3)))
    return dict(
        ate_cm=round(r["rmse_cm"], 3),
        max_cm=round(r["max_cm"], 2),
        err_at=at,
        scale_windows=windows,
        worst=[(int(j) + first, round(float(e[j]), 1)) for j in np.argsort(-e)[:5]],
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", default="synthetic/office0_replica_size", help="a dataset config")
    ap.add_argument("--path", default="", help="dataset.path of a recorded sequence")
    ap.add_argument("--width", type=int, default=640, help="synthetic datasets only")
    ap.add_argument("--height", type=int, default=360, help="synthetic datasets only")
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--init", choices=("ess", "gt", "run"), default="ess")
    ap.add_argument("--run", default="", help="--init run: a SLAM run folder (trajectory.txt)")
    ap.add_argument("--init-frame", type=int, default=20)
    ap.add_argument("--boot-deg", type=float, default=2.0, help="median triangulation angle for the bootstrap")
    ap.add_argument("--json", default="")
    ap.add_argument("--tag", default="")
    ap.add_argument("overrides", nargs="*", help="keypoints.KEY=VALUE")
    a = ap.parse_args()

    size = [f"dataset.width={a.width}", f"dataset.height={a.height}"] if a.dataset.startswith("synthetic/") else []
    path = [f"dataset.path={a.path}"] if a.path else []
    cfg = load_config([f"dataset={a.dataset}", *size, *path, f"dataset.max_frames={a.frames}", *a.overrides])
    ds = open_dataset(cfg, device="cpu")
    width, height = ds.camera.width, ds.camera.height
    n = min(a.frames, len(ds))
    gt = np.array([ds[i].pose_gt for i in range(n)], np.float64)

    ba_seconds: list[float] = []
    bundle_adjust = keypoint_odometry._bundle_adjust

    def timed_bundle_adjust(*args, **kwargs):
        t0 = time.perf_counter()
        out = bundle_adjust(*args, **kwargs)
        ba_seconds.append(time.perf_counter() - t0)
        return out

    keypoint_odometry._bundle_adjust = timed_bundle_adjust

    def rgb(i):
        return ds[i].rgb

    if a.init == "gt":
        k, T_first, T_last = a.init_frame, gt[0], gt[a.init_frame]
    elif a.init == "run":
        _, run = read_tum_trajectory(Path(a.run) / "trajectory.txt")
        k, T_first, T_last = a.init_frame, run[0], run[a.init_frame]
    else:
        k, T_first, T_last = essential_start(rgb, ds.camera.K.astype(np.float64), width, height, a.boot_deg)
    odometry = KeypointOdometry(cfg.keypoints, ds.camera)
    t_start = time.perf_counter()
    poses = odometry.start([rgb(i) for i in range(k + 1)], T_first, T_last)
    rotation_only, lost, keyframes = [], [], [0, k]
    track_seconds = 0.0
    for i in range(k + 1, n):
        image = rgb(i)
        t0 = time.perf_counter()
        result = odometry.track(image)
        track_seconds += time.perf_counter() - t0
        poses.append(result.T_WC if result.T_WC is not None else poses[-1])
        if result.T_WC is None:
            lost.append(i)
        if result.rotation_only:
            rotation_only.append(i)
        if result.keyframe:
            keyframes.append(i)
    total = time.perf_counter() - t_start
    first = a.init_frame if a.init == "gt" else 0
    online = evaluate(np.array(poses), gt, first)
    ba = np.array(ba_seconds) if ba_seconds else np.zeros(1)
    tracked = n - k - 1
    out = dict(
        tag=a.tag,
        dataset=a.dataset,
        size=f"{width}x{height}",
        frames=n,
        init=a.init,
        start_frame=k,
        overrides=a.overrides,
        online=online,
        lost=lost,
        rot_only=rotation_only,
        keyframes=len(keyframes),
        landmarks=len(odometry),
        ba_n=len(ba_seconds),
        ba_mean_s=round(float(ba.mean()), 3),
        ba_max_s=round(float(ba.max()), 3),
        ba_total_s=round(float(ba.sum()), 1),
        fps_front=round(tracked / max(track_seconds - ba.sum(), 1e-9), 1),
        fps_all=round(tracked / track_seconds, 1),
        total_s=round(total, 1),
    )
    print(json.dumps(out))
    if a.json:
        out["pos_online"] = np.array(poses)[:, :3, 3].round(6).tolist()
        out["pos_gt"] = gt[:, :3, 3].round(6).tolist()
        with open(a.json, "a") as f:
            f.write(json.dumps(out) + "\n")


if __name__ == "__main__":
    main()
