"""Dense float64 NumPy reference of the rasterizer: every Gaussian evaluated at every pixel, composited
in global depth order with the renderer's conventions (see rgs_warp.kernels.rasterize): pixel centres
at integer (u, v), EWA covariance with a 0.3 px dilation and the Jacobian's tangent clamp, SH colour
+ 0.5 clamped at 0, alpha = min(0.99, o G) skipped below 1/255, stop before T < 1e-4.

No tiles, no radii, no sorting by tile: if the renderer's culling ever dropped a visible
contribution, the comparison would show it.

``decisions`` freezes the discrete choices (depth order, which splats contribute where, where alpha
is clamped) of a nominal evaluation, so that finite differences measure the derivative of the
piece of the function the analytic gradient differentiates, not jumps across the 1/255 threshold.
"""

from __future__ import annotations

import numpy as np

from rgs_warp.geometry import invert_pose, quat_to_matrix, se3_exp

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_basis(d: np.ndarray, num_sh: int) -> np.ndarray:
    """(N, num_sh) real SH basis (3DGS order and signs) at unit directions d (N, 3)."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    xx, yy, zz = x * x, y * y, z * z
    cols = [np.full_like(x, C0), -C1 * y, C1 * z, -C1 * x]
    cols += [
        C2[0] * x * y,
        C2[1] * y * z,
        C2[2] * (2 * zz - xx - yy),
        C2[3] * x * z,
        C2[4] * (xx - yy),
    ]
    cols += [
        C3[0] * y * (3 * xx - yy),
        C3[1] * x * y * z,
        C3[2] * y * (4 * zz - xx - yy),
        C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
        C3[4] * x * (4 * zz - xx - yy),
        C3[5] * z * (xx - yy),
        C3[6] * x * (xx - 3 * yy),
    ]
    return np.stack(cols[:num_sh], axis=1)


def project_reference(scene: dict, camera, T_CW: np.ndarray, near: float = 0.01, margin: float = 0.3):
    """Screen-space Gaussians: mean2d (N,2), conic (N,2,2), opacity (N,), colour (N,3), depth (N,),
    valid (N,) (in front of the near plane, positive-definite, opacity >= 1/255)."""
    means = np.asarray(scene["means"], np.float64)
    W, t = T_CW[:3, :3], T_CW[:3, 3]
    X = means @ W.T + t
    z = X[:, 2]
    zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
    R = quat_to_matrix(scene["quats"])
    S = np.exp(np.asarray(scene["log_scales"], np.float64))
    M = R * S[:, None, :]
    cov_c = W @ (M @ M.transpose(0, 2, 1)) @ W.T
    w_, h_ = camera.width, camera.height
    u = np.clip(
        X[:, 0] / zs, (-0.5 - margin * w_ - camera.cx) / camera.fx, (w_ - 0.5 + margin * w_ - camera.cx) / camera.fx
    )
    v = np.clip(
        X[:, 1] / zs, (-0.5 - margin * h_ - camera.cy) / camera.fy, (h_ - 0.5 + margin * h_ - camera.cy) / camera.fy
    )
    J = np.zeros((len(z), 2, 3))
    J[:, 0, 0] = camera.fx / zs
    J[:, 0, 2] = -camera.fx * u / zs
    J[:, 1, 1] = camera.fy / zs
    J[:, 1, 2] = -camera.fy * v / zs
    cov2d = J @ cov_c @ J.transpose(0, 2, 1) + 0.3 * np.eye(2)
    det = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] ** 2
    opacity = 1.0 / (1.0 + np.exp(-np.asarray(scene["opacity_logits"], np.float64)))
    valid = (z >= near) & (det > 0) & (opacity >= ALPHA_MIN)
    conic = np.linalg.inv(np.where(valid[:, None, None], cov2d, np.eye(2)))
    mean2d = np.stack([camera.fx * X[:, 0] / zs + camera.cx, camera.fy * X[:, 1] / zs + camera.cy], axis=1)
    centre = -W.T @ t
    d = means - centre
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sh = np.asarray(scene["sh"], np.float64)
    color = np.maximum(np.einsum("nk,nkc->nc", sh_basis(d, sh.shape[1]), sh) + 0.5, 0.0)
    return mean2d, conic, opacity, color, z, valid


def render_reference(scene: dict, camera, T_WC, background=(0.0, 0.0, 0.0), xi=None, decisions=None, near=0.01):
    """(color (H,W,3), depth (H,W), alpha (H,W), decisions) in float64; ``xi`` perturbs the pose as
    T_CW <- Exp(xi) T_CW."""
    T_CW = invert_pose(np.asarray(T_WC, np.float64))
    if xi is not None:
        T_CW = se3_exp(np.asarray(xi, np.float64)) @ T_CW
    mean2d, conic, opacity, color, z, valid = project_reference(scene, camera, T_CW, near)
    H, W = camera.height, camera.width
    vv, uu = np.mgrid[0:H, 0:W]
    pix = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(np.float64)
    P = pix.shape[0]
    order = np.argsort(z, kind="stable") if decisions is None else decisions["order"]
    T = np.ones(P)
    C = np.zeros((P, 3))
    D = np.zeros(P)
    done = np.zeros(P, bool)
    record = {"order": order, "contrib": [], "clamped": []}
    for step, i in enumerate(order):
        if decisions is None and not valid[i]:
            record["contrib"].append(np.zeros(P, bool))
            record["clamped"].append(np.zeros(P, bool))
            continue
        d = mean2d[i] - pix
        Q = conic[i]
        power = -0.5 * (Q[0, 0] * d[:, 0] ** 2 + Q[1, 1] * d[:, 1] ** 2) - Q[0, 1] * d[:, 0] * d[:, 1]
        raw = opacity[i] * np.exp(power)
        if decisions is None:
            clamped = raw > ALPHA_MAX
            a = np.minimum(raw, ALPHA_MAX)
            active = ~done & (a >= ALPHA_MIN)
            stop = active & (T * (1.0 - a) < T_MIN)
            done |= stop
            contrib = active & ~stop
            record["contrib"].append(contrib)
            record["clamped"].append(clamped)
        else:
            contrib = decisions["contrib"][step]
            clamped = decisions["clamped"][step]
            a = np.where(clamped, ALPHA_MAX, raw)
        w = np.where(contrib, a * T, 0.0)
        C += w[:, None] * color[i]
        D += w * z[i]
        T = np.where(contrib, T * (1.0 - a), T)
    C += T[:, None] * np.asarray(background, np.float64)
    return C.reshape(H, W, 3), D.reshape(H, W), (1.0 - T).reshape(H, W), record


def random_scene(rng: np.random.Generator, n: int, T_WC: np.ndarray, sh_degree: int = 2) -> dict:
    """n Gaussians spread over and beyond the view frustum of a ~64x48, f = 60 camera at T_WC, with
    the awkward cases mixed in: behind the camera, straddling the near plane, huge, tiny, nearly
    transparent, centred outside the image but overlapping it, an opaque stack that saturates."""
    z = rng.uniform(0.6, 4.0, n)
    x = rng.uniform(-0.75, 0.75, n) * z
    y = rng.uniform(-0.6, 0.6, n) * z
    log_s = rng.uniform(np.log(0.005), np.log(0.06), (n, 3))
    logit = rng.uniform(-1.5, 3.0, n)
    k = max(n // 10, 1)
    z[:k] = -rng.uniform(0.2, 2.0, k)  # behind
    z[k : k + 2] = rng.uniform(-0.05, 0.05, 2)  # at the near plane
    log_s[2 * k : 3 * k] = np.log(rng.uniform(0.5, 1.5, (k, 3)))  # huge
    logit[2 * k : 3 * k] = rng.uniform(-4.0, -2.0, k)
    log_s[3 * k : 4 * k] = np.log(rng.uniform(1e-4, 1e-3, (k, 3)))  # tiny
    logit[4 * k : 5 * k] = rng.uniform(-6.5, -5.0, k)  # nearly transparent
    x[5 * k : 6 * k] = rng.choice([-1.0, 1.0], k) * rng.uniform(0.55, 0.65, k) * z[5 * k : 6 * k]  # border
    m = min(4, n - 6 * k)  # an opaque stack: alpha clamped at 0.99, pixels saturate (T < 1e-4)
    x[6 * k : 6 * k + m] = rng.uniform(-0.05, 0.05, m)
    y[6 * k : 6 * k + m] = rng.uniform(-0.05, 0.05, m)
    z[6 * k : 6 * k + m] = 1.0 + 0.2 * np.arange(m)
    log_s[6 * k : 6 * k + m] = np.log(0.12)
    logit[6 * k : 6 * k + m] = 3.0  # opacity 0.953: T passes 1e-4 between splats, never at it
    logit[6 * k] = 7.0  # clamped
    X_C = np.stack([x, y, z], axis=1)
    means = X_C @ T_WC[:3, :3].T + T_WC[:3, 3]
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    num_sh = (sh_degree + 1) ** 2
    sh = rng.normal(0.0, 0.25, (n, num_sh, 3))
    sh[:, 0] += rng.uniform(-1.0, 1.0, (n, 3))
    return {"means": means, "quats": quats, "log_scales": log_s, "opacity_logits": logit, "sh": sh}
