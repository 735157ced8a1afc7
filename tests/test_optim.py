"""Map Adam against a NumPy Adam with global-norm clipping; moment bookkeeping across growth and removal."""

import numpy as np
import pytest
import warp as wp

from rgs_warp.optim import MapAdam, MapLearningRates, cosine_factor
from rgs_warp.render import GaussianGrads
from rgs_warp.types import GaussianMap


def _map(rng, n, device, capacity=None):
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return GaussianMap.from_numpy(
        rng.standard_normal((n, 3)),
        q,
        rng.standard_normal((n, 3)) - 4,
        rng.standard_normal(n),
        rng.standard_normal((n, 9, 3)) * 0.1,
        device=device,
        capacity=capacity,
    )


def _grads(rng, gmap, scale):
    g = GaussianGrads.of_map_grads(GaussianMap(gmap.capacity, gmap.sh_degree, gmap.device, requires_grad=True))
    values = {}
    for name in GaussianMap.PARAMETERS:
        arr = getattr(g, name)
        v = (scale * rng.standard_normal(arr.numpy().shape)).astype(np.float32)
        values[name] = v
        wp.copy(arr, wp.array(v, dtype=arr.dtype, device=gmap.device))
    return g, values


def _numpy_adam(params, grads_seq, lrs, n, max_norm, b1=0.9, b2=0.999, eps=1e-15, factors=None):
    m = {k: np.zeros_like(v[:n], dtype=np.float64) for k, v in params.items()}
    v2 = {k: np.zeros_like(v[:n], dtype=np.float64) for k, v in params.items()}
    p = {k: v[:n].astype(np.float64) for k, v in params.items()}
    for t, grads in enumerate(grads_seq, 1):
        norm = np.sqrt(sum((grads[k][:n].astype(np.float64) ** 2).sum() for k in p))
        clip = min(1.0, max_norm / (norm + 1e-6))
        for k in p:
            g = grads[k][:n] * clip
            m[k] = b1 * m[k] + (1 - b1) * g
            v2[k] = b2 * v2[k] + (1 - b2) * g * g
            lr = lrs.of(k) * (factors[t - 1] if factors else 1.0)
            if k == "sh":  # rows of coefficients: the first (DC) at lrs.sh, the others at lrs.sh_rest
                lr = np.full(p[k].shape, lr)
                lr[:, 1:] *= lrs.rest(k) / lrs.of(k)
            p[k] -= lr * (m[k] / (1 - b1**t)) / (np.sqrt(v2[k] / (1 - b2**t)) + eps)
    return p


# 600 Gaussians: 54 blocks of the norms; 12000: the 1024 blocks' threads stride over the entries
@pytest.mark.parametrize("sh_rest, n", [(None, 40), (2.5e-4, 40), (None, 600), (None, 12000)])
@pytest.mark.parametrize("grad_scale", [1e-3, 10.0])  # below and far above the clipping norm
def test_adam_matches_numpy(device, grad_scale, sh_rest, n):
    rng = np.random.default_rng(0)
    gmap = _map(rng, n, device, capacity=n + 24)
    start = {k: v.copy() for k, v in gmap.to_numpy().items()}
    lrs = MapLearningRates(means=1e-3, rotations=2e-3, log_scales=3e-3, opacity_logits=4e-3, sh=5e-3, sh_rest=sh_rest)
    opt = MapAdam(gmap, lrs, max_grad_norm=1.0)
    factors = [cosine_factor(step, 3, final=0.1) for step in range(3)]
    opt.schedule(factors)  # each step reads its row through the device counter
    counter = wp.zeros(1, dtype=wp.int32, device=device)
    seq = []
    for step in range(3):
        g, values = _grads(rng, gmap, grad_scale)
        counter.assign(np.array([step], dtype=np.int32))
        opt.step(g, counter)
        seq.append(values)
    expected = _numpy_adam(start, seq, lrs, n, 1.0, factors=factors)
    got = gmap.to_numpy()
    for k in GaussianMap.PARAMETERS:
        np.testing.assert_allclose(got[k], expected[k], rtol=1e-5, atol=1e-6, err_msg=k)
    norm = np.sqrt(sum((seq[-1][k][:n].astype(np.float64) ** 2).sum() for k in GaussianMap.PARAMETERS))
    assert opt.clip.numpy()[1] == pytest.approx(norm, rel=1e-4)


def test_moments_follow_growth_and_removal(device):
    # the moments are columns of the map: they grow with it, start at zero for appended rows and
    # compact with the map's removal, in the rows' order
    rng = np.random.default_rng(1)
    gmap = _map(rng, 6, device, capacity=8)
    opt = MapAdam(gmap, MapLearningRates())
    g, _ = _grads(rng, gmap, 0.1)
    opt.schedule([1.0])
    opt.step(g, wp.zeros(1, dtype=wp.int32, device=device))
    m_means, v_sh = opt.moments("means")[0], opt.moments("sh")[1]
    m_before = m_means.numpy().reshape(-1, 3)[:6].copy()
    v_sh_before = v_sh.numpy().reshape(-1, 27)[:6].copy()
    assert np.abs(m_before).min() > 0 and np.abs(v_sh_before).min() > 0
    extra = _map(rng, 5, device).to_numpy()
    gmap.append(extra["means"], extra["rotations"], extra["log_scales"], extra["opacity_logits"], extra["sh"])
    m_means, v_sh = opt.moments("means")[0], opt.moments("sh")[1]
    assert gmap.capacity == 16 and v_sh.shape[0] == 16 * 27
    np.testing.assert_array_equal(m_means.numpy().reshape(-1, 3)[:6], m_before)
    assert not m_means.numpy().reshape(-1, 3)[6:11].any() and not v_sh.numpy().reshape(-1, 27)[6:11].any()
    mask = np.zeros(11, bool)
    mask[[1, 4]] = True
    gmap.remove(mask)
    np.testing.assert_array_equal(opt.moments("means")[0].numpy().reshape(-1, 3)[:4], m_before[[0, 2, 3, 5]])
    np.testing.assert_array_equal(opt.moments("sh")[1].numpy().reshape(-1, 27)[:4], v_sh_before[[0, 2, 3, 5]])
    assert opt.moments("opacity_logits")[0].numpy()[:4].any()
    opt.reset_field("opacity_logits")
    assert not opt.moments("opacity_logits")[0].numpy().any() and not opt.moments("opacity_logits")[1].numpy().any()
    assert opt.moments("sh")[1].numpy()[:27].any()  # other fields untouched
    with pytest.raises(ValueError, match="unknown map parameter"):
        opt.reset_field("colour")


def test_cosine_factor():
    assert cosine_factor(0, 10) == 1.0 and cosine_factor(9, 10, final=0.1) == pytest.approx(0.1)
    assert cosine_factor(0, 1) == 1.0 and 0.1 < cosine_factor(5, 10, final=0.1) < 1.0
