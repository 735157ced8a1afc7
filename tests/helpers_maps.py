"""Gaussian maps built from ground truth, for the tracking tests and experiments.

``map_from_rgbd`` places one flat, nearly opaque Gaussian disc on every ``stride``-th pixel of each
given RGB-D frame at its ground-truth pose: the map the tracker would see if mapping were perfect,
so tracking errors measured against it are the tracker's own.
"""

from __future__ import annotations

import numpy as np

from rgs_warp.types import Camera, GaussianMap

SH_C0 = 0.28209479177387814  # real SH band-0 constant: colour = SH_C0 * dc + 0.5 (3DGS)


def backproject(depth_m: np.ndarray, camera: Camera) -> np.ndarray:
    """(H, W, 3) camera-frame points of every pixel centre (OpenCV; pixel (u, v) at (u, v))."""
    v, u = np.mgrid[0 : depth_m.shape[0], 0 : depth_m.shape[1]].astype(np.float64)
    z = depth_m.astype(np.float64)
    return np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], axis=-1)


def _quat_z_to(n: np.ndarray) -> np.ndarray:
    """Unit quaternions (x, y, z, w) rotating +z onto the unit vectors n (N, 3): axis e_z x n, half-angle
    form q = (e_z x n, 1 + e_z . n) normalised; n = -e_z (no unique axis) takes a half turn about x."""
    q = np.stack([-n[:, 1], n[:, 0], np.zeros(len(n)), 1.0 + n[:, 2]], axis=1)
    flip = q[:, 3] < 1e-6
    q[flip] = [1.0, 0.0, 0.0, 0.0]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def map_from_rgbd(
    frames: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    camera: Camera,
    stride: int = 1,
    sigma_per_spacing: float = 0.6,
    thickness: float = 0.1,
    opacity: float = 0.98,
    max_rel_jump: float = 0.02,
    max_widening: float = 3.0,
    device=None,
) -> GaussianMap:
    """Map from ``(rgb HxWx3, depth HxW metres, T_WC 4x4)`` frames at ``camera``'s resolution.

    Per kept pixel: mean = back-projected pixel centre; rotation takes +z to the depth normal (cross
    product of the neighbours' back-projections); tangential standard deviation =
    ``sigma_per_spacing`` x the grid spacing on the surface (stride x depth / f, widened by
    1 / cos(incidence), capped at 3x), axial = ``thickness`` x tangential (a disc); SH DC from the
    colour, higher bands 0; opacity ``opacity``.  Pixels on a depth edge (second difference of depth along u or v
    above ``max_rel_jump`` of the depth) are skipped: their normal is meaningless.
    """
    means, quats, log_scales, colours = [], [], [], []
    f = 0.5 * (camera.fx + camera.fy)
    for rgb, depth, T_WC in frames:
        P = backproject(depth, camera)
        du = P[1:-1, 2:] - P[1:-1, :-2]
        dv = P[2:, 1:-1] - P[:-2, 1:-1]
        n = np.cross(du, dv)
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
        centre = P[1:-1, 1:-1]
        n = np.where(np.sum(n * centre, axis=-1, keepdims=True) > 0, -n, n)  # face the camera
        d = depth[1:-1, 1:-1]
        # depth edge: the second difference along either axis (0 on a plane up to perspective) is large
        d_uu = depth[1:-1, 2:] + depth[1:-1, :-2] - 2.0 * d
        d_vv = depth[2:, 1:-1] + depth[:-2, 1:-1] - 2.0 * d
        neighbours = (depth[1:-1, 2:], depth[1:-1, :-2], depth[2:, 1:-1], depth[:-2, 1:-1])
        valid = (d > 0) & np.all([nb > 0 for nb in neighbours], axis=0)
        ok = valid & (np.abs(d_uu) <= max_rel_jump * d) & (np.abs(d_vv) <= max_rel_jump * d)
        grid = np.zeros_like(ok)
        grid[::stride, ::stride] = True
        ok &= grid
        cos_inc = np.abs(np.sum(n * centre, axis=-1)) / np.maximum(np.linalg.norm(centre, axis=-1), 1e-12)
        sigma = sigma_per_spacing * stride * d / f / np.maximum(cos_inc, 1.0 / max_widening)
        R, t = T_WC[:3, :3], T_WC[:3, 3]
        means.append(centre[ok] @ R.T + t)
        quats.append(_quat_z_to(n[ok] @ R.T))
        s = sigma[ok]
        log_scales.append(np.log(np.stack([s, s, thickness * s], axis=1)))
        colours.append(rgb[1:-1, 1:-1][ok])
    colour = np.concatenate(colours).astype(np.float64)
    sh = np.zeros((len(colour), 9, 3), dtype=np.float32)
    sh[:, 0] = (colour - 0.5) / SH_C0
    count = len(colour)
    return GaussianMap.from_numpy(
        np.concatenate(means).astype(np.float32),
        np.concatenate(quats).astype(np.float32),
        np.concatenate(log_scales).astype(np.float32),
        np.full(count, np.log(opacity / (1.0 - opacity)), dtype=np.float32),
        sh,
        device=device,
    )


def refine_colours(gmap: GaussianMap, frames, camera: Camera, iters: int = 30, lr: float = 0.05, renderer=None):
    """Fit the SH DC colours to the frames (``(rgb, T_WC)`` pairs) by Adam on the L2 photometric loss.

    Front-to-back compositing lets each nearly opaque disc cover part of its neighbours' pixels, so a
    map whose colours are the raw pixel colours renders its own frames displaced by a fraction of a
    pixel (nearer discs win on slanted surfaces); refitting the colours, as mapping would, removes
    that bias from the tests' reference map.
    """
    import warp as wp

    from rgs_warp.render import Renderer

    renderer = renderer or Renderer(gmap.device)
    n = len(gmap)
    sh = gmap.sh.numpy()[:n].copy()
    m, v = np.zeros_like(sh[:, 0]), np.zeros_like(sh[:, 0])
    targets = [wp.array(rgb, dtype=wp.vec3, device=gmap.device) for rgb, _ in frames]
    for k in range(iters):
        grad = np.zeros_like(sh[:, 0])
        for (_, T_WC), target in zip(frames, targets, strict=True):
            res = renderer.forward(gmap, camera, T_WC)
            d_color = wp.array(2.0 * (res.color.numpy() - target.numpy()), dtype=wp.vec3, device=gmap.device)
            grads, _ = renderer.backward(d_color)
            grad += grads.sh.numpy()[:n, 0]
        m = 0.9 * m + 0.1 * grad
        v = 0.999 * v + 0.001 * grad**2
        sh[:, 0] -= lr * (m / (1 - 0.9 ** (k + 1))) / (np.sqrt(v / (1 - 0.999 ** (k + 1))) + 1e-8)
        wp.copy(gmap.sh, wp.array(sh, dtype=wp.vec3, device=gmap.device), count=n * sh.shape[1])
    return gmap


# The tracking tests' room: room0 at 96x54 (fx = 48), a map of discs on the ground-truth depth of frames
# MAP_FRAMES (seen 1.5x wider, so that the frames' borders are covered), the frames observed as the map's
# renders at the true poses: the tests measure the tracker, not how faithfully a 96-pixel map reproduces
# the ray-traced images (experiments/bench/tracking_gt_map.py does that).
ROOM_SIZE = (96, 54)
MAP_FRAMES = (0, 4, 8)


def room_scene(device) -> dict:
    """{"camera", "poses", "map", "observe", "view"}: ``view(T_WC, camera=...)`` is the map's (colour,
    depth per opacity where the opacity passes 0.5) at a pose, ``observe(i, camera=...)`` at frame i's."""
    from rgs_warp.datasets.synthetic import SequenceRenderer, SyntheticConfig
    from rgs_warp.datasets.synthetic.textures import linear_to_srgb
    from rgs_warp.render import Renderer

    cfg = SyntheticConfig(scene="room0", width=ROOM_SIZE[0], height=ROOM_SIZE[1], n_frames=100)
    seq = SequenceRenderer(cfg, device=device)
    cam = cfg.camera
    wide = Camera(cam.fx, cam.fy, (1.5 * cam.width - 1) / 2, (1.5 * cam.height - 1) / 2, 144, 81)
    frames = []
    for i in MAP_FRAMES:
        rgb, depth = seq.renderer.render(wide, seq.poses[i : i + 1], seq.poses[i], n_ss=2, seed=i)
        frames.append((np.clip(linear_to_srgb(rgb), 0, 1).astype(np.float32), depth, seq.poses[i]))
    gmap = map_from_rgbd(frames, wide, stride=2, sigma_per_spacing=0.5, device=device)
    renderer = Renderer(device)

    def view(T_WC: np.ndarray, camera=cam):
        res = renderer.forward(gmap, camera, T_WC)
        alpha = res.alpha.numpy()
        depth = np.where(alpha > 0.5, res.depth.numpy() / np.maximum(alpha, 1e-6), 0.0).astype(np.float32)
        return res.color.numpy().copy(), depth

    def observe(i: int, camera=cam):
        return view(seq.poses[i], camera)

    return {"camera": cam, "poses": seq.poses, "map": gmap, "observe": observe, "view": view}


def perturbed(T_WC: np.ndarray, t_m: float, r_deg: float, seed: int) -> np.ndarray:
    """``T_WC`` moved by a twist of ``t_m`` metres and ``r_deg`` degrees in random directions (left, on
    the world-to-camera pose)."""
    from rgs_warp.geometry import invert_pose, se3_exp

    rng = np.random.default_rng(seed)
    a, b = rng.normal(size=3), rng.normal(size=3)
    xi = np.concatenate([a / np.linalg.norm(a) * t_m, b / np.linalg.norm(b) * np.radians(r_deg)])
    return invert_pose(se3_exp(xi) @ invert_pose(T_WC))


def flat_map(n: int, log_scale: float, device) -> GaussianMap:
    """n small, opaque Gaussians at the origin."""
    quats = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    return GaussianMap.from_numpy(
        np.zeros((n, 3)), quats, np.full((n, 3), log_scale), np.full(n, 2.0), np.zeros((n, 9, 3)), device
    )
