"""Probe (issue 22, session 16): a host-only keypoint visual odometry on the synthetic office path, to
see whether sparse keypoints alone pass the sections where monocular photometric tracking fails.

    python experiments/bench/keypoint_vo.py W H N_FRAMES FRAMES [KF_EVERY] [INIT]
    env: SRC=dir (frames as NNN.npy uint8 + poses.npy + K.npy instead of the dataset cache),
         GTTRI=1 (landmarks triangulated with the true poses: exact landmarks), NOBA=1 (no local BA)

KLT tracks (forward-backward checked) from Shi-Tomasi corners; frames INIT and 0 at their true poses
(the bootstrap); landmarks triangulated between a track's first and latest keyframe (>= 1.5 deg);
each frame's pose by PnP RANSAC + LM from the constant-velocity prediction; a keyframe every KF_EVERY
frames or when fewer than half the tracks have landmarks.  Prints the position error (the scale is the
truth's) every 3rd frame and the Sim(3) ATE.  The local BA (scipy) made it worse and is unfinished.
"""
import sys, time, os
import numpy as np, cv2
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from rgs_warp.config import load_config
from rgs_warp.datasets import open_dataset
from rgs_warp.eval.ate import ate

w, h, n = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
nf = int(sys.argv[4]) if len(sys.argv) > 4 else 300
KF_EVERY = int(sys.argv[5]) if len(sys.argv) > 5 else 4
BA_WIN = 8
import os
GTTRI = os.environ.get('GTTRI') == '1'
NOBA = os.environ.get('NOBA') == '1'
SRC = os.environ.get("SRC")
if SRC:
    K = np.load(SRC + "/K.npy").astype(np.float64)
    _P = np.load(SRC + "/poses.npy")
    class _F:
        def __init__(s, i): s.pose_gt = _P[i]; s.rgb = np.load(f"{SRC}/{i:03d}.npy").astype(np.float32) / 255.0
    class _DS:
        def __getitem__(s, i): return _F(i)
    ds = _DS()
else:
    cfg = load_config(["dataset=synthetic/office0", f"dataset.width={w}", f"dataset.height={h}", f"dataset.n_frames={n}"])
    ds = open_dataset(cfg, device="cpu")
    K = ds.camera.K.astype(np.float64)
scale_px = w / 640.0
MAX_FEAT = int(600 * max(scale_px, 0.5))
MIN_DIST = max(int(12 * scale_px), 5)
PNP_PX = 2.0 * max(scale_px, 0.5)


def grey(i):
    return cv2.cvtColor(np.clip(ds[i].rgb * 255 + 0.5, 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)


def inv(T):
    R, t = T[:3, :3], T[:3, 3]
    o = np.eye(4); o[:3, :3] = R.T; o[:3, 3] = -R.T @ t
    return o


def proj(T_CW, X):
    Xc = X @ T_CW[:3, :3].T + T_CW[:3, 3]
    uv = Xc[:, :2] / Xc[:, 2:3]
    return uv * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]], Xc[:, 2]


gt = [ds[i].pose_gt for i in range(min(n, nf))] if not SRC else [_P[i] for i in range(nf)]
N = len(gt)
poses = [None] * N  # T_CW
# tracks
next_id = 0
pts = np.zeros((0, 2), np.float32); ids = np.zeros(0, int)
obs = {}  # track id -> list of (kf index, uv)
land = {}  # track id -> X
kfs = []  # frame indices
prev = grey(0)
poses[0] = inv(gt[0])


def detect(img, pts):
    global next_id
    mask = np.full(img.shape, 255, np.uint8)
    for p in pts:
        cv2.circle(mask, (int(p[0]), int(p[1])), MIN_DIST, 0, -1)
    want = MAX_FEAT - len(pts)
    if want <= 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, int)
    c = cv2.goodFeaturesToTrack(img, want, 0.01, MIN_DIST, mask=mask, blockSize=3)
    if c is None:
        return np.zeros((0, 2), np.float32), np.zeros(0, int)
    c = cv2.cornerSubPix(img, c, (3, 3), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.01))
    new_ids = np.arange(next_id, next_id + len(c)); next_id += len(c)
    return c.reshape(-1, 2).astype(np.float32), new_ids


def add_kf(i, img):
    global pts, ids
    kfs.append(i)
    k = len(kfs) - 1
    for p, t in zip(pts, ids):
        obs.setdefault(t, []).append((k, p.astype(np.float64)))
    # triangulate
    T = poses[i]
    for t in ids:
        if t in land or len(obs[t]) < 2:
            continue
        o = obs[t]
        (k0, u0), (k1, u1) = o[0], o[-1]
        T0, T1 = (inv(gt[kfs[k0]]), inv(gt[kfs[k1]])) if GTTRI else (poses[kfs[k0]], poses[kfs[k1]])
        r0 = inv(T0)[:3, :3] @ np.linalg.solve(K, [u0[0], u0[1], 1.0])
        r1 = inv(T1)[:3, :3] @ np.linalg.solve(K, [u1[0], u1[1], 1.0])
        cosang = r0 @ r1 / np.linalg.norm(r0) / np.linalg.norm(r1)
        if cosang > np.cos(np.radians(1.5)):
            continue
        X = cv2.triangulatePoints(K @ T0[:3], K @ T1[:3], u0.reshape(2, 1), u1.reshape(2, 1))
        X = (X[:3] / X[3]).ravel()
        ok = True
        for kk, uu in o:
            uvp, z = proj(inv(gt[kfs[kk]]) if GTTRI else poses[kfs[kk]], X[None])
            if z[0] <= 0 or np.linalg.norm(uvp[0] - uu) > 2.0 * max(scale_px, 0.5):
                ok = False; break
        if ok:
            land[t] = X
    newp, newi = detect(img, pts)
    for p, t in zip(newp, newi):
        obs[t] = [(k, p.astype(np.float64))]
    pts = np.vstack([pts, newp]); ids = np.concatenate([ids, newi])


def rodr(T):
    r, _ = cv2.Rodrigues(T[:3, :3]); return r.ravel()


def local_ba():
    ks = list(range(max(0, len(kfs) - BA_WIN), len(kfs)))
    fixed = set(ks[:2]) if len(kfs) > 2 else set(ks)
    free = [k for k in ks if k not in fixed]
    lids = [t for t in land if any(kk in ks for kk, _ in obs[t])]
    if not free or not lids:
        return
    fidx = {k: j for j, k in enumerate(free)}
    lidx = {t: j for j, t in enumerate(lids)}
    O = [(kk, lidx[t], uu) for t in lids for kk, uu in obs[t] if kk in ks]
    x0 = np.concatenate([np.concatenate([rodr(poses[kfs[k]]), poses[kfs[k]][:3, 3]]) for k in free] + [np.array([land[t] for t in lids]).ravel()])
    nfree = len(free)
    okk = np.array([o[0] for o in O]); oli = np.array([o[1] for o in O]); ouv = np.array([o[2] for o in O])
    fixedT = {k: poses[kfs[k]] for k in fixed}

    def res(x):
        P = x[: 6 * nfree].reshape(-1, 6); X = x[6 * nfree:].reshape(-1, 3)
        Rs = {}
        for k in ks:
            if k in fidx:
                R, _ = cv2.Rodrigues(P[fidx[k], :3]); Rs[k] = (R, P[fidx[k], 3:])
            else:
                Rs[k] = (fixedT[k][:3, :3], fixedT[k][:3, 3])
        out = np.empty((len(O), 2))
        for k in ks:
            m = okk == k
            R, t = Rs[k]
            Xc = X[oli[m]] @ R.T + t
            uv = Xc[:, :2] / Xc[:, 2:3] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
            out[m] = uv - ouv[m]
        return out.ravel()

    A = lil_matrix((2 * len(O), len(x0)), dtype=int)
    for j, (kk, li, _) in enumerate(O):
        if kk in fidx:
            A[2 * j:2 * j + 2, 6 * fidx[kk]:6 * fidx[kk] + 6] = 1
        A[2 * j:2 * j + 2, 6 * nfree + 3 * li:6 * nfree + 3 * li + 3] = 1
    r = least_squares(res, x0, jac_sparsity=A, loss="huber", f_scale=1.0 * max(scale_px, 0.5), x_scale="jac", method="trf", max_nfev=30)
    P = r.x[: 6 * nfree].reshape(-1, 6); X = r.x[6 * nfree:].reshape(-1, 3)
    for k in free:
        T = np.eye(4); T[:3, :3], _ = cv2.Rodrigues(P[fidx[k], :3]); T[:3, 3] = P[fidx[k], 3:]
        poses[kfs[k]] = T
    for t in lids:
        land[t] = X[lidx[t]]
    # drop landmarks with large residuals
    rr = np.linalg.norm(r.fun.reshape(-1, 2), axis=1)
    bad = set(np.array(lids)[oli[rr > 3.0 * max(scale_px, 0.5)]])
    for t in bad:
        land.pop(t, None)


t0 = time.time()
pts, ids = detect(prev, pts)
add_kf(0, prev)
INIT = int(sys.argv[6]) if len(sys.argv) > 6 else 20
last_kf = 0
for i in range(1, N):
    img = grey(i)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(prev, img, pts, None, winSize=(21, 21), maxLevel=3)
    p0r, st2, _ = cv2.calcOpticalFlowPyrLK(img, prev, p1, None, winSize=(21, 21), maxLevel=3)
    good = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(p0r - pts, axis=1) < 0.5) \
        & (p1[:, 0] >= 0) & (p1[:, 0] < w) & (p1[:, 1] >= 0) & (p1[:, 1] < h)
    pts, ids = p1[good], ids[good]
    if i <= INIT:
        if i == INIT:
            poses[i] = inv(gt[i])
            add_kf(i, img); last_kf = i
        prev = img
        continue
    # pose by PnP
    has = np.array([t in land for t in ids])
    Tpred = poses[i - 1] @ inv(poses[i - 2]) @ poses[i - 1] if poses[i - 2] is not None else poses[i - 1]
    obj = np.array([land[t] for t in ids[has]]); img_pts = pts[has].astype(np.float64)
    rv, tv = rodr(Tpred), Tpred[:3, 3].copy()
    if len(obj) < 8:
        print('lost (few)', i, len(obj)); poses[i] = Tpred; prev = img; add_kf(i, img); last_kf = i; continue
    ok, rv, tv, inl = cv2.solvePnPRansac(obj, img_pts, K, None, rvec=rv.reshape(3, 1), tvec=tv.reshape(3, 1), useExtrinsicGuess=True, iterationsCount=100, reprojectionError=PNP_PX, confidence=0.999, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok or inl is None or len(inl) < 15:
        print("lost", i, len(obj)); poses[i] = Tpred
    else:
        inl = inl.ravel()
        rv, tv = cv2.solvePnPRefineLM(obj[inl], img_pts[inl], K, None, rv, tv)
        T = np.eye(4); T[:3, :3], _ = cv2.Rodrigues(rv); T[:3, 3] = tv.ravel(); poses[i] = T
        # drop outlier tracks
        out = np.ones(len(obj), bool); out[inl] = False
        bad_ids = ids[has][out]
        keep = ~np.isin(ids, bad_ids)
        pts, ids = pts[keep], ids[keep]
    nland = int(has.sum())
    if i % 3 == 0 and i < 140:
        ee = np.linalg.norm(inv(poses[i])[:3, 3] - gt[i][:3, 3]) * 100
        print(f'frame {i} tracks {len(ids)} withland {nland} inl {0 if inl is None else len(inl)} err {ee:.2f} cm kfs {len(kfs)} land {len(land)}')
    if i - last_kf >= KF_EVERY or nland < 0.5 * MAX_FEAT:
        add_kf(i, img); last_kf = i
        if not NOBA: local_ba()
    prev = img
print("time", time.time() - t0, "keyframes", len(kfs), "landmarks", len(land))
est = np.array([inv(poses[i]) for i in range(INIT, N)])
g = np.array(gt[INIT:N])
r = ate(est, g, "sim3")
print("sim3 ATE rmse cm %.3f median %.3f max %.3f scale %.3f" % (r["rmse_cm"], r["median_cm"], r["max_cm"], r["align_scale"]))
e = np.linalg.norm(est[:, :3, 3] - g[:, :3, 3], axis=1) * 100
print("raw err at 20,50,100,150,200,250,-1:", [round(float(e[min(k, len(e) - 1)]), 2) for k in (20, 50, 100, 150, 200, 250, -1)])
