"""The frame check at the library's boundary (``rgs_warp.frame_check``): every frame, the first one
included, is checked at ``SLAM.process``; a frame of the wrong shape, type or range is refused with
what to do, non-finite pixels are masked and counted, a frame with too little usable input is lost;
poses given to the SLAM must be rigid and finite.  Fuzzed through the check and through a whole SLAM."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from rgs_warp.config import load_config
from rgs_warp.slam import SLAM
from rgs_warp.types import Camera

W, H = 64, 48
CAMERA = Camera(fx=60.0, fy=60.0, cx=31.5, cy=23.5, width=W, height=H)
SMALL = ["device=cpu", "mapping.init_iters=10", "mapping.iters_per_frame=1", "tracking.iters=3"]


def _frame(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.random((H, W, 3), dtype=np.float32), np.full((H, W), 2.0, np.float32)


def _images(frame) -> tuple[np.ndarray, np.ndarray | None]:
    """A checked frame's images (device arrays) on the host."""
    return frame.rgb.numpy(), None if frame.depth is None else frame.depth.numpy()


def _transposed(rgb, depth):
    return np.ascontiguousarray(rgb.transpose(1, 0, 2)), depth


@pytest.mark.parametrize(
    "name, bad, message",
    [
        ("rgb transposed", _transposed, r"rgb: expected shape \(48, 64, 3\).*got \(64, 48, 3\): transposed"),
        ("rgb half-size", lambda r, d: (r[::2, ::2], d), r"32x24 images need a Camera of that size"),
        ("rgb uint8", lambda r, d: ((r * 255).astype(np.uint8), d), r"uint8 is not converted.*/ 255"),
        ("rgb 0-255 floats", lambda r, d: (r * 255, d), r"expected \[0, 1\] \(8-bit values\? divide by 255\)"),
        ("rgb RGBA", lambda r, d: (np.dstack([r, r[..., :1]]), d), r"drop the alpha channel"),
        ("depth transposed", lambda r, d: (r, np.ascontiguousarray(d.T)), r"depth: expected shape.*transposed"),
        ("depth uint16 mm", lambda r, d: (r, (d * 1000).astype(np.uint16)), r"uint16 is not converted.*metres"),
        ("depth HxWx3", lambda r, d: (r, np.dstack([d] * 3)), r"depth: expected shape \(48, 64\) .*got \(48, 64, 3\)"),
        ("depth negative", lambda r, d: (r, -d), r"3072 pixels are negative"),
        ("depth all zero", lambda r, d: (r, 0 * d), r"frame 0 cannot start the map: depth at 0 of 3072 pixels"),
        ("depth all NaN", lambda r, d: (r, np.full_like(d, np.nan)), r"frame 0 cannot start the map: depth at 0"),
        ("rgb 10 % NaN", lambda r, d: (np.where(np.arange(H)[:, None, None] < 5, np.nan, r), d), r"not finite"),
    ],
)
def test_first_frame_is_checked(name, bad, message):
    """8dc16f7 checked frames in the tracker only, which the first frame skips: a transposed, half-size
    or uint8 first frame built a map.  Now each is refused with what to do, and nothing changes."""
    slam = SLAM(load_config(SMALL), CAMERA, device="cpu")
    rgb, depth = bad(*_frame())
    with pytest.raises(ValueError, match=message):
        slam.process(rgb, depth)
    assert len(slam.poses) == 0 and len(slam.map) == 0 and len(slam.keyframes) == 0


def test_frame_check_masks_and_counts_nonfinite_pixels():
    from rgs_warp.frame_check import MAX_NONFINITE_RGB, MIN_VALID_DEPTH, FrameChecker

    check = FrameChecker(CAMERA, "cpu").check
    rgb, depth = _frame()
    clean = check(rgb, depth)
    clean_rgb, clean_depth = _images(clean)
    assert np.array_equal(clean_rgb, rgb) and np.array_equal(clean_depth, depth) and not clean.unusable  # as given
    assert (clean.nonfinite_rgb, clean.nonfinite_depth) == (0, 0)

    patch = rgb.copy()
    patch[10:12, 20:22] = np.nan  # a sensor's 2x2 dropout
    patch[30, 5, 1] = np.inf
    depth_holes = depth.copy()
    depth_holes[0, :7] = np.nan
    depth_holes[1, 0] = -np.inf
    out = check(patch, depth_holes)
    assert (out.nonfinite_rgb, out.nonfinite_depth, out.unusable) == (5, 8, "")
    out_rgb, out_depth = _images(out)
    assert np.isfinite(out_rgb).all() and np.isfinite(out_depth).all()
    # the nearest finite pixel's colour, and no depth there; the rest as given
    assert np.array_equal(out_rgb[30, 5], rgb[29, 5]) or np.array_equal(out_rgb[30, 5], rgb[30, 4])
    assert {tuple(out_rgb[10, 20])} <= {tuple(rgb[9, 20]), tuple(rgb[10, 19])}
    assert (out_depth[10:12, 20:22] == 0).all() and out_depth[30, 5] == 0 and (out_depth[:2, :7][0] == 0).all()
    untouched = np.ones((H, W), bool)
    untouched[10:12, 20:22] = untouched[30, 5] = untouched[0, :7] = untouched[1, 0] = False
    assert np.array_equal(out_rgb[untouched], rgb[untouched]) and np.array_equal(out_depth[untouched], depth[untouched])

    too_many = rgb.copy()
    too_many[: int(np.ceil(MAX_NONFINITE_RGB * H)) + 1] = np.nan
    assert "colour pixels" in check(too_many, depth).unusable
    sparse = np.zeros_like(depth)
    sparse.flat[: int(MIN_VALID_DEPTH * H * W) - 1] = 1.0
    assert "depth at 29 of 3072 pixels" in check(rgb, sparse).unusable
    assert not FrameChecker(CAMERA, "cpu", mode="mono").check(rgb, sparse).unusable  # mono ignores depth


def test_frame_check_device_arrays_agree_with_host():
    """wp.array frames are counted by a kernel and only copied to the host when something is off:
    the same outcome as the host check."""
    import warp as wp

    from rgs_warp.frame_check import FrameChecker

    check = FrameChecker(CAMERA, "cpu").check
    rgb, depth = _frame()
    as_wp = (wp.array(rgb, dtype=wp.vec3, device="cpu"), wp.array(depth, dtype=wp.float32, device="cpu"))
    out = check(*as_wp)
    assert out.rgb is as_wp[0] and out.depth is as_wp[1] and not out.unusable
    rgb[3, 3] = np.nan
    depth[4, 4] = np.inf
    host, device = check(rgb, depth), check(wp.array(rgb, dtype=wp.vec3), wp.array(depth, dtype=wp.float32))
    assert (host.nonfinite_rgb, host.nonfinite_depth) == (device.nonfinite_rgb, device.nonfinite_depth) == (1, 1)
    assert all(np.array_equal(a, b) for a, b in zip(_images(host), _images(device), strict=True))
    with pytest.raises(ValueError, match="8-bit values"):
        check(wp.array(rgb * 255, dtype=wp.vec3), wp.array(depth, dtype=wp.float32))
    with pytest.raises(ValueError, match=r"expected a \(48, 64\) wp.array of vec3f?.*got \(64, 48\)"):
        check(wp.zeros((W, H), dtype=wp.vec3), as_wp[1])
    with pytest.raises(ValueError, match="depth at 0 of 3072"):
        SLAM(load_config(SMALL), CAMERA, device="cpu").process(as_wp[0], wp.zeros((H, W), dtype=wp.float32))


def test_given_poses_must_be_rigid():
    slam = SLAM(load_config(SMALL), CAMERA, device="cpu")
    with pytest.raises(ValueError, match="T_WC: the rotation is not orthonormal"):
        slam.process(*_frame(), T_WC=np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="T_first_WC: expected a finite 4x4"):
        SLAM(load_config(SMALL), CAMERA, device="cpu", T_first_WC=np.full((4, 4), np.nan))


def test_frame_check_uploaded_numpy_frames_agree_with_host():
    """NumPy frames uploaded first and counted by the kernel (the default on CUDA devices, forced here
    on the CPU) get the host check's answers; a clean frame comes back as the checker's device arrays."""
    import warp as wp

    from rgs_warp.frame_check import FrameChecker

    host, uploaded = FrameChecker(CAMERA, "cpu", upload=False), FrameChecker(CAMERA, "cpu", upload=True)
    rgb, depth = _frame()
    out = uploaded.check(rgb, depth)
    assert isinstance(out.rgb, wp.array) and isinstance(out.depth, wp.array) and not out.unusable
    assert np.array_equal(out.rgb.numpy(), rgb) and np.array_equal(out.depth.numpy(), depth)
    rgb[3, 3] = np.nan
    depth[4, 4] = np.inf
    a, b = host.check(rgb, depth), uploaded.check(rgb, depth)
    assert (a.nonfinite_rgb, a.nonfinite_depth) == (b.nonfinite_rgb, b.nonfinite_depth) == (1, 1)
    assert all(np.array_equal(x, y) for x, y in zip(_images(a), _images(b), strict=True))
    for bad, message in (((rgb * 255, depth), "8-bit values"), ((rgb, -np.abs(depth)), "negative")):
        with pytest.raises(ValueError, match=message):
            uploaded.check(*bad)
    sparse = np.zeros_like(depth)
    assert uploaded.check(np.nan_to_num(rgb), sparse).unusable == host.check(np.nan_to_num(rgb), sparse).unusable != ""
    # float64 frames take the host path, which converts them, and are then staged as float32
    as_float64 = uploaded.check(np.nan_to_num(rgb).astype(np.float64), depth.astype(np.float64))
    assert np.array_equal(as_float64.rgb.numpy(), np.nan_to_num(rgb))


DTYPES = st.sampled_from([np.float32, np.float64, np.float16, np.uint8, np.uint16, np.int32, np.bool_, np.complex64])


SHAPES = st.one_of(
    st.just((H, W, 3)),
    st.just((W, H, 3)),
    hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=70),
)


def _image(shape, dtype):
    floats = st.one_of(st.floats(0, 1, width=32), st.sampled_from([np.nan, np.inf, -np.inf, -0.5, 255.0, 1.0005]))
    elements = floats if np.dtype(dtype).kind == "f" else None
    return hnp.arrays(dtype, shape, elements=elements)


@st.composite
def frames(draw):
    """Mostly (3 in 4) frames of the right shape and dtype with patches of NaN, inf, out-of-range and
    valid values, the others of any shape and dtype."""
    right = draw(st.sampled_from([True, True, True, False]))
    rgb_shape = (H, W, 3) if right else draw(SHAPES)
    depth_shape = (H, W) if right or draw(st.booleans()) else draw(SHAPES)
    rgb_dtype = np.float32 if right else draw(DTYPES)
    depth_dtype = np.float32 if right else draw(DTYPES)
    if right:
        rgb = np.full(rgb_shape, 0.5, np.float32)
        depth = np.full(depth_shape, draw(st.sampled_from([2.0, 2.0, 2.0, 0.0])), np.float32)
        for _ in range(draw(st.integers(0, 6))):  # patches of a special value, mostly small
            y, x = draw(st.integers(0, H - 1)), draw(st.integers(0, W - 1))
            h, w = (draw(st.sampled_from([1, 2, 3, 8, n])) for n in (H, W))
            target = draw(st.sampled_from(["rgb", "depth"]))
            value = draw(st.sampled_from([np.nan, np.nan, np.inf, -np.inf, 0.0, 0.0, 0.7, 2.0, -1.0, 1.5, 1e30]))
            (rgb if target == "rgb" else depth)[y : y + h, x : x + w] = value
        return rgb, depth
    return draw(_image(rgb_shape, rgb_dtype)), draw(_image(depth_shape, depth_dtype))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(frames())
def test_fuzz_frame_check(frame):
    """Whatever the frame, the check raises ValueError (a message, no other exception) or returns a
    frame of the camera's shape on the device, float32, finite, colour in [0, 1], depth >= 0, with its counts; a
    usable one has more than 1 % of its pixels with depth and at most 1 % of its colour filled.  Given
    as wp.arrays (where they can be), the frame gets the same answer from the device check."""
    import warp as wp

    from rgs_warp.frame_check import RANGE_TOL, FrameChecker

    def check(rgb, depth):
        try:
            return FrameChecker(CAMERA, "cpu").check(rgb, depth)
        except ValueError as e:
            return str(e)

    rgb, depth = frame
    out = check(rgb, depth)
    if rgb.shape == (H, W, 3) and depth.shape == (H, W) and rgb.dtype == depth.dtype == np.float32:
        on_device = check(wp.array(rgb, dtype=wp.vec3, device="cpu"), wp.array(depth, dtype=wp.float32, device="cpu"))
        if isinstance(out, str):
            assert on_device == out
        else:
            assert (on_device.nonfinite_rgb, on_device.nonfinite_depth) == (out.nonfinite_rgb, out.nonfinite_depth)
            assert on_device.unusable == out.unusable
            as_host, host = _images(on_device), _images(out)
            assert np.array_equal(as_host[0], host[0], equal_nan=True) and np.array_equal(as_host[1], host[1])
    if isinstance(out, str):
        assert out.startswith(("rgb:", "depth:")), out
        return
    assert isinstance(out.rgb, wp.array) and isinstance(out.depth, wp.array)
    out_rgb, out_depth = _images(out)
    assert out_rgb.shape == (H, W, 3) and out_depth.shape == (H, W)
    assert out_rgb.dtype == np.float32 and out_depth.dtype == np.float32
    assert out_depth.min() >= 0 and np.isfinite(out_depth).all()
    if not out.unusable:
        assert np.isfinite(out_rgb).all() and -RANGE_TOL <= out_rgb.min() and out_rgb.max() <= 1 + RANGE_TOL
        assert np.count_nonzero(out_depth) >= 0.01 * H * W and out.nonfinite_rgb <= 0.01 * H * W
    assert out.nonfinite_rgb == np.count_nonzero(~np.isfinite(np.asarray(rgb, np.float32)).all(axis=2))


@pytest.mark.slow
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(frames(), min_size=2, max_size=3))
def test_fuzz_slam_process(frame_list):
    """Frames from the same generator through a whole SLAM: ValueError or a result with a finite pose;
    the map stays finite."""
    slam = SLAM(load_config([*SMALL, "mapping.init_window=2"]), CAMERA, device="cpu")
    for rgb, depth in frame_list:
        try:
            result = slam.process(rgb, depth)
        except ValueError:
            continue
        assert np.isfinite(result.T_WC).all()
    assert all(np.isfinite(v).all() for v in slam.map.to_numpy().values())


def test_a_pose_with_nan_names_the_entry():
    """A NaN in a given pose is named, not reported as a shape the pose has (4 x 4)."""
    T = np.eye(4)
    T[1, 3] = np.nan
    with pytest.raises(ValueError, match=r"T_WC: .*non-finite entries: \[1, 3\] = nan$"):
        SLAM(load_config(SMALL), CAMERA, device="cpu").process(*_frame(), T_WC=T)
