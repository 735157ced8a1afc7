"""Session 12 one-off: the keyframe-exposure estimator (reduced major axis between two frames' colours at the
same surface points) against the ratio of mean colours, on the shared 7-Scenes frames at their ground-truth poses
and depths, at full resolution and 8x8-pooled; writes /tmp/expo/pairs.json.  Kept in git history only
(experiments/results/fidelity.md cites the commit)."""

import json

import numpy as np

from rgs_warp.config import load_config
from rgs_warp.datasets import open_dataset

cfg = load_config(["dataset=7scenes/redkitchen", "dataset.path=/work/shared/data/7scenes-redkitchen", "device=cpu"])
ds = open_dataset(cfg, device="cpu")
cam = ds.camera
LO, HI = 1 / 255, 254 / 255


def pool(a, k):
    h, w = a.shape[:2]
    h2, w2 = h // k * k, w // k * k
    a = a[:h2, :w2]
    return a.reshape(h2 // k, k, w2 // k, k, *a.shape[2:]).mean(axis=(1, 3))


def pool_depth(d, k):
    h, w = d.shape
    h2, w2 = h // k * k, w // k * k
    d = d[:h2, :w2].reshape(h2 // k, k, w2 // k, k)
    valid = d > 0
    n = valid.sum(axis=(1, 3))
    s = (d * valid).sum(axis=(1, 3))
    spread = np.where(valid, d, np.nan)
    with np.errstate(all="ignore"):
        out = np.where(n == k * k, s / np.maximum(n, 1), 0.0)  # only fully valid blocks
        rng = np.nanmax(spread, axis=(1, 3)) - np.nanmin(spread, axis=(1, 3))
    out[(rng > 0.05 * out)] = 0.0  # depth edges out
    return out


def pairs(fa, fb, k):
    # y: frame b's colour, x: frame a's colour at the same surface point (b's depth projected into a)
    ra, rb = fa.rgb, fb.rgb
    da, db = fa.depth, fb.depth
    fx, fy, cx, cy = cam.fx, cam.fy, cam.cx, cam.cy
    if k > 1:
        ra, rb = pool(ra, k), pool(rb, k)
        da, db = pool_depth(da, k), pool_depth(db, k)
        fx, fy = fx / k, fy / k
        cx, cy = (cx + 0.5) / k - 0.5, (cy + 0.5) / k - 0.5
    H, W = db.shape
    v, u = np.mgrid[0:H, 0:W]
    z = db
    m = (z > 0) & np.all((rb > LO) & (rb < HI), -1)
    X = np.stack([(u - cx) * z / fx, (v - cy) * z / fy, z, np.ones_like(z)], -1)[m]
    T = np.linalg.inv(fa.pose_gt) @ fb.pose_gt
    Xa = X @ T.T
    za = Xa[:, 2]
    ok = za > 0
    ua = fx * Xa[:, 0] / np.where(ok, za, 1) + cx
    va = fy * Xa[:, 1] / np.where(ok, za, 1) + cy
    ok &= (ua >= 0) & (ua <= W - 1) & (va >= 0) & (va <= H - 1)
    ia = np.round(va[ok]).astype(int)
    ja = np.round(ua[ok]).astype(int)
    dref = da[ia, ja]
    agree = (dref > 0) & (np.abs(dref - za[ok]) < 0.05 * za[ok])
    cref = ra[ia, ja][agree]
    cb = rb[m][ok][agree]
    good = np.all((cref > LO) & (cref < HI), -1)
    return cref[good].ravel(), cb[good].ravel()


def fits(x, y):
    if x.size < 1000:
        return None
    g_rma = np.sqrt(y.var() / x.var())
    g_ls = np.cov(x, y, bias=True)[0, 1] / x.var()
    g_mean = y.mean() / x.mean()
    return dict(
        n=int(x.size), rma=float(g_rma), ls=float(g_ls), mean=float(g_mean), corr=float(np.corrcoef(x, y)[0, 1])
    )


def sharp(f):
    g = f.rgb.mean(-1)
    return float(np.mean(np.abs(np.diff(g, axis=1))) + np.mean(np.abs(np.diff(g, axis=0))))


out = []
for i in range(0, 480, 8):
    for step in (5,):
        a, b = ds[i], ds[i + step]
        rec = dict(a=i, b=i + step, sharp_a=sharp(a), sharp_b=sharp(b))
        for k in (1, 8):
            x, y = pairs(a, b, k)
            rec[f"k{k}"] = fits(x, y)
        out.append(rec)
json.dump(out, open("/tmp/expo/pairs.json", "w"))
print(len(out))
