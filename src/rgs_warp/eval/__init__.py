"""Evaluation metrics (supplement §3): ATE, PSNR/SSIM/LPIPS/depth L1, mesh Acc/Comp."""

from rgs_warp.eval.ate import ate, ate_keyframes_and_all, umeyama_alignment
from rgs_warp.eval.photometric import (
    LPIPS,
    cached_alexnet_path,
    compensate_exposure,
    depth_l1_cm,
    eval_frame_indices,
    fit_exposure,
    frame_scores,
    mean_scores,
    metric_device,
    ms_ssim,
    photometric_metrics,
    psnr,
    ssim,
    ssim_3dgs,
)
from rgs_warp.eval.reconstruction import mesh_metrics, sample_surface, tsdf_fuse

__all__ = [
    "LPIPS",
    "cached_alexnet_path",
    "compensate_exposure",
    "fit_exposure",
    "frame_scores",
    "ate",
    "ate_keyframes_and_all",
    "depth_l1_cm",
    "eval_frame_indices",
    "mesh_metrics",
    "mean_scores",
    "metric_device",
    "ms_ssim",
    "photometric_metrics",
    "psnr",
    "sample_surface",
    "ssim",
    "ssim_3dgs",
    "tsdf_fuse",
    "umeyama_alignment",
]
