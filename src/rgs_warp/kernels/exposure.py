"""Kernels of the keyframe exposure (issue 18's gauge, ``exposure.py``): the moments of a frame's
colours against the older keyframes' colours at the same surface points, each keyframe's brought to
the first keyframe's exposure, for the reduced-major-axis fit of the frame's exposure (g, b).
"""

import warp as wp

from rgs_warp.kernels.math import REDUCE_BLOCK, CameraParams, block_sum, vec6

wp.set_module_options({"enable_backward": False})

# Columns of the moment sums: count, sum x, sum y, sum x^2, sum y^2, sum x y (x: a keyframe's colour in
# the first keyframe's exposure, y: the frame's colour at the same point; one term per channel)
M_N = 0
M_X = 1
M_Y = 2
M_XX = 3
M_YY = 4
M_XY = 5
M_COLUMNS = 6

# A channel at or beyond these values may be clipped: its value says nothing about the exposure.
CLIP_LO = wp.constant(1.0 / 255.0)
CLIP_HI = wp.constant(254.0 / 255.0)


@wp.func
def _unclipped(c: wp.vec3):
    return wp.min(c) > CLIP_LO and wp.max(c) < CLIP_HI


@wp.kernel
def exposure_moments(
    # in: the frame (colour, measured depth, camera-to-world pose) and its camera
    rgb: wp.array2d(dtype=wp.vec3),
    depth: wp.array2d(dtype=wp.float32),
    T_WC: wp.mat44,
    cam: CameraParams,
    # in: the keyframe buffer's images and the reference keyframes (world-to-camera pose, slot, (g, b))
    kf_rgb: wp.array3d(dtype=wp.vec3),
    kf_depth: wp.array3d(dtype=wp.float32),
    ref_T_CW: wp.array(dtype=wp.mat44),
    ref_slot: wp.array(dtype=wp.int32),
    ref_exposure: wp.array(dtype=wp.vec2),
    n_refs: int,
    max_rel_depth: float,
    # out: columns M_* (zeroed beforehand)
    moments_out: wp.array(dtype=wp.float64),
):
    # A pixel with measured depth is a surface point; a reference keyframe sees the same point where
    # its own measured depth at the projection agrees within max_rel_depth (else it is occluded there).
    block, lane = wp.tid()
    i = block * REDUCE_BLOCK + lane
    width = rgb.shape[1]
    height = rgb.shape[0]
    s = vec6()
    if i < height * width:
        py = i // width
        px = i - py * width
        z = depth[py, px]
        c = rgb[py, px]
        if z > 0.0 and _unclipped(c):
            X_C = wp.vec4((float(px) - cam.cx) * z / cam.fx, (float(py) - cam.cy) * z / cam.fy, z, 1.0)
            X_W = T_WC @ X_C
            for r in range(n_refs):
                X_R = ref_T_CW[r] @ X_W
                zr = X_R[2]
                if zr > 0.0:
                    u = cam.fx * X_R[0] / zr + cam.cx
                    v = cam.fy * X_R[1] / zr + cam.cy
                    if u >= 0.0 and u <= float(width - 1) and v >= 0.0 and v <= float(height - 1):
                        slot = ref_slot[r]
                        # the nearest sample, not a bilinear one: interpolation smooths the reference,
                        # which the reduced major axis reads as a gain above 1 (+2 % a keyframe on the
                        # synthetic room at true poses, -0.2 % with the nearest)
                        ry = int(v + 0.5)
                        rx = int(u + 0.5)
                        d_ref = kf_depth[slot, ry, rx]
                        if d_ref > 0.0 and wp.abs(d_ref - zr) < max_rel_depth * zr:
                            c_ref = kf_rgb[slot, ry, rx]
                            if _unclipped(c_ref):
                                e = ref_exposure[r]
                                for ch in range(3):
                                    xr = (c_ref[ch] - e[1]) / e[0]
                                    s += vec6(1.0, xr, c[ch], xr * xr, c[ch] * c[ch], xr * c[ch])
    total = block_sum(s)
    if lane == 0:
        for k in range(M_COLUMNS):
            wp.atomic_add(moments_out, k, wp.float64(total[k]))
