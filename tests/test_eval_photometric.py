"""PSNR, SSIM (against skimage), LPIPS (against the lpips package), depth L1, the §3 frame protocol,
and the report writer's handling of metrics that are not available."""

import json

import cv2
import numpy as np
import pytest
from skimage.metrics import structural_similarity

from rgs_warp.app.report import write_report
from rgs_warp.eval import (
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


@pytest.fixture(scope="module")
def frames(shared_data):
    folder = shared_data / "7scenes-redkitchen"
    return [cv2.imread(str(folder / f"frame-{i:06d}.color.jpg"))[..., ::-1].astype(np.float64) / 255.0 for i in (0, 10)]


def _skimage_ssim(a, b):
    return structural_similarity(
        a,
        b,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=1.0,
        channel_axis=-1 if a.ndim == 3 else None,
    )


def test_ssim_matches_skimage(frames):
    a, b = frames
    rng = np.random.default_rng(0)
    noisy = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)
    blurred = cv2.GaussianBlur(a, (7, 7), 2.0)
    pairs = [(a, b), (a, noisy), (a, blurred), (a[:37, 5:300, 1], b[:37, 5:300, 1]), (a[::7, ::5], noisy[::7, ::5])]
    for x, y in pairs:
        ours = ssim(x.astype(np.float32), y.astype(np.float32))
        assert abs(ours - _skimage_ssim(x.astype(np.float32), y.astype(np.float32))) < 1e-6
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    assert ssim(a, blurred) > ssim(a, noisy) > ssim(a, b) > 0.0


def test_ssim_rejects_bad_input(frames):
    with pytest.raises(ValueError, match="differs"):
        ssim(frames[0], frames[0][:-1])
    with pytest.raises(ValueError, match="at least 11x11"):
        ssim(frames[0][:10], frames[1][:10])


def test_psnr_hand_computed():
    ref = np.zeros((10, 10, 3))
    assert psnr(ref + 0.1, ref) == pytest.approx(20.0, abs=1e-12)  # MSE 0.01
    img = ref.copy()
    img[3, 4, 1] = 0.5  # MSE = 0.25 / 300
    assert psnr(img, ref) == pytest.approx(10.0 * np.log10(1200.0), abs=1e-12)
    assert psnr(ref, ref) == float("inf")


def test_depth_l1_on_valid_pixels_only():
    ref = np.array([[1.0, 2.0, 0.0], [4.0, np.nan, 3.0]], dtype=np.float32)
    depth = np.array([[1.5, 1.0, 9.0], [0.0, 1.0, 3.25]], dtype=np.float32)
    # Valid in both: (0,0) 0.5 m, (0,1) 1.0 m, (1,2) 0.25 m.
    assert depth_l1_cm(depth, ref) == pytest.approx(100.0 * 1.75 / 3, rel=1e-6)
    with pytest.raises(ValueError, match="no pixel"):
        depth_l1_cm(np.zeros((2, 2)), np.ones((2, 2)))


def test_eval_frame_indices():
    np.testing.assert_array_equal(eval_frame_indices(23, [0, 10, 12]), [5, 15, 20])
    np.testing.assert_array_equal(eval_frame_indices(10, [], every=3), [0, 3, 6, 9])
    with pytest.raises(ValueError):
        eval_frame_indices(10, [], every=0)


_CONVS = ((3, 64, 11), (64, 192, 5), (192, 384, 3), (384, 256, 3), (256, 256, 3))


def _synthetic_lpips_weights(tmp_path):
    """AlexNet-shaped random weights (torchvision key names) and non-negative LPIPS heads."""
    import torch

    rng = np.random.default_rng(0)
    backbone, heads = {}, {}
    for (cin, cout, k), i in zip(_CONVS, (0, 3, 6, 8, 10), strict=True):
        weight = rng.normal(0, np.sqrt(2 / (cin * k * k)), (cout, cin, k, k))
        backbone[f"features.{i}.weight"] = torch.from_numpy(weight.astype(np.float32))
        backbone[f"features.{i}.bias"] = torch.from_numpy(rng.normal(0, 0.01, cout).astype(np.float32))
    for n, (_, cout, _) in enumerate(_CONVS):
        heads[f"lin{n}.model.1.weight"] = torch.from_numpy(
            np.abs(rng.normal(0, 0.1, (1, cout, 1, 1))).astype(np.float32)
        )
    torch.save(backbone, tmp_path / "alexnet.pth")
    torch.save(heads, tmp_path / "heads.pth")
    return tmp_path / "alexnet.pth", tmp_path / "heads.pth"


def test_lpips_matches_reference_value(frames, tmp_path):
    # Reference: lpips 0.1.4 (LPIPS(net="alex"), normalize=True) with these same synthetic weights
    # loaded into its AlexNet slices and linear heads, on the same two frames.
    reference = 0.029268525540828705
    model = LPIPS(*_synthetic_lpips_weights(tmp_path))
    assert model.available and model.reason is None
    a, b = frames
    assert model(a, b) == pytest.approx(reference, rel=1e-5)
    assert model(b, a) == pytest.approx(reference, rel=1e-5)
    assert model(a, a) == pytest.approx(0.0, abs=1e-9)


def test_lpips_package_agrees_when_installed(frames, tmp_path):
    lpips = pytest.importorskip("lpips")
    import torch

    alexnet_path, heads_path = _synthetic_lpips_weights(tmp_path)
    backbone, heads = torch.load(alexnet_path), torch.load(heads_path)
    reference = lpips.LPIPS(net="alex", pretrained=False, pnet_rand=True, verbose=False).eval()
    for i, k in zip((0, 3, 6, 8, 10), range(1, 6), strict=True):
        conv = getattr(reference.net, f"slice{k}")._modules[str(i)]
        conv.weight.data.copy_(backbone[f"features.{i}.weight"])
        conv.bias.data.copy_(backbone[f"features.{i}.bias"])
    for n in range(5):
        getattr(reference, f"lin{n}").model[1].weight.data.copy_(heads[f"lin{n}.model.1.weight"])
    a, b = (torch.from_numpy(x.transpose(2, 0, 1)[None].astype(np.float32)) for x in frames)
    with torch.no_grad():
        expected = reference(a, b, normalize=True).item()
    assert LPIPS(alexnet_path, heads_path)(*frames) == pytest.approx(expected, rel=1e-5)


def test_lpips_unavailable_is_reported_not_invented(frames, tmp_path):
    model = LPIPS(None)
    assert not model.available and "no AlexNet weights path" in model.reason
    assert model(*frames) is None
    missing = tmp_path / "nowhere" / "alexnet.pth"
    model = LPIPS(missing, tmp_path / "heads.pth")
    assert model(*frames) is None and str(missing) in model.reason
    torch = pytest.importorskip("torch")
    alexnet_path, heads_path = _synthetic_lpips_weights(tmp_path)
    torch.save({"features.0.weight": torch.zeros(3)}, tmp_path / "broken.pth")
    assert "could not load" in LPIPS(tmp_path / "broken.pth", heads_path).reason
    wrong_heads = {f"lin{n}.model.1.weight": torch.zeros(1, 7, 1, 1) for n in range(5)}
    torch.save(wrong_heads, tmp_path / "wrong_heads.pth")
    assert "layer shapes" in LPIPS(alexnet_path, tmp_path / "wrong_heads.pth").reason


def test_photometric_metrics_and_report(frames, tmp_path):
    a, b = (f[:240, :320] for f in frames)
    depth = np.full(a.shape[:2], 2.0, dtype=np.float32)
    out = photometric_metrics([a, b], [a, a], LPIPS(None), [depth, depth], [depth + 0.01, depth])
    assert out["psnr_db"] == float("inf")  # a frame identical to its reference
    assert out["ssim"] == pytest.approx((1.0 + ssim(b, a)) / 2, abs=1e-12)
    assert out["depth_l1_cm"] == pytest.approx(0.5, abs=1e-5)
    assert out["lpips"] is None and "no AlexNet weights path" in out["lpips_na_reason"]
    # a frame where the map renders no depth (lost region) is left out; none at all: n/a with why
    empty = np.zeros_like(depth)
    rows: list = []
    out2 = photometric_metrics([a, b], [a, a], None, [empty, depth], [depth, depth + 0.02], frame_scores_out=rows)
    assert (rows[0]["psnr"], rows[0]["psnr_compensated"]) == (float("inf"), float("inf"))
    assert rows[1]["psnr"] == pytest.approx(psnr(b, a), abs=1e-9) and rows[1]["ssim"] == pytest.approx(ssim(b, a))
    assert "frame_scores_out" not in out2 and len(rows) == 2
    assert out2["depth_l1_cm"] == pytest.approx(2.0, abs=1e-4)
    out3 = photometric_metrics([a], [a], None, [empty], [depth])
    assert out3["depth_l1_cm"] is None and "rendered and a measured depth" in out3["depth_l1_cm_na_reason"]

    out["psnr_db"] = psnr(b, a)
    metrics = {
        "dataset": "redkitchen",
        "ate": {"keyframes": {"rmse_cm": 1.23456, "n_poses": 12}, "all_frames": {"rmse_cm": 2.5}},
        "photometric": out,
        "align_T": np.eye(4),
    }
    json_path, md_path = write_report(tmp_path / "run", metrics, notes={"photometric": "PSNR raw: the render as is"})
    loaded = json.loads(json_path.read_text())
    assert loaded["photometric"]["lpips"] is None
    assert loaded["align_T"] == np.eye(4).tolist()
    markdown = md_path.read_text()
    assert (
        "| psnr (dB) | ssim | psnr_compensated (dB) | ssim_compensated | exposure_gain | psnr_tracked_exposure (dB) "
        "| ssim_tracked_exposure | ssim_3dgs | ms_ssim | lpips |" in markdown
    )
    assert f"n/a ({out['lpips_na_reason']})" in markdown
    assert "| keyframes | 1.235 | 12 |" in markdown and "| all_frames | 2.5 |  |" in markdown
    # a section's note: the line after its table, once
    assert markdown.count("PSNR raw: the render as is") == 1
    assert markdown.split("## photometric")[1].split("\n\n")[2].strip() == "PSNR raw: the render as is"

    with pytest.raises(ValueError, match="photometric.lpips is None without a reason"):
        write_report(tmp_path / "bad", {"photometric": {"lpips": None}})
    json_path, _ = write_report(tmp_path / "inf", {"psnr_db": float("inf")})
    assert json.loads(json_path.read_text())["psnr_db"] == "inf"


def test_exposure_fit_matches_lstsq_and_compensation_scores_the_map(frames):
    # a real frame seen at another exposure (darker and offset, as auto-exposure does): the raw
    # PSNR counts the exposure as error, the compensated one does not
    a, _ = frames
    rng = np.random.default_rng(3)
    render = np.clip(a + rng.normal(0.0, 0.01, a.shape), 0.0, 1.0)  # the map: the frame with a little error
    ref = 0.7 * a + 0.05  # the frame at another exposure (inside [0, 1]: nothing clipped)
    alpha = np.ones(a.shape[:2])
    alpha[:, : a.shape[1] // 3] = 0.2  # a part the map does not cover: left out of the fit
    render[:, : a.shape[1] // 3] = 0.0
    covered = alpha >= 0.5
    x, y = render[covered].reshape(-1), ref[covered].reshape(-1)
    g_ref, b_ref = np.linalg.lstsq(np.stack([x, np.ones_like(x)], 1), y, rcond=None)[0]
    g, b = fit_exposure(render, ref, alpha)
    assert (g, b) == pytest.approx((g_ref, b_ref), rel=1e-9, abs=1e-12)
    assert g == pytest.approx(0.7, abs=0.02) and b == pytest.approx(0.05, abs=0.01)
    compensated = compensate_exposure(render, ref, alpha)
    np.testing.assert_allclose(compensated, np.clip(g_ref * render + b_ref, 0, 1), atol=1e-12)
    assert psnr(compensated[covered], ref[covered]) > psnr(render[covered], ref[covered]) + 8.0
    out = photometric_metrics([render], [ref], None, alphas=[alpha])
    assert out["psnr_compensated_db"] == pytest.approx(psnr(compensated, ref), abs=1e-9)
    assert out["psnr_compensated_db"] > out["psnr_db"] + 2.0 and out["ssim_compensated"] > out["ssim"]
    assert out["exposure_gain"] == pytest.approx(g)
    # a uniform render does not determine the fit: the identity
    assert fit_exposure(np.full_like(a, 0.5), ref) == (1.0, 0.0)


def _ssim_3dgs_torch(img, ref):
    """The 3DGS training code's SSIM, written out with torch conv2d: an 11x11 Gaussian window (sigma
    1.5) per channel, zero padding of 5, population statistics, mean over every pixel and channel."""
    import torch
    import torch.nn.functional as F

    x = torch.from_numpy(np.asarray(img, np.float64).transpose(2, 0, 1)[None])
    y = torch.from_numpy(np.asarray(ref, np.float64).transpose(2, 0, 1)[None])
    g = torch.exp(-((torch.arange(11, dtype=torch.float64) - 5) ** 2) / (2 * 1.5**2))
    g = g / g.sum()
    w = (g[:, None] @ g[None, :]).expand(3, 1, 11, 11).contiguous()

    def conv(t):
        return F.conv2d(t, w, padding=5, groups=3)

    mu_x, mu_y = conv(x), conv(y)
    sxx, syy, sxy = conv(x * x) - mu_x**2, conv(y * y) - mu_y**2, conv(x * y) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    return float((((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))).mean())


def test_peer_ssim_variants(frames):
    # 3DGS's zero-padded SSIM (MonoGS) against torch conv2d; MS-SSIM (SplaTAM's "SSIM") where the image
    # allows its five scales, n/a with the reason where it does not (crops: the full frames cost 6 s)
    a, b = (f[:200, :240] for f in frames)
    assert ssim_3dgs(b, a) == pytest.approx(_ssim_3dgs_torch(b, a), abs=1e-10)
    assert ssim_3dgs(b, a) != pytest.approx(ssim(b, a), abs=1e-4)  # the border counts: a different number
    assert ssim_3dgs(a, a) == pytest.approx(1.0) and ms_ssim(a, a) == pytest.approx(1.0, abs=1e-6)
    assert 0.0 < ms_ssim(b, a) < 1.0
    small = a[:120, :200]
    assert ms_ssim(small, small) is None
    out = photometric_metrics([small], [small])
    assert out["ms_ssim"] is None and "161 px" in out["ms_ssim_na_reason"]
    assert out["ssim_3dgs"] == pytest.approx(1.0)


def test_scores_at_the_tracked_exposure(frames):
    # the render at the (g, b) tracking estimated for the frame: no fit against the frame; n/a without
    a, b = (f[:120, :160] for f in frames)
    render = np.clip((a - 0.05) / 1.3, 0, 1)  # the map's colour; the frame saw it at g = 1.3, b = 0.05
    out = photometric_metrics([render, b], [a, b], tracked_exposures=[(1.3, 0.05), (1.0, 0.0)])
    assert out["psnr_tracked_exposure_db"] == pytest.approx(
        (psnr(np.clip(1.3 * render + 0.05, 0, 1), a) + float("inf")) / 2
    )
    out = photometric_metrics([render], [a], tracked_exposures=[(1.3, 0.05)])
    assert out["psnr_tracked_exposure_db"] > out["psnr_db"] + 5.0
    assert out["ssim_tracked_exposure"] == pytest.approx(ssim(np.clip(1.3 * render + 0.05, 0, 1), a))
    wrong = photometric_metrics([render], [a], tracked_exposures=[(1.0, 0.0)])
    assert wrong["psnr_tracked_exposure_db"] == pytest.approx(wrong["psnr_db"])
    none = photometric_metrics([render], [a])
    assert none["psnr_tracked_exposure_db"] is None and none["psnr_tracked_exposure_db_na_reason"]
    with pytest.raises(ValueError, match="one tracked exposure per render"):
        photometric_metrics([render, b], [a, b], tracked_exposures=[(1.0, 0.0)])


def test_the_camera_clips_after_the_exposure():
    # a map of a scene whose exposure changes holds colours above 1 (what a darker frame shows of a surface
    # a brighter one saw saturated): the frame at (g, b) is clip(g render + b), not g clip(render) + b
    a = np.random.default_rng(3).uniform(0.0, 1.0, (40, 50, 3))
    mapped = a / 0.8  # up to 1.25; the frame saw it at g = 0.8
    assert (mapped > 1.0).mean() > 0.01
    for device in (None, "cpu"):
        row = frame_scores(mapped, a, None, (0.8, 0.0), device, psnr_only=True)
        assert row["psnr_tracked"] > 100.0  # the frame itself
        assert row["psnr_compensated"] > 100.0
        assert row["psnr"] == pytest.approx(psnr(np.clip(mapped, 0, 1), a), abs=1e-10)  # raw: the render clipped
        assert psnr(0.8 * np.clip(mapped, 0, 1), a) < 60.0  # clipping first would have lost the bright pixels


def test_lpips_at_the_tracked_exposure_and_means_of_frame_rows(frames, tmp_path):
    # LPIPS of the render as tracking exposed it; mean_scores of rows from different passes (SplaTAM's
    # protocol joins held-out frames and keyframes) is the mean over all of them
    pytest.importorskip("torch")
    model = LPIPS(*_synthetic_lpips_weights(tmp_path))
    a, b = (f[:120, :160] for f in frames)
    render = np.clip((a - 0.05) / 1.3, 0, 1)
    rows: list = []
    out = photometric_metrics([render], [a], model, tracked_exposures=[(1.3, 0.05)], frame_scores_out=rows)
    at_tracked = np.clip(1.3 * render + 0.05, 0, 1)
    assert out["lpips_tracked_exposure"] == pytest.approx(model(at_tracked, a), rel=1e-6)
    assert out["lpips"] == pytest.approx(model(render, a), rel=1e-6)
    assert out["lpips_tracked_exposure"] < out["lpips"]
    other = frame_scores(b, a, None, (1.0, 0.0), None, model)
    joined = mean_scores([*rows, other])
    assert joined["n_frames"] == 2
    for name, key in (("psnr_tracked_exposure_db", "psnr_tracked"), ("lpips_tracked_exposure", "lpips_tracked")):
        assert joined[name] == pytest.approx((rows[0][key] + other[key]) / 2)
    assert joined["psnr_compensated_db"] == pytest.approx((rows[0]["psnr_compensated"] + other["psnr_compensated"]) / 2)
    # without a model or tracked exposures: n/a with the reason
    bare = mean_scores([frame_scores(b, a)], "no weights here")
    assert bare["lpips"] is None and bare["lpips_tracked_exposure_na_reason"] == "no weights here"
    assert bare["psnr_tracked_exposure_db"] is None and bare["psnr_tracked_exposure_db_na_reason"]
    untracked = mean_scores([frame_scores(b, a, lpips_model=model)])
    assert untracked["lpips"] is not None and untracked["lpips_tracked_exposure"] is None
    assert untracked["lpips_tracked_exposure_na_reason"] == "no tracked exposures given"


def test_the_metrics_on_a_torch_device_are_the_hosts(frames):
    # A GPU run computes PSNR and the SSIMs with torch on its GPU (float64, the same sums in another
    # order); torch's CPU runs that code here, against the NumPy / SciPy code of the host path.
    a, b = (f[:200, :320] for f in frames)  # MS-SSIM's five scales need 161 px: it runs too
    rng = np.random.default_rng(1)
    noisy = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)
    for x, y in [(b, a), (noisy, a), (a[:37, 5:300, 1], b[:37, 5:300, 1]), (a[::3, ::2], noisy[::3, ::2])]:
        assert ssim(x, y, "cpu") == pytest.approx(ssim(x, y), abs=1e-12)
        assert ssim_3dgs(x, y, "cpu") == pytest.approx(ssim_3dgs(x, y), abs=1e-12)
        assert psnr(x, y, "cpu") == pytest.approx(psnr(x, y), abs=1e-10)
    assert psnr(a, a, "cpu") == float("inf")
    alpha = np.ones(a.shape[:2])
    partial = np.where(np.arange(a.shape[1]) < 200, 0.9, 0.1) * np.ones((a.shape[0], 1))  # 200 of 320 columns
    # float32 renders, as a run gives them (copied to the device as they are, cast there)
    dark, bright = (np.clip(k * x, 0, 1).astype(np.float32) for k, x in ((0.7, b), (1.2, noisy)))
    for alphas, tracked in [([alpha, alpha], None), ([partial, alpha], [(1.3, 0.02), (0.9, -0.01)])]:
        host = photometric_metrics([dark, bright], [a, a], alphas=alphas, tracked_exposures=tracked)
        on_torch = photometric_metrics([dark, bright], [a, a], alphas=alphas, tracked_exposures=tracked, device="cpu")
        assert host.keys() == on_torch.keys()
        for key, value in host.items():
            if isinstance(value, float):
                assert on_torch[key] == pytest.approx(value, abs=1e-10), key
        assert abs(host["exposure_gain"] - 1.0) > 0.05  # the fit is exercised
    row = frame_scores(dark, a, partial, (1.3, 0.02), psnr_only=True)
    assert row.keys() == {"gain", "psnr", "psnr_compensated", "psnr_tracked"}  # the keyframe fit's scores
    on_torch = frame_scores(dark, a, partial, (1.3, 0.02), "cpu", psnr_only=True)
    assert [row[k] for k in row] == pytest.approx([on_torch[k] for k in row], abs=1e-10)
    raw, compensated = row["psnr"], row["psnr_compensated"]
    assert row["psnr_tracked"] == pytest.approx(psnr(np.clip(1.3 * dark.astype(np.float64) + 0.02, 0, 1), a))
    g, bias = fit_exposure(dark, a, partial)
    assert raw == pytest.approx(psnr(dark, a), abs=1e-12)
    assert compensated == pytest.approx(psnr(np.clip(g * dark.astype(np.float64) + bias, 0, 1), a), abs=1e-12)
    assert compensated > raw + 1.0
    assert metric_device("cpu") is None  # a CPU run keeps the host code


def test_alexnet_weights_found_in_torch_hub_cache(tmp_path, monkeypatch):
    """Where the lpips package (through torchvision) keeps AlexNet: used when no path is configured."""
    torch = pytest.importorskip("torch")
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    assert cached_alexnet_path() is None
    path = tmp_path / "hub" / "checkpoints" / "alexnet-owt-7be5be79.pth"
    path.parent.mkdir(parents=True)
    path.write_bytes(b"")
    assert cached_alexnet_path() == path
