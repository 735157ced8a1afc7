"""Warp ray caster of the synthetic scenes: light baking, supersampled colour, pixel-centre z-depth.

Lighting is diffuse only, so it does not depend on the viewer: per-light soft-shadow visibility and
ambient occlusion are baked once per mesh corner (``_bake_light``) and interpolated across triangles;
the Lambert term itself is evaluated per sample.  Textures are sampled trilinearly from a mip-mapped
atlas, the level chosen from the sample's footprint, which keeps distant textures from aliasing and
makes the same surface look the same from different distances (what the photometric tests check).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from rgs_warp.datasets.synthetic.textures import CLAMP, MIRROR, build_atlas

wp.set_module_options({"enable_backward": False})

MAX_LIGHTS = 3
MAX_LEVELS = 12
_RAY_MAX_M = wp.constant(1.0e3)
_SHADOW_BIAS_M = wp.constant(2.0e-3)
_CLAMP = wp.constant(CLAMP)
_MIRROR = wp.constant(MIRROR)


@wp.struct
class _Scene:
    mesh: wp.uint64
    corner_uv: wp.array(dtype=wp.vec2)
    corner_normal: wp.array(dtype=wp.vec3)
    corner_light: wp.array(dtype=wp.vec4)  # visibility of lights 0..2, ambient occlusion
    face_material: wp.array(dtype=wp.int32)
    face_uv_per_m: wp.array(dtype=wp.float32)
    material_texture: wp.array(dtype=wp.int32)
    material_tint: wp.array(dtype=wp.vec3)
    material_address: wp.array(dtype=wp.int32)
    material_emission: wp.array(dtype=wp.float32)
    atlas: wp.array(dtype=wp.vec3)
    texture_level: wp.array2d(dtype=wp.vec3i)  # (offset, width, height) per texture and mip level
    texture_n_levels: wp.array(dtype=wp.int32)
    light_pos: wp.array(dtype=wp.vec3)
    light_colour: wp.array(dtype=wp.vec3)
    light_radius: wp.array(dtype=wp.float32)
    light_facing: wp.array(dtype=wp.vec3)  # unit axis of a one-sided (Lambertian) emitter; zero: omni
    n_lights: int
    ambient: wp.vec3


@wp.func
def _bary(a0: wp.vec3, a1: wp.vec3, a2: wp.vec3, u: float, v: float):
    # wp.mesh_query_ray's (u, v) weight corners 0 and 1; corner 2 gets the rest
    return a0 * u + a1 * v + a2 * (1.0 - u - v)


@wp.func
def _address(i: int, n: int, mode: int):
    if mode == _CLAMP:
        return wp.clamp(i, 0, n - 1)
    if mode == _MIRROR:
        p = ((i % (2 * n)) + 2 * n) % (2 * n)
        if p >= n:
            p = 2 * n - 1 - p
        return p
    return ((i % n) + n) % n


@wp.func
def _bilinear(atlas: wp.array(dtype=wp.vec3), level: wp.vec3i, uv: wp.vec2, mode: int):
    w = level[1]
    h = level[2]
    x = uv[0] * float(w) - 0.5
    y = uv[1] * float(h) - 0.5
    x0f = wp.floor(x)
    y0f = wp.floor(y)
    fx = x - x0f
    fy = y - y0f
    x0 = int(x0f)
    y0 = int(y0f)
    xa = _address(x0, w, mode)
    xb = _address(x0 + 1, w, mode)
    ya = _address(y0, h, mode)
    yb = _address(y0 + 1, h, mode)
    o = level[0]
    top = atlas[o + ya * w + xa] * (1.0 - fx) + atlas[o + ya * w + xb] * fx
    bottom = atlas[o + yb * w + xa] * (1.0 - fx) + atlas[o + yb * w + xb] * fx
    return top * (1.0 - fy) + bottom * fy


@wp.func
def _shade(scene: _Scene, face: int, bu: float, bv: float, p: wp.vec3, view_dir: wp.vec3, footprint_m: float):
    """Linear-light radiance of surface point ``p`` on ``face`` seen along ``view_dir``; ``footprint_m``
    is the sample's width on a fronto-parallel surface (it picks the mip level)."""
    c = 3 * face
    n = wp.normalize(_bary(scene.corner_normal[c], scene.corner_normal[c + 1], scene.corner_normal[c + 2], bu, bv))
    if wp.dot(n, view_dir) > 0.0:
        n = -n
    uv0 = scene.corner_uv[c]
    uv1 = scene.corner_uv[c + 1]
    uv2 = scene.corner_uv[c + 2]
    uv = uv0 * bu + uv1 * bv + uv2 * (1.0 - bu - bv)
    lit = scene.corner_light[c] * bu + scene.corner_light[c + 1] * bv + scene.corner_light[c + 2] * (1.0 - bu - bv)

    m = scene.face_material[face]
    tex = scene.material_texture[m]
    mode = scene.material_address[m]
    base = scene.texture_level[tex, 0]
    # a grazing view stretches the footprint along one axis; the square root splits the difference
    # between blurring across and aliasing along it
    cos_view = wp.max(wp.abs(wp.dot(n, view_dir)), 0.1)
    texels = footprint_m / wp.sqrt(cos_view) * scene.face_uv_per_m[face] * wp.sqrt(float(base[1] * base[2]))
    lod = wp.clamp(wp.log2(wp.max(texels, 1.0)), 0.0, float(scene.texture_n_levels[tex] - 1))
    l0 = int(wp.floor(lod))
    l1 = wp.min(l0 + 1, scene.texture_n_levels[tex] - 1)
    t = lod - float(l0)
    a = _bilinear(scene.atlas, scene.texture_level[tex, l0], uv, mode)
    b = _bilinear(scene.atlas, scene.texture_level[tex, l1], uv, mode)
    albedo = wp.cw_mul(a * (1.0 - t) + b * t, scene.material_tint[m])

    irradiance = scene.ambient * lit[3]
    for k in range(scene.n_lights):
        d = scene.light_pos[k] - p
        dist2 = wp.dot(d, d)
        ld = d / wp.sqrt(dist2)
        cos_surface = wp.max(wp.dot(n, ld), 0.0)
        facing = scene.light_facing[k]
        cos_emit = wp.where(wp.length_sq(facing) > 0.0, wp.max(-wp.dot(ld, facing), 0.0), 1.0)
        r = scene.light_radius[k]
        irradiance += scene.light_colour[k] * (lit[k] * cos_surface * cos_emit / (dist2 + r * r))
    return wp.cw_mul(albedo, irradiance) + albedo * scene.material_emission[m]


@wp.func
def _tangent_frame(n: wp.vec3):
    # branchless orthonormal basis (Duff et al. 2017), so baking is a pure function of (p, n)
    s = wp.where(n[2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (s + n[2])
    b = n[0] * n[1] * a
    t = wp.vec3(1.0 + s * n[0] * n[0] * a, s * b, -s * n[0])
    bt = wp.vec3(b, s + n[1] * n[1] * a, -n[1])
    return wp.mat33(t[0], bt[0], n[0], t[1], bt[1], n[1], t[2], bt[2], n[2])


@wp.kernel
def _bake_light(
    # Scene:
    scene: _Scene,
    # Points to light:
    point: wp.array(dtype=wp.vec3),
    normal: wp.array(dtype=wp.vec3),
    # Fixed sample patterns (unit disc for the area lights, cosine-weighted hemisphere):
    disc: wp.array(dtype=wp.vec2),
    hemisphere: wp.array(dtype=wp.vec3),
    ao_range_m: float,
    # Out:
    light_out: wp.array(dtype=wp.vec4),
):
    i = wp.tid()
    n = wp.normalize(normal[i])
    p = point[i] + n * _SHADOW_BIAS_M
    out = wp.vec4(0.0)
    for k in range(scene.n_lights):
        seen = float(0.0)  # noqa: UP018 (Warp: a typed variable, mutable in the dynamic loop)
        for s in range(disc.shape[0]):
            r = scene.light_radius[k]
            target = scene.light_pos[k] + wp.vec3(disc[s][0] * r, disc[s][1] * r, 0.0)
            d = target - p
            dist = wp.length(d)
            q = wp.mesh_query_ray(scene.mesh, p, d / dist, dist - _SHADOW_BIAS_M)
            if not q.result:
                seen += 1.0
        out[k] = seen / float(disc.shape[0])
    frame = _tangent_frame(n)
    open_sky = float(0.0)  # noqa: UP018 (Warp: a typed variable, mutable in the dynamic loop)
    for s in range(hemisphere.shape[0]):
        q = wp.mesh_query_ray(scene.mesh, p, frame * hemisphere[s], ao_range_m)
        if q.result:
            open_sky += q.t / ao_range_m
        else:
            open_sky += 1.0
    out[3] = open_sky / float(hemisphere.shape[0])
    light_out[i] = out


@wp.kernel
def _render(
    # Scene:
    scene: _Scene,
    # Camera: world-from-camera rotation and centre per colour sub-frame (motion blur), and for depth
    rot_wc: wp.array(dtype=wp.mat33),
    centre_w: wp.array(dtype=wp.vec3),
    depth_rot_wc: wp.mat33,
    depth_centre_w: wp.vec3,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    # Sampling: n_ss x n_ss jittered sub-pixels per sub-frame (0: depth only)
    n_ss: int,
    seed: int,
    # Out:
    rgb_out: wp.array2d(dtype=wp.vec3),
    depth_out: wp.array2d(dtype=wp.float32),
):
    y, x = wp.tid()
    width = rgb_out.shape[1]
    # depth of the ray through the pixel centre (u, v) = (x, y): the project's pixel convention
    d_c = wp.vec3((float(x) - cx) / fx, (float(y) - cy) / fy, 1.0)
    inv_len = 1.0 / wp.length(d_c)
    q = wp.mesh_query_ray(scene.mesh, depth_centre_w, depth_rot_wc * (d_c * inv_len), _RAY_MAX_M)
    depth_out[y, x] = wp.where(q.result, q.t * inv_len, 0.0)
    if n_ss == 0:
        return

    state = wp.rand_init(seed, y * width + x)
    acc = wp.vec3(0.0)
    step = 1.0 / float(n_ss)
    footprint_per_m = step / (0.5 * (fx + fy))
    for k in range(rot_wc.shape[0]):
        for sy in range(n_ss):
            for sx in range(n_ss):
                u = float(x) - 0.5 + (float(sx) + wp.randf(state)) * step
                v = float(y) - 0.5 + (float(sy) + wp.randf(state)) * step
                d = wp.normalize(rot_wc[k] * wp.vec3((u - cx) / fx, (v - cy) / fy, 1.0))
                h = wp.mesh_query_ray(scene.mesh, centre_w[k], d, _RAY_MAX_M)
                if h.result:
                    p = centre_w[k] + d * h.t
                    acc += _shade(scene, h.face, h.u, h.v, p, d, h.t * footprint_per_m)
    rgb_out[y, x] = acc / float(rot_wc.shape[0] * n_ss * n_ss)


@wp.kernel
def _corner_colour(
    scene: _Scene,
    corner_point: wp.array(dtype=wp.vec3),
    footprint_m: float,
    colour_out: wp.array(dtype=wp.vec3),
):
    c = wp.tid()
    face = c // 3
    k = c - 3 * face
    bu = wp.where(k == 0, 1.0, 0.0)
    bv = wp.where(k == 1, 1.0, 0.0)
    n = scene.corner_normal[c]
    colour_out[c] = _shade(scene, face, bu, bv, corner_point[c], -n, footprint_m)


def _fibonacci_disc(n: int) -> np.ndarray:
    k = np.arange(n) + 0.5
    r = np.sqrt(k / n)
    a = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(a), r * np.sin(a)], 1).astype(np.float32)


def _cosine_hemisphere(n: int) -> np.ndarray:
    d = _fibonacci_disc(n)
    z = np.sqrt(np.maximum(0.0, 1.0 - (d**2).sum(1)))
    return np.concatenate([d, z[:, None]], 1).astype(np.float32)


class SceneRenderer:
    """Uploads a ``Scene`` to ``device``, bakes its lighting, and renders views of it.

    ``render(camera, colour_poses_wc, depth_pose_wc, n_ss, seed)`` returns linear-light colour (HxWx3,
    averaged over the jittered sub-pixels of every pose in ``colour_poses_wc``) and the z-depth (HxW,
    metres) of the pixel-centre rays from ``depth_pose_wc``.
    """

    def __init__(self, scene, device: str, light_samples: int = 16, ao_samples: int = 24, ao_range_m: float = 0.6):
        if len(scene.lights) > MAX_LIGHTS:
            raise ValueError(f"at most {MAX_LIGHTS} lights, scene has {len(scene.lights)}")
        self.device = device
        F = scene.positions.shape[0]
        corners = scene.positions.reshape(-1, 3).astype(np.float32)
        self._corners = wp.array(corners, dtype=wp.vec3, device=device)
        self.mesh = wp.Mesh(points=self._corners, indices=wp.array(np.arange(3 * F, dtype=np.int32), device=device))
        texels, level, n_levels = build_atlas(scene.textures, MAX_LEVELS)
        mats = scene.materials
        s = _Scene()
        s.mesh = self.mesh.id
        s.corner_uv = wp.array(scene.uvs.reshape(-1, 2).astype(np.float32), dtype=wp.vec2, device=device)
        s.corner_normal = wp.array(scene.normals.reshape(-1, 3).astype(np.float32), dtype=wp.vec3, device=device)
        s.face_material = wp.array(scene.face_material.astype(np.int32), dtype=wp.int32, device=device)
        s.face_uv_per_m = wp.array(scene.face_uv_per_m.astype(np.float32), dtype=wp.float32, device=device)
        s.material_texture = wp.array([m.texture for m in mats], dtype=wp.int32, device=device)
        s.material_tint = wp.array([m.tint for m in mats], dtype=wp.vec3, device=device)
        s.material_address = wp.array([m.address for m in mats], dtype=wp.int32, device=device)
        s.material_emission = wp.array([m.emission for m in mats], dtype=wp.float32, device=device)
        s.atlas = wp.array(texels, dtype=wp.vec3, device=device)
        s.texture_level = wp.array(level, dtype=wp.vec3i, device=device)
        s.texture_n_levels = wp.array(n_levels, dtype=wp.int32, device=device)
        lights = scene.lights or []
        s.light_pos = wp.array([li.position for li in lights] or [(0.0, 0.0, 0.0)], dtype=wp.vec3, device=device)
        s.light_colour = wp.array([li.colour for li in lights] or [(0.0, 0.0, 0.0)], dtype=wp.vec3, device=device)
        s.light_radius = wp.array([li.radius for li in lights] or [0.0], dtype=wp.float32, device=device)
        s.light_facing = wp.array([li.facing for li in lights] or [(0.0, 0.0, 0.0)], dtype=wp.vec3, device=device)
        s.n_lights = len(lights)
        s.ambient = wp.vec3(*scene.ambient)
        s.corner_light = wp.zeros(3 * F, dtype=wp.vec4, device=device)
        self._scene = s
        self._bake(corners, scene.normals.reshape(-1, 3), light_samples, ao_samples, ao_range_m)
        self._rgb = self._depth = None

    def _bake(self, corners, normals, light_samples, ao_samples, ao_range_m):
        # corners shared by neighbouring triangles get one bake (and so identical values: no seams)
        key = np.round(np.concatenate([corners, normals], 1) * 1e4).astype(np.int64)
        _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
        d = self.device
        out = wp.zeros(len(first), dtype=wp.vec4, device=d)
        wp.launch(
            _bake_light,
            dim=len(first),
            inputs=[
                self._scene,
                wp.array(corners[first], dtype=wp.vec3, device=d),
                wp.array(normals[first].astype(np.float32), dtype=wp.vec3, device=d),
                wp.array(_fibonacci_disc(light_samples), dtype=wp.vec2, device=d),
                wp.array(_cosine_hemisphere(ao_samples), dtype=wp.vec3, device=d),
                float(ao_range_m),
            ],
            outputs=[out],
            device=d,
        )
        self._scene.corner_light = wp.array(out.numpy()[inverse.ravel()], dtype=wp.vec4, device=d)

    def render(self, camera, colour_poses_wc, depth_pose_wc, n_ss: int = 3, seed: int = 0):
        H, W = camera.height, camera.width
        if self._rgb is None or self._rgb.shape != (H, W):
            self._rgb = wp.zeros((H, W), dtype=wp.vec3, device=self.device)
            self._depth = wp.zeros((H, W), dtype=wp.float32, device=self.device)
        poses = np.asarray(colour_poses_wc, dtype=np.float32).reshape(-1, 4, 4)
        depth_pose = np.asarray(depth_pose_wc, dtype=np.float32)
        wp.launch(
            _render,
            dim=(H, W),
            inputs=[
                self._scene,
                wp.array(poses[:, :3, :3], dtype=wp.mat33, device=self.device),
                wp.array(poses[:, :3, 3], dtype=wp.vec3, device=self.device),
                wp.mat33(*depth_pose[:3, :3].ravel()),
                wp.vec3(*depth_pose[:3, 3]),
                float(camera.fx),
                float(camera.fy),
                float(camera.cx),
                float(camera.cy),
                int(n_ss),
                int(seed),
            ],
            outputs=[self._rgb, self._depth],
            device=self.device,
        )
        # .numpy() of a CPU array aliases it: copy, or the next render would overwrite this one
        return self._rgb.numpy().copy(), self._depth.numpy().copy()

    def corner_colours(self, footprint_m: float = 0.01) -> np.ndarray:
        """Linear-light colour of every mesh corner (3F x 3), textures averaged over ``footprint_m``."""
        out = wp.zeros(self._corners.shape[0], dtype=wp.vec3, device=self.device)
        wp.launch(
            _corner_colour,
            dim=out.shape[0],
            inputs=[self._scene, self._corners, float(footprint_m)],
            outputs=[out],
            device=self.device,
        )
        return out.numpy()
