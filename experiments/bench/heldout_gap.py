"""Why held-out frames render worse than keyframes (issue 18): one SLAM run, then every frame rendered
at its estimated pose and scored, and each scored pixel's error put in a bin by how many keyframes saw
that surface point.

    python experiments/bench/heldout_gap.py --out DIR --case NAME:override,override [--device cuda:0]

After the run (``SLAM.finish``, so ``mapping.final_iters`` counts), for every frame: PSNR raw and at the
frame's exposure (``compensate_exposure``, as ``metrics.json``), the fraction the map does not cover
(accumulated opacity < 0.5), and its distance to the nearest keyframe (frames, cm, degrees).  For the
scored frames (every 5th, keyframes excluded, and every keyframe) each pixel with measured depth is
lifted with that depth at the frame's estimated pose and projected into every keyframe (estimated
poses); a keyframe *sees* it where it lands inside the image and the keyframe's own measured depth there
agrees within 3 %.  The compensated squared error is then summed per bin: seen by 0, 1, 2, 3-4, 5+
keyframes, and pixels without measured depth.

Writes DIR/NAME.json (per-frame rows, per-bin pixel and error shares, run metrics), DIR/NAME.png
(PSNR against frame index with the keyframes marked; error share per bin) and DIR/NAME_frames.jpg
(``--panels``, default the worst and median scored frame: render | frame | error x4 at the
frame's exposure | keyframes seeing each pixel, grey where no depth was measured).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from rgs_warp.config import load_config
from rgs_warp.datasets import open_dataset
from rgs_warp.eval.ate import ate
from rgs_warp.eval.photometric import compensate_exposure, eval_frame_indices, psnr
from rgs_warp.slam import SLAM

BINS = ("0", "1", "2", "3-4", "5+", "no depth")
DEPTH_TOL = 0.03


def view_counts(depth: torch.Tensor, T_WC: np.ndarray, kf_depths: list, kf_poses: list, cam) -> torch.Tensor:
    """Per pixel: keyframes that see the point this pixel's depth puts at pose T_WC (-1: no depth)."""
    h, w = depth.shape
    dev = depth.device
    v, u = torch.meshgrid(torch.arange(h, device=dev), torch.arange(w, device=dev), indexing="ij")
    z = depth
    x = (u - cam.cx) / cam.fx * z
    y = (v - cam.cy) / cam.fy * z
    pts = torch.stack([x, y, z], -1).reshape(-1, 3).double()
    T = torch.as_tensor(T_WC, device=dev)
    world = pts @ T[:3, :3].T + T[:3, 3]
    count = torch.zeros(h * w, dtype=torch.int32, device=dev)
    for kd, kT in zip(kf_depths, kf_poses, strict=True):
        Tinv = torch.linalg.inv(torch.as_tensor(kT, device=dev))
        pc = world @ Tinv[:3, :3].T + Tinv[:3, 3]
        zc = pc[:, 2]
        ok = zc > 1e-3
        uk = torch.round(cam.fx * pc[:, 0] / zc.clamp(min=1e-3) + cam.cx).long()
        vk = torch.round(cam.fy * pc[:, 1] / zc.clamp(min=1e-3) + cam.cy).long()
        ok &= (uk >= 0) & (uk < w) & (vk >= 0) & (vk < h)
        dk = torch.zeros_like(zc)
        dk[ok] = kd[vk[ok], uk[ok]].double()
        ok &= (dk > 0) & ((dk - zc).abs() < DEPTH_TOL * zc)
        count += ok.int()
    count = count.reshape(h, w)
    count[depth <= 0] = -1
    return count


def bin_index(count: torch.Tensor) -> torch.Tensor:
    b = torch.full_like(count, 5)  # no depth
    b[count == 0] = 0
    b[count == 1] = 1
    b[count == 2] = 2
    b[(count >= 3) & (count <= 4)] = 3
    b[count >= 5] = 4
    return b


def panel(render, ref, err, count) -> np.ndarray:
    import matplotlib

    cmap = matplotlib.colormaps["viridis"]
    c = np.clip(count, 0, 6) / 6.0
    cc = cmap(c)[..., :3]
    cc[count < 0] = 0.3
    e = np.repeat(np.clip(4 * err, 0, 1)[..., None], 3, axis=2)
    return np.concatenate([render, ref, e, cc], axis=1)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--case", required=True, help="name:override,override")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--panels", default="", help="scored frames to show, comma separated (default: worst, median)")
    args = ap.parse_args(argv)
    name, _, ov = args.case.partition(":")
    overrides = [o for o in ov.split(",") if o]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = load_config(overrides + [f"device={args.device}"])
    ds = open_dataset(cfg, device=args.device)
    n = len(ds)
    slam = SLAM(cfg, ds.camera, device=args.device, T_first_WC=ds[0].pose_gt)
    t0 = time.time()
    for i in range(n):
        f = ds[i]
        slam.process(f.rgb, f.depth if cfg.mode == "rgbd" else None, f.timestamp)
    slam.finish()
    run_s = time.time() - t0
    _, est = slam.trajectory()
    kfs = [int(k) for k in slam.keyframe_indices]
    cam = ds.camera
    tdev = "cuda" if torch.cuda.is_available() else "cpu"
    kf_depths = [torch.as_tensor(ds[k].depth, device=tdev) for k in kfs]
    kf_poses = [est[k] for k in kfs]
    scored = set(int(i) for i in eval_frame_indices(n, kfs, cfg.eval.every))
    rows, sums, pixels, panels = [], np.zeros(len(BINS)), np.zeros(len(BINS)), {}
    kf_pos = np.array([p[:3, 3] for p in kf_poses])
    for i in range(n):
        res = slam.render(est[i])
        render = np.clip(res.color.numpy(), 0, 1)
        alpha = res.alpha.numpy()
        ref = ds[i].rgb
        comp = compensate_exposure(render, ref, alpha)
        se = ((comp - ref) ** 2).mean(axis=2)
        d_frames = min(abs(i - k) for k in kfs)
        dists = np.linalg.norm(kf_pos - est[i][:3, 3], axis=1)
        j = int(np.argmin(dists))
        rel = np.linalg.inv(kf_poses[j])[:3, :3] @ est[i][:3, :3]
        ang = float(np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1))))
        row = {
            "frame": i,
            "keyframe": i in kfs,
            "scored": i in scored,
            "psnr_raw": psnr(render, ref),
            "psnr_comp": psnr(comp, ref),
            "uncovered": float((alpha < 0.5).mean()),
            "frames_to_keyframe": d_frames,
            "cm_to_keyframe": float(100 * dists[j]),
            "deg_to_that_keyframe": ang,
        }
        if (i in scored or i in kfs) and ds[i].depth is not None:
            count = view_counts(torch.as_tensor(ds[i].depth, device=tdev), est[i], kf_depths, kf_poses, cam)
            bins = bin_index(count).cpu().numpy()
            se_bins = np.bincount(bins.ravel(), weights=se.ravel(), minlength=len(BINS))
            px_bins = np.bincount(bins.ravel(), minlength=len(BINS)).astype(float)
            row["pixel_share"] = (px_bins / px_bins.sum()).tolist()
            row["error_share"] = (se_bins / max(se_bins.sum(), 1e-12)).tolist()
            if i in scored:
                sums += se_bins
                pixels += px_bins
                panels[i] = (render, ref, np.abs(comp - ref).mean(axis=2), count.cpu().numpy())
        rows.append(row)
    sc = [r for r in rows if r["scored"]]
    kr = [r for r in rows if r["keyframe"]]
    summary = {
        "case": name,
        "overrides": overrides,
        "run_s": run_s,
        "frames": n,
        "keyframes": kfs,
        "gaussians": len(slam.map),
        "ate_cm": ate(est, np.array([ds[i].pose_gt for i in range(n)]), "se3")["rmse_cm"],
        "scored_psnr_raw": float(np.mean([r["psnr_raw"] for r in sc])),
        "scored_psnr_comp": float(np.mean([r["psnr_comp"] for r in sc])),
        "keyframe_psnr_comp": float(np.mean([r["psnr_comp"] for r in kr])),
        "all_frames_psnr_comp": float(np.mean([r["psnr_comp"] for r in rows])),
        "bins": list(BINS),
        "scored_pixel_share": (pixels / max(pixels.sum(), 1)).tolist(),
        "scored_error_share": (sums / max(sums.sum(), 1e-12)).tolist(),
        # PSNR of the pixels of each bin alone (pooled over the scored frames)
        "scored_bin_psnr": [float(10 * np.log10(p / s)) if s > 0 else None for s, p in zip(sums, pixels, strict=True)],
        "rows": rows,
    }
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(14, 4), gridspec_kw={"width_ratios": [3, 1]})
    fr = [r["frame"] for r in rows]
    ax[0].plot(fr, [r["psnr_comp"] for r in rows], lw=0.8, color="0.4", label="every frame")
    ax[0].scatter([r["frame"] for r in sc], [r["psnr_comp"] for r in sc], s=10, label="scored")
    ax[0].scatter([r["frame"] for r in kr], [r["psnr_comp"] for r in kr], s=14, color="r", label="keyframes")
    ax[0].set_xlabel("frame")
    ax[0].set_ylabel("PSNR at the frame's exposure (dB)")
    ax[0].legend()
    scores = f"scored {summary['scored_psnr_comp']:.2f} dB, keyframes {summary['keyframe_psnr_comp']:.2f}"
    ax[0].set_title(f"{name}: {scores}")
    xs = np.arange(len(BINS))
    ax[1].bar(xs - 0.2, summary["scored_pixel_share"], 0.4, label="pixels")
    ax[1].bar(xs + 0.2, summary["scored_error_share"], 0.4, label="squared error")
    ax[1].set_xticks(xs, BINS)
    ax[1].set_xlabel("keyframes that see the pixel")
    ax[1].legend()
    fig.tight_layout()
    fig.savefig(out / f"{name}.png", dpi=90)
    if panels:
        order = sorted(panels, key=lambda i: rows[i]["psnr_comp"])
        wanted = [int(v) for v in args.panels.split(",") if v]
        pick = [i for i in wanted if i in panels] or [order[0], order[len(order) // 2]]
        img = np.concatenate([panel(*panels[i]) for i in pick], axis=0)
        import cv2

        scale = min(1.0, 2400 / img.shape[1])
        img = cv2.resize(img.astype(np.float32), None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        jpeg = (255 * img[..., ::-1]).astype(np.uint8)
        cv2.imwrite(str(out / f"{name}_frames.jpg"), jpeg, [cv2.IMWRITE_JPEG_QUALITY, 85])
        summary["panel_frames"] = pick
    (out / f"{name}.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}))


if __name__ == "__main__":
    main()
