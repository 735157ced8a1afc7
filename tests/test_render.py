"""Forward rasterizer stages against the dense float64 NumPy reference (tests/reference_render.py)."""

import numpy as np
import pytest
import warp as wp

from helpers_render import BACKGROUND, CAMERA, SMALL_CAMERA, T_WC, to_map
from reference_render import project_reference, random_scene, render_reference
from rgs_warp.geometry import invert_pose
from rgs_warp.kernels.projection import intersection_key_layout
from rgs_warp.render import Renderer, render
from rgs_warp.types import Camera, GaussianMap

TOL = 1e-4


def _check_images(result, ref):
    color, depth, alpha, _ = ref
    assert np.abs(result.color.numpy() - color).max() < TOL
    assert np.abs(result.depth.numpy() - depth).max() < TOL
    assert np.abs(result.alpha.numpy() - alpha).max() < TOL


@pytest.mark.parametrize("tiled", [True, False])
@pytest.mark.parametrize("n, seed, sh_degree", [(50, 0, 2), (150, 1, 3), (300, 2, 2), (120, 3, 0), (80, 4, 1)])
def test_forward_matches_dense_reference(device, tiled, n, seed, sh_degree):
    rng = np.random.default_rng(seed)
    scene = random_scene(rng, n, T_WC, sh_degree)
    ref = render_reference(scene, CAMERA, T_WC, BACKGROUND)
    # the scene must exercise coverage, saturation and empty pixels, or the test proves little
    assert 0.2 < ref[2].mean() < 0.95 and (ref[2] > 0.999).any() and ref[2].min() < 0.5
    result = Renderer(device, tiled=tiled).forward(to_map(scene, device), CAMERA, T_WC, BACKGROUND)
    _check_images(result, ref)


def test_partial_tiles_and_device_pose(device):
    """Image size not a multiple of 16, pose given as a device mat44 (camera-to-world)."""
    scene = random_scene(np.random.default_rng(5), 100, T_WC)
    ref = render_reference(scene, SMALL_CAMERA, T_WC, BACKGROUND)
    pose = wp.array([T_WC.astype(np.float32)], dtype=wp.mat44, device=device)
    result = Renderer(device).forward(to_map(scene, device), SMALL_CAMERA, pose, BACKGROUND)
    _check_images(result, ref)


def test_empty_map(device):
    gmap = GaussianMap(capacity=4, device=device)
    result = render(gmap, CAMERA, T_WC, background=BACKGROUND)
    assert result.num_intersections == 0
    np.testing.assert_array_equal(result.color.numpy(), np.broadcast_to(np.float32(BACKGROUND), (48, 64, 3)))
    assert not result.depth.numpy().any() and not result.alpha.numpy().any()


def test_renderer_reuse_grows_buffers(device):
    """One renderer, a small map then a larger one and another image size: buffers grow, results stay exact."""
    renderer = Renderer(device)
    for n, seed, cam in [(20, 6, CAMERA), (250, 7, CAMERA), (60, 8, SMALL_CAMERA)]:
        scene = random_scene(np.random.default_rng(seed), n, T_WC)
        result = renderer.forward(to_map(scene, device), cam, T_WC, BACKGROUND)
        _check_images(result, render_reference(scene, cam, T_WC, BACKGROUND))


def test_projection_stage(device):
    scene = random_scene(np.random.default_rng(9), 200, T_WC)
    gmap = to_map(scene, device)
    result = Renderer(device).forward(gmap, CAMERA, T_WC)
    mean2d, conic, opacity, color, z, valid = project_reference(scene, CAMERA, invert_pose(T_WC))
    radii = result.radii.numpy()[:200]
    xyod = result.xy_opacity_depth.numpy()[:200]
    kept = radii[:, 0] > 0
    # culled: behind the near plane, transparent, or reaching no pixel (off-image, or an ellipse between
    # tiles' pixels); kept: a subset of the valid ones
    assert not (kept & ~valid).any() and kept.sum() > 90
    assert (radii[scene["means"] @ invert_pose(T_WC)[2, :3] + invert_pose(T_WC)[2, 3] < 0.01] == 0).all()
    np.testing.assert_allclose(xyod[kept, :2], mean2d[kept], rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(xyod[kept, 2], opacity[kept], rtol=1e-5)
    np.testing.assert_allclose(xyod[kept, 3], z[kept], rtol=1e-5)
    # radius: extent of the ellipse where o G = 1/255 along each axis
    extent = np.sqrt(2 * np.log(255 * opacity[kept]))
    cov = np.linalg.inv(conic[kept])
    expected = np.ceil(extent[:, None] * np.sqrt(np.stack([cov[:, 0, 0], cov[:, 1, 1]], 1)))
    assert np.abs(radii[kept] - expected).max() <= 1
    # culling drops nothing visible: every valid Gaussian not kept stays below 1/255 on every pixel
    vv, uu = np.mgrid[0 : CAMERA.height, 0 : CAMERA.width]
    dropped = np.flatnonzero(valid & ~kept)
    assert len(dropped) > 0
    for i in dropped:
        dx, dy = mean2d[i, 0] - uu, mean2d[i, 1] - vv
        q = conic[i]
        power = -0.5 * (q[0, 0] * dx * dx + q[1, 1] * dy * dy) - q[0, 1] * dx * dy
        assert (opacity[i] * np.exp(power)).max() < 1 / 255


def _min_q(mean, conic, xs, ys):
    """The least d^T Q d (d = mean - p) over the points p of the grid xs x ys."""
    dx = mean[0] - xs[None, :]
    dy = mean[1] - ys[:, None]
    return (conic[0, 0] * dx * dx + 2 * conic[0, 1] * dx * dy + conic[1, 1] * dy * dy).min()


def test_binning_and_sort(device):
    """Each tile's list holds the projected Gaussians whose ellipse o G = 1/255 reaches the tile, sorted by
    depth: every one that is at least 1/255 at one of the tile's pixels (the compositing's rule, dense
    float64 reference), every one whose ellipse reaches the tile's rectangle of pixel centres (sampled
    every 1/8 px), none outside its radius box; elongated, tilted splats leave out most of their box."""
    scene = random_scene(np.random.default_rng(10), 150, T_WC)
    scene["log_scales"][::2, 0] += np.log(6.0)  # half of them stretched 6x along one axis: thin, tilted
    result = Renderer(device).forward(to_map(scene, device), CAMERA, T_WC)
    mean2d, conic, opacity, _, _, valid = project_reference(scene, CAMERA, invert_pose(T_WC))
    radii = result.radii.numpy()[:150]
    xyod = result.xy_opacity_depth.numpy()[:150]
    ranges = result.tile_ranges.numpy()
    ids = result.sorted_ids.numpy()[: result.num_intersections]
    tiles_x = (CAMERA.width + 15) // 16
    total = boxed = 0
    for tile in range(ranges.shape[0]):
        ty, tx = divmod(tile, tiles_x)
        lst = set(ids[ranges[tile, 0] : ranges[tile, 1]].tolist())
        total += len(lst)
        assert (np.diff(xyod[ids[ranges[tile, 0] : ranges[tile, 1]], 3]) >= 0).all()
        px = np.arange(16 * tx, min(16 * tx + 16, CAMERA.width), dtype=float)
        py = np.arange(16 * ty, min(16 * ty + 16, CAMERA.height), dtype=float)
        fine_x = np.linspace(16 * tx, 16 * tx + 15, 121)
        fine_y = np.linspace(16 * ty, 16 * ty + 15, 121)
        for i in range(150):
            in_box = (
                radii[i, 0] > 0
                and np.floor((xyod[i, 0] - radii[i, 0]) / 16) <= tx <= np.floor((xyod[i, 0] + radii[i, 0]) / 16)
                and np.floor((xyod[i, 1] - radii[i, 1]) / 16) <= ty <= np.floor((xyod[i, 1] + radii[i, 1]) / 16)
            )
            boxed += in_box
            if i in lst:
                assert in_box, (tile, i)
            if not valid[i]:
                continue
            extent2 = 2 * np.log(255 * opacity[i])
            if _min_q(mean2d[i], conic[i], px, py) <= extent2 * 0.999:  # a pixel the compositing keeps
                assert i in lst, (tile, i, "a pixel at 1/255 or more")
            if _min_q(mean2d[i], conic[i], fine_x, fine_y) <= extent2 * 0.999:
                assert i in lst, (tile, i, "the ellipse reaches the tile's pixel rectangle")
    assert total == result.num_intersections > 150
    assert total < 0.95 * boxed  # 320 of 358: the box alone would list them all


def test_intersection_keys_with_many_tiles(device):
    """At 1200x680 (3,225 tiles: 12 bits of the 32-bit keys for the tile, 20 for the depth) each tile's
    list holds its Gaussians in depth order over 0.03-300 m, except pairs closer than the keys' depth
    step (a relative 2^-15 here), which keep their index order; a pair twice that far apart is ordered."""
    cam = Camera(fx=600.0, fy=600.0, cx=599.5, cy=339.5, width=1200, height=680)
    depth_bits, _ = intersection_key_layout(((1200 + 15) // 16) * ((680 + 15) // 16))
    assert depth_bits == 20
    step = 2.0 ** -(depth_bits - 5)
    rng = np.random.default_rng(3)
    n = 400
    z = np.exp(rng.uniform(np.log(0.03), np.log(300.0), n))
    z[0] = z[1] = 2.0  # an exact tie
    z[2], z[3] = 2.0 * (1 + 0.3 * step), 2.0  # within one key step: either order
    z[4], z[5] = 3.0 * (1 + 2.5 * step), 3.0  # 2.5 steps apart: ordered by depth
    u = rng.uniform(50, 1150, n)
    v = rng.uniform(50, 630, n)
    u[:6] = v[:6] = 100.0
    # 20 more pairs, the deeper one first, 1.2 steps apart: ordered by depth whatever the octave
    z[6:46:2] = z[7:46:2] * (1 + 1.2 * step)
    u[6:46:2], v[6:46:2] = u[7:46:2], v[7:46:2]
    X = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], 1)
    scene = {
        "means": X,
        "quats": np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)),
        "log_scales": np.log(np.repeat(z[:, None] * 0.02, 3, 1)),  # about 12 px wide at every depth
        "opacity_logits": np.full(n, 2.0),
        "sh": rng.normal(0.0, 0.3, (n, 1, 3)),
    }
    result = Renderer(device).forward(to_map(scene, device), cam, np.eye(4))
    ranges = result.tile_ranges.numpy()
    ids = result.sorted_ids.numpy()[: result.num_intersections]
    pairs = 0
    for tile in range(ranges.shape[0]):
        lst = ids[ranges[tile, 0] : ranges[tile, 1]]
        za, zb = z[lst[:-1]], z[lst[1:]]
        out_of_order = zb < za
        pairs += len(za)
        # a pair out of depth order lies within one key step, and then in index order
        assert (za[out_of_order] - zb[out_of_order] <= za[out_of_order] * step).all(), tile
        assert (lst[1:][out_of_order] > lst[:-1][out_of_order]).all(), tile
    tile0 = (100 // 16) * ((1200 + 15) // 16) + 100 // 16
    first = list(ids[ranges[tile0, 0] : ranges[tile0, 1]])
    assert first.index(0) < first.index(1)  # a tie: index order
    assert first.index(5) < first.index(4)  # apart by more than a step: depth order
    tiles_x = (1200 + 15) // 16
    for k in range(7, 46, 2):
        tile = int(v[k] // 16) * tiles_x + int(u[k] // 16)
        listed = list(ids[ranges[tile, 0] : ranges[tile, 1]])
        assert listed.index(k) < listed.index(k - 1), k
    assert pairs > 300


def test_intersection_key_layout():
    assert intersection_key_layout(12) == (28, 0)  # few tiles: the depth keeps every float bit
    assert intersection_key_layout(3225) == (20, 8)
    assert intersection_key_layout(2**16 - 1) == (16, 12)
    with pytest.raises(ValueError, match="65536 image tiles"):
        intersection_key_layout(2**16)


def test_intersection_capacity_and_overflow(device):
    """Capacity comes from the previous render's count; a render that needs more drops the excess,
    says so, and the next one grows the buffers and is exact again."""
    rng = np.random.default_rng(12)
    scene = random_scene(rng, 120, T_WC)
    gmap = to_map(scene, device)
    renderer = Renderer(device, isect_margin=1.1)
    first = renderer.forward(gmap, CAMERA, T_WC, BACKGROUND)  # no count to go by: sized exactly
    needed = first.num_intersections
    assert not first.overflowed and needed <= first.intersection_capacity <= 1.1 * needed + 2
    _check_images(first, render_reference(scene, CAMERA, T_WC, BACKGROUND))

    # same map size and camera, larger splats: the capacity from the previous count is too small
    big = dict(scene, log_scales=scene["log_scales"] + 0.7)
    big_map = to_map(big, device)
    ref = render_reference(big, CAMERA, T_WC, BACKGROUND)
    truncated = renderer.forward(big_map, CAMERA, T_WC, BACKGROUND)
    assert truncated.overflowed and renderer.intersections_overflowed()
    assert truncated.num_intersections > truncated.intersection_capacity == first.intersection_capacity
    assert np.abs(truncated.color.numpy() - ref[0]).max() > TOL
    again = renderer.forward(big_map, CAMERA, T_WC, BACKGROUND)
    assert not again.overflowed and again.intersection_capacity >= again.num_intersections
    _check_images(again, ref)

    # back to the small splats: the capacity shrinks (the sort covers all of it), results stay exact
    small = renderer.forward(gmap, CAMERA, T_WC, BACKGROUND)
    small = renderer.forward(gmap, CAMERA, T_WC, BACKGROUND)
    assert small.intersection_capacity < again.intersection_capacity and not small.overflowed
    _check_images(small, render_reference(scene, CAMERA, T_WC, BACKGROUND))

    # reserving ahead (as before capturing a graph) keeps the capacity until a count says otherwise
    renderer.reserve_intersections(10 * needed)
    assert renderer.intersection_capacity >= 10 * needed


def test_overflow_is_counted_and_view_keys_prevent_it(device):
    """A render sized by a previous view that saw little drops intersections; the next forward counts
    it (``overflowed_renders``).  With ``view`` keys each view is also sized by its own last render,
    so alternating between a sparse and a dense view no longer overflows, and the image is exact; so does
    a render with ``fit``, sized by its own count."""
    scene = random_scene(np.random.default_rng(11), 200, T_WC)
    gmap = to_map(scene, device)
    away = T_WC.copy()
    away[:3, :3] = T_WC[:3, :3] @ np.diag([-1.0, 1.0, -1.0])  # turned around: little in view
    ref = render_reference(scene, CAMERA, T_WC, BACKGROUND)
    renderer = Renderer(device)
    few = renderer.forward(gmap, CAMERA, away, BACKGROUND).num_intersections
    dropped = renderer.forward(gmap, CAMERA, T_WC, BACKGROUND)
    assert dropped.num_intersections > 2 * few and dropped.overflowed
    assert renderer.overflowed_renders == 0  # known at the next forward
    renderer.forward(gmap, CAMERA, away, BACKGROUND)
    assert renderer.overflowed_renders == 1
    # the same alternation with view keys: the first dense render overflows, later ones do not
    keyed = Renderer(device)
    for k in range(3):
        keyed.forward(gmap, CAMERA, away, BACKGROUND, view="away")
        result = keyed.forward(gmap, CAMERA, T_WC, BACKGROUND, view="dense")
        assert result.overflowed == (k == 0)
    _check_images(result, ref)
    keyed.forward(gmap, CAMERA, away, BACKGROUND, view="away")
    assert keyed.overflowed_renders == 1
    # fit=True: the dense render after the sparse one is sized by its own count, exact at once
    fitted = Renderer(device)
    fitted.forward(gmap, CAMERA, away, BACKGROUND)
    result = fitted.forward(gmap, CAMERA, T_WC, BACKGROUND, fit=True)
    assert not result.overflowed and result.intersection_capacity >= result.num_intersections > 2 * few
    _check_images(result, ref)
