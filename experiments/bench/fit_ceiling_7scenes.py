"""Why does the map not fit its 7-Scenes keyframes?  Fit-ceiling diagnosis on CPU, with the library's
own Seeder (measured-depth seeds, as the SLAM's depth fill), Mapper (the SLAM's mapping step) and
Renderer; ground-truth poses of the shared redkitchen frames (depth registered to the colour camera).

    python experiments/bench/fit_ceiling_7scenes.py CASE [CASE ...]   (cases: CASES at the bottom)

Results go to $OUT/results.json (updated per case; default ./bench_out) with side-by-side images;
RGS_DEVICE picks the device (default cpu), RGS_7SCENES the frames' folder (default the shared
sample); the *_tracked cases take the poses from a run's trajectory (RGS_TRAJECTORY=RUN_DIR/
trajectory.txt of a 7-Scenes run, in its ground truth's world).
Findings: experiments/results/fidelity.md, "Why the map does not fit the 7-Scenes keyframes"
(session 13).

Per view it reports PSNR of the render at the training pose: raw (the keyframe's exposure (g, b) as the
Mapper holds it, (1, 0) unless lr_exposure), compensated (one gain + bias fitted per image, over the
pixels the map covers, eval.compensate_exposure), both over the whole image and over the pixels with
measured depth ("surf": what depth seeds can cover; registration leaves the colour image's border
and dark / specular surfaces without depth).
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import warp as wp

wp.config.quiet = True

from rgs_warp.config import load_config  # noqa: E402
from rgs_warp.datasets import SevenScenesDataset  # noqa: E402
from rgs_warp.eval import compensate_exposure, psnr  # noqa: E402
from rgs_warp.keyframes import KeyframeBuffer  # noqa: E402
from rgs_warp.mapping import Mapper  # noqa: E402
from rgs_warp.render import Renderer  # noqa: E402
from rgs_warp.seeding import Seeder  # noqa: E402
from rgs_warp.types import GaussianMap  # noqa: E402

OUT = Path(os.environ.get("OUT", "bench_out"))
ROOT = os.environ.get(
    "RGS_7SCENES", str(Path(__file__).resolve().parents[2].parent / "shared" / "data" / "7scenes-redkitchen")
)
DEV = os.environ.get("RGS_DEVICE", "cpu")
_DS: dict[int, SevenScenesDataset] = {}


def dataset(factor: int) -> SevenScenesDataset:
    if factor not in _DS:
        _DS[factor] = SevenScenesDataset(ROOT, downscale=factor, prefetch=0)
    return _DS[factor]


def sharpness(frame_id: int) -> dict:
    """Variance of the Laplacian of the grey image (full 640x480 and at 160x120), and the mean
    gradient magnitude: lower = blurrier."""
    grey = cv2.imread(f"{ROOT}/frame-{frame_id:06d}.color.jpg", cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255.0
    small = cv2.resize(grey, (160, 120), interpolation=cv2.INTER_AREA)
    gx, gy = cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1)
    return {
        "lapvar_full": float(cv2.Laplacian(grey, cv2.CV_32F).var() * 1e4),
        "lapvar_160": float(cv2.Laplacian(small, cv2.CV_32F).var() * 1e4),
        "grad_full": float(np.hypot(gx, gy).mean()),
    }


def gt_consistency(ref_id: int, others, factor: int = 1) -> list[dict]:
    """How well the ground-truth poses (and registered depth) align two frames, without any map: frame
    ``ref_id``'s pixels with measured depth, moved into frame j by the poses and sampled there
    (cv2.remap), against ``ref_id``'s own image.  The residual misalignment is the dense optical flow
    (Farneback) from the reference to the warped image over textured pixels with depth: its median
    vector (a systematic shift: pose / calibration error) and median length (px at 640x480 / factor)."""
    ds = dataset(factor)
    cam = ds.camera
    a = ds[ref_id]
    v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
    z = a.depth.astype(np.float64)
    P = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z, np.ones_like(z)], -1)
    grey_a = cv2.cvtColor(a.rgb, cv2.COLOR_RGB2GRAY)
    gx, gy = cv2.Sobel(grey_a, cv2.CV_32F, 1, 0), cv2.Sobel(grey_a, cv2.CV_32F, 0, 1)
    textured = np.hypot(gx, gy) > 0.1
    out = []
    for j in others:
        b = ds[j]
        Q = P @ (np.linalg.inv(b.pose_gt) @ a.pose_gt).T
        mx = (cam.fx * Q[..., 0] / Q[..., 2] + cam.cx).astype(np.float32)
        my = (cam.fy * Q[..., 1] / Q[..., 2] + cam.cy).astype(np.float32)
        warped = cv2.remap(b.rgb, mx, my, cv2.INTER_LINEAR)
        ok = (z > 0) & (mx > 2) & (my > 2) & (mx < cam.width - 3) & (my < cam.height - 3)
        grey_w = cv2.cvtColor(warped, cv2.COLOR_RGB2GRAY)
        flow = cv2.calcOpticalFlowFarneback(
            (grey_a * 255).astype(np.uint8), (grey_w * 255).astype(np.uint8), None, 0.5, 3, 15, 5, 5, 1.1, 0
        )
        sel = ok & textured
        fl = flow[sel]
        # the same warp after taking out the median flow (a uniform shift)
        med = np.median(fl, axis=0)
        shifted = cv2.remap(b.rgb, mx + np.float32(med[0]), my + np.float32(med[1]), cv2.INTER_LINEAR)
        # PnP on the corrected correspondences: the relative pose that these pixels say, against the truth
        tu = (u + flow[..., 0]).astype(np.float32)
        tv = (v + flow[..., 1]).astype(np.float32)
        cu = cv2.remap(mx, tu, tv, cv2.INTER_LINEAR)[sel]
        cv_ = cv2.remap(my, tu, tv, cv2.INTER_LINEAR)[sel]
        obj = P[sel][:, :3].astype(np.float64)
        img = np.stack([cu, cv_], 1).astype(np.float64)
        K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
        T_gt = np.linalg.inv(b.pose_gt) @ a.pose_gt
        rv0, _ = cv2.Rodrigues(T_gt[:3, :3])
        ok_pnp, rv, tv_, inl = cv2.solvePnPRansac(
            obj, img, K, None, rv0.copy(), T_gt[:3, 3:].copy(), True, 200, 1.0 * cam.width / 640, 0.999
        )
        R_est, _ = cv2.Rodrigues(rv)
        dR = R_est @ T_gt[:3, :3].T
        ang = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
        proj_gt = obj @ T_gt[:3, :3].T + T_gt[:3, 3]
        proj_est = obj @ R_est.T + tv_.ravel()
        res_gt = np.linalg.norm(
            proj_gt[:, :2] / proj_gt[:, 2:] @ np.diag([cam.fx, cam.fy]) + [cam.cx, cam.cy] - img, axis=1
        )
        res_est = np.linalg.norm(
            proj_est[:, :2] / proj_est[:, 2:] @ np.diag([cam.fx, cam.fy]) + [cam.cx, cam.cy] - img, axis=1
        )
        rot_gt = float(np.degrees(np.linalg.norm(rv0)))
        out.append(
            {
                "pair": [ref_id, j],
                "gt_relative_motion_deg_cm": [round(rot_gt, 2), round(float(np.linalg.norm(T_gt[:3, 3])) * 100, 2)],
                "pnp_correction_deg_mm": [
                    round(ang, 3),
                    round(float(np.linalg.norm(tv_.ravel() - T_gt[:3, 3])) * 1000, 1),
                ],
                "pnp_inliers": round(float(len(inl) / len(obj)), 3) if inl is not None else 0.0,
                "median_residual_px_gt_vs_pnp": [
                    round(float(np.median(res_gt)), 3),
                    round(float(np.median(res_est)), 3),
                ],
                "px_scale": f"{cam.width}x{cam.height}",
                "median_flow_px": [round(float(med[0]), 3), round(float(med[1]), 3)],
                "median_abs_flow_px": round(float(np.median(np.linalg.norm(fl, axis=1))), 3),
                "p90_abs_flow_px": round(float(np.percentile(np.linalg.norm(fl, axis=1), 90)), 3),
                "warp_psnr_surf": round(psnr(warped[ok], a.rgb[ok]), 2),
                "warp_psnr_surf_shift_removed": round(psnr(shifted[ok], a.rgb[ok]), 2),
                "textured_px": int(sel.sum()),
            }
        )
    return out


def perturb(T: np.ndarray, rng, trans_m: float, rot_deg: float) -> np.ndarray:
    """T moved by trans_m in a random direction and turned by rot_deg about a random axis."""
    d = rng.normal(size=3)
    a = rng.normal(size=3)
    R, _ = cv2.Rodrigues((a / np.linalg.norm(a) * np.deg2rad(rot_deg)).reshape(3, 1))
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ R
    out[:3, 3] = T[:3, 3] + d / np.linalg.norm(d) * trans_m
    return out


def filled(depth: np.ndarray) -> np.ndarray:
    from scipy.ndimage import distance_transform_edt

    idx = distance_transform_edt(depth <= 0, return_distances=False, return_indices=True)
    return depth[idx[0], idx[1]].astype(np.float32)


def sigma_px(gmap: GaussianMap, T_WC: np.ndarray, f: float) -> np.ndarray:
    """Largest tangential standard deviation of every Gaussian in pixels at this view (f / z)."""
    g = gmap.to_numpy()
    z = (g["means"] - T_WC[:3, 3]) @ T_WC[:3, 2]
    s = np.sort(np.exp(g["log_scales"]), axis=1)
    ok = z > 0.05
    return (s[ok, 2] * f / z[ok]), (s[ok, 1] * f / z[ok])


def evaluate(gmap, cam, frames, poses, exposures, renderer) -> list[dict]:
    out = []
    for fr, T, (g, b) in zip(frames, poses, exposures, strict=True):
        res = renderer.forward(gmap, cam, T)
        c, a = res.color.numpy().astype(np.float64), res.alpha.numpy()
        ref = fr.rgb.astype(np.float64)
        raw = np.clip(g * c + b, 0, 1)
        comp = compensate_exposure(c, ref, a)
        surf = fr.depth > 0
        out.append(
            {
                "frame": int(fr.index),
                "raw": psnr(raw, ref),
                "comp": psnr(comp, ref),
                "raw_surf": psnr(raw[surf], ref[surf]),
                "comp_surf": psnr(comp[surf], ref[surf]),
                "coverage": float((a > 0.5).mean()),
                "depth_px": float(surf.mean()),
                "_img": (comp, ref),
            }
        )
    return out


def tracked_poses(frames) -> list[np.ndarray]:
    """The frames' poses in the run trajectory named by RGS_TRAJECTORY (TUM format), by timestamp."""
    from rgs_warp.io.trajectory import read_tum_trajectory

    stamps, poses = read_tum_trajectory(os.environ["RGS_TRAJECTORY"])
    out = []
    for f in frames:
        k = int(np.argmin(np.abs(stamps - f.timestamp)))
        if abs(stamps[k] - f.timestamp) > 1e-3:
            raise ValueError(f"frame {f.index} (t={f.timestamp:.3f} s) is not in the trajectory")
        out.append(poses[k].copy())
    return out


def side_by_side(path: Path, comp: np.ndarray, ref: np.ndarray, scale: int = 2) -> None:
    err = np.clip(np.abs(comp - ref) * 4.0, 0, 1)
    img = np.concatenate([comp, ref, err], axis=1)
    img = cv2.resize(img, (img.shape[1] * scale, img.shape[0] * scale), interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(path), (np.clip(img, 0, 1)[..., ::-1] * 255).round().astype(np.uint8))


def fit(
    ids,
    *,
    factor=4,
    renders_per_view=500,
    chunk=250,
    overrides=(),
    lr_exposure=0.0,
    pose_noise=None,
    tracked=False,
    fill_depth=False,
    png=None,
    log=print,
) -> dict:
    """Seed from each view's measured depth (later views: where the map does not cover them yet, the
    SLAM's depth fill), then Mapper.optimize with views_per_iter=1 (the SLAM default) for
    renders_per_view x len(ids) iterations, in calls of chunk x len(ids) (each with its own cosine
    decay, as successive windows); evaluation after every call."""
    ds = dataset(factor)
    cam = ds.camera
    k = len(ids)
    cfg = load_config(["dataset=7scenes/redkitchen", f"device={DEV}", f"mapping.lr_exposure={lr_exposure}", *overrides])
    frames = [ds[i] for i in ids]
    poses = tracked_poses(frames) if tracked else [f.pose_gt.copy() for f in frames]
    if pose_noise is not None:
        rng = np.random.default_rng(1)
        poses = [perturb(T, rng, *pose_noise) for T in poses]
    kf = KeyframeBuffer(k, cam.width, cam.height, DEV)
    # fill_depth: seed from the depth with its holes filled by the nearest measured depth (the whole
    # image gets seeds); mapping's depth term still sees only the measured depth
    seed_depths = [filled(f.depth) if fill_depth else f.depth for f in frames]
    slots = [kf.add(f.index, T, f.rgb, d) for f, T, d in zip(frames, poses, seed_depths, strict=True)]
    renderer = Renderer(DEV)
    gmap = GaussianMap(4096, cfg.render.sh_degree, DEV)
    seeder = Seeder(cfg.seeding, cam, DEV, sh_degree=cfg.render.sh_degree, renderer=renderer)
    seeded = [seeder.seed_depth(gmap, kf, s) for s in slots]
    if fill_depth:
        for f, s in zip(frames, slots, strict=True):
            wp.copy(kf.depth[s], wp.array(f.depth.astype(np.float32), dtype=wp.float32, device=DEV))
    mapper = Mapper(cfg.mapping, cam, gmap, DEV, renderer=renderer, seed=0)
    f = 0.5 * (cam.fx + cam.fy)
    s0 = sigma_px(gmap, poses[k // 2], f)

    def summary(ev):
        return {key: round(float(np.mean([e[key] for e in ev])), 2) for key in ("raw", "comp", "raw_surf", "comp_surf")}

    ev = evaluate(gmap, cam, frames, poses, kf.exposure[slots], renderer)
    curve = [{"renders_per_view": 0, **summary(ev)}]
    log(f"  seeded {seeded} -> {len(gmap)}; before: {curve[-1]}")
    t0 = time.perf_counter()
    done = 0
    while done < renders_per_view:
        step = min(chunk, renders_per_view - done)
        mapper.optimize(kf, slots, step * k, fixed_exposure=slots[:1])
        done += step
        ev = evaluate(gmap, cam, frames, poses, kf.exposure[slots], renderer)
        curve.append({"renders_per_view": done, **summary(ev), "s": round(time.perf_counter() - t0, 1)})
        log(f"  {curve[-1]}")
    seconds = time.perf_counter() - t0
    s1 = sigma_px(gmap, poses[k // 2], f)
    worst = int(np.argmin([e["comp_surf"] for e in ev]))
    if png is not None:
        side_by_side(OUT / png, *ev[worst if k > 1 else 0]["_img"])
    views = [{kk: (round(v, 3) if isinstance(v, float) else v) for kk, v in e.items() if kk != "_img"} for e in ev]
    for v, slot in zip(views, slots, strict=True):
        v["exposure_gb"] = [round(float(x), 4) for x in kf.exposure[slot]]
    return {
        "ids": list(ids),
        "resolution": [cam.width, cam.height],
        "overrides": list(overrides),
        "lr_exposure": lr_exposure,
        "pose_noise_m_deg": pose_noise,
        "tracked_poses": os.environ.get("RGS_TRAJECTORY") if tracked else None,
        "fill_depth": fill_depth,
        "gaussians": len(gmap),
        "seeded": seeded,
        "mapping_iterations": renders_per_view * k,
        "renders_per_view": renders_per_view,
        "seconds": round(seconds, 1),
        "curve": curve,
        "views": views,
        "mean": summary(ev),
        "worst_view": views[worst]["frame"],
        "sigma_px_median_before_after": [round(float(np.median(s0[0])), 3), round(float(np.median(s1[0])), 3)],
        "sigma_px_p10_before_after": [
            round(float(np.percentile(s0[0], 10)), 3),
            round(float(np.percentile(s1[0], 10)), 3),
        ],
        "png": png,
    }


WINDOW = [140, 150, 160, 170, 180]
FAST_LR = ["mapping.lr_scale=1e-2", "mapping.lr_opacity=5e-2", "mapping.lr_color=5e-3"]
CASES = {
    # 1: one view, the capacity / optimiser ceiling
    "c1": lambda: fit([160], renders_per_view=2000, png="case1_frame160.png"),
    "c1_filled": lambda: fit([160], renders_per_view=1000, fill_depth=True, png="case1_frame160_filled.png"),
    "c1_fastlr": lambda: fit([160], renders_per_view=1000, overrides=FAST_LR, png="case1_frame160_fastlr.png"),
    "c1_dense": lambda: fit([160], renders_per_view=1000, overrides=["seeding.depth_stride=1"]),
    "c1_plain": lambda: fit(
        [160], renders_per_view=1000, overrides=["mapping.robust_scale=0", "mapping.depth_weight=0"]
    ),
    "c1_320": lambda: fit([160], factor=2, renders_per_view=500, png="case1_frame160_320.png"),
    "c1_320_fastlr": lambda: fit(
        [160], factor=2, renders_per_view=300, chunk=150, overrides=FAST_LR, png="case1_frame160_320_fastlr.png"
    ),
    # single-view ceilings of every window view (the reference for case 2's per-view numbers)
    **{f"single{i}": (lambda i=i: fit([i], renders_per_view=500)) for i in WINDOW},
    **{f"single{i}_fastlr": (lambda i=i: fit([i], renders_per_view=500, overrides=FAST_LR)) for i in WINDOW},
    # 2: the 5-view window at ground-truth poses, same renders per view
    "c2": lambda: fit(WINDOW, renders_per_view=500, png="case2_worst.png"),
    "c2_fastlr": lambda: fit(WINDOW, renders_per_view=500, overrides=FAST_LR, png="case2_worst_fastlr.png"),
    # 3: + one exposure (g, b) per view refined with the map (the first held)
    "c3_fastlr": lambda: fit(WINDOW, renders_per_view=250, overrides=FAST_LR, lr_exposure=1e-2),
    # 5: poses perturbed (5 mm, 0.2 deg each, random directions)
    "c5_fastlr": lambda: fit(WINDOW, renders_per_view=250, overrides=FAST_LR, pose_noise=(0.005, 0.2)),
    "c5_small_fastlr": lambda: fit(WINDOW, renders_per_view=250, overrides=FAST_LR, pose_noise=(0.002, 0.08)),
    # the window without mapping's depth term: does the registered depth (colour and depth not captured at
    # the same instant) hold the Gaussians where the colour views disagree?
    "c2_nodepth_fastlr": lambda: fit(
        WINDOW, renders_per_view=500, overrides=[*FAST_LR, "mapping.depth_weight=0"], png="case2_nodepth_fastlr.png"
    ),
    # the window at the SLAM's tracked poses (RGS_TRAJECTORY): do they agree better than the ground truth?
    "c2_tracked": lambda: fit(WINDOW, renders_per_view=500, tracked=True, png="case2_tracked.png"),
    "c2_tracked_640": lambda: fit(WINDOW, factor=1, renders_per_view=500, chunk=125, tracked=True),
    "c2_tracked_640_fastlr": lambda: fit(
        WINDOW, factor=1, renders_per_view=500, chunk=125, overrides=FAST_LR, tracked=True, png="case2_tracked_640.png"
    ),
    "c2_tracked_320": lambda: fit(WINDOW, factor=2, renders_per_view=250, chunk=125, tracked=True),
    "c2_tracked_320_fastlr": lambda: fit(
        WINDOW, factor=2, renders_per_view=250, chunk=125, overrides=FAST_LR, tracked=True, png="case2_tracked_320.png"
    ),
    "c2_tracked_fastlr": lambda: fit(
        WINDOW, renders_per_view=500, overrides=FAST_LR, tracked=True, png="case2_tracked_fastlr.png"
    ),
}


def main(names) -> None:
    path = OUT / "results.json"
    results = json.loads(path.read_text()) if path.exists() else {}
    for name in names:
        if name == "sharpness":
            results["sharpness"] = {str(i): sharpness(i) for i in range(130, 196, 2)}
            print(json.dumps({k: v["lapvar_full"] for k, v in results["sharpness"].items()}))
        elif name == "consistency":
            results[name] = {
                "640": gt_consistency(160, [140, 150, 158, 162, 170, 180]),
                "160": gt_consistency(160, [140, 150, 170, 180], factor=4),
            }
            for row in results[name]["640"] + results[name]["160"]:
                print(row)
        elif name.startswith(("sharp5", "blur5")):  # the 5 sharpest / blurriest of 136..184, >= 6 frames apart
            sh = results["sharpness"]
            sign = -1.0 if name.startswith("sharp5") else 1.0
            order = sorted((k for k in sh if 136 <= int(k) <= 184), key=lambda k: sign * sh[k]["lapvar_full"])
            pick: list[int] = []
            for k in order:
                if all(abs(int(k) - p) >= 6 for p in pick):
                    pick.append(int(k))
                if len(pick) == 5:
                    break
            print(name, sorted(pick), [round(sh[str(p)]["lapvar_full"], 1) for p in sorted(pick)])
            over = FAST_LR if name.endswith("fastlr") else []
            results[name] = fit(sorted(pick), renders_per_view=250, overrides=over, png=f"{name}_worst.png")
        else:
            print(name)
            results[name] = CASES[name]()
        merged = json.loads(path.read_text()) if path.exists() else {}  # other processes' cases stay
        merged[name] = results[name]
        results = merged
        path.write_text(json.dumps(results, indent=1))
        r = results.get(name, {})
        if "views" in r:
            print(name, "mean", r["mean"], "gaussians", r["gaussians"], "s", r["seconds"])
            for v in r["views"]:
                print("   ", v)


if __name__ == "__main__":
    main(sys.argv[1:])
