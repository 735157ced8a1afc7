"""Host-side image metrics for evaluation (supplement §3): PSNR, SSIM, LPIPS (AlexNet), depth L1.

SSIM here is the reference the differentiable Warp SSIM (mapping loss) is tested against: Wang et
al. 2004 with an 11x11 Gaussian window of sigma 1.5, K1 = 0.01, K2 = 0.03, population covariances,
computed on the valid region only (no padding: the map is (H-10) x (W-10)), per channel, averaged.
This equals ``skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1)``. It is single-scale SSIM; the peers' variants are here
too, each under its own name: ``ssim_3dgs`` (the zero-padded 'same' variant of the 3DGS training
code, which MonoGS reports) and ``ms_ssim`` (multi-scale, pytorch-msssim, which SplaTAM reports).

``device``: PSNR and the SSIMs also run with torch on a GPU (``device="cuda:0"``), in float64 like
the host code, so the numbers agree with the host's to rounding (the same sums in another order;
tested on torch's CPU). On the host they cost about 2.6 s a 1200x680 frame on two cores, which made
the evaluation two thirds of a GPU run's time (experiments/results/sweeps.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.ndimage import correlate1d

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def _check_shapes(img: np.ndarray, ref: np.ndarray) -> None:
    if np.shape(img) != np.shape(ref):
        raise ValueError(f"image shape {np.shape(img)} differs from reference shape {np.shape(ref)}")
    if np.ndim(img) not in (2, 3):
        raise ValueError(f"expected HxW or HxWxC images, got shape {np.shape(img)}")


def _check_pair(img: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    _check_shapes(img, ref)
    return np.asarray(img, dtype=np.float64), np.asarray(ref, dtype=np.float64)


def psnr(img: np.ndarray, ref: np.ndarray, device: str | None = None) -> float:
    """Peak signal-to-noise ratio in dB of images in [0, 1] (peak 1), MSE over all pixels and
    channels; ``inf`` for identical images.  ``device``: a torch device to compute it on."""
    if device is not None:
        _check_shapes(img, ref)
        return _psnr_torch(_to_torch(img, device), _to_torch(ref, device))
    img, ref = _check_pair(img, ref)
    mse = float(np.mean((img - ref) ** 2))
    return float("inf") if mse == 0.0 else -10.0 * np.log10(mse)


def _to_torch(img: np.ndarray, device: str):
    """An HxW(xC) image as a 1xCxHxW float64 torch tensor on ``device``: copied there as it is (a float32
    render or frame moves half the bytes of a float64 one, and needs no transposed copy on the host),
    then cast and laid out on the device."""
    import torch

    t = torch.from_numpy(np.ascontiguousarray(np.atleast_3d(img))).to(device)
    return t.to(torch.float64).permute(2, 0, 1).contiguous()[None]


def _psnr_torch(x, y) -> float:
    mse = float(((x - y) ** 2).mean())
    return float("inf") if mse == 0.0 else -10.0 * np.log10(mse)


def _ssim_torch(x, y, pad: int) -> float:
    """``ssim`` (``pad`` 0: the valid region) or ``ssim_3dgs`` (``pad`` = the window's radius: zero
    padding) of two ``_to_torch`` images, in float64: the five local moments of all channels blurred
    together by one grouped separable convolution."""
    import torch
    import torch.nn.functional as F

    device = x.device
    c = x.shape[1]
    moments = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    k = moments.shape[1]
    w = torch.from_numpy(_gaussian_window_1d()).to(device)
    moments = F.conv2d(moments, w.view(1, 1, 1, -1).repeat(k, 1, 1, 1), padding=(0, pad), groups=k)
    moments = F.conv2d(moments, w.view(1, 1, -1, 1).repeat(k, 1, 1, 1), padding=(pad, 0), groups=k)
    mu_x, mu_y, exx, eyy, exy = moments.split(c, dim=1)
    var_x, var_y, cov_xy = exx - mu_x**2, eyy - mu_y**2, exy - mu_x * mu_y
    c1, c2 = SSIM_K1**2, SSIM_K2**2
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * cov_xy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    return float(ssim_map.mean())


def _gaussian_window_1d() -> np.ndarray:
    x = np.arange(SSIM_WINDOW, dtype=np.float64) - (SSIM_WINDOW - 1) / 2
    w = np.exp(-0.5 * (x / SSIM_SIGMA) ** 2)
    return w / w.sum()


def _filter_valid(x: np.ndarray, window: np.ndarray) -> np.ndarray:
    """Separable Gaussian filtering of an HxW(xC) array, keeping only the pixels whose whole window
    lies inside the image (the boundary mode then never matters)."""
    r = (SSIM_WINDOW - 1) // 2
    y = correlate1d(correlate1d(x, window, axis=0, mode="nearest"), window, axis=1, mode="nearest")
    return y[r:-r, r:-r]


def ssim(img: np.ndarray, ref: np.ndarray, device: str | None = None) -> float:
    """Mean SSIM of images in [0, 1] (HxW or HxWxC; channels averaged); see the module docstring.
    ``device``: a torch device to compute it on."""
    _check_shapes(img, ref)
    if min(np.shape(img)[:2]) < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW}, got {np.shape(img)[:2]}")
    if device is not None:
        return _ssim_torch(_to_torch(img, device), _to_torch(ref, device), pad=0)
    img, ref = _check_pair(img, ref)
    window = _gaussian_window_1d()
    mu_x, mu_y = _filter_valid(img, window), _filter_valid(ref, window)
    var_x = _filter_valid(img * img, window) - mu_x**2
    var_y = _filter_valid(ref * ref, window) - mu_y**2
    cov_xy = _filter_valid(img * ref, window) - mu_x * mu_y
    c1, c2 = SSIM_K1**2, SSIM_K2**2
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * cov_xy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    return float(ssim_map.mean())


def ssim_3dgs(img: np.ndarray, ref: np.ndarray, device: str | None = None) -> float:
    """SSIM as the 3DGS training code computes it (MonoGS reports this one): the same Gaussian window
    and constants as ``ssim``, but 'same' filtering with zero padding, so every pixel counts in the
    mean and the border's statistics take zeros in (it reads a little lower near the border).
    ``device``: a torch device to compute it on."""
    if device is not None:
        _check_shapes(img, ref)
        return _ssim_torch(_to_torch(img, device), _to_torch(ref, device), pad=(SSIM_WINDOW - 1) // 2)
    img, ref = _check_pair(img, ref)
    window = _gaussian_window_1d()

    def same(x: np.ndarray) -> np.ndarray:
        return correlate1d(correlate1d(x, window, axis=0, mode="constant"), window, axis=1, mode="constant")

    mu_x, mu_y = same(img), same(ref)
    var_x, var_y, cov_xy = same(img * img) - mu_x**2, same(ref * ref) - mu_y**2, same(img * ref) - mu_x * mu_y
    c1, c2 = SSIM_K1**2, SSIM_K2**2
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * cov_xy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    return float(ssim_map.mean())


# pytorch-msssim's five scales halve the image four times and need an 11-pixel window at the last one
MS_SSIM_MIN_SIDE = (SSIM_WINDOW - 1) * 2**4 + 1


def ms_ssim(img: np.ndarray, ref: np.ndarray, device: str | None = None) -> float | None:
    """Multi-scale SSIM (Wang et al. 2003) with pytorch-msssim's defaults, data range 1: what SplaTAM
    reports as "SSIM".  None for images smaller than ``MS_SSIM_MIN_SIDE`` on their shorter side.
    In float32, as pytorch-msssim is used; on torch's CPU unless ``device``."""
    _check_shapes(img, ref)
    if min(np.shape(img)[:2]) < MS_SSIM_MIN_SIDE:
        return None
    return _ms_ssim_torch(_to_torch(img, device or "cpu"), _to_torch(ref, device or "cpu"))


def _ms_ssim_torch(x, y) -> float:
    from pytorch_msssim import ms_ssim as _ms_ssim

    return float(_ms_ssim(x.float(), y.float(), data_range=1.0, size_average=True))


def depth_l1_cm(depth_m: np.ndarray, ref_m: np.ndarray) -> float:
    """Mean absolute depth difference in cm over pixels valid (finite, > 0) in both HxW maps."""
    depth_m, ref_m = _check_pair(depth_m, ref_m)
    valid = np.isfinite(depth_m) & np.isfinite(ref_m) & (depth_m > 0) & (ref_m > 0)
    if not valid.any():
        raise ValueError("no pixel has a valid depth in both maps")
    return float(100.0 * np.mean(np.abs(depth_m[valid] - ref_m[valid])))


# Pixels the map covers at least this much take part in the exposure fit of a scored frame.
EXPOSURE_MIN_ALPHA = 0.5


def fit_exposure(render: np.ndarray, ref: np.ndarray, alpha: np.ndarray | None = None) -> tuple[float, float]:
    """The affine brightness (gain g, bias b; one each for all channels) that maps ``render`` onto
    ``ref`` in the least-squares sense (Eq. 4), over the pixels the map covers (``alpha`` >=
    ``EXPOSURE_MIN_ALPHA``; every pixel without ``alpha``); (1, 0) when those pixels do not determine
    it (fewer than two, or a uniform render).  A real camera changes its exposure from frame to
    frame while the map has one colour: an exposure-compensated metric scores the map, not the
    exposure (MonoGS's protocol)."""
    render, ref = _check_pair(render, ref)
    covered = np.ones(render.shape[:2], bool) if alpha is None else np.asarray(alpha) >= EXPOSURE_MIN_ALPHA
    x, y = render[covered].reshape(-1), ref[covered].reshape(-1)
    return _affine_fit(float(x.size), x.sum(), y.sum(), (x * x).sum(), (x * y).sum())


def _affine_fit(n: float, sx, sy, sxx, sxy) -> tuple[float, float]:
    """The least-squares gain and bias of ``fit_exposure`` from the sums of x, y, x^2 and xy over n values."""
    sx, sy, sxx, sxy = (float(v) for v in (sx, sy, sxx, sxy))
    det = n * sxx - sx * sx
    if n < 2 or det <= 1e-12 * n * n:
        return 1.0, 0.0
    return float((n * sxy - sx * sy) / det), float((sxx * sy - sx * sxy) / det)


def _fit_exposure_torch(x, y, alpha: np.ndarray | None) -> tuple[float, float]:
    """``fit_exposure`` of two ``_to_torch`` images (the sums in float64 on their device)."""
    if alpha is not None:
        covered = _to_torch(np.asarray(alpha) >= EXPOSURE_MIN_ALPHA, x.device).bool().expand_as(x)
        x, y = x[covered], y[covered]
    return _affine_fit(float(x.numel()), x.sum(), y.sum(), (x * x).sum(), (x * y).sum())


def compensate_exposure(render: np.ndarray, ref: np.ndarray, alpha: np.ndarray | None = None) -> np.ndarray:
    """``render`` at ``ref``'s exposure: clip(g render + b, 0, 1) with ``fit_exposure``'s (g, b)."""
    g, b = fit_exposure(render, ref, alpha)
    return np.clip(g * np.asarray(render, dtype=np.float64) + b, 0.0, 1.0)


def eval_frame_indices(n_frames: int, keyframe_indices: Sequence[int], every: int = 5) -> np.ndarray:
    """Frames scored by the photometric metrics (§3): every ``every``-th frame (0, every, 2*every,
    ...), keyframes excluded, since the map was fitted to them."""
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    candidates = np.arange(0, n_frames, every)
    return candidates[~np.isin(candidates, np.asarray(keyframe_indices, dtype=np.int64))]


def metric_device(device) -> str | None:
    """The torch device the image metrics of a run on Warp ``device`` use: the same GPU when torch
    has CUDA, else None (the host; torch's CPU is slower there than NumPy and SciPy)."""
    import warp as wp

    device = wp.get_device(device)
    if not device.is_cuda:
        return None
    import torch

    return f"cuda:{device.ordinal}" if torch.cuda.is_available() else None


# torchvision's ImageNet AlexNet, the backbone the ``lpips`` package loads (``LPIPS(net="alex")``
# downloads it into torch's hub cache on first use).
ALEXNET_FILE = "alexnet-owt-7be5be79.pth"


def cached_alexnet_path() -> Path | None:
    """The AlexNet weights of torch's hub cache (``$TORCH_HOME/hub/checkpoints``), where the ``lpips``
    package and torchvision keep them, or None when they are not there (nothing is downloaded)."""
    try:
        import torch
    except ImportError:
        return None
    path = Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_FILE
    return path if path.is_file() else None


class LPIPS:
    """LPIPS with the AlexNet backbone (Zhang et al. 2018, v0.1 linear heads), in plain torch.

    Needs two local weight files and downloads nothing: ``alexnet_path``, torchvision's ImageNet
    AlexNet state dict (``alexnet-owt-7be5be79.pth``, keys ``features.N.weight/bias``), and
    ``linear_path``, the LPIPS v0.1 heads (``alex.pth``, keys ``linK.model.1.weight``); when
    ``linear_path`` is None the heads are taken from an installed ``lpips`` package, which ships
    them. If anything is missing, ``available`` is False, ``reason`` says why and ``__call__``
    returns None: a metric it cannot compute is reported as "n/a", never as a number.
    """

    # ImageNet-style input normalisation of LPIPS for inputs in [-1, 1].
    _SHIFT = (-0.030, -0.088, -0.188)
    _SCALE = (0.458, 0.448, 0.450)
    # (out channels, kernel, stride, padding) of AlexNet's five convolutions; torchvision indices
    # 0, 3, 6, 8, 10 in ``features``; max-pooling (3, stride 2) precedes conv 2 and conv 3.
    _CONVS = ((64, 11, 4, 2), (192, 5, 1, 2), (384, 3, 1, 1), (256, 3, 1, 1), (256, 3, 1, 1))
    _FEATURE_INDICES = (0, 3, 6, 8, 10)

    def __init__(self, alexnet_path: str | Path | None, linear_path: str | Path | None = None, device: str = "cpu"):
        self.available = False
        self.reason: str | None = None
        self._device = device
        try:
            import torch
        except ImportError as e:
            self.reason = f"torch is not importable ({e})"
            return
        self._torch = torch
        if alexnet_path is None:
            self.reason = (
                f"no AlexNet weights path configured (eval.lpips_alexnet_path; a run also looks for {ALEXNET_FILE} "
                "in torch's hub cache, where the lpips package keeps it)"
            )
            return
        if not Path(alexnet_path).is_file():
            self.reason = f"AlexNet weights not found at {alexnet_path}"
            return
        if linear_path is None:
            linear_path = self._lpips_package_heads()
            if linear_path is None:
                self.reason = "no LPIPS linear-head weights path configured and the lpips package is not installed"
                return
        if not Path(linear_path).is_file():
            self.reason = f"LPIPS linear-head weights not found at {linear_path}"
            return
        try:
            backbone = torch.load(alexnet_path, map_location=device, weights_only=True)
            heads = torch.load(linear_path, map_location=device, weights_only=True)
            self._conv_weights = [
                (backbone[f"features.{i}.weight"].float(), backbone[f"features.{i}.bias"].float())
                for i in self._FEATURE_INDICES
            ]
            self._head_weights = [heads[f"lin{k}.model.1.weight"].float() for k in range(5)]
        except (KeyError, RuntimeError, OSError) as e:
            self.reason = f"could not load LPIPS weights ({type(e).__name__}: {e})"
            return
        for (w, _), (channels, kernel, _, _), head in zip(
            self._conv_weights, self._CONVS, self._head_weights, strict=True
        ):
            if w.shape[0] != channels or w.shape[-1] != kernel or head.shape != (1, channels, 1, 1):
                self.reason = "LPIPS weights do not have AlexNet's layer shapes"
                return
        self.available = True

    @staticmethod
    def _lpips_package_heads() -> Path | None:
        try:
            import lpips
        except ImportError:
            return None
        return Path(lpips.__file__).parent / "weights" / "v0.1" / "alex.pth"

    def _features(self, x):
        F = self._torch.nn.functional
        taps = []
        for k, ((w, b), (_, _, stride, padding)) in enumerate(zip(self._conv_weights, self._CONVS, strict=True)):
            if k in (1, 2):
                x = F.max_pool2d(x, kernel_size=3, stride=2)
            x = F.relu(F.conv2d(x, w, b, stride=stride, padding=padding))
            taps.append(x)
        return taps

    def __call__(self, img: np.ndarray, ref: np.ndarray) -> float | None:
        """LPIPS distance of two HxWx3 images in [0, 1] (lower is more similar), or None when
        unavailable (see ``reason``)."""
        if not self.available:
            return None
        img, ref = _check_pair(img, ref)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"LPIPS needs HxWx3 images, got {img.shape}")
        torch = self._torch
        shift = torch.tensor(self._SHIFT, device=self._device).view(1, 3, 1, 1)
        scale = torch.tensor(self._SCALE, device=self._device).view(1, 3, 1, 1)
        batch = torch.from_numpy(np.stack([img, ref]).transpose(0, 3, 1, 2).astype(np.float32))
        batch = ((2.0 * batch.to(self._device) - 1.0) - shift) / scale
        with torch.no_grad():
            distance = 0.0
            for feats, head in zip(self._features(batch), self._head_weights, strict=True):
                # Unit-normalise each feature vector across channels (eps as in LPIPS).
                feats = feats / (torch.sqrt(torch.sum(feats**2, dim=1, keepdim=True)) + 1e-10)
                diff_sq = (feats[0:1] - feats[1:2]) ** 2
                distance += float(torch.nn.functional.conv2d(diff_sq, head).mean())
        return distance


def frame_scores(
    render: np.ndarray,
    ref: np.ndarray,
    alpha: np.ndarray | None = None,
    tracked: tuple[float, float] | None = None,
    device: str | None = None,
    lpips_model: LPIPS | None = None,
    psnr_only: bool = False,
) -> dict:
    """One scored frame's numbers for ``mean_scores``: ``psnr`` of the raw render, ``psnr_compensated`` at
    the frame's fitted exposure (``fit_exposure`` where ``alpha`` >= 0.5) and its ``gain``, ``psnr_tracked``
    at the ``tracked`` (g, b) (absent without); unless ``psnr_only``, the same for SSIM (``ssim``,
    ``ssim_compensated``, ``ssim_tracked``), ``ssim_3dgs`` and ``ms_ssim``, and with an available
    ``lpips_model`` ``lpips`` and ``lpips_tracked``.  ``render``: the map's colour as rendered, not clipped:
    a frame at exposure (g, b) shows clip(g render + b, 0, 1), as the camera clips (a map of a scene whose
    exposure changes holds colours above 1 that darker frames show), the raw render clip(render, 0, 1).
    ``device``: a torch device (``metric_device``), where each image is copied once and PSNR and the SSIMs
    computed (the host's numbers to rounding)."""
    _check_shapes(render, ref)
    if not psnr_only and min(np.shape(render)[:2]) < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW}, got {np.shape(render)[:2]}")
    if device is None:
        mapped, y = _check_pair(render, ref)
        x = np.clip(mapped, 0.0, 1.0)
        g, b = fit_exposure(mapped, y, alpha)
        compensated = np.clip(g * mapped + b, 0.0, 1.0)
        at_tracked = None if tracked is None else np.clip(tracked[0] * mapped + tracked[1], 0.0, 1.0)
        psnr_of, ssim_of, ssim_3dgs_of, ms_ssim_of = psnr, ssim, ssim_3dgs, ms_ssim
    else:
        mapped, y = _to_torch(render, device), _to_torch(ref, device)
        x = mapped.clamp(0.0, 1.0)
        g, b = _fit_exposure_torch(mapped, y, alpha)
        compensated = (g * mapped + b).clamp(0.0, 1.0)
        at_tracked = None if tracked is None else (tracked[0] * mapped + tracked[1]).clamp(0.0, 1.0)
        radius = (SSIM_WINDOW - 1) // 2
        psnr_of = _psnr_torch

        def ssim_of(u, v):
            return _ssim_torch(u, v, 0)

        def ssim_3dgs_of(u, v):
            return _ssim_torch(u, v, radius)

        def ms_ssim_of(u, v):
            return _ms_ssim_torch(u, v) if min(np.shape(render)[:2]) >= MS_SSIM_MIN_SIDE else None

    row = {"gain": g, "psnr": psnr_of(x, y), "psnr_compensated": psnr_of(compensated, y)}
    if at_tracked is not None:
        row["psnr_tracked"] = psnr_of(at_tracked, y)
    if psnr_only:
        return row
    row.update(ssim=ssim_of(x, y), ssim_compensated=ssim_of(compensated, y))
    row.update(ssim_3dgs=ssim_3dgs_of(x, y), ms_ssim=ms_ssim_of(x, y))
    if at_tracked is not None:
        row["ssim_tracked"] = ssim_of(at_tracked, y)
    if lpips_model is not None and lpips_model.available:
        row["lpips"] = lpips_model(np.clip(render, 0.0, 1.0), ref)
        if tracked is not None:
            row["lpips_tracked"] = lpips_model(np.clip(tracked[0] * np.asarray(render) + tracked[1], 0.0, 1.0), ref)
    return row


def mean_scores(rows: Sequence[dict], lpips_na_reason: str = "no LPIPS model given") -> dict:
    """Means over frames of their ``frame_scores`` rows (none ``psnr_only``), named as
    ``photometric_metrics`` reports them; a score some row lacks is None with its reason (the tracked
    exposures missing, or ``lpips_na_reason``)."""
    if not rows:
        raise ValueError("need at least one scored frame")

    def mean(key: str) -> float | None:
        return float(np.mean([row[key] for row in rows])) if all(key in row for row in rows) else None

    out: dict = {
        "n_frames": len(rows),
        "psnr_db": mean("psnr"),
        "ssim": mean("ssim"),
        "psnr_compensated_db": mean("psnr_compensated"),
        "ssim_compensated": mean("ssim_compensated"),
        "exposure_gain": mean("gain"),
        "psnr_tracked_exposure_db": mean("psnr_tracked"),
        "ssim_tracked_exposure": mean("ssim_tracked"),
        "ssim_3dgs": mean("ssim_3dgs"),
    }
    for name in ("psnr_tracked_exposure_db", "ssim_tracked_exposure"):
        if out[name] is None:
            out[name + "_na_reason"] = "no tracked exposures given"
    multi = [row["ms_ssim"] for row in rows]
    out["ms_ssim"] = None if None in multi else float(np.mean(multi))
    if out["ms_ssim"] is None:
        out["ms_ssim_na_reason"] = f"MS-SSIM needs images of at least {MS_SSIM_MIN_SIDE} px on the shorter side"
    out["lpips"], out["lpips_tracked_exposure"] = mean("lpips"), mean("lpips_tracked")
    if out["lpips"] is None:
        out["lpips_na_reason"] = lpips_na_reason
    if out["lpips_tracked_exposure"] is None:
        out["lpips_tracked_exposure_na_reason"] = out.get("lpips_na_reason", "no tracked exposures given")
    return out


def photometric_metrics(
    renders: Sequence[np.ndarray],
    refs: Sequence[np.ndarray],
    lpips_model: LPIPS | None = None,
    depths_m: Sequence[np.ndarray] | None = None,
    ref_depths_m: Sequence[np.ndarray] | None = None,
    alphas: Sequence[np.ndarray] | None = None,
    device: str | None = None,
    tracked_exposures: Sequence[tuple[float, float]] | None = None,
    frame_scores_out: list | None = None,
) -> dict:
    """Means over the scored frames (pick them with ``eval_frame_indices``) of PSNR, SSIM, LPIPS
    and depth L1, for ``write_report``: ``psnr_db``, ``ssim`` and ``lpips`` of the raw render, and
    ``psnr_compensated_db`` and ``ssim_compensated`` of the render at each frame's exposure
    (``compensate_exposure``, fitted where ``alphas`` >= 0.5), with the mean fitted gain
    ``exposure_gain`` (1 where the map's colour is the frames' exposure); peers' SSIM variants of the
    raw render, each named: ``ssim_3dgs`` (zero-padded, MonoGS) and ``ms_ssim`` (SplaTAM's "SSIM").
    ``psnr_tracked_exposure_db``, ``ssim_tracked_exposure`` and ``lpips_tracked_exposure``: the render at
    the exposure (g, b) that tracking estimated for each frame (``tracked_exposures``), as the SLAM itself
    would show the frame: nothing fitted to the frame at evaluation time.
    ``frame_scores_out``: a list to which each frame's ``frame_scores`` row is appended, in order.
    A metric that cannot be computed is None with its reason under ``<name>_na_reason``.  ``device``: a
    torch device for PSNR and the SSIMs (``metric_device``; the host's numbers to rounding)."""
    if len(renders) != len(refs) or not renders:
        raise ValueError(f"need matching non-empty render/reference lists, got {len(renders)}, {len(refs)}")
    alphas = [None] * len(renders) if alphas is None else alphas
    if tracked_exposures is not None and len(tracked_exposures) != len(renders):
        raise ValueError(f"need one tracked exposure per render, got {len(tracked_exposures)} for {len(renders)}")
    tracked = [None] * len(renders) if tracked_exposures is None else tracked_exposures
    scores = [
        frame_scores(x, y, a, t, device, lpips_model) for x, y, a, t in zip(renders, refs, alphas, tracked, strict=True)
    ]
    if frame_scores_out is not None:
        frame_scores_out.extend(scores)
    out = mean_scores(scores, lpips_model.reason if lpips_model is not None else "no LPIPS model given")
    if depths_m is None or ref_depths_m is None:
        out["depth_l1_cm"] = None
        out["depth_l1_cm_na_reason"] = "no depth given (monocular run or no ground-truth depth)"
    else:
        # frames where the map renders no depth over any measured pixel (a lost region) do not count
        values = []
        for d, r in zip(depths_m, ref_depths_m, strict=True):
            try:
                values.append(depth_l1_cm(d, r))
            except ValueError:
                continue
        out["depth_l1_cm"] = float(np.mean(values)) if values else None
        if not values:
            out["depth_l1_cm_na_reason"] = "no scored frame has a pixel with both a rendered and a measured depth"
    return out
