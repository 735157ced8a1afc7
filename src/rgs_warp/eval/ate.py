"""Absolute trajectory error after Umeyama alignment (supplement §3: SE(3) for RGB-D, Sim(3) for
monocular), matching ``evo``'s APE on the translation part: the estimate is aligned onto the
ground truth, ``p_gt ~ s R p_est + t``."""

from __future__ import annotations

from typing import Literal

import numpy as np

Alignment = Literal["se3", "sim3", "none"]


def umeyama_alignment(src_m: np.ndarray, dst_m: np.ndarray, with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity ``dst ~ s R src + t`` between registered points (N, 3) (Umeyama 1991).

    Returns ``(R (3, 3), t_m (3,), s)`` with ``det R = +1``: when the best orthogonal matrix is a
    reflection (noisy or near-planar data), the last singular direction is flipped (Umeyama Eq. 43).
    ``s`` is 1 unless ``with_scale``.
    """
    src_m = np.asarray(src_m, dtype=np.float64)
    dst_m = np.asarray(dst_m, dtype=np.float64)
    mean_src, mean_dst = src_m.mean(axis=0), dst_m.mean(axis=0)
    src_c, dst_c = src_m - mean_src, dst_m - mean_dst
    var_src = float(np.mean(np.sum(src_c**2, axis=1)))
    if var_src <= 0.0:
        raise ValueError("Umeyama alignment needs points that are not all identical")
    cov = dst_c.T @ src_c / len(src_m)
    U, d, Vt = np.linalg.svd(cov)
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[2] = -1.0
    R = (U * S) @ Vt
    s = float(np.dot(d, S) / var_src) if with_scale else 1.0
    t_m = mean_dst - s * R @ mean_src
    return R, t_m, s


def _positions_m(poses: np.ndarray, name: str) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim == 3 and poses.shape[1:] == (4, 4):
        return poses[:, :3, 3]
    if poses.ndim == 2 and poses.shape[1] == 3:
        return poses
    raise ValueError(f"{name} must be (N, 4, 4) camera-to-world poses or (N, 3) positions, got {poses.shape}")


def ate(est: np.ndarray, gt: np.ndarray, align: Alignment = "se3") -> dict:
    """Absolute trajectory error of camera positions, in centimetres.

    ``est``, ``gt``: (N, 4, 4) camera-to-world poses or (N, 3) positions in metres, registered
    (row i of both is the same frame). ``align``: "se3" (RGB-D), "sim3" (monocular) or "none".
    Returns ``rmse_cm, mean_cm, median_cm, max_cm, n_poses``, plus ``align_T`` (4x4 rigid part
    [R | t_m] of the alignment applied to ``est``) and ``align_scale`` (s; 1 unless sim3).
    """
    p_est_m, p_gt_m = _positions_m(est, "est"), _positions_m(gt, "gt")
    if len(p_est_m) != len(p_gt_m):
        raise ValueError(f"est has {len(p_est_m)} poses, gt has {len(p_gt_m)}: they must be registered")
    if len(p_est_m) < 3:
        raise ValueError(f"ATE needs at least 3 poses, got {len(p_est_m)}")
    if not (np.all(np.isfinite(p_est_m)) and np.all(np.isfinite(p_gt_m))):
        raise ValueError("ATE needs finite poses")
    if align == "none":
        R, t_m, s = np.eye(3), np.zeros(3), 1.0
    elif align in ("se3", "sim3"):
        R, t_m, s = umeyama_alignment(p_est_m, p_gt_m, with_scale=align == "sim3")
    else:
        raise ValueError(f"align must be 'se3', 'sim3' or 'none', got {align!r}")
    errors_cm = 100.0 * np.linalg.norm(s * p_est_m @ R.T + t_m - p_gt_m, axis=1)
    align_T = np.eye(4)
    align_T[:3, :3] = R
    align_T[:3, 3] = t_m
    return {
        "rmse_cm": float(np.sqrt(np.mean(errors_cm**2))),
        "mean_cm": float(np.mean(errors_cm)),
        "median_cm": float(np.median(errors_cm)),
        "max_cm": float(np.max(errors_cm)),
        "n_poses": len(errors_cm),
        "align": align,
        "align_T": align_T,
        "align_scale": s,
    }


def ate_keyframes_and_all(
    est: np.ndarray, gt: np.ndarray, keyframe_indices: np.ndarray, align: Alignment = "se3"
) -> dict:
    """ATE on the keyframes (the paper's number, §3) and on all frames, each aligned on its own poses.

    ``est``/``gt`` hold every frame; ``keyframe_indices`` index into them.  With fewer than 3
    keyframes (a monocular start that fell back to one keyframe and lost the rest) ``keyframes`` is
    None and ``keyframes_na_reason`` says why: the run's other metrics still count.
    """
    keyframe_indices = np.asarray(keyframe_indices, dtype=np.int64)
    out = {"all_frames": ate(est, gt, align)}
    if len(keyframe_indices) < 3:
        return {"keyframes": None, "keyframes_na_reason": f"{len(keyframe_indices)} keyframe(s): ATE needs 3"} | out
    return {"keyframes": ate(np.asarray(est)[keyframe_indices], np.asarray(gt)[keyframe_indices], align)} | out
