"""Mixed precision in the rasterizer: does storing the per-Gaussian inputs of the compositing kernels
(and the SH coefficients) in half precision make rendering faster, and what does it cost in accuracy?

Baseline: the real ``Renderer`` (fp32 everywhere).  Variants run the same pipeline (``Renderer``
subclass: same projection, scan, sort and tile ranges) with copies of the projection, the tiled
compositing forward and its general backward, and the projection backward, whose only change is the
storage type of what they exchange.  The math is the repo's own: the compositing copies call
``rasterize.splat_alpha`` / ``splat_grad`` / ``warp_sum`` and are compiled with fast math as the
rasterize module is; the projection copies call the projection module's functions.  Accumulation
(transmittance, colour and depth sums, gradients, atomics) stays fp32; only loads change.

Storage variants (per Gaussian, what the compositing kernels gather; fp32 layout: xy_opacity_depth
vec4 16 B + conic vec3 12 B + colour vec3 12 B = 40 B):
* ``copy32``: the fp32 layout through the bench's kernel copies (the control: must equal the
  baseline's image and time, else the copies differ from the real kernels);
* ``sh16``: SH coefficients stored as vec3h (108 -> 54 B per Gaussian at degree 2) for the projection
  and its backward, compositing fp32.  The half copy is made once before timing (a real map would have
  Adam write it next to the fp32 master);
* ``color16``: colour vec3h (34 B);
* ``conic16``: conic and colour vec3h (28 B);
* ``packed16``: xy fp32 (vec2) | conic + opacity (vec4h) | colour + depth (vec4h): 24 B, every value
  but the pixel position in half (positions keep fp32: fp16 spacing is 1 px between 1024 and 2048 px);
* ``all16``: xy_opacity_depth vec4h as well (20 B in all): shows what fp16 positions cost;
* ``packed16_sh16``: packed16 + sh16.
Suffix ``_s32``: the batch staged into shared memory is converted to fp32 as it is loaded (one
conversion per Gaussian and tile; the inner per-pixel loop is then the fp32 code); without it, the
shared tiles hold the storage type and each per-pixel use converts.

Where the fp32 xy_opacity_depth is not the compositing input (packed16, all16) the projection also
writes it (16 B per Gaussian) because the repo's emit_intersections reads it; that costs the variant a
little projection time.  Not measured: the pose-only backward (tracking), whose per-Gaussian staging
is dominated by the 128-byte pose Jacobians.

Per variant and N: forward and forward + backward (all Gaussian parameters) GPU times as the
CUDA-event median of graph replays (variants interleaved round by round; eager + perf_counter on the
CPU), per-kernel GPU times (Warp's CUDA activity timer), and errors against the baseline: image
colour / depth / alpha max and mean abs difference, relative L2 error of the gradients (3D means,
SH = colour parameters, opacity logits, rotations, log-scales, pose twist; and of the screen-space
per-Gaussian gradients of colour, xy, opacity).  A variant's forward image "passes" when its colour
is within one 8-bit level (1/255) of fp32 everywhere and within 1e-4 on average.

    python experiments/bench/mixed_precision.py [--device cuda:0] [--gaussians 300000 1000000]
        [--width 1200 --height 680] [--repeats 30] [--variants copy32 color16 ...] [--out DIR]
"""

# no "from __future__ import annotations": Warp evaluates the kernel factories' annotations
# with their closures

import argparse
import json
import os
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp
from raster import room_scene
from raster_variants import resources

import rgs_warp.kernels.projection as proj
import rgs_warp.kernels.rasterize as rast
from rgs_warp.kernels.projection import (
    ALPHA_MIN,
    COV2D_DILATION,
    POSE_JAC_COLOR,
    POSE_JAC_CONIC,
    POSE_JAC_X,
    PROJECT_BLOCK,
    TILE_SIZE,
    CameraParams,
    conic_backward,
    conic_twist_jacobian,
    covariance_twist_grad,
    direction_backward,
    exp3,
    jacobian_backward,
    projection_jacobian,
    quat_to_rot,
    quat_to_rot_vjp,
    sh_basis,
    tile_rect,
    vec6,
    vec10,
    vec32,
    view_direction,
)
from rgs_warp.kernels.rasterize import BLOCK, T_MIN, splat_alpha, splat_grad, warp_any, warp_leader, warp_sum
from rgs_warp.render import Renderer
from rgs_warp.types import Camera, GaussianMap

# Colour tolerance of a variant's forward image against fp32: max within one 8-bit level, mean 1e-4.
TOL_MAX = 1.0 / 255.0
TOL_MEAN = 1.0e-4
# Gradient relative error regarded as harmless for optimisation.
TOL_GRAD = 1.0e-2


@dataclass(frozen=True)
class Variant:
    name: str
    packed: bool = False  # xy vec2 | conic+opacity vec4h | colour+depth vec4h
    geo_half: bool = False  # split layout: xy_opacity_depth as vec4h
    conic_half: bool = False
    color_half: bool = False
    sh_half: bool = False
    stage32: bool = False  # convert to fp32 when staging into shared memory

    @property
    def layout_key(self) -> str:
        if self.packed:
            return "packed"
        return "split_" + "".join("h" if f else "f" for f in (self.geo_half, self.conic_half, self.color_half))

    @property
    def dtypes(self):
        if self.packed:
            return wp.vec2, wp.vec4h, wp.vec4h
        return (
            wp.vec4h if self.geo_half else wp.vec4,
            wp.vec3h if self.conic_half else wp.vec3,
            wp.vec3h if self.color_half else wp.vec3,
        )


VARIANTS = [
    Variant("copy32"),
    Variant("sh16", sh_half=True),
    Variant("color16", color_half=True),
    Variant("color16_s32", color_half=True, stage32=True),
    Variant("conic16", conic_half=True, color_half=True),
    Variant("conic16_s32", conic_half=True, color_half=True, stage32=True),
    Variant("packed16", packed=True),
    Variant("packed16_s32", packed=True, stage32=True),
    Variant("all16_s32", geo_half=True, conic_half=True, color_half=True, stage32=True),
    Variant("packed16_sh16_s32", packed=True, sh_half=True, stage32=True),
]


@wp.func_native("WP_TILE_SYNC();")
def block_sync(unused: int): ...


# ---- storage layouts: pack (projection) and the accessors of the compositing kernels ---------------
_LAYOUT_CACHE: dict = {}


def layout_funcs(v: Variant):
    """(pack, xyo, conic_of, color_depth, unpack32) for the variant's layout, as wp.funcs.

    pack(mean2d, opacity, z, conic, colour) -> the three stored values;
    xyo(v0, v1) -> vec4 (x, y, opacity, depth or 0): what splat_alpha reads;
    conic_of(v1) -> vec3; color_depth(v0, v2) -> (vec3 colour, depth);
    unpack32(v0, v1, v2) -> (xy_opacity_depth vec4, conic vec3, colour vec3), all fp32."""
    key = v.layout_key
    if key in _LAYOUT_CACHE:
        return _LAYOUT_CACHE[key]
    T0, T1, T2 = v.dtypes
    module = f"mp_layout_{key}"
    if v.packed:

        def pack(mean2d: wp.vec2, opacity: float, z: float, conic: wp.vec3, color: wp.vec3):
            return (
                wp.vec2(mean2d[0], mean2d[1]),
                wp.vec4h(wp.float16(conic[0]), wp.float16(conic[1]), wp.float16(conic[2]), wp.float16(opacity)),
                wp.vec4h(wp.float16(color[0]), wp.float16(color[1]), wp.float16(color[2]), wp.float16(z)),
            )

        def xyo(v0: T0, v1: T1):
            return wp.vec4(v0[0], v0[1], float(v1[3]), 0.0)

        def conic_of(v1: T1):
            return wp.vec3(float(v1[0]), float(v1[1]), float(v1[2]))

        def color_depth(v0: T0, v2: T2):
            return wp.vec3(float(v2[0]), float(v2[1]), float(v2[2])), float(v2[3])

        def unpack32(v0: T0, v1: T1, v2: T2):
            return (
                wp.vec4(v0[0], v0[1], float(v1[3]), float(v2[3])),
                wp.vec3(float(v1[0]), float(v1[1]), float(v1[2])),
                wp.vec3(float(v2[0]), float(v2[1]), float(v2[2])),
            )

    else:

        def pack(mean2d: wp.vec2, opacity: float, z: float, conic: wp.vec3, color: wp.vec3):
            return T0(wp.vec4(mean2d[0], mean2d[1], opacity, z)), T1(conic), T2(color)

        def xyo(v0: T0, v1: T1):
            return wp.vec4(v0)

        def conic_of(v1: T1):
            return wp.vec3(v1)

        def color_depth(v0: T0, v2: T2):
            return wp.vec3(v2), float(v0[3])

        def unpack32(v0: T0, v1: T1, v2: T2):
            return wp.vec4(v0), wp.vec3(v1), wp.vec3(v2)

    funcs = tuple(
        wp.func(f, module=module, name=f"mp_{f.__name__}_{key}") for f in (pack, xyo, conic_of, color_depth, unpack32)
    )
    _LAYOUT_CACHE[key] = funcs
    return funcs


def _module(name: str, fast_math: bool):
    m = wp.get_module(name)
    wp.set_module_options({"enable_backward": False, "fast_math": fast_math}, module=m)
    return m


# ---- projection (copy of projection.project_gaussians; outputs in the variant's storage) ------------
def make_project(v: Variant):
    T0, T1, T2 = v.dtypes
    TS = wp.vec3h if v.sh_half else wp.vec3
    pack = layout_funcs(v)[0]
    # the fp32 xy_opacity_depth (read by emit_intersections) is a separate output unless it is the
    # compositing input itself
    write32 = v.packed or v.geo_half
    tag = f"{v.layout_key}_{'sh16' if v.sh_half else 'sh32'}"

    def project(
        means: wp.array(dtype=wp.vec3),
        rotations: wp.array(dtype=wp.quat),
        log_scales: wp.array(dtype=wp.vec3),
        opacity_logits: wp.array(dtype=float),
        sh: wp.array2d(dtype=TS),
        num_sh: int,
        view: wp.array(dtype=wp.mat44),
        cam: CameraParams,
        with_pose_jac: int,
        xy_opacity_depth_out: wp.array(dtype=wp.vec4),
        depth_out: wp.array(dtype=float),
        a0_out: wp.array(dtype=T0),
        a1_out: wp.array(dtype=T1),
        a2_out: wp.array(dtype=T2),
        radii_out: wp.array(dtype=wp.vec2i),
        tiles_touched_out: wp.array(dtype=wp.int32),
        pose_jac_out: wp.array(dtype=vec32),
    ):
        i = wp.tid()
        radii_out[i] = wp.vec2i(0, 0)
        tiles_touched_out[i] = 0

        mean = means[i]
        V = view[0]
        dir_raw, W, t = view_direction(mean, V)
        X = W @ mean + t
        z = X[2]
        if z < cam.near:
            return
        opacity = 1.0 / (1.0 + wp.exp(-opacity_logits[i]))
        if opacity < ALPHA_MIN:
            return

        q = wp.normalize(rotations[i])
        R = quat_to_rot(q)
        s = exp3(log_scales[i])
        M = R @ wp.diag(s)
        cov_c = W @ (M @ wp.transpose(M)) @ wp.transpose(W)
        J = projection_jacobian(X, cam)
        cov2d = J @ cov_c @ wp.transpose(J)
        a = cov2d[0, 0] + COV2D_DILATION
        b = cov2d[0, 1]
        c = cov2d[1, 1] + COV2D_DILATION
        det = a * c - b * b
        if det <= 0.0:
            return

        extent = wp.sqrt(2.0 * wp.log(opacity / ALPHA_MIN))
        rx = int(wp.ceil(wp.min(extent * wp.sqrt(a), 1.0e6)))
        ry = int(wp.ceil(wp.min(extent * wp.sqrt(c), 1.0e6)))
        mean2d = wp.vec2(cam.fx * X[0] / z + cam.cx, cam.fy * X[1] / z + cam.cy)
        radii = wp.vec2i(rx, ry)
        rect = tile_rect(mean2d, radii, cam)
        touched = (rect[1] - rect[0]) * (rect[3] - rect[2])
        if touched <= 0:
            return

        d = wp.normalize(dir_raw)
        raw = wp.vec3(0.0)
        g_dr = wp.vec3(0.0)
        g_dg = wp.vec3(0.0)
        g_db = wp.vec3(0.0)
        for k in range(num_sh):
            y, dy = sh_basis(k, d)
            coeff = wp.vec3(sh[i, k])
            raw += y * coeff
            if with_pose_jac != 0:
                g_dr += coeff[0] * dy
                g_dg += coeff[1] * dy
                g_db += coeff[2] * dy
        color = wp.vec3(wp.max(raw[0] + 0.5, 0.0), wp.max(raw[1] + 0.5, 0.0), wp.max(raw[2] + 0.5, 0.0))
        conic = wp.vec3(c / det, -b / det, a / det)

        v0, v1, v2 = pack(mean2d, opacity, z, conic, color)
        if wp.static(write32):
            xy_opacity_depth_out[i] = wp.vec4(mean2d[0], mean2d[1], opacity, z)
        depth_out[i] = z
        a0_out[i] = v0
        a1_out[i] = v1
        a2_out[i] = v2
        radii_out[i] = radii
        tiles_touched_out[i] = touched

        if with_pose_jac != 0:
            jac = vec32()
            jac[POSE_JAC_X + 0] = X[0]
            jac[POSE_JAC_X + 1] = X[1]
            jac[POSE_JAC_X + 2] = X[2]
            jac[POSE_JAC_X + 3] = 1.0 / z
            for r in range(3):
                e = wp.vec3(0.0)
                e[r] = 1.0
                row = conic_twist_jacobian(conic, J, cov_c, X, cam, e)
                for j in range(6):
                    jac[POSE_JAC_CONIC + 6 * r + j] = row[j]
            col_r = wp.where(raw[0] + 0.5 > 0.0, 1.0, 0.0) * (W @ direction_backward(g_dr, d, dir_raw))
            col_g = wp.where(raw[1] + 0.5 > 0.0, 1.0, 0.0) * (W @ direction_backward(g_dg, d, dir_raw))
            col_b = wp.where(raw[2] + 0.5 > 0.0, 1.0, 0.0) * (W @ direction_backward(g_db, d, dir_raw))
            for j in range(3):
                jac[POSE_JAC_COLOR + j] = col_r[j]
                jac[POSE_JAC_COLOR + 3 + j] = col_g[j]
                jac[POSE_JAC_COLOR + 6 + j] = col_b[j]
            pose_jac_out[i] = jac

    return wp.kernel(project, module=_module(f"mp_project_{tag}", False), name=f"mp_project_{tag}")


def make_project_backward(v: Variant):
    """Copy of projection.project_gaussians_backward reading the stored conic and the SH in the
    variant's types."""
    T1 = v.dtypes[1]
    TS = wp.vec3h if v.sh_half else wp.vec3
    conic_of = layout_funcs(v)[2]
    tag = f"{v.layout_key}_{'sh16' if v.sh_half else 'sh32'}"

    def project_backward(
        means: wp.array(dtype=wp.vec3),
        rotations: wp.array(dtype=wp.quat),
        log_scales: wp.array(dtype=wp.vec3),
        opacity_logits: wp.array(dtype=float),
        sh: wp.array2d(dtype=TS),
        num_sh: int,
        count: int,
        view: wp.array(dtype=wp.mat44),
        cam: CameraParams,
        radii: wp.array(dtype=wp.vec2i),
        conic: wp.array(dtype=T1),
        grad2d: wp.array(dtype=vec10),
        pose_only: int,
        accumulate: int,
        grad_means_out: wp.array(dtype=wp.vec3),
        grad_rotations_out: wp.array(dtype=wp.quat),
        grad_log_scales_out: wp.array(dtype=wp.vec3),
        grad_opacity_logits_out: wp.array(dtype=float),
        grad_sh_out: wp.array2d(dtype=wp.vec3),
        grad_pose_out: wp.array(dtype=float),
    ):
        block, lane = wp.tid()
        i = block * PROJECT_BLOCK + lane
        g_pose = vec6()
        g_mean = wp.vec3(0.0)
        g_quat = wp.quat(0.0, 0.0, 0.0, 0.0)
        g_log_s = wp.vec3(0.0)
        g_logit = wp.float32(0.0)
        live = i < count
        if live:
            live = radii[i][0] > 0
        if live:
            g = grad2d[i]
            mean = means[i]
            V = view[0]
            dir_raw, W, t = view_direction(mean, V)
            X = W @ mean + t
            z = X[2]

            cn = conic_of(conic[i])
            q_raw = rotations[i]
            q = wp.normalize(q_raw)
            R = quat_to_rot(q)
            s = exp3(log_scales[i])
            M = R @ wp.diag(s)
            cov_w = M @ wp.transpose(M)
            cov_c = W @ cov_w @ wp.transpose(W)
            J = projection_jacobian(X, cam)
            g_cov_c, g_J = conic_backward(cn, wp.vec3(g[2], g[3], g[4]), J, cov_c)
            g_X = jacobian_backward(g_J, X, cam)
            z2 = z * z
            g_X += wp.vec3(
                g[0] * cam.fx / z,
                g[1] * cam.fy / z,
                -(g[0] * cam.fx * X[0] + g[1] * cam.fy * X[1]) / z2 + g[9],
            )

            d = wp.normalize(dir_raw)
            raw = wp.vec3(0.0)
            for k in range(num_sh):
                y, dy = sh_basis(k, d)
                raw += y * wp.vec3(sh[i, k])
            g_col = wp.vec3(
                wp.where(raw[0] + 0.5 > 0.0, g[6], 0.0),
                wp.where(raw[1] + 0.5 > 0.0, g[7], 0.0),
                wp.where(raw[2] + 0.5 > 0.0, g[8], 0.0),
            )
            g_d = wp.vec3(0.0)
            for k in range(num_sh):
                y, dy = sh_basis(k, d)
                g_d += wp.dot(g_col, wp.vec3(sh[i, k])) * dy
                if pose_only == 0:
                    g_sh_k = y * g_col
                    if accumulate != 0:
                        g_sh_k += grad_sh_out[i, k]
                    grad_sh_out[i, k] = g_sh_k
            g_dir = direction_backward(g_d, d, dir_raw)

            g_phi = wp.cross(X, g_X) + covariance_twist_grad(g_cov_c, cov_c)
            g_rho = g_X + W @ g_dir
            g_pose = vec6(g_rho[0], g_rho[1], g_rho[2], g_phi[0], g_phi[1], g_phi[2])

            if pose_only == 0:
                g_mean = wp.transpose(W) @ g_X + g_dir
                g_cov_w = wp.transpose(W) @ g_cov_c @ W
                g_M = 2.0 * (g_cov_w @ M)
                g_R = g_M @ wp.diag(s)
                g_s = wp.vec3(
                    R[0, 0] * g_M[0, 0] + R[1, 0] * g_M[1, 0] + R[2, 0] * g_M[2, 0],
                    R[0, 1] * g_M[0, 1] + R[1, 1] * g_M[1, 1] + R[2, 1] * g_M[2, 1],
                    R[0, 2] * g_M[0, 2] + R[1, 2] * g_M[1, 2] + R[2, 2] * g_M[2, 2],
                )
                g_log_s = wp.cw_mul(g_s, s)
                g_qn = quat_to_rot_vjp(q, g_R)
                g_quat = (g_qn - q * wp.dot(q, g_qn)) / wp.length(q_raw)
                opacity = 1.0 / (1.0 + wp.exp(-opacity_logits[i]))
                g_logit = g[5] * opacity * (1.0 - opacity)
        elif i < count and pose_only == 0:
            for k in range(num_sh):
                if accumulate == 0:
                    grad_sh_out[i, k] = wp.vec3(0.0)

        if i < count and pose_only == 0:
            if accumulate != 0:
                g_mean += grad_means_out[i]
                g_quat += grad_rotations_out[i]
                g_log_s += grad_log_scales_out[i]
                g_logit += grad_opacity_logits_out[i]
            grad_means_out[i] = g_mean
            grad_rotations_out[i] = g_quat
            grad_log_scales_out[i] = g_log_s
            grad_opacity_logits_out[i] = g_logit

        total = wp.tile_extract(wp.tile_sum(wp.tile(g_pose, preserve_type=True)), 0)
        if lane == 0:
            for c in range(6):
                wp.atomic_add(grad_pose_out, c, total[c])

    return wp.kernel(project_backward, module=_module(f"mp_project_bwd_{tag}", False), name=f"mp_project_bwd_{tag}")


# ---- compositing (copies of rasterize.rasterize_tiles / the general rasterize_tiles_backward) ------
def make_raster_forward(v: Variant, module):
    T0, T1, T2 = v.dtypes
    _, xyo, conic_of, color_depth, unpack32 = layout_funcs(v)
    stage32 = v.stage32

    def raster_forward(
        ranges: wp.array2d(dtype=wp.int32),
        sorted_ids: wp.array(dtype=wp.int32),
        a0: wp.array(dtype=T0),
        a1: wp.array(dtype=T1),
        a2: wp.array(dtype=T2),
        background: wp.vec3,
        width: int,
        height: int,
        tiles_x: int,
        color_out: wp.array2d(dtype=wp.vec3),
        depth_out: wp.array2d(dtype=float),
        alpha_out: wp.array2d(dtype=float),
        final_t_out: wp.array2d(dtype=float),
        n_contrib_out: wp.array2d(dtype=wp.int32),
    ):
        tile, lane = wp.tid()
        ty = tile // tiles_x
        px_i = (tile - ty * tiles_x) * TILE_SIZE + lane % TILE_SIZE
        py_i = ty * TILE_SIZE + lane // TILE_SIZE
        inside = px_i < width and py_i < height
        px = float(px_i)
        py = float(py_i)
        start = ranges[tile, 0]
        end = ranges[tile, 1]
        n_batches = (end - start + BLOCK - 1) // BLOCK

        T = wp.float32(1.0)
        acc_color = wp.vec3(0.0)
        acc_depth = wp.float32(0.0)
        last = wp.int32(0)
        done = not inside
        if wp.static(stage32):
            s_xyod = wp.tile_zeros(shape=BLOCK, dtype=wp.vec4, storage="shared")
            s_conic = wp.tile_zeros(shape=BLOCK, dtype=wp.vec3, storage="shared")
            s_color = wp.tile_zeros(shape=BLOCK, dtype=wp.vec3, storage="shared")
        for b in range(n_batches):
            # block-wide early exit; the reduction is also the barrier before the shared tiles are reused
            n_done = wp.tile_extract(wp.tile_sum(wp.tile(wp.where(done, 1, 0))), 0)
            if n_done == BLOCK:
                break
            batch_start = start + b * BLOCK
            if wp.static(stage32):
                j = batch_start + lane
                xyod_j = wp.vec4(0.0)
                con_j = wp.vec3(0.0)
                col_j = wp.vec3(0.0)
                if j < end:
                    gid = sorted_ids[j]
                    xyod_j, con_j, col_j = unpack32(a0[gid], a1[gid], a2[gid])
                wp.tile_assign(s_xyod, wp.tile(xyod_j, preserve_type=True))
                wp.tile_assign(s_conic, wp.tile(con_j, preserve_type=True))
                wp.tile_assign(s_color, wp.tile(col_j, preserve_type=True))
            else:
                ids = wp.tile_load(sorted_ids, shape=BLOCK, offset=batch_start, storage="shared")
                s0 = wp.tile_load_indexed(a0, ids, shape=(BLOCK,), storage="shared")
                s1 = wp.tile_load_indexed(a1, ids, shape=(BLOCK,), storage="shared")
                s2 = wp.tile_load_indexed(a2, ids, shape=(BLOCK,), storage="shared")
            count = wp.min(BLOCK, end - batch_start)
            for k in range(count):
                if done:
                    break
                if wp.static(stage32):
                    xyod = wp.tile_extract(s_xyod, k)
                    alpha, dx, dy = splat_alpha(xyod, wp.tile_extract(s_conic, k), px, py)
                else:
                    v1 = wp.tile_extract(s1, k)
                    xyod = xyo(wp.tile_extract(s0, k), v1)
                    alpha, dx, dy = splat_alpha(xyod, conic_of(v1), px, py)
                if alpha < ALPHA_MIN:
                    continue
                t_next = T * (1.0 - alpha)
                if t_next < T_MIN:
                    done = True
                    break
                w = alpha * T
                if wp.static(stage32):
                    acc_color += w * wp.tile_extract(s_color, k)
                    acc_depth += w * xyod[3]
                else:
                    col, dep = color_depth(wp.tile_extract(s0, k), wp.tile_extract(s2, k))
                    acc_color += w * col
                    acc_depth += w * dep
                T = t_next
                last = batch_start + k + 1 - start

        if inside:
            color_out[py_i, px_i] = acc_color + T * background
            depth_out[py_i, px_i] = acc_depth
            alpha_out[py_i, px_i] = 1.0 - T
            final_t_out[py_i, px_i] = T
            n_contrib_out[py_i, px_i] = last

    return wp.kernel(raster_forward, module=module, name=f"mp_raster_fwd_{v.name}")


def make_raster_backward(v: Variant, module):
    T0, T1, T2 = v.dtypes
    _, xyo, conic_of, color_depth, unpack32 = layout_funcs(v)
    stage32 = v.stage32

    def raster_backward(
        ranges: wp.array2d(dtype=wp.int32),
        sorted_ids: wp.array(dtype=wp.int32),
        a0: wp.array(dtype=T0),
        a1: wp.array(dtype=T1),
        a2: wp.array(dtype=T2),
        background: wp.vec3,
        width: int,
        height: int,
        tiles_x: int,
        final_t: wp.array2d(dtype=float),
        n_contrib: wp.array2d(dtype=wp.int32),
        grad_color: wp.array2d(dtype=wp.vec3),
        grad_depth: wp.array2d(dtype=float),
        grad_alpha: wp.array2d(dtype=float),
        grad2d_out: wp.array(dtype=vec10),
    ):
        tile, lane = wp.tid()
        ty = tile // tiles_x
        px_i = (tile - ty * tiles_x) * TILE_SIZE + lane % TILE_SIZE
        py_i = ty * TILE_SIZE + lane // TILE_SIZE
        inside = px_i < width and py_i < height
        px = float(px_i)
        py = float(py_i)
        start = ranges[tile, 0]

        last = wp.int32(0)
        T = wp.float32(1.0)
        g_color = wp.vec3(0.0)
        g_depth = wp.float32(0.0)
        g_alpha = wp.float32(0.0)
        if inside:
            last = n_contrib[py_i, px_i]
            T = final_t[py_i, px_i]
            g_color = grad_color[py_i, px_i]
            g_depth = grad_depth[py_i, px_i]
            g_alpha = grad_alpha[py_i, px_i]
        t_final = T
        acc_color = T * background
        acc_depth = wp.float32(0.0)

        block_last = wp.tile_extract(wp.tile_max(wp.tile(last)), 0)
        n_batches = (block_last + BLOCK - 1) // BLOCK
        if wp.static(stage32):
            s_xyod = wp.tile_zeros(shape=BLOCK, dtype=wp.vec4, storage="shared")
            s_conic = wp.tile_zeros(shape=BLOCK, dtype=wp.vec3, storage="shared")
            s_color = wp.tile_zeros(shape=BLOCK, dtype=wp.vec3, storage="shared")
        for bb in range(n_batches):
            b = n_batches - 1 - bb
            batch_start = start + b * BLOCK
            if wp.static(stage32):
                block_sync(0)  # every thread is done with the previous batch's shared tiles
            ids = wp.tile_load(sorted_ids, shape=BLOCK, offset=batch_start, storage="shared")
            if wp.static(stage32):
                j = batch_start + lane
                xyod_j = wp.vec4(0.0)
                con_j = wp.vec3(0.0)
                col_j = wp.vec3(0.0)
                if j < start + block_last:
                    gid = sorted_ids[j]
                    xyod_j, con_j, col_j = unpack32(a0[gid], a1[gid], a2[gid])
                wp.tile_assign(s_xyod, wp.tile(xyod_j, preserve_type=True))
                wp.tile_assign(s_conic, wp.tile(con_j, preserve_type=True))
                wp.tile_assign(s_color, wp.tile(col_j, preserve_type=True))
            else:
                s0 = wp.tile_load_indexed(a0, ids, shape=(BLOCK,), storage="shared")
                s1 = wp.tile_load_indexed(a1, ids, shape=(BLOCK,), storage="shared")
                s2 = wp.tile_load_indexed(a2, ids, shape=(BLOCK,), storage="shared")
            count = wp.min(BLOCK, block_last - b * BLOCK)
            for kk in range(count):
                k = count - 1 - kk
                g = vec10()
                hit = wp.int32(0)
                if b * BLOCK + k < last:
                    if wp.static(stage32):
                        xyod = wp.tile_extract(s_xyod, k)
                        con = wp.tile_extract(s_conic, k)
                    else:
                        v1 = wp.tile_extract(s1, k)
                        xyod = xyo(wp.tile_extract(s0, k), v1)
                        con = conic_of(v1)
                    alpha, dx, dy = splat_alpha(xyod, con, px, py)
                    if alpha >= ALPHA_MIN:
                        T = T / (1.0 - alpha)
                        if wp.static(stage32):
                            col = wp.tile_extract(s_color, k)
                        else:
                            col, dep = color_depth(wp.tile_extract(s0, k), wp.tile_extract(s2, k))
                            xyod = wp.vec4(xyod[0], xyod[1], xyod[2], dep)
                        g = splat_grad(
                            xyod, con, col, dx, dy, alpha, T, t_final, acc_color, acc_depth, g_color, g_depth, g_alpha
                        )
                        w = alpha * T
                        acc_color += w * col
                        acc_depth += w * xyod[3]
                        hit = 1
                if warp_any(hit) != 0:
                    total = warp_sum(g)
                    if warp_leader(lane) != 0:
                        wp.atomic_add(grad2d_out, wp.tile_extract(ids, k), total)

    return wp.kernel(raster_backward, module=module, name=f"mp_raster_bwd_{v.name}")


@dataclass
class VariantKernels:
    project: wp.Kernel
    project_backward: wp.Kernel
    forward: wp.Kernel
    backward: wp.Kernel


_PROJECT_CACHE: dict = {}


def make_kernels(v: Variant) -> VariantKernels:
    key = (v.layout_key, v.sh_half)
    if key not in _PROJECT_CACHE:
        _PROJECT_CACHE[key] = (make_project(v), make_project_backward(v))
    module = _module(f"mp_raster_{v.name}", True)  # fast math, as the rasterize module
    return VariantKernels(*_PROJECT_CACHE[key], make_raster_forward(v, module), make_raster_backward(v, module))


class VariantRenderer(Renderer):
    """The real Renderer with the variant's projection, compositing and projection backward."""

    def __init__(self, variant: Variant, kernels: VariantKernels, device):
        super().__init__(device, tiled=True)
        self.variant = variant
        self.k = kernels
        self.sh_half = None  # (N, K) vec3h copy of the map's SH, for sh_half variants
        self._a_capacity = 0

    def _ensure_gaussians(self, capacity: int, num_sh: int) -> None:
        super()._ensure_gaussians(capacity, num_sh)
        n = self._gaussian_capacity
        v = self.variant
        T0, T1, T2 = v.dtypes
        if self._a_capacity != n:
            kw = {"device": self.device}
            self._a0_own = None if T0 is wp.vec4 else wp.zeros(n, dtype=T0, **kw)
            self._a1_own = None if T1 is wp.vec3 else wp.zeros(n, dtype=T1, **kw)
            self._a2_own = None if T2 is wp.vec3 else wp.zeros(n, dtype=T2, **kw)
            self._a_capacity = n
        # fp32 inputs are the base renderer's own buffers
        self._a0 = self._xyod if self._a0_own is None else self._a0_own
        self._a1 = self._conic if self._a1_own is None else self._a1_own
        self._a2 = self._color if self._a2_own is None else self._a2_own

    def _sh(self, gmap: GaussianMap):
        if not self.variant.sh_half:
            return gmap.sh
        if self.sh_half is None:
            raise RuntimeError("set renderer.sh_half to the half copy of the map's SH first")
        return self.sh_half

    def _project(self, gmap: GaussianMap, n: int, cam, pose_jacobians: bool) -> None:
        if pose_jacobians:
            raise NotImplementedError("the pose-only path is not part of this benchmark")
        wp.launch(
            self.k.project,
            dim=n,
            inputs=[gmap.means, gmap.rotations, gmap.log_scales, gmap.opacity_logits, self._sh(gmap), gmap.num_sh]
            + [self._view, cam, 0],
            outputs=[self._xyod, self._depth, self._a0, self._a1, self._a2, self._radii, self._touched, self._pose_jac],
            device=self.device,
            record_tape=False,
        )

    def _launch_raster(self, cam, bg, backward: bool, grads=None, pose_only: bool = False) -> None:
        if pose_only:
            raise NotImplementedError("the pose-only path is not part of this benchmark")
        common = [self._ranges, self._ids, self._a0, self._a1, self._a2, bg, cam.width, cam.height, cam.tiles_x]
        if backward:
            kernel, inputs, outputs = self.k.backward, common + [self._final_t, self._n_contrib, *grads], [self._grad2d]
        else:
            kernel, inputs = self.k.forward, common
            outputs = [self._out_color, self._out_depth, self._out_alpha, self._final_t, self._n_contrib]
        wp.launch_tiled(
            kernel,
            dim=[self._ranges.shape[0]],
            inputs=inputs,
            outputs=outputs,
            block_dim=BLOCK,
            device=self.device,
            record_tape=False,
        )

    def backward(self, dL_dcolor, dL_ddepth=None, dL_dalpha=None, pose_only=False, grads_out=None, accumulate=False):
        """Renderer.backward's general path with the variant's kernels."""
        if pose_only:
            raise NotImplementedError("the pose-only path is not part of this benchmark")
        gmap, n, cam, bg, _ = self._last
        self._last_pose_only = False
        if not accumulate:
            self.pose_grad.zero_()
        grads = grads_out or self.grads
        if n == 0:
            return grads, self.pose_grad
        image_grads = [
            dL_dcolor,
            self._zero_depth if dL_ddepth is None else dL_ddepth,
            self._zero_alpha if dL_dalpha is None else dL_dalpha,
        ]
        self._grad2d.zero_()
        self._launch_raster(cam, bg, backward=True, grads=image_grads)
        wp.launch_tiled(
            self.k.project_backward,
            dim=[(n + PROJECT_BLOCK - 1) // PROJECT_BLOCK],
            inputs=[gmap.means, gmap.rotations, gmap.log_scales, gmap.opacity_logits, self._sh(gmap), gmap.num_sh, n]
            + [self._view, cam, self._radii, self._a1, self._grad2d, 0, int(accumulate)],
            outputs=[grads.means, grads.rotations, grads.log_scales, grads.opacity_logits, grads.sh, self.pose_grad],
            block_dim=PROJECT_BLOCK,
            device=self.device,
            record_tape=False,
        )
        return grads, self.pose_grad


# ---- measurement ---------------------------------------------------------------------------------
def kernel_category(name: str) -> str:
    for prefix, cat in (
        ("mp_raster_fwd", "raster_fwd"),
        ("mp_raster_bwd", "raster_bwd"),
        ("rasterize_tiles_backward", "raster_bwd"),
        ("rasterize_tiles", "raster_fwd"),
        ("mp_project_bwd", "project_bwd"),
        ("project_gaussians_backward", "project_bwd"),
        ("mp_project", "project"),
        ("project_gaussians", "project"),
    ):
        if name.startswith(prefix):
            return cat
    return "other"


def rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm((a - b).ravel()) / max(float(np.linalg.norm(b.ravel())), 1e-30))


def snapshot(renderer: Renderer, result, n: int) -> dict:
    grads = renderer.grads.to_numpy(n)
    g2d = renderer.grad2d.numpy()[:n]
    return {
        "color": result.color.numpy().copy(),
        "depth": result.depth.numpy().copy(),
        "alpha": result.alpha.numpy().copy(),
        "grads": grads,
        "pose": renderer.pose_grad.numpy().copy(),
        "g2d_xy": g2d[:, 0:2].copy(),
        "g2d_opacity": g2d[:, 5].copy(),
        "g2d_color": g2d[:, 6:9].copy(),
    }


def errors(s: dict, ref: dict) -> dict:
    dc = np.abs(s["color"] - ref["color"])
    out = {
        "color_max_abs": float(dc.max()),
        "color_mean_abs": float(dc.mean()),
        "depth_max_abs": float(np.abs(s["depth"] - ref["depth"]).max()),
        "depth_mean_abs": float(np.abs(s["depth"] - ref["depth"]).mean()),
        "alpha_max_abs": float(np.abs(s["alpha"] - ref["alpha"]).max()),
    }
    for name in ("means", "sh", "opacity_logits", "rotations", "log_scales"):
        out[f"grad_{name}_rel"] = rel(s["grads"][name], ref["grads"][name])
    out["grad_pose_rel"] = rel(s["pose"], ref["pose"])
    for name in ("g2d_xy", "g2d_opacity", "g2d_color"):
        out[f"{name}_rel"] = rel(s[name], ref[name])
    out["image_ok"] = out["color_max_abs"] <= TOL_MAX and out["color_mean_abs"] <= TOL_MEAN
    out["grads_ok"] = all(out[f"grad_{k}_rel"] <= TOL_GRAD for k in ("means", "sh", "opacity_logits"))
    return out


def bench_size(n, camera, variants, kernels, device, args) -> dict:
    scene = room_scene(n)
    gmap = GaussianMap.from_numpy(
        scene["means"], scene["quats_xyzw"], scene["log_scales"], scene["opacity_logits"], scene["sh"], device=device
    )
    sh_half = None
    if any(v.sh_half for v in variants):
        sh_half = wp.array(scene["sh"].astype(np.float16), dtype=wp.vec3h, device=device)
    rng = np.random.default_rng(1)
    g_color = wp.array(
        rng.normal(size=(camera.height, camera.width, 3)).astype(np.float32), dtype=wp.vec3, device=device
    )
    g_depth = wp.array(rng.normal(size=(camera.height, camera.width)).astype(np.float32), device=device)
    # the pose on the device, as the tracker's: graph replays read its current value
    T = wp.array([np.eye(4, dtype=np.float32)], dtype=wp.mat44, device=device)

    renderers = {"fp32": Renderer(device)}
    for v in variants:
        r = VariantRenderer(v, kernels[v.name], device)
        r.sh_half = sh_half
        renderers[v.name] = r

    # accuracy (and the first, compiling, launches)
    row = {"n": n, "variants": {}}
    ref = None
    for name, r in renderers.items():
        t0 = time.perf_counter()
        result = r.forward(gmap, camera, T, pose_jacobians=False)
        r.backward(g_color, g_depth)
        wp.synchronize_device(device)
        snap = snapshot(r, result, n)
        entry = {"first_call_s": time.perf_counter() - t0, "intersections": result.num_intersections}
        if ref is None:
            ref = snap
            entry["mean_alpha"] = float(snap["alpha"].mean())
        else:
            entry["error"] = errors(snap, ref)
        row["variants"][name] = entry
    del ref, snap

    def step_fns(r):
        def fwd():
            r.forward(gmap, camera, T, pose_jacobians=False)

        def fwd_bwd():
            r.forward(gmap, camera, T, pose_jacobians=False)
            r.backward(g_color, g_depth)

        return {"forward_ms": fwd, "forward_backward_ms": fwd_bwd}

    # timing: graphs of each step on CUDA (no host overhead), eager on the CPU; variants interleaved
    runners = {}
    for name, r in renderers.items():
        for step, fn in step_fns(r).items():
            fn()  # eager: sizes the intersection buffers from this view's count
            launch = fn
            if device.is_cuda and not args.eager:
                with wp.ScopedCapture(device) as capture:
                    fn()
                launch = lambda g=capture.graph: wp.capture_launch(g)  # noqa: E731
            runners[(name, step)] = launch

    def timed(launch, reps) -> float:
        if not device.is_cuda:
            t0 = time.perf_counter()
            for _ in range(reps):
                launch()
            return 1e3 * (time.perf_counter() - t0) / reps
        e0, e1 = wp.Event(device, enable_timing=True), wp.Event(device, enable_timing=True)
        wp.record_event(e0)
        for _ in range(reps):
            launch()
        wp.record_event(e1)
        wp.synchronize_event(e1)
        return wp.get_event_elapsed_time(e0, e1) / reps

    for launch in runners.values():
        for _ in range(args.warmup):
            launch()
    wp.synchronize_device(device)
    samples = {key: [] for key in runners}
    for _ in range(args.repeats):
        for key, launch in runners.items():
            samples[key].append(timed(launch, args.reps_per_sample))
    for (name, step), vals in samples.items():
        row["variants"][name][step] = float(np.median(vals))
        row["variants"][name][step.replace("_ms", "_iqr_ms")] = float(np.subtract(*np.percentile(vals, [75, 25])))
    for name, r in renderers.items():
        if device.is_cuda and not args.eager:
            row["variants"][name]["overflowed"] = r.intersections_overflowed()

    # per-kernel GPU times of the eager forward + backward (Warp's CUDA activity timer)
    if device.is_cuda:
        for name, r in renderers.items():
            fn = step_fns(r)["forward_backward_ms"]
            with wp.ScopedTimer(name, print=False, synchronize=True, cuda_filter=wp.TIMING_KERNEL) as timer:
                for _ in range(args.profile_iters):
                    fn()
            cats: dict[str, float] = {}
            for res in timer.timing_results:
                cat = kernel_category(res.name.split()[-1])
                cats[cat] = cats.get(cat, 0.0) + res.elapsed / args.profile_iters
            row["variants"][name]["kernels_ms"] = cats

    # registers, spills (local bytes) and static shared memory of the compositing kernels
    if device.is_cuda:
        for name, r in renderers.items():
            pair = (
                (rast.rasterize_tiles, rast.rasterize_tiles_backward) if name == "fp32" else (r.k.forward, r.k.backward)
            )
            row["variants"][name]["resources"] = {
                step: resources(k, device) for step, k in zip(("raster_fwd", "raster_bwd"), pair, strict=True)
            }

    base = row["variants"]["fp32"]
    for entry in row["variants"].values():
        for step in ("forward_ms", "forward_backward_ms"):
            entry[step.replace("_ms", "_speedup")] = base[step] / entry[step]
    return row


def git_commit() -> str:
    commit = os.environ.get("RGS_COMMIT")
    if commit:
        return commit
    try:
        return subprocess.check_output(
            ["git", "rev-parse", "--short", "HEAD"], text=True, stderr=subprocess.DEVNULL
        ).strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default=None, help="cuda:0 (default when a GPU is present) or cpu")
    parser.add_argument("--gaussians", type=int, nargs="+", default=[300_000, 1_000_000])
    parser.add_argument("--width", type=int, default=1200)
    parser.add_argument("--height", type=int, default=680)
    parser.add_argument("--repeats", type=int, default=30, help="timing samples per variant and step")
    parser.add_argument("--reps-per-sample", type=int, default=3, help="launches averaged in one sample")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--profile-iters", type=int, default=5)
    parser.add_argument("--variants", nargs="+", default=[v.name for v in VARIANTS], choices=[v.name for v in VARIANTS])
    parser.add_argument("--eager", action="store_true", help="time eager launches instead of CUDA graph replays")
    parser.add_argument("--out", default=os.environ.get("OUT", "experiments/results"))
    args = parser.parse_args()

    t_start = time.time()
    wp.init()
    device = wp.get_device(args.device or ("cuda:0" if wp.get_cuda_device_count() else "cpu"))
    # the benchmark's camera: raster.py's (fx = fy = 600, centred principal point) scaled to the size
    s = args.width / 1200.0
    camera = Camera(
        fx=600.0 * s,
        fy=600.0 * s,
        cx=(args.width - 1) / 2,
        cy=(args.height - 1) / 2,
        width=args.width,
        height=args.height,
    )
    variants = [v for v in VARIANTS if v.name in args.variants]
    kernels = {v.name: make_kernels(v) for v in variants}

    # compile every module up front, in parallel on the GPU host (NVRTC runs one module per thread)
    t0 = time.time()
    modules = {k.module for ks in kernels.values() for k in vars(ks).values()}
    modules |= {proj.project_gaussians.module, rast.rasterize_tiles.module}
    if device.is_cuda:
        wp.force_load(device=device, modules=list(modules), block_dim=BLOCK, max_workers=min(16, os.cpu_count() or 1))
    compile_s = time.time() - t0
    print(f"{device.name}: {len(variants)} variants, modules loaded in {compile_s:.1f} s", flush=True)

    rows = []
    for n in args.gaussians:
        t0 = time.time()
        rows.append(bench_size(n, camera, variants, kernels, device, args))
        print(f"N = {n:,}: {time.time() - t0:.1f} s", flush=True)

    report = {
        "device": device.name,
        "commit": git_commit(),
        "warp": wp.config.version,
        "camera": {"width": camera.width, "height": camera.height, "fx": camera.fx},
        "timing": "graph replays (CUDA events)" if device.is_cuda and not args.eager else "eager",
        "repeats": args.repeats,
        "reps_per_sample": args.reps_per_sample,
        "tolerance": {"color_max_abs": TOL_MAX, "color_mean_abs": TOL_MEAN, "grad_rel": TOL_GRAD},
        "variants": {v.name: {k: getattr(v, k) for k in vars(v) if k != "name"} for v in variants},
        "module_load_s": compile_s,
        "rows": rows,
        "total_s": time.time() - t_start,
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "mixed_precision.json").write_text(json.dumps(report, indent=2))

    nan = float("nan")
    lines = [
        f"{device.name}; warp {wp.config.version}; commit {report['commit']}; {camera.width}x{camera.height}; "
        f"times: {report['timing']}, median of {args.repeats}",
        "",
        "| N | variant | fwd ms | x | fwd+bwd ms | x | raster fwd | raster bwd | proj | proj bwd "
        "| regs f/b | col max | col mean | depth max | g means | g sh | g opac | image |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        for name, e in row["variants"].items():
            err = e.get("error", {})
            km = e.get("kernels_ms", {})
            ok = "ref" if not err else ("ok" if err["image_ok"] else "FAIL")
            if err and not err["grads_ok"]:
                ok += " (grads FAIL)"
            cells = [f"{row['n']:,}", name, f"{e['forward_ms']:.3f}", f"{e['forward_speedup']:.3f}"]
            cells += [f"{e['forward_backward_ms']:.3f}", f"{e['forward_backward_speedup']:.3f}"]
            cells += [f"{km.get(c, nan):.3f}" for c in ("raster_fwd", "raster_bwd", "project", "project_bwd")]
            res = e.get("resources", {})
            cells.append("/".join(str(res.get(k, {}).get("registers", "-")) for k in ("raster_fwd", "raster_bwd")))
            cells += [f"{err.get(k, 0.0):.1e}" for k in ("color_max_abs", "color_mean_abs", "depth_max_abs")]
            cells += [f"{err.get(k, 0.0):.1e}" for k in ("grad_means_rel", "grad_sh_rel", "grad_opacity_logits_rel")]
            cells.append(ok)
            lines.append("| " + " | ".join(cells) + " |")
    (out / "mixed_precision_table.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"total {time.time() - t_start:.1f} s; JSON: {out / 'mixed_precision.json'}")


if __name__ == "__main__":
    main()
