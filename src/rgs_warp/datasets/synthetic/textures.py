"""Texture library of the synthetic scenes: procedural patterns and scikit-image's bundled photographs.

Every texture is linear-light RGB float32 (shading happens in linear light, the renderer writes sRGB).
Procedural textures are periodic so that they tile without seams; photographs that repeat use mirrored
addressing instead.  Power-of-two sizes keep every mip level an exact 2x2 box average.
"""

from __future__ import annotations

import cv2
import numpy as np
import skimage.data

REPEAT, CLAMP, MIRROR = 0, 1, 2


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.asarray(c, dtype=np.float32)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    c = np.clip(np.asarray(c, dtype=np.float32), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1.0 / 2.4) - 0.055).astype(np.float32)


def periodic_noise(rng: np.random.Generator, shape: tuple[int, int], beta: float, fmin: float = 1.0) -> np.ndarray:
    """Zero-mean, unit-std noise with a 1/f^beta amplitude spectrum; periodic because it is built in
    Fourier space, so it tiles seamlessly.  ``fmin`` (cycles per texture) removes the largest scales."""
    h, w = shape
    fy = np.fft.fftfreq(h)[:, None] * h
    fx = np.fft.rfftfreq(w)[None, :] * w
    f = np.sqrt(fx * fx + fy * fy)
    amp = np.where(f >= fmin, np.maximum(f, 1.0) ** -beta, 0.0)
    spec = amp * (rng.standard_normal(amp.shape) + 1j * rng.standard_normal(amp.shape))
    n = np.fft.irfft2(spec, s=shape)
    return ((n - n.mean()) / (n.std() + 1e-12)).astype(np.float32)


def _mix(a, b, t: np.ndarray) -> np.ndarray:
    a = np.asarray(a, np.float32)
    b = np.asarray(b, np.float32)
    return a + (b - a) * t[..., None]


def plaster(rng, colour, amount: float = 0.012, size: int = 64) -> np.ndarray:
    """Nearly plain paint: the variation stays below what a JPEG keeps, so it reads as textureless."""
    n = periodic_noise(rng, (size, size), 1.5)
    return np.asarray(colour, np.float32) * (1.0 + amount * n)[..., None]


def wood_planks(rng, light, dark, planks: int = 4, size: int = 512) -> np.ndarray:
    """Floor boards: ``planks`` boards across, grain along the board, per-board tone and ring phase."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    board = np.minimum((y * planks).astype(int), planks - 1)
    warp = periodic_noise(rng, (size, size), 2.2, fmin=2.0)
    phase = rng.uniform(0, 1, planks)[board]
    rings = 0.5 + 0.5 * np.sin(2 * np.pi * (6 * y * planks + 0.35 * warp + phase * 7))
    grain = periodic_noise(rng, (size, size), 0.6)
    t = np.clip(0.55 * rings + 0.12 * grain + 0.15 * rng.uniform(-1, 1, planks)[board] + 0.2, 0, 1)
    img = _mix(light, dark, t)
    # dark joints between boards, and staggered butt joints along them
    yb = (y * planks) % 1.0
    joint = (yb < 0.012) | (yb > 0.988)
    offs = rng.uniform(0, 1, planks)[board]
    xb = (x + offs) % 0.5
    joint |= xb < 0.004
    img[joint] *= 0.45
    return img


def tiles(rng, colour, grout, n: int = 4, size: int = 512, jitter: float = 0.08, grout_w: float = 0.03) -> np.ndarray:
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    ix, iy = (x * n).astype(int), (y * n).astype(int)
    tone = 1.0 + jitter * rng.standard_normal((n, n)).astype(np.float32)[iy % n, ix % n]
    fine = periodic_noise(rng, (size, size), 1.0)
    img = np.asarray(colour, np.float32) * (tone * (1.0 + 0.05 * fine))[..., None]
    fx, fy = (x * n) % 1.0, (y * n) % 1.0
    g = (np.minimum(fx, 1 - fx) < grout_w / 2) | (np.minimum(fy, 1 - fy) < grout_w / 2)
    img[g] = np.asarray(grout, np.float32) * (1.0 + 0.1 * fine[g])[:, None]
    return img


def wallpaper(rng, base, stripe, n: int = 8, size: int = 256) -> np.ndarray:
    """Vertical stripes with a faint damask-like pattern inside the light stripes."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    s = ((x * n) % 1.0) < 0.35
    motif = 0.5 + 0.5 * np.sin(2 * np.pi * n * x) * np.sin(2 * np.pi * n * 2 * y)
    img = _mix(base, stripe, s.astype(np.float32))
    img *= (1.0 + 0.08 * motif * ~s + 0.02 * periodic_noise(rng, (size, size), 1.0))[..., None]
    return img


def fabric(rng, colour, size: int = 256) -> np.ndarray:
    """Woven upholstery: a fine twill plus blotchy low-frequency wear."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float32)
    weave = 0.5 + 0.5 * np.sign(np.sin(2 * np.pi * (x + y) / 8.0)) * np.sin(2 * np.pi * x / 4.0)
    blotch = periodic_noise(rng, (size, size), 2.0, fmin=2.0)
    fine = periodic_noise(rng, (size, size), 0.3)
    return np.asarray(colour, np.float32) * (0.85 + 0.12 * weave + 0.06 * blotch + 0.05 * fine)[..., None]


def carpet(rng, colour, n: int = 2, size: int = 256) -> np.ndarray:
    """Carpet tiles: grainy pile, tiles laid with alternating pile direction (a visible tone checker)."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    checker = (((x * n).astype(int) + (y * n).astype(int)) % 2).astype(np.float32)
    pile = periodic_noise(rng, (size, size), 0.2)
    mottle = periodic_noise(rng, (size, size), 1.8, fmin=2.0)
    return np.asarray(colour, np.float32) * (0.9 + 0.08 * checker + 0.12 * pile + 0.08 * mottle)[..., None]


def rug(rng, size: int = 512) -> np.ndarray:
    """A patterned rug: border bands, a lozenge field and pile noise."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    d = np.minimum(np.minimum(x, 1 - x), np.minimum(y, 1 - y))
    palette = np.array([[0.45, 0.08, 0.06], [0.85, 0.7, 0.45], [0.08, 0.12, 0.3], [0.6, 0.3, 0.1]], np.float32)
    lozenge = ((np.abs((x * 6) % 1 - 0.5) + np.abs((y * 4) % 1 - 0.5)) < 0.35).astype(int)
    idx = np.where(d < 0.06, 2, np.where(d < 0.09, 1, np.where(lozenge == 1, 3, 0)))
    img = palette[idx]
    pile = periodic_noise(rng, (size, size), 0.4)
    return img * (1.0 + 0.12 * pile)[..., None]


def books(rng, size: int = 512) -> np.ndarray:
    """A row of book spines (texture v runs up the spines): random widths, colours, title bands."""
    h = w = size
    img = np.zeros((h, w, 3), np.float32)
    x = 0
    while x < w:
        bw = int(rng.integers(w // 40, w // 12))
        top = int(rng.uniform(0.0, 0.25) * h)
        colour = srgb_to_linear(rng.uniform(0.1, 0.85, 3))
        img[top:, x : x + bw] = colour
        for band in rng.uniform(0.2, 0.8, int(rng.integers(1, 4))):
            b0 = int(band * h)
            img[b0 : b0 + max(2, h // 60), x + 1 : x + bw - 1] = srgb_to_linear(rng.uniform(0.6, 0.95, 3))
        img[top:, x : x + 1] *= 0.3
        x += bw
    img[:, :] *= (1.0 + 0.04 * periodic_noise(rng, (h, w), 0.5))[..., None]
    return img


def drawers(rng, colour, n: int = 3, size: int = 256) -> np.ndarray:
    """Cabinet front: ``n`` drawers with gaps and a handle each."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    img = np.asarray(colour, np.float32) * (1 + 0.015 * periodic_noise(rng, (size, size), 1.2))[..., None]
    fy = (y * n) % 1.0
    img[(fy < 0.02) | (fy > 0.98)] *= 0.25
    img[(x < 0.015) | (x > 0.985)] *= 0.25
    handle = (np.abs(x - 0.5) < 0.12) & (np.abs(fy - 0.2) < 0.03)
    img[handle] = 0.6
    return img


def _photo(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    if image.dtype == bool:
        image = image.astype(np.uint8) * 255
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    image = image[..., :3]
    h, w = size
    return srgb_to_linear(cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0)


def photo(name: str, size: tuple[int, int] = (256, 256), tint=(1.0, 1.0, 1.0)) -> np.ndarray:
    """One of scikit-image's bundled images (on disk with the package), resized and tinted."""
    return _photo(getattr(skimage.data, name)(), size) * np.asarray(tint, np.float32)


def ink_on_white(name: str, size: tuple[int, int], ink=(0.05, 0.1, 0.35)) -> np.ndarray:
    """A whiteboard/notice: a grayscale document image (dark ink on light) recoloured as coloured ink."""
    g = _photo(getattr(skimage.data, name)(), size)[..., :1]
    g = np.clip((g - g.min()) / (g.max() - g.min() + 1e-6), 0, 1)
    white = np.float32(0.82)
    return white * g + np.asarray(ink, np.float32) * (1 - g)


def mip_levels(image: np.ndarray) -> list[np.ndarray]:
    """Mip chain down to 1x1 by 2x2 box averages (exact for power-of-two sizes, and wrap-consistent)."""
    levels = [np.ascontiguousarray(image, np.float32)]
    while max(levels[-1].shape[:2]) > 1:
        h, w = levels[-1].shape[:2]
        levels.append(cv2.resize(levels[-1], (max(w // 2, 1), max(h // 2, 1)), interpolation=cv2.INTER_AREA))
    return levels


def build_atlas(images: list[np.ndarray], max_levels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flat texel array holding every mip level of every texture, and its look-up table.

    Returns (texels (N, 3) float32, info (n_tex, max_levels, 3) int32 of (offset, width, height),
    n_levels (n_tex,) int32)."""
    chunks, info = [], np.zeros((len(images), max_levels, 3), np.int32)
    n_levels = np.zeros(len(images), np.int32)
    offset = 0
    for t, img in enumerate(images):
        levels = mip_levels(img)[:max_levels]
        n_levels[t] = len(levels)
        for k, lev in enumerate(levels):
            h, w = lev.shape[:2]
            info[t, k] = (offset, w, h)
            chunks.append(lev.reshape(-1, 3))
            offset += w * h
    return np.concatenate(chunks).astype(np.float32), info, n_levels
