"""Kernels of the Seeder (supplement §4.5): per-seed Gaussian initialisation (Eq. 13-14, one
triangulated point per thread), and where seeds go: points the map already covers or that disagree
with the measured depth are dropped, and measured-depth seeds are taken where the map is missing.

Views are indexed as in the Triangulator: view 0 is the reference, view v its neighbour v - 1, and
bit v of a point's support mask says that view was used.  ``view_T_CW`` holds their world-to-camera
poses, ``view_slot`` their keyframe-buffer slots, ``view_exposure`` their (g, b) of Eq. 3.
"""

import warp as wp

from rgs_warp.kernels.math import SH_C0, CameraParams, bilerp, bilinear_corner, grey_level, hash_lattice

wp.set_module_options({"enable_backward": False})

# Support masks are int32 bit sets (Triangulator: at most 30 neighbours + the reference).
MAX_VIEWS = 32
vec_views = wp.types.vector(length=MAX_VIEWS, dtype=wp.float32)
# Opacity stays strictly inside (0, 1) so that its logit is finite.
OPACITY_EPS = wp.constant(1.0e-6)


@wp.struct
class SeedParams:
    cam: CameraParams  # intrinsics and image size
    poisson_radius_px: float
    plane_radius_px: float
    plane_min_neighbours: int
    tangential_scale: float
    min_residual_px: float
    axial_min_ratio: float
    axial_max_ratio: float
    alpha_min: float
    alpha_max: float


@wp.func
def to_camera(T_CW: wp.mat44, p: wp.vec3) -> wp.vec3:
    return wp.vec3(
        T_CW[0, 0] * p[0] + T_CW[0, 1] * p[1] + T_CW[0, 2] * p[2] + T_CW[0, 3],
        T_CW[1, 0] * p[0] + T_CW[1, 1] * p[1] + T_CW[1, 2] * p[2] + T_CW[1, 3],
        T_CW[2, 0] * p[0] + T_CW[2, 1] * p[1] + T_CW[2, 2] * p[2] + T_CW[2, 3],
    )


@wp.func
def camera_centre(T_CW: wp.mat44) -> wp.vec3:
    """C = -R^T t of a world-to-camera pose."""
    t = wp.vec3(T_CW[0, 3], T_CW[1, 3], T_CW[2, 3])
    return -wp.vec3(
        T_CW[0, 0] * t[0] + T_CW[1, 0] * t[1] + T_CW[2, 0] * t[2],
        T_CW[0, 1] * t[0] + T_CW[1, 1] * t[1] + T_CW[2, 1] * t[2],
        T_CW[0, 2] * t[0] + T_CW[1, 2] * t[1] + T_CW[2, 2] * t[2],
    )


# Where dropped points wait in the hash grid (``parked_point``): the hash lattice at this spacing
# (metres), behind the reference camera.
PARKED_SPACING = wp.constant(0.033)


@wp.func
def parked_point(T_CW: wp.mat44, i: int) -> wp.vec3:
    """Where dropped point ``i`` sits in the hash grid: behind the reference camera (z < 0 there), where
    no seed lies, on the hash lattice (``kernels/math.hash_lattice``)."""
    q = PARKED_SPACING * hash_lattice(i)
    q = wp.vec3(q[0], q[1], -1.0 - q[2])
    return camera_centre(T_CW) + wp.vec3(
        T_CW[0, 0] * q[0] + T_CW[1, 0] * q[1] + T_CW[2, 0] * q[2],
        T_CW[0, 1] * q[0] + T_CW[1, 1] * q[1] + T_CW[2, 1] * q[2],
        T_CW[0, 2] * q[0] + T_CW[1, 2] * q[1] + T_CW[2, 2] * q[2],
    )


@wp.func
def focal(prm: SeedParams) -> float:
    """One focal length for an isotropic footprint: the geometric mean keeps the pixel's area."""
    return wp.sqrt(prm.cam.fx * prm.cam.fy)


@wp.kernel
def seed_footprint(
    # in:
    X: wp.array(dtype=wp.vec3d),
    valid: wp.array(dtype=wp.int32),
    view_T_CW: wp.array(dtype=wp.mat44),
    prm: SeedParams,
    # out:
    points_out: wp.array(dtype=wp.vec3),
    footprint_out: wp.array(dtype=wp.float32),
    radius_out: wp.array(dtype=wp.float32),
    plane_radius_stats_out: wp.array(dtype=wp.float32),
):
    """World points in float32, the one-pixel footprint z / f at the reference view (metres per
    pixel, Eq. 13's tangential scale before its factor) and the Poisson-disk radius; footprint and
    radius 0 drop a point.  Accumulates (sum, count) of the plane-fit radii: the hash grid's next cell size."""
    i = wp.tid()
    p = wp.vec3(wp.float32(X[i][0]), wp.float32(X[i][1]), wp.float32(X[i][2]))
    z = to_camera(view_T_CW[0], p)[2]
    ok = valid[i] != 0 and z > wp.float32(0.0) and wp.isfinite(p)
    footprint = wp.where(ok, z / focal(prm), wp.float32(0.0))
    # Dropped points still sit in the hash grid: parked behind the reference camera, not at the world
    # origin, which may be inside the scene
    points_out[i] = wp.where(ok, p, parked_point(view_T_CW[0], i))
    footprint_out[i] = footprint
    radius_out[i] = prm.poisson_radius_px * footprint
    if ok:
        wp.atomic_add(plane_radius_stats_out, 0, prm.plane_radius_px * footprint)
        wp.atomic_add(plane_radius_stats_out, 1, wp.float32(1.0))


@wp.func
def plane_normal(
    grid: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    footprint: wp.array(dtype=wp.float32),
    k: int,
    prm: SeedParams,
    view_dir: wp.vec3,
) -> wp.vec3:
    """Normal of the plane fitted to the valid points within ``plane_radius_px`` footprints of
    point k (smallest eigenvector of their covariance), facing the reference camera; the direction
    to the camera when there are too few neighbours to define a plane."""
    p = points[k]
    radius = prm.plane_radius_px * footprint[k]
    # Offsets from p rather than raw coordinates: the covariance of a few-centimetre patch metres
    # away from the origin would otherwise lose its digits to cancellation in float32.
    s1 = wp.vec3(0.0)
    s2 = wp.mat33(0.0)
    n = int(0)
    for j in wp.hash_grid_query(grid, p, radius):
        if footprint[j] > wp.float32(0.0):
            d = points[j] - p
            if wp.length(d) < radius:
                s1 += d
                s2 += wp.outer(d, d)
                n += 1
    normal = view_dir
    if n >= prm.plane_min_neighbours:
        inv_n = wp.float32(1.0) / wp.float32(n)
        mean = s1 * inv_n
        Q, lam = wp.eig3(s2 * inv_n - wp.outer(mean, mean))
        # wp.eig3 returns eigenvalues unsorted, eigenvectors as columns
        c = int(0)
        if lam[1] < lam[c]:
            c = 1
        if lam[2] < lam[c]:
            c = 2
        normal = wp.normalize(wp.vec3(Q[0, c], Q[1, c], Q[2, c]))
    return wp.where(wp.dot(normal, view_dir) < wp.float32(0.0), -normal, normal)


@wp.func
def frame_from_normal(v: wp.vec3) -> wp.quat:
    """Rotation U = [t1, t2, v] (right-handed, columns) as a quaternion: local z maps to v."""
    a = wp.where(wp.abs(v[0]) < wp.float32(0.9), wp.vec3(1.0, 0.0, 0.0), wp.vec3(0.0, 1.0, 0.0))
    t1 = wp.normalize(wp.cross(a, v))
    t2 = wp.cross(v, t1)
    U = wp.mat33(t1[0], t2[0], v[0], t1[1], t2[1], v[1], t1[2], t2[2], v[2])
    return wp.normalize(wp.quat_from_matrix(U))


@wp.func
def axial_scale(
    z: float, residual_px: float, parallax_deg: float, views: int, cos_incidence: float, s_perp: float, prm: SeedParams
) -> float:
    """Eq. 13's s_parallel: the depth standard deviation of a triangulated point along the normal.

    The pixel noise is estimated from the RMS residual over V views: 2V coordinates fitted by 3
    unknowns leave E[rms^2] = (2V - 3) / (2V) sigma^2, floored at ``min_residual_px`` (the residual
    of a single point is a noisy estimate and is ~0 for two views that happen to agree).  A depth
    error dz moves the pixel of a view at angle theta by f tan(theta) dz / z, so
    sigma_z = z sigma_px / (f tan theta) along the ray; the surface moves by sigma_z cos(incidence)
    along its normal.  Clipped to [axial_min_ratio, axial_max_ratio] x s_perp: a flat disc at
    best, never a needle sticking out of the surface.
    """
    dof = wp.float32(2 * views - 3)
    sigma_px = wp.max(residual_px * wp.sqrt(wp.float32(2 * views) / wp.max(dof, wp.float32(1.0))), prm.min_residual_px)
    tan_parallax = wp.tan(wp.radians(wp.clamp(parallax_deg, wp.float32(1.0e-3), wp.float32(89.0))))
    sigma_z = z * sigma_px / (focal(prm) * tan_parallax)
    return wp.clamp(sigma_z * cos_incidence, prm.axial_min_ratio * s_perp, prm.axial_max_ratio * s_perp)


@wp.func
def bilinear(image: wp.array3d(dtype=wp.vec3), slot: int, u: float, v: float) -> wp.vec3:
    """Bilinear sample at (u, v), pixel centres at integer coordinates (types.py), in the image's
    sample grid [0, W-1] x [0, H-1] (the caller skips points outside it)."""
    x0, y0, fx, fy = bilinear_corner(u, v, image.shape[2], image.shape[1])
    return bilerp(
        image[slot, y0, x0], image[slot, y0, x0 + 1], image[slot, y0 + 1, x0], image[slot, y0 + 1, x0 + 1], fx, fy
    )


@wp.func
def sorted_insert(values: vec_views, count: int, x: float) -> vec_views:
    """Insert x into the ascending first ``count`` entries."""
    j = int(count)
    while j > 0:
        if values[j - 1] <= x:
            break
        values[j] = values[j - 1]
        j -= 1
    values[j] = x
    return values


@wp.func
def median_of_sorted(values: vec_views, count: int) -> float:
    """NumPy's median: the mean of the two middle entries for an even count."""
    lo = values[(count - 1) // 2]
    hi = values[count // 2]
    return wp.float32(0.5) * (lo + hi)


@wp.func
def median_colour(
    p: wp.vec3,
    support: int,
    rgb: wp.array3d(dtype=wp.vec3),
    view_T_CW: wp.array(dtype=wp.mat44),
    view_slot: wp.array(dtype=wp.int32),
    view_exposure: wp.array(dtype=wp.vec2),
    prm: SeedParams,
) -> wp.vec3:
    """Per-channel median over the supporting views of the exposure-corrected bilinear samples
    (I - b) / g at p's projection (Eq. 3 inverted, so every view speaks in the map's radiance);
    views where p falls outside the image or behind the camera are skipped."""
    r = vec_views()
    g = vec_views()
    b = vec_views()
    count = int(0)
    for v in range(view_T_CW.shape[0]):
        if (support >> v) & 1:
            x = to_camera(view_T_CW[v], p)
            if x[2] > wp.float32(0.0):
                cam = prm.cam
                px = cam.fx * x[0] / x[2] + cam.cx
                py = cam.fy * x[1] / x[2] + cam.cy
                inside_x = px >= wp.float32(0.0) and px <= wp.float32(cam.width - 1)
                if inside_x and py >= wp.float32(0.0) and py <= wp.float32(cam.height - 1):
                    e = view_exposure[v]
                    c = (bilinear(rgb, view_slot[v], px, py) - wp.vec3(e[1])) / e[0]
                    r = sorted_insert(r, count, c[0])
                    g = sorted_insert(g, count, c[1])
                    b = sorted_insert(b, count, c[2])
                    count += 1
    if count == 0:
        return wp.vec3(0.5)
    return wp.vec3(median_of_sorted(r, count), median_of_sorted(g, count), median_of_sorted(b, count))


@wp.kernel
def seed_gaussians(
    # in:
    grid: wp.uint64,
    indices: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    points: wp.array(dtype=wp.vec3),
    footprint: wp.array(dtype=wp.float32),
    residual_px: wp.array(dtype=wp.float64),
    parallax_deg: wp.array(dtype=wp.float64),
    support: wp.array(dtype=wp.int32),
    confidence: wp.array(dtype=wp.float32),
    rgb: wp.array3d(dtype=wp.vec3),
    view_T_CW: wp.array(dtype=wp.mat44),
    view_slot: wp.array(dtype=wp.int32),
    view_exposure: wp.array(dtype=wp.vec2),
    prm: SeedParams,
    row0: int,
    # out:
    means_out: wp.array(dtype=wp.vec3),
    rotations_out: wp.array(dtype=wp.quat),
    log_scales_out: wp.array(dtype=wp.vec3),
    opacity_logits_out: wp.array(dtype=wp.float32),
    sh_out: wp.array2d(dtype=wp.vec3),
    seed_index_out: wp.array(dtype=wp.int32),
):
    """Gaussian i of the compacted Poisson-disk seeds, written to map row ``row0 + i``; launched
    over an upper bound, threads past the device ``count`` return (no host read of it)."""
    i = wp.tid()
    if i >= count[0]:
        return
    k = indices[i]
    p = points[k]
    row = row0 + i
    T_ref = view_T_CW[0]
    to_cam = camera_centre(T_ref) - p
    z = to_camera(T_ref, p)[2]
    view_dir = wp.normalize(to_cam)
    normal = plane_normal(grid, points, footprint, k, prm, view_dir)

    # Eq. 13: s_perp from the one-pixel footprint, scaled to the Poisson-disk spacing so that
    # neighbouring seeds overlap into a closed surface; s_parallel from the depth uncertainty.
    s_perp = prm.tangential_scale * prm.poisson_radius_px * footprint[k]
    views = int(0)
    for v in range(view_T_CW.shape[0]):
        views += (support[k] >> v) & 1
    s_par = axial_scale(
        z,
        wp.float32(residual_px[k]),
        wp.float32(parallax_deg[k]),
        views,
        wp.abs(wp.dot(normal, view_dir)),
        s_perp,
        prm,
    )

    # Eq. 14, stored as a logit
    kappa = wp.clamp(confidence[k], wp.float32(0.0), wp.float32(1.0))
    alpha = wp.clamp(prm.alpha_min + (prm.alpha_max - prm.alpha_min) * kappa, OPACITY_EPS, 1.0 - OPACITY_EPS)

    colour = median_colour(p, support[k], rgb, view_T_CW, view_slot, view_exposure, prm)
    means_out[row] = p
    rotations_out[row] = frame_from_normal(normal)
    log_scales_out[row] = wp.vec3(wp.log(s_perp), wp.log(s_perp), wp.log(s_par))
    opacity_logits_out[row] = wp.log(alpha / (wp.float32(1.0) - alpha))
    # colour = SH + 0.5 with the DC basis C0 (types.py); higher bands start at zero (view-independent)
    sh_out[row, 0] = (colour - wp.vec3(0.5)) / wp.float32(SH_C0)
    for c in range(1, sh_out.shape[1]):
        sh_out[row, c] = wp.vec3(0.0)
    seed_index_out[i] = k


# ---- where seeds go: coverage by the map, agreement with measured depth, depth seeds ----------------
@wp.kernel
def depth_points(
    # in: keyframe depth (metres, 0 = invalid), pinhole intrinsics, camera-to-world pose
    depth: wp.array2d(dtype=wp.float32),
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    T_WC: wp.mat44d,
    stride: int,
    max_rel_jump: float,
    residual_px: float,
    parallax_deg: float,
    # in: the map's accumulated opacity at this keyframe (empty map: zeros) and the coverage bound
    alpha: wp.array2d(dtype=wp.float32),
    max_alpha: float,
    # out: one point per grid cell (the Triangulator's output layout, single view)
    X_out: wp.array(dtype=wp.vec3d),
    residual_out: wp.array(dtype=wp.float64),
    parallax_out: wp.array(dtype=wp.float64),
    support_out: wp.array(dtype=wp.int32),
    valid_out: wp.array(dtype=wp.int32),
):
    # RGB-D seeds: the pixel at the centre of each stride x stride cell, back-projected with its
    # measured depth, where the map does not cover the view yet (alpha < max_alpha) and the depth is
    # not on a discontinuity (neighbours at +-stride within max_rel_jump after a linear fit, i.e.
    # the second difference): a point straddling an edge would float between two surfaces.
    gy, gx = wp.tid()
    i = gy * (depth.shape[1] // stride) + gx
    u = gx * stride + stride // 2
    v = gy * stride + stride // 2
    z = depth[v, u]
    ok = z > 0.0 and alpha[v, u] < max_alpha
    if ok and u >= stride and u + stride < depth.shape[1] and v >= stride and v + stride < depth.shape[0]:
        zl = depth[v, u - stride]
        zr = depth[v, u + stride]
        zu = depth[v - stride, u]
        zd = depth[v + stride, u]
        ok = zl > 0.0 and zr > 0.0 and zu > 0.0 and zd > 0.0
        if ok:
            ok = wp.abs(zl + zr - 2.0 * z) < max_rel_jump * z and wp.abs(zu + zd - 2.0 * z) < max_rel_jump * z
    zd64 = wp.float64(z)
    pc = wp.vec4d(
        (wp.float64(u) - wp.float64(cx)) / wp.float64(fx) * zd64,
        (wp.float64(v) - wp.float64(cy)) / wp.float64(fy) * zd64,
        zd64,
        wp.float64(1.0),
    )
    pw = T_WC @ pc
    X_out[i] = wp.vec3d(pw[0], pw[1], pw[2])
    residual_out[i] = wp.float64(residual_px)
    parallax_out[i] = wp.float64(parallax_deg)
    support_out[i] = 1
    valid_out[i] = wp.where(ok, 1, 0)


@wp.kernel
def keep_detail_points(
    # in: the keyframe's colour, the fine grid's stride (depth_points' layout), the coarse grid's, and
    # the smallest grey-level gradient magnitude (per pixel) that counts as detail
    rgb: wp.array2d(dtype=wp.vec3),
    stride: int,
    coarse_stride: int,
    min_gradient: float,
    # in/out: the fine grid's points, invalidated on plain image or where the coarse grid has one
    valid: wp.array(dtype=wp.int32),
):
    # Detail seeds: a fine-grid point stays where the image changes (central differences of the grey
    # level, clamped at the border) and the coarse depth grid has no point at that pixel.
    gy, gx = wp.tid()
    width, height = rgb.shape[1], rgb.shape[0]
    i = gy * (width // stride) + gx
    u = gx * stride + stride // 2
    v = gy * stride + stride // 2
    on_coarse = u < (width // coarse_stride) * coarse_stride and v < (height // coarse_stride) * coarse_stride
    on_coarse = on_coarse and u % coarse_stride == coarse_stride // 2 and v % coarse_stride == coarse_stride // 2
    du = 0.5 * (grey_level(rgb[v, wp.min(u + 1, width - 1)]) - grey_level(rgb[v, wp.max(u - 1, 0)]))
    dv = 0.5 * (grey_level(rgb[wp.min(v + 1, height - 1), u]) - grey_level(rgb[wp.max(v - 1, 0), u]))
    if on_coarse or du * du + dv * dv < min_gradient * min_gradient:
        valid[i] = 0


@wp.func
def reference_pixel(coordinate: wp.float64, size: int):
    """The pixel index of an image coordinate (pixel centres at integers), clamped into the image."""
    return wp.clamp(int(wp.round(float(coordinate))), 0, size - 1)


@wp.func
def camera_depth(X: wp.vec3d, T_CW: wp.mat44d):
    """z of the world point X in the camera T_CW (metres, float32)."""
    return float((T_CW @ wp.vec4d(X[0], X[1], X[2], wp.float64(1.0)))[2])


@wp.kernel
def mask_covered_points(
    # in: reference-view pixels of the triangulated points and the map's render at the reference
    ref_uv: wp.array(dtype=wp.vec2d),
    alpha: wp.array2d(dtype=wp.float32),
    rendered_depth: wp.array2d(dtype=wp.float32),
    X: wp.array(dtype=wp.vec3d),
    T_CW: wp.mat44d,
    max_alpha: float,
    depth_rel_tol: float,
    # in/out: validity of each point
    valid: wp.array(dtype=wp.int32),
):
    # A new keyframe's seeds go where the map is missing: pixels it does not cover yet, or where the
    # map's surface (alpha-normalised depth) is off the triangulated point by more than depth_rel_tol.
    # Elsewhere the map already explains the keyframe and a seed would only double the density.
    i = wp.tid()
    if valid[i] == 0:
        return
    u = reference_pixel(ref_uv[i][0], alpha.shape[1])
    v = reference_pixel(ref_uv[i][1], alpha.shape[0])
    a = alpha[v, u]
    if a < max_alpha:
        return
    z = camera_depth(X[i], T_CW)
    d_map = rendered_depth[v, u] / a
    if wp.abs(d_map - z) > depth_rel_tol * z:
        return
    valid[i] = 0


@wp.kernel
def reject_depth_inconsistent_points(
    # in: reference-view pixels of the triangulated points and the reference keyframe's measured depth
    ref_uv: wp.array(dtype=wp.vec2d),
    measured_depth: wp.array2d(dtype=wp.float32),
    X: wp.array(dtype=wp.vec3d),
    T_CW: wp.mat44d,
    depth_rel_tol: float,
    # in/out: validity of each point
    valid: wp.array(dtype=wp.int32),
):
    # RGB-D: a triangulated point whose depth in the reference view is off the sensor's by more than
    # depth_rel_tol is a wrong match (or a low-parallax triangulation) and would seed a floater; the
    # measured-depth fill covers its pixel instead.  Pixels without a measurement keep their points.
    i = wp.tid()
    if valid[i] == 0:
        return
    u = reference_pixel(ref_uv[i][0], measured_depth.shape[1])
    v = reference_pixel(ref_uv[i][1], measured_depth.shape[0])
    d = measured_depth[v, u]
    if d <= 0.0:
        return
    if wp.abs(camera_depth(X[i], T_CW) - d) > depth_rel_tol * d:
        valid[i] = 0


@wp.kernel
def union_alpha(
    # in: accumulated opacities of two maps rendered at the same pose
    alpha_a: wp.array2d(dtype=wp.float32),
    alpha_b: wp.array2d(dtype=wp.float32),
    # out: the opacity of both together, 1 - (1 - a)(1 - b) (order-independent)
    alpha_out: wp.array2d(dtype=wp.float32),
):
    y, x = wp.tid()
    alpha_out[y, x] = 1.0 - (1.0 - alpha_a[y, x]) * (1.0 - alpha_b[y, x])


@wp.kernel
def extrapolate_depth_step(
    # in: depth (metres, 0 = none)
    depth: wp.array2d(dtype=wp.float32),
    # out: the same where it is set; elsewhere the largest of the 8 neighbours' (0 if none is set)
    depth_out: wp.array2d(dtype=wp.float32),
):
    # One step of carrying measured depth into the pixels without it (the colour border that the depth
    # camera does not see, shadows, glass, dark surfaces); n steps reach n pixels.  The farthest
    # neighbour wins: beside a foreground edge the missing depth is the background's (a depth camera's
    # shadow), and a seed put too far back is hidden by the surface in front, one put too near floats.
    y, x = wp.tid()
    d = depth[y, x]
    if d <= 0.0:
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                v = y + dy
                u = x + dx
                if v >= 0 and v < depth.shape[0] and u >= 0 and u < depth.shape[1]:
                    d = wp.max(d, depth[v, u])
    depth_out[y, x] = d
