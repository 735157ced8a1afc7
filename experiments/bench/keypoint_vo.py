"""Monocular keypoint odometry with a windowed local bundle adjustment (issue 22, session 28, CPU).

A host-only (NumPy / OpenCV / SciPy, float64) monocular front end, measured on the synthetic office:
does a sparse keypoint odometry with a local BA hold the scale and pass the fast turn onto the striped
wall (frames 93-110)?  It shares nothing with the SLAM's Gaussian map.

Pipeline (one pass over the frames, causal):

- **Tracks**: Shi-Tomasi corners, pyramidal KLT frame to frame, forward-backward checked.  With
  ``--predict-flow`` (default) KLT starts from the motion model: landmarks at their projection in the
  predicted pose, other tracks moved by the predicted rotation.
- **Stripe rejection** (each can be switched off): ``--eig-ratio`` drops corners whose structure tensor
  over the KLT window has lambda_min / lambda_max below the ratio (an edge, or parallel stripes: the
  aperture problem); ``--fb-px`` the forward-backward limit; ``--res-px`` drops a landmark's track as
  soon as its reprojection residual after the frame's pose exceeds it (a track that slides);
  ``--min-kf-obs`` uses a landmark for the pose only once it is seen in that many keyframes.
- **Bootstrap** (``--init ess``, default): frame 0 against the first frame whose essential-matrix
  two-view geometry (``findEssentialMat`` / ``recoverPose``) gives a median triangulation angle of
  ``--boot-deg``; the scale is that baseline's (median depth 1); frames in between by PnP afterwards.
  ``--init gt`` starts from frames 0 and ``--init-frame`` at their true poses (session 16's start).
- **Pose per frame**: PnP (RANSAC, AP3P) and the constant-velocity prediction compete by inlier count,
  then Levenberg-Marquardt on the inliers.  Too few inliers or a pose far from the prediction: the
  rotation alone is estimated from all tracks (translation from the motion model), counted as a
  rotation-only frame; with too few tracks even for that the frame is lost (pose = prediction).
- **Keyframes** by tracked fraction / landmark count / parallax (``--kf-frac``, ``--kf-min-land``,
  ``--kf-deg``), not every frame.  At each keyframe every track seen in >= 2 keyframes without a
  landmark is triangulated from all its keyframe observations (linear, multi-view) when its rays span
  ``--tri-deg``, with every reprojection below ``--tri-px``.
- **Local BA** (``--ba-win`` N > 0): ``scipy.optimize.least_squares`` (trf, sparse ``jac_sparsity``,
  Huber loss of ``--ba-px`` pixels) over the poses of the last N keyframes and every landmark they see;
  the older keyframes that see those landmarks enter with their poses held (gauge and scale), at least
  two held.  Observations with residual > 3 ``--ba-px`` afterwards are removed (a landmark left with
  fewer than 2 is removed with its track).

Measures (printed, and as JSON with ``--json``): the position error after one Sim(3) fit of the whole
trajectory at frames 51/90/96/102/120/150/200/250, the Sim(3) ATE of the online (causal) poses and
of the final poses (non-keyframes re-attached to their reference keyframe after the last BA), the
Sim(3) scale fitted over each 50-frame window relative to the whole fit (the scale drift), lost and
rotation-only frames, BA seconds, and the front end's frames per second.

    PYTHONPATH=src .venv/bin/python experiments/bench/keypoint_vo.py --width 640 --height 360 --frames 300
    ... --ba-win 0                      # no local BA
    ... --init gt --init-frame 20       # start from the true poses of frames 0 and 20
    ... --eig-ratio 0.1 / --res-px 0 / --min-kf-obs 3 / --no-predict-flow   # one stripe measure changed

Pixel thresholds are given for 640 pixels of width and scaled with the image width.
"""

from __future__ import annotations

import argparse
import json
import time

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix

from rgs_warp.config import load_config
from rgs_warp.datasets import open_dataset
from rgs_warp.eval.ate import ate, umeyama_alignment

REPORT_FRAMES = (51, 90, 96, 102, 120, 150, 200, 250, 299)


# ----------------------------------------------------------------------------------------- geometry
def inv(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    o = np.eye(4)
    o[:3, :3] = R.T
    o[:3, 3] = -R.T @ t
    return o


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.ravel(t)
    return T


def rodrigues_batch(w: np.ndarray) -> np.ndarray:
    """(n, 3) rotation vectors -> (n, 3, 3) rotation matrices."""
    th = np.linalg.norm(w, axis=1)
    small = th < 1e-12
    k = w / np.where(small, 1.0, th)[:, None]
    Kx = np.zeros((len(w), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2] = -k[:, 2], k[:, 1]
    Kx[:, 1, 0], Kx[:, 1, 2] = k[:, 2], -k[:, 0]
    Kx[:, 2, 0], Kx[:, 2, 1] = -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], (1 - np.cos(th))[:, None, None]
    R = np.eye(3)[None] + s * Kx + c * (Kx @ Kx)
    R[small] = np.eye(3)
    return R


def rot_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


# ----------------------------------------------------------------------------------------- odometry
class KeypointVO:
    def __init__(self, K: np.ndarray, w: int, h: int, args):
        self.K, self.Kinv, self.w, self.h, self.a = K, np.linalg.inv(K), w, h, args
        s = w / 640.0
        self.px = s  # pixels per "640-pixel" unit
        self.max_feat = int(args.max_feat * max(s, 0.5))
        self.min_dist = max(int(round(args.min_dist * s)), 5)
        self.win = int(round(21 * max(s, 1.0))) | 1
        self.lk = dict(winSize=(self.win, self.win), maxLevel=4 if s > 1.5 else 3,
                       criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
        self.next_id = 0
        self.pts = np.zeros((0, 2), np.float32)
        self.ids = np.zeros(0, np.int64)
        self.obs: dict[int, list] = {}  # track id -> [(keyframe index, uv float64)]
        self.land: dict[int, np.ndarray] = {}  # track id -> X (world)
        self.banned: set[int] = set()
        self.kf_frame: list[int] = []
        self.kf_T: list[np.ndarray] = []  # T_CW of each keyframe
        self.poses: dict[int, np.ndarray] = {}  # frame -> T_CW (online)
        self.ref: dict[int, tuple[int, np.ndarray]] = {}  # frame -> (keyframe, T_frame @ inv(T_kf))
        self.status: dict[int, str] = {}
        self.ba_times: list[float] = []
        self.ba_sizes: list[tuple[int, int, int]] = []
        self.kf_land_count = 0
        self.kf_ids: set[int] = set()
        self.tri_stats = [0, 0, 0]  # triangulations refused for the angle, for a reprojection; made

    # ---------------------------------------------------------------- features
    def _eig_ratio(self, img: np.ndarray, p: np.ndarray) -> np.ndarray:
        """lambda_min / lambda_max of the structure tensor over the KLT window at points p."""
        f = img.astype(np.float32)
        gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3)
        k = (self.win, self.win)
        xx, yy, xy = cv2.boxFilter(gx * gx, -1, k), cv2.boxFilter(gy * gy, -1, k), cv2.boxFilter(gx * gy, -1, k)
        xi = np.clip(np.round(p[:, 0]).astype(int), 0, self.w - 1)
        yi = np.clip(np.round(p[:, 1]).astype(int), 0, self.h - 1)
        a, b, c = xx[yi, xi].astype(np.float64), yy[yi, xi].astype(np.float64), xy[yi, xi].astype(np.float64)
        tr, d = a + b, np.sqrt((a - b) ** 2 + 4 * c * c)
        return (tr - d) / np.maximum(tr + d, 1e-12)

    def detect(self, img: np.ndarray) -> None:
        want = self.max_feat - len(self.pts)
        if want <= 0:
            return
        mask = np.full(img.shape, 255, np.uint8)
        for p in self.pts:
            cv2.circle(mask, (int(p[0]), int(p[1])), self.min_dist, 0, -1)
        c = cv2.goodFeaturesToTrack(img, want * 2, 0.01, self.min_dist, mask=mask, blockSize=3)
        if c is None:
            return
        c = cv2.cornerSubPix(img, c, (3, 3), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.01))
        c = c.reshape(-1, 2).astype(np.float32)
        if self.a.eig_ratio > 0:
            c = c[self._eig_ratio(img, c) >= self.a.eig_ratio]
        c = c[:want]
        new = np.arange(self.next_id, self.next_id + len(c))
        self.next_id += len(c)
        self.pts = np.vstack([self.pts, c])
        self.ids = np.concatenate([self.ids, new])

    def track(self, prev: np.ndarray, img: np.ndarray, guess: np.ndarray | None) -> None:
        if len(self.pts) == 0:
            return
        if guess is not None:
            p1, st, _ = cv2.calcOpticalFlowPyrLK(prev, img, self.pts, guess.astype(np.float32).copy(),
                                                 flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **self.lk)
        else:
            p1, st, _ = cv2.calcOpticalFlowPyrLK(prev, img, self.pts, None, **self.lk)
        p0r, st2, _ = cv2.calcOpticalFlowPyrLK(img, prev, p1, self.pts.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                                               **self.lk)
        m = 4
        good = ((st.ravel() == 1) & (st2.ravel() == 1)
                & (np.linalg.norm(p0r - self.pts, axis=1) < self.a.fb_px * max(self.px, 0.5))
                & (p1[:, 0] >= m) & (p1[:, 0] < self.w - m) & (p1[:, 1] >= m) & (p1[:, 1] < self.h - m))
        self.pts, self.ids = p1[good], self.ids[good]

    def drop_tracks(self, bad_ids) -> None:
        bad_ids = np.asarray(list(bad_ids), np.int64)
        if len(bad_ids) == 0:
            return
        keep = ~np.isin(self.ids, bad_ids)
        self.pts, self.ids = self.pts[keep], self.ids[keep]
        for t in bad_ids.tolist():
            self.land.pop(t, None)
            self.banned.add(t)

    # ---------------------------------------------------------------- projection helpers
    def project(self, T: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Xc = X @ T[:3, :3].T + T[:3, 3]
        z = Xc[:, 2]
        uv = Xc[:, :2] / np.where(np.abs(z) < 1e-12, 1e-12, z)[:, None]
        return uv * [self.K[0, 0], self.K[1, 1]] + [self.K[0, 2], self.K[1, 2]], z

    def bearings(self, uv: np.ndarray) -> np.ndarray:
        b = np.c_[uv, np.ones(len(uv))] @ self.Kinv.T
        return b / np.linalg.norm(b, axis=1, keepdims=True)

    def usable(self) -> np.ndarray:
        mk = self.a.min_kf_obs
        return np.array([(t in self.land) and len(self.obs.get(t, ())) >= mk for t in self.ids.tolist()], bool)

    # ---------------------------------------------------------------- keyframes and triangulation
    def add_keyframe(self, i: int, img: np.ndarray, T: np.ndarray) -> None:
        k = len(self.kf_frame)
        self.kf_frame.append(i)
        self.kf_T.append(T.copy())
        for p, t in zip(self.pts.astype(np.float64), self.ids.tolist()):
            self.obs.setdefault(t, []).append((k, p))
        self.triangulate()
        self.detect(img)
        for p, t in zip(self.pts.astype(np.float64), self.ids.tolist()):
            if t not in self.obs:
                self.obs[t] = [(k, p)]
        self.kf_ids = set(self.ids.tolist())
        self.kf_land_count = int(self.usable().sum())

    def triangulate(self) -> None:
        cos_min = np.cos(np.radians(self.a.tri_deg))
        tri_px = self.a.tri_px * max(self.px, 0.5)
        for t in self.ids.tolist():
            if t in self.land or t in self.banned:
                continue
            o = self.obs.get(t, ())
            if len(o) < 2:
                continue
            Ts = [self.kf_T[k] for k, _ in o]
            uv = np.array([u for _, u in o])
            b = self.bearings(uv)
            bw = np.stack([T[:3, :3].T @ bb for T, bb in zip(Ts, b)])  # world-frame rays
            if np.min(bw @ bw[-1]) > cos_min and np.min(bw @ bw[0]) > cos_min:
                self.tri_stats[0] += 1
                continue
            A = []
            for T, uu in zip(Ts, uv):
                x = self.Kinv @ [uu[0], uu[1], 1.0]
                P = T[:3]
                A.append(x[0] * P[2] - P[0])
                A.append(x[1] * P[2] - P[1])
            _, _, Vt = np.linalg.svd(np.array(A))
            Xh = Vt[-1]
            if abs(Xh[3]) < 1e-12:
                continue
            X = Xh[:3] / Xh[3]
            ok = True
            for T, uu in zip(Ts, uv):
                p, z = self.project(T, X[None])
                if z[0] <= 0 or np.linalg.norm(p[0] - uu) > tri_px:
                    ok = False
                    break
            if ok:
                self.land[t] = X
                self.tri_stats[2] += 1
            else:
                self.tri_stats[1] += 1

    # ---------------------------------------------------------------- local bundle adjustment
    def local_ba(self) -> None:
        a = self.a
        nk = len(self.kf_frame)
        if a.ba_win <= 0 or nk < 2:
            return
        t0 = time.perf_counter()
        win = list(range(max(0, nk - a.ba_win), nk))
        wset = set(win)
        lids = [t for t, X in self.land.items() if any(k in wset for k, _ in self.obs[t])]
        if len(lids) < 10:
            return
        fixed = sorted({k for t in lids for k, _ in self.obs[t] if k not in wset})
        fixed = fixed[-a.ba_fixed_max:]
        free = list(win)
        # two-view start (essential matrix): only keyframe 0 held, so the bootstrap's pose is refined
        # too (its scale left to the damping); later at least two keyframes are held (gauge + scale)
        n_hold = 1 if (nk == 2 and a.init == "ess") else 2
        if nk == 2 and a.init == "gt":
            return
        while len(fixed) < n_hold and free:
            fixed.append(free.pop(0))
        if not free:
            return
        cams = free + fixed
        cidx = {k: j for j, k in enumerate(cams)}
        lidx = {t: j for j, t in enumerate(lids)}
        oc, ol, ouv = [], [], []
        for t in lids:
            for k, u in self.obs[t]:
                if k in cidx:
                    oc.append(cidx[k])
                    ol.append(lidx[t])
                    ouv.append(u)
        oc, ol, ouv = np.array(oc), np.array(ol), np.array(ouv)
        nf, nl, no = len(free), len(lids), len(oc)
        R0 = np.stack([self.kf_T[k][:3, :3] for k in cams])
        t0v = np.stack([self.kf_T[k][:3, 3] for k in cams])
        X0 = np.stack([self.land[t] for t in lids])
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]

        def unpack(x):
            d = x[: 6 * nf].reshape(nf, 6)
            R = R0.copy()
            tt = t0v.copy()
            R[:nf] = rodrigues_batch(d[:, :3]) @ R0[:nf]
            tt[:nf] = t0v[:nf] + d[:, 3:]
            return R, tt, x[6 * nf:].reshape(nl, 3)

        def res(x):
            R, tt, X = unpack(x)
            Xc = np.einsum("nij,nj->ni", R[oc], X[ol]) + tt[oc]
            z = np.where(Xc[:, 2] > 1e-6, Xc[:, 2], 1e-6)
            return np.c_[fx * Xc[:, 0] / z + cx - ouv[:, 0], fy * Xc[:, 1] / z + cy - ouv[:, 1]].ravel()

        rows, cols = [], []
        r2 = np.repeat(np.arange(no) * 2, 2) + np.tile([0, 1], no)
        for j in range(6):
            m = oc < nf
            rows.append(r2.reshape(-1, 2)[m].ravel())
            cols.append(np.repeat(6 * oc[m] + j, 2))
        for j in range(3):
            rows.append(r2)
            cols.append(np.repeat(6 * nf + 3 * ol + j, 2))
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        A = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(2 * no, 6 * nf + 3 * nl)).tocsr()
        x0 = np.concatenate([np.zeros(6 * nf), X0.ravel()])
        f_scale = a.ba_px * max(self.px, 0.5)
        r = least_squares(res, x0, jac_sparsity=A, loss="huber", f_scale=f_scale, x_scale="jac", method="trf",
                          max_nfev=a.ba_iters, ftol=1e-6, xtol=1e-8)
        R, tt, X = unpack(r.x)
        for j, k in enumerate(free):
            self.kf_T[k] = make_T(R[j], tt[j])
            self.poses[self.kf_frame[k]] = self.kf_T[k]
        for t, j in lidx.items():
            self.land[t] = X[j]
        # observations with large residuals: remove; landmarks left with < 2 observations: remove (+ track)
        rr = np.linalg.norm(r.fun.reshape(-1, 2), axis=1)
        bad = rr > 3 * f_scale
        if bad.any():
            badset = {}
            for c, l in zip(oc[bad], ol[bad]):
                badset.setdefault(lids[l], set()).add(cams[c])
            drop = []
            for t, ks in badset.items():
                self.obs[t] = [(k, u) for k, u in self.obs[t] if k not in ks]
                if len(self.obs[t]) < 2:
                    drop.append(t)
            self.drop_tracks(drop)
        self.ba_times.append(time.perf_counter() - t0)
        self.ba_sizes.append((nf, len(fixed), nl))

    # ---------------------------------------------------------------- pose
    def estimate_pose(self, Tpred: np.ndarray, prev_pts: dict, Tprev: np.ndarray) -> tuple[np.ndarray, str]:
        a = self.a
        use = self.usable()
        obj = np.array([self.land[t] for t in self.ids[use].tolist()]).reshape(-1, 3)
        uv = self.pts[use].astype(np.float64)
        thr = a.pnp_px * max(self.px, 0.5)
        T, inl = None, None
        if len(obj) >= a.min_inliers:
            def inliers(TT):
                p, z = self.project(TT, obj)
                return (np.linalg.norm(p - uv, axis=1) < thr) & (z > 0)

            cands = [Tpred]
            ok, rv, tv, _ = cv2.solvePnPRansac(obj, uv, self.K, None, iterationsCount=200, reprojectionError=thr,
                                               confidence=0.999, flags=cv2.SOLVEPNP_AP3P)
            if ok:
                cands.append(make_T(cv2.Rodrigues(rv)[0], tv))
            best = max(cands, key=lambda TT: inliers(TT).sum())
            m = inliers(best)
            for _ in range(3):
                if m.sum() < 6:
                    break
                rv, tv = cv2.Rodrigues(best[:3, :3])[0], best[:3, 3].copy()
                rv, tv = cv2.solvePnPRefineLM(obj[m], uv[m], self.K, None, rv, tv.reshape(3, 1))
                best = make_T(cv2.Rodrigues(rv)[0], tv)
                m = inliers(best)
            if m.sum() >= a.min_inliers:
                T, inl = best, m
        if T is not None:
            # consistency with the motion model
            step = np.linalg.norm(inv(Tprev)[:3, 3] - inv(Tpred)[:3, 3])
            dt = np.linalg.norm(inv(T)[:3, 3] - inv(Tpred)[:3, 3])
            dr = rot_deg(T[:3, :3] @ Tpred[:3, :3].T)
            if dr > a.max_dev_deg or dt > a.max_dev_step * step + a.max_dev_abs * self.scene_depth:
                T = None
        if T is not None:
            # drop landmark tracks that do not fit the pose (sliding tracks)
            p, _ = self.project(T, obj)
            r = np.linalg.norm(p - uv, axis=1)
            lim = (a.res_px * max(self.px, 0.5)) if a.res_px > 0 else thr
            self.drop_tracks(self.ids[use][r > lim])
            return T, "ok"
        # rotation only, from all tracks seen in the previous frame; translation of the motion model
        common = [j for j, t in enumerate(self.ids.tolist()) if t in prev_pts]
        if len(common) >= 20:
            b1 = self.bearings(self.pts[common].astype(np.float64))
            b0 = self.bearings(np.array([prev_pts[t] for t in self.ids[common].tolist()]))
            Rrel = None
            mask = np.ones(len(b0), bool)
            for _ in range(3):  # Kabsch with outlier trimming: b1 ~ Rrel b0
                U, _, Vt = np.linalg.svd(b1[mask].T @ b0[mask])
                D = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
                Rrel = U @ D @ Vt
                ang = np.degrees(np.arccos(np.clip(np.sum((b0 @ Rrel.T) * b1, axis=1), -1, 1)))
                mask = ang < max(3 * np.median(ang), 0.2)
            R = Rrel @ Tprev[:3, :3]
            C = inv(Tpred)[:3, 3]  # camera centre of the motion model
            return make_T(R, -R @ C), "rot"
        return Tpred, "lost"

    # ---------------------------------------------------------------- main loop
    def run(self, grey, gt, n: int, log=print) -> None:
        a = self.a
        img0 = grey(0)
        self.detect(img0)
        prev = img0
        hist = {0: (self.pts.copy(), self.ids.copy())}
        # ---- bootstrap
        k1 = None
        for i in range(1, n):
            img = grey(i)
            self.track(prev, img, None)
            hist[i] = (self.pts.copy(), self.ids.copy())
            prev = img
            if a.init == "gt":
                if i == a.init_frame:
                    k1 = i
                    T0, T1 = inv(gt[0]), inv(gt[i])
                    break
                continue
            p0d = dict(zip(hist[0][1].tolist(), hist[0][0]))
            common = [j for j, t in enumerate(self.ids.tolist()) if t in p0d]
            if len(common) < 50:
                continue
            u1 = self.pts[common].astype(np.float64)
            u0 = np.array([p0d[t] for t in self.ids[common].tolist()], np.float64)
            if np.median(np.linalg.norm(u1 - u0, axis=1)) < 5 * self.px:
                continue
            E, m = cv2.findEssentialMat(u0, u1, self.K, cv2.RANSAC, 0.999, 1.0 * max(self.px, 0.5))
            if E is None or E.shape != (3, 3):
                continue
            ninl, R, t, m2 = cv2.recoverPose(E, u0, u1, self.K, mask=m.copy())
            sel = m2.ravel() > 0
            if sel.sum() < 50:
                continue
            Ta, Tb = np.eye(4), make_T(R, t)
            X = cv2.triangulatePoints(self.K @ Ta[:3], self.K @ Tb[:3], u0[sel].T, u1[sel].T)
            X = (X[:3] / X[3]).T
            r0 = X / np.linalg.norm(X, axis=1, keepdims=True)
            C1 = -R.T @ t.ravel()
            r1 = X - C1
            r1 /= np.linalg.norm(r1, axis=1, keepdims=True)
            ang = np.degrees(np.arccos(np.clip(np.sum(r0 * r1, axis=1), -1, 1)))
            if np.median(ang) >= a.boot_deg:
                med = np.median(X[:, 2])
                T0, T1 = Ta, make_T(R, t.ravel() / med)
                k1 = i
                log(f"bootstrap: frames 0 and {i}, {int(sel.sum())} essential inliers, median angle {np.median(ang):.2f} deg")
                break
        if k1 is None:
            raise RuntimeError("no bootstrap")
        # keyframes 0 and k1 with the observations of their tracks
        cur_pts, cur_ids = self.pts, self.ids
        self.pts, self.ids = hist[0]
        self.kf_frame.append(0)
        self.kf_T.append(T0)
        for p, t in zip(self.pts.astype(np.float64), self.ids.tolist()):
            self.obs[t] = [(0, p)]
        self.poses[0] = T0
        self.pts, self.ids = cur_pts, cur_ids
        self.poses[k1] = T1
        self.add_keyframe(k1, prev, T1)
        self.scene_depth = float(np.median([(T1[:3, :3] @ X + T1[:3, 3])[2] for X in self.land.values()]))
        log(f"  {len(self.land)} landmarks, median depth {self.scene_depth:.3f}")
        # frames in between: PnP against the bootstrap landmarks
        for i in range(1, k1):
            p, ids = hist[i]
            sel = np.array([t in self.land for t in ids.tolist()], bool)
            if sel.sum() >= 6:
                obj = np.array([self.land[t] for t in ids[sel].tolist()])
                ok, rv, tv, _ = cv2.solvePnPRansac(obj, p[sel].astype(np.float64), self.K, None,
                                                   reprojectionError=a.pnp_px * max(self.px, 0.5),
                                                   flags=cv2.SOLVEPNP_AP3P)
                self.poses[i] = make_T(cv2.Rodrigues(rv)[0], tv) if ok else T0
            else:
                self.poses[i] = T0
            self.status[i] = "boot"
            self.ref[i] = (0, self.poses[i] @ inv(T0))
        self.status[0] = self.status[k1] = "kf"
        self.ref[0] = (0, np.eye(4))
        self.ref[k1] = (1, np.eye(4))
        self.local_ba()
        # ---- tracking
        t_start = time.perf_counter()
        for i in range(k1 + 1, n):
            img = grey(i)
            Tp, Tpp = self.poses[i - 1], self.poses[i - 2]
            Tpred = (Tp @ inv(Tpp)) @ Tp if a.motion_prior else Tp
            prev_pts = dict(zip(self.ids.tolist(), self.pts.astype(np.float64)))
            guess = None
            if a.predict_flow and len(self.pts):
                Trel = Tpred @ inv(Tp)
                Hr = self.K @ Trel[:3, :3] @ self.Kinv
                q = np.c_[self.pts, np.ones(len(self.pts))] @ Hr.T
                guess = q[:, :2] / q[:, 2:3]
                has = np.array([t in self.land for t in self.ids.tolist()], bool)
                if has.any():
                    pl, z = self.project(Tpred, np.array([self.land[t] for t in self.ids[has].tolist()]))
                    pl[z <= 0] = guess[has][z <= 0]
                    guess[has] = pl
            self.track(prev, img, guess)
            T, st = self.estimate_pose(Tpred, prev_pts, Tp)
            if a.detect_every and len(self.pts) < 0.8 * self.max_feat:
                self.detect(img)  # new tracks get their first observation at the next keyframe
            self.poses[i] = T
            self.status[i] = st
            nland = int(self.usable().sum())
            alive = len(self.kf_ids.intersection(self.ids.tolist())) / max(len(self.kf_ids), 1)
            lastT = self.kf_T[-1]
            par = self._parallax_deg(lastT, T)
            need = (alive < a.kf_frac or nland < a.kf_min_land * max(self.kf_land_count, 1)
                    or nland < a.kf_abs_land or par > a.kf_deg or st != "ok")
            if need and i - self.kf_frame[-1] >= a.kf_min_gap:
                self.add_keyframe(i, img, T)
                self.local_ba()
                T = self.poses[i] = self.kf_T[-1]
                self.ref[i] = (len(self.kf_frame) - 1, np.eye(4))
                self.status[i] = st + "+kf"
            else:
                self.ref[i] = (len(self.kf_frame) - 1, T @ inv(lastT))
            if a.verbose and (i % a.verbose == 0 or i in REPORT_FRAMES):
                e = np.linalg.norm(inv(T)[:3, 3] - gt[i][:3, 3]) if a.init == "gt" else float("nan")
                log(f"frame {i} {st} tracks {len(self.ids)} usable {nland} kfs {len(self.kf_frame)} "
                    f"land {len(self.land)} err(gt scale) {100 * e:.2f} cm tri {self.tri_stats}")
            prev = img
        self.track_seconds = time.perf_counter() - t_start
        self.n_tracked = n - k1 - 1

    def _parallax_deg(self, Tk: np.ndarray, T: np.ndarray) -> float:
        """Median angle at the landmarks (seen now) between the rays from keyframe Tk and pose T."""
        use = [t for t in self.ids.tolist() if t in self.land]
        if not use:
            return 0.0
        X = np.array([self.land[t] for t in use[:300]])
        c0, c1 = inv(Tk)[:3, 3], inv(T)[:3, 3]
        r0 = X - c0
        r1 = X - c1
        cs = np.sum(r0 * r1, axis=1) / np.linalg.norm(r0, axis=1) / np.linalg.norm(r1, axis=1)
        return float(np.degrees(np.median(np.arccos(np.clip(cs, -1, 1)))))

    def final_poses(self, n: int) -> list:
        return [self.ref[i][1] @ self.kf_T[self.ref[i][0]] for i in range(n)]


# ----------------------------------------------------------------------------------------- evaluation
def evaluate(est_T_cw: list, gt: list, first: int) -> dict:
    est = np.array([inv(T) for T in est_T_cw])[first:]
    g = np.array(gt)[first:]
    r = ate(est, g, "sim3")
    R, t, s = umeyama_alignment(est[:, :3, 3], g[:, :3, 3], True)
    e = 100 * np.linalg.norm(s * est[:, :3, 3] @ R.T + t - g[:, :3, 3], axis=1)
    at = {f: round(float(e[f - first]), 2) for f in REPORT_FRAMES if first <= f < first + len(e)}
    win = []
    for w0 in range(0, len(est) + first, 50):
        lo, hi = max(w0, first), min(w0 + 50, first + len(est))
        if hi - lo < 10:
            continue
        _, _, sw = umeyama_alignment(est[lo - first:hi - first, :3, 3], g[lo - first:hi - first, :3, 3], True)
        win.append((lo, hi - 1, round(sw / s, 3)))
    return dict(ate_cm=round(r["rmse_cm"], 3), max_cm=round(r["max_cm"], 2), err_at=at, scale_windows=win,
                worst=[(int(j) + first, round(float(e[j]), 1)) for j in np.argsort(-e)[:5]],
                err_all=[round(float(x), 2) for x in e])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=360)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--init", choices=("ess", "gt"), default="ess")
    ap.add_argument("--init-frame", type=int, default=20)
    ap.add_argument("--boot-deg", type=float, default=2.0, help="median triangulation angle for the bootstrap")
    ap.add_argument("--max-feat", type=int, default=600, help="corners kept (at 640 width)")
    ap.add_argument("--min-dist", type=float, default=12)
    ap.add_argument("--eig-ratio", type=float, default=0.0, help="0: off (0.1 measured worse, session 28)")
    ap.add_argument("--fb-px", type=float, default=0.5)
    ap.add_argument("--res-px", type=float, default=1.5, help="0: only the PnP inlier limit")
    ap.add_argument("--min-kf-obs", type=int, default=2)
    ap.add_argument("--no-predict-flow", dest="predict_flow", action="store_false")
    ap.add_argument("--no-motion-prior", dest="motion_prior", action="store_false")
    ap.add_argument("--pnp-px", type=float, default=2.0)
    ap.add_argument("--min-inliers", type=int, default=15)
    ap.add_argument("--max-dev-deg", type=float, default=5.0)
    ap.add_argument("--max-dev-step", type=float, default=4.0)
    ap.add_argument("--max-dev-abs", type=float, default=0.01, help="x median scene depth")
    ap.add_argument("--tri-deg", type=float, default=1.5)
    ap.add_argument("--tri-px", type=float, default=2.0)
    ap.add_argument("--kf-frac", type=float, default=0.7)
    ap.add_argument("--kf-min-land", type=float, default=0.6)
    ap.add_argument("--kf-abs-land", type=int, default=100, help="keyframe when fewer usable landmarks")
    ap.add_argument("--no-detect-every", dest="detect_every", action="store_false",
                    help="detect new corners only at keyframes")
    ap.add_argument("--kf-deg", type=float, default=2.0)
    ap.add_argument("--kf-min-gap", type=int, default=1)
    ap.add_argument("--ba-win", type=int, default=8, help="0: no local BA")
    ap.add_argument("--ba-fixed-max", type=int, default=12)
    ap.add_argument("--ba-px", type=float, default=1.0)
    ap.add_argument("--ba-iters", type=int, default=30)
    ap.add_argument("--verbose", type=int, default=0, help="log every N frames")
    ap.add_argument("--json", default="")
    ap.add_argument("--tag", default="")
    a = ap.parse_args()

    cfg = load_config(["dataset=synthetic/office0_replica_size", f"dataset.width={a.width}",
                       f"dataset.height={a.height}", f"dataset.max_frames={a.frames}"])
    ds = open_dataset(cfg, device="cpu")
    K = ds.camera.K.astype(np.float64)
    n = min(a.frames, len(ds))
    t = time.perf_counter()
    frames = [ds[i] for i in range(n)]
    gt = [f.pose_gt.astype(np.float64) for f in frames]
    greys = [cv2.cvtColor(np.clip(f.rgb * 255 + 0.5, 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY) for f in frames]
    del frames
    load_s = time.perf_counter() - t
    vo = KeypointVO(K, a.width, a.height, a)
    t = time.perf_counter()
    vo.run(lambda i: greys[i], gt, n)
    total = time.perf_counter() - t
    first = a.init_frame if a.init == "gt" else 0
    online = evaluate([vo.poses[i] for i in range(n)], gt, first)
    final = evaluate(vo.final_poses(n), gt, first)
    st = [vo.status[i] for i in range(n)]
    ba = np.array(vo.ba_times) if vo.ba_times else np.zeros(1)
    out = dict(
        tag=a.tag, size=f"{a.width}x{a.height}", frames=n, init=a.init, args=vars(a),
        online=online, final=final,
        lost=[i for i, s in enumerate(st) if s.startswith("lost")],
        rot_only=[i for i, s in enumerate(st) if s.startswith("rot")],
        keyframes=len(vo.kf_frame), landmarks=len(vo.land),
        ba_n=len(vo.ba_times), ba_mean_s=round(float(ba.mean()), 3), ba_max_s=round(float(ba.max()), 3),
        ba_total_s=round(float(ba.sum()), 1),
        fps_front=round(vo.n_tracked / max(vo.track_seconds - ba.sum(), 1e-9), 1),
        fps_all=round(vo.n_tracked / vo.track_seconds, 1), total_s=round(total, 1), load_s=round(load_s, 1),
    )
    brief = {k: v for k, v in out.items() if k != "args"}
    brief["online"] = {k: v for k, v in online.items() if k != "err_all"}
    brief["final"] = {k: v for k, v in final.items() if k != "err_all"}
    print(json.dumps(brief))
    if a.json:
        out["pos_online"] = [inv(vo.poses[i])[:3, 3].round(6).tolist() for i in range(n)]
        out["pos_gt"] = [g[:3, 3].round(6).tolist() for g in gt]
        with open(a.json, "a") as f:
            f.write(json.dumps(out) + "\n")


if __name__ == "__main__":
    main()
