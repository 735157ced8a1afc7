"""Dense L2-normalised descriptors at reduced resolution from a pluggable backbone (supplement §4.4).

A backbone has ``name``, ``stride`` (image pixels per feature pixel), ``dim`` (D),
``grid_shape(H, W) -> (Hf, Wf)`` and ``describe(rgb, out=None) -> (Hf, Wf, D) float32 wp.array`` on
its device, where ``rgb`` is an (H, W) ``wp.vec3`` array or (H, W, 3) NumPy image in [0, 1].
Feature pixel (i, j) is centred at image coordinates (stride*j + (stride-1)/2, stride*i + (stride-1)/2).

Backbones: ``classic`` (Warp, training-free, the default: see docs/matching.md), ``xfeat`` (optional
extra ``rgs_warp[xfeat]``), ``dinov2`` and ``dinov3`` (ViTs from a local official weights file named by
``matching.weights_path``; stride 14 and 16).
"""

from __future__ import annotations

import numpy as np

from rgs_warp.config import MatchingConfig
from rgs_warp.features.classic import ClassicBackbone

BACKBONES = ("classic", "xfeat", "dinov2", "dinov3")


def make_backbone(cfg: MatchingConfig, device=None):
    """The backbone named by ``cfg.backbone`` on ``device``."""
    if cfg.backbone == "classic":
        return ClassicBackbone(cfg.classic_stride, device)
    if cfg.backbone == "xfeat":
        from rgs_warp.features.torch_backbones import XFeatBackbone

        return XFeatBackbone(device)
    if cfg.backbone == "dinov2":
        from rgs_warp.features.torch_backbones import DinoV2Backbone

        return DinoV2Backbone(cfg.weights_path, device)
    if cfg.backbone == "dinov3":
        from rgs_warp.features.torch_backbones import DinoV3Backbone

        return DinoV3Backbone(cfg.weights_path, device)
    raise ValueError(f"matching.backbone {cfg.backbone!r} is not one of {', '.join(BACKBONES)}")


def feature_centres(grid: tuple[int, int], stride: int) -> np.ndarray:
    """(Hf * Wf, 2) float64 image coordinates (u, v) of the centres of the feature pixels of an
    (Hf, Wf) ``grid`` of ``stride``, row-major."""
    hf, wf = grid
    offset = 0.5 * (stride - 1)
    u, v = np.meshgrid(np.arange(wf) * stride + offset, np.arange(hf) * stride + offset)
    return np.stack([u, v], -1).reshape(-1, 2)


__all__ = ["BACKBONES", "ClassicBackbone", "feature_centres", "make_backbone"]
