"""Loaders against the real samples in ../shared/data, and their errors on bad input."""

import shutil

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rgs_warp.datasets import DatasetError, ReplicaDataset, SevenScenesDataset, TUMDataset
from rgs_warp.datasets.base import downscale_depth, reproject_depth
from rgs_warp.datasets.replica import read_matrix_lines
from rgs_warp.datasets.tum import TUM_CAMERAS, associate, read_tum_list
from rgs_warp.io.trajectory import write_tum_trajectory
from rgs_warp.types import Camera


@pytest.fixture(scope="module")
def replica_root(shared_data):
    return shared_data / "replica-office0-sample" / "office0"


def test_replica_sample_exact(replica_root):
    ds = ReplicaDataset(replica_root)
    assert len(ds) == 4  # the trajectory lists 2000 poses: frames are counted from the images
    cam = ds.camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (600.0, 600.0, 599.5, 339.5, 1200, 680)
    f = ds[0]
    assert f.rgb.shape == (680, 1200, 3) and f.rgb.dtype == np.float32
    assert 0.0 <= f.rgb.min() and f.rgb.max() <= 1.0
    raw = cv2.imread(str(replica_root / "results" / "depth000000.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(f.depth, raw.astype(np.float32) / np.float32(6553.5))
    first = np.array((replica_root / "traj.txt").read_text().splitlines()[0].split(), dtype=np.float64)
    np.testing.assert_array_equal(f.pose_gt, first.reshape(4, 4))
    assert f.pose_gt[0, 0] == pytest.approx(0.9062491181555123)
    last = ds[-1]
    assert last.index == 3 and last.timestamp == pytest.approx(3 / 30)


def _warp_error(src, dst, cam: Camera):
    """Median colour error of ``dst`` resampled into ``src``'s view with ``src``'s depth."""
    h, w = src.depth.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    z = src.depth
    valid = z > 0
    X_c = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], -1)
    T = np.linalg.inv(dst.pose_gt) @ src.pose_gt
    Y = X_c @ T[:3, :3].T + T[:3, 3]
    uu = cam.fx * Y[..., 0] / Y[..., 2] + cam.cx
    vv = cam.fy * Y[..., 1] / Y[..., 2] + cam.cy
    inside = valid & (Y[..., 2] > 0.1) & (uu > 1) & (uu < w - 2) & (vv > 1) & (vv < h - 2)
    warped = cv2.remap(dst.rgb, uu.astype(np.float32), vv.astype(np.float32), cv2.INTER_LINEAR)
    # Occlusion: the destination's own depth at the landing pixel must agree with the warped depth.
    zd = cv2.remap(dst.depth, uu.astype(np.float32), vv.astype(np.float32), cv2.INTER_NEAREST)
    visible = inside & (np.abs(zd - Y[..., 2]) < 0.05 * Y[..., 2])
    err = np.abs(warped - src.rgb).mean(-1)[visible]
    still = np.abs(dst.rgb - src.rgb).mean(-1)[visible]
    return float(np.median(err)), float(np.median(still)), visible.mean()


def test_replica_warp_consistency(replica_root):
    """Depth, poses (camera-to-world) and intrinsics agree: frame 1 warped into frame 0 reproduces it."""
    ds = ReplicaDataset(replica_root)
    err, still, frac = _warp_error(ds[0], ds[1], ds.camera)
    assert frac > 0.5
    assert err < 0.02 and err < 0.25 * still, (err, still)


def test_replica_warp_detects_wrong_convention(replica_root):
    """The same check fails with the poses read as world-to-camera: the test can tell."""
    ds = ReplicaDataset(replica_root)
    a, b = ds[0], ds[3]
    a.pose_gt, b.pose_gt = np.linalg.inv(a.pose_gt), np.linalg.inv(b.pose_gt)
    err_wrong, _, _ = _warp_error(a, b, ds.camera)
    a, b = ds[0], ds[3]
    err_right, _, _ = _warp_error(a, b, ds.camera)
    assert err_right < 0.5 * err_wrong


def test_sevenscenes_real(shared_data, tmp_path):
    root = shared_data / "7scenes-redkitchen"
    ds = SevenScenesDataset(root, register_depth=False)
    assert len(ds) == 500
    assert (ds.camera.fx, ds.camera.cx, ds.camera.width) == (585.0, 320.0, 640)
    f = ds[10]
    raw = cv2.imread(str(root / "frame-000010.depth.png"), cv2.IMREAD_UNCHANGED).astype(np.float32)
    raw[raw == 65535] = 0
    np.testing.assert_allclose(f.depth, raw / 1000.0, rtol=1e-6)
    np.testing.assert_allclose(f.pose_gt, np.loadtxt(root / "frame-000010.pose.txt"), atol=5e-4)
    # the file's rotation is orthonormal to ~2e-4 only; the loader returns the nearest rotation, which
    # a TUM trajectory writer (1e-6) accepts
    R_file = np.loadtxt(root / "frame-000000.pose.txt")[:3, :3]
    assert np.abs(R_file @ R_file.T - np.eye(3)).max() > 1e-5
    for T in (ds[0].pose_gt, f.pose_gt):
        assert np.abs(T[:3, :3] @ T[:3, :3].T - np.eye(3)).max() < 1e-12
    write_tum_trajectory(tmp_path / "gt.txt", np.arange(2.0), np.stack([ds[0].pose_gt, f.pose_gt]))
    sub = SevenScenesDataset(root, start=100, stride=20, max_frames=5, downscale=2, register_depth=False)
    assert len(sub) == 5 and sub[4].pose_gt is not None
    np.testing.assert_allclose(sub[4].pose_gt, np.loadtxt(root / "frame-000180.pose.txt"), atol=5e-4)
    assert sub[0].rgb.shape == (240, 320, 3) and sub[0].depth.shape == (240, 320)
    assert sub.camera.cx == pytest.approx(159.75)  # (320 + 0.5) / 2 - 0.5
    gt = sub.gt_poses()
    assert gt.shape == (5, 4, 4)


def test_reproject_depth_plane_and_occlusion():
    """reproject_depth against geometry worked out by hand: a fronto-parallel plane seen from a camera
    shifted sideways and with another focal length, and a near patch in front of it."""
    src = Camera(fx=100.0, fy=100.0, cx=39.5, cy=29.5, width=80, height=60)
    dst = Camera(fx=80.0, fy=80.0, cx=40.0, cy=31.0, width=80, height=60)
    offset = np.array([0.1, -0.05, 0.2])
    depth = np.full((60, 80), 2.0, dtype=np.float32)
    depth[25:35, 35:45] = 1.0  # a near patch
    out = reproject_depth(depth, src, dst, offset)
    # every target pixel whose ray meets the plane z = 2.2 (target coordinates) inside the source's view
    # and outside the patch's shadow sees 2.2; the patch's points (z = 1.2) win over the plane behind them
    v, u = np.mgrid[0:60, 0:80]

    def source_pixel(z_target):  # where the target pixel's ray meets the depth z_target, in the source image
        xs = (u - dst.cx) / dst.fx * z_target - offset[0]
        ys = (v - dst.cy) / dst.fy * z_target - offset[1]
        return src.fx * xs / (z_target - offset[2]) + src.cx, src.fy * ys / (z_target - offset[2]) + src.cy

    un, vn = source_pixel(1.2)  # the patch's depth in target coordinates
    near_ok = (un > 35.5) & (un < 43.5) & (vn > 25.5) & (vn < 33.5)
    near_margin = (un > 33) & (un < 46) & (vn > 23) & (vn < 36)
    uf, vf = source_pixel(2.2)  # the plane's
    shadow = (uf > 33) & (uf < 46) & (vf > 23) & (vf < 36)  # plane hidden from the source by the patch
    far_ok = (uf > 1) & (uf < 78) & (vf > 1) & (vf < 58) & ~shadow & ~near_margin
    assert far_ok.sum() > 1500 and near_ok.sum() > 20
    np.testing.assert_allclose(out[far_ok], 2.2, atol=1e-5)
    np.testing.assert_allclose(out[near_ok], 1.2, atol=1e-5)
    # the same camera and no offset give the image back
    np.testing.assert_array_equal(reproject_depth(depth, src, src, np.zeros(3)), depth)


def test_reproject_depth_rotation():
    """A quarter turn about the optical axis of a square camera maps pixel (u, v) to (39 - v, u)
    exactly: the depth image comes back rotated, each pixel's depth unchanged.  With a shift along
    the axis every depth grows by the shift."""
    cam = Camera(fx=50.0, fy=50.0, cx=19.5, cy=19.5, width=40, height=40)
    depth = np.random.default_rng(0).uniform(1.0, 3.0, (40, 40)).astype(np.float32)
    depth[5, 7] = 0.0  # no depth: nothing lands
    quarter = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # (x, y) -> (-y, x)
    out = reproject_depth(depth, cam, cam, np.zeros(3), rotation=quarter)
    v, u = np.mgrid[0:40, 0:40]
    expected = np.zeros_like(depth)
    expected[u, 39 - v] = depth[v, u]
    np.testing.assert_allclose(out, expected, rtol=1e-6)
    assert out[7, 39 - 5] == 0.0
    far = reproject_depth(depth, cam, cam, np.array([0.0, 0.0, 0.5]), rotation=np.eye(3))
    inner = far > 0
    assert inner.sum() > 300 and np.all(far[inner] >= 1.5 - 1e-6)


def test_sevenscenes_registration(shared_data):
    """The registered frames: the colour camera's calibration, ground truth moved to the colour camera
    (a surface point seen through the raw depth and the file's pose lands where the registered frame
    puts it), and depth discontinuities on colour edges (the measurement behind the calibration)."""
    root = shared_data / "7scenes-redkitchen"
    ds = SevenScenesDataset(root)
    raw = SevenScenesDataset(root, register_depth=False)
    assert (ds.camera.fx, ds.camera.cx, ds.camera.cy) == (526.0, 322.0, 238.0)
    f, g = ds[120], raw[120]
    np.testing.assert_allclose(f.pose_gt[:3, :3], g.pose_gt[:3, :3])
    assert np.linalg.norm(f.pose_gt[:3, 3] - g.pose_gt[:3, 3]) == pytest.approx(0.03, abs=1e-9)
    c, k = g.depth > 0, ds.camera
    v, u = np.nonzero(c)
    v, u = v[::97], u[::97]
    z = g.depth[v, u].astype(np.float64)
    pts = np.stack([(u - 320.0) / 585.0 * z, (v - 240.0) / 585.0 * z, z, np.ones_like(z)])
    world = g.pose_gt @ pts
    cam = np.linalg.inv(f.pose_gt) @ world
    uc, vc = k.fx * cam[0] / cam[2] + k.cx, k.fy * cam[1] / cam[2] + k.cy
    ui, vi = np.rint(uc).astype(int), np.rint(vc).astype(int)
    seen = f.depth[vi, ui] > 0
    assert seen.mean() > 0.97
    close = np.abs(f.depth[vi, ui][seen] - cam[2][seen]) < 0.01 * cam[2][seen]
    assert close.mean() > 0.97  # the rest lie behind a nearer surface at a discontinuity

    def edge_gradient(frame):  # mean colour gradient magnitude on the near side of depth jumps > 10 %
        grey = cv2.GaussianBlur(frame.rgb.mean(axis=-1).astype(np.float32), (5, 5), 1.0)
        grad = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1))
        d = frame.depth
        far = cv2.erode(np.where(d > 0, d, 100.0).astype(np.float32), np.ones((3, 3)))
        edge = (d > 0) & (cv2.dilate(d, np.ones((3, 3))) > 1.1 * d) & (d <= far + 1e-6)
        return grad[edge].mean()

    registered = np.mean([edge_gradient(ds[i]) for i in (0, 200, 400)])
    unregistered = np.mean([edge_gradient(raw[i]) for i in (0, 200, 400)])
    assert registered > 1.6 * unregistered


def test_sevenscenes_colour_distortion_undone(tmp_path):
    """A frame recorded through a lens with barrel distortion (``dataset.colour_distortion``): loaded with
    the lens's coefficients, the image is the pinhole camera's again; loaded without, its periphery is off."""
    k1 = -0.04
    fx, fy, cx, cy = 526.0, 526.0, 322.0, 238.0
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    v, u = np.mgrid[0:480, 0:640].astype(np.float32)
    pinhole = 0.5 + 0.4 * np.sin(u / 9.0) * np.cos(v / 7.0)  # what a pinhole camera sees, smooth texture

    # the recording: each recorded pixel q shows what the pinhole camera sees at undistort(q)
    q = np.stack([u.ravel(), v.ravel()], axis=1)[:, None, :].astype(np.float64)
    p = cv2.undistortPoints(q, K, np.array([k1, 0.0, 0.0, 0.0, 0.0]), P=K).reshape(480, 640, 2).astype(np.float32)
    recorded = cv2.remap(pinhole, p[..., 0], p[..., 1], cv2.INTER_LINEAR)
    cv2.imwrite(str(tmp_path / "frame-000000.color.png"), np.repeat(np.rint(recorded * 255)[..., None], 3, axis=2))
    cv2.imwrite(str(tmp_path / "frame-000000.depth.png"), np.full((480, 640), 2000, np.uint16))
    (tmp_path / "frame-000000.pose.txt").write_text(" ".join(map(str, np.eye(4).ravel())))

    inner = (slice(16, -16), slice(16, -16))
    fixed = SevenScenesDataset(tmp_path, colour_distortion=(k1, 0.0, 0.0, 0.0, 0.0))[0]
    as_is = SevenScenesDataset(tmp_path, colour_distortion=(0.0, 0.0, 0.0, 0.0, 0.0))[0]
    err_fixed = np.abs(fixed.rgb[..., 0] - pinhole)[inner].mean()
    err_as_is = np.abs(as_is.rgb[..., 0] - pinhole)[inner].mean()
    assert err_fixed < 0.01 and err_as_is > 5 * err_fixed
    np.testing.assert_array_equal(fixed.depth, as_is.depth)  # depth registration does not change
    with pytest.raises(DatasetError, match=r"dataset.colour_distortion \[1.0, 2.0, 3.0\]: expected OpenCV.s 4, 5, 8"):
        SevenScenesDataset(tmp_path, colour_distortion=(1.0, 2.0, 3.0))


def test_your_own_camera_lens_from_cam_params_is_undone(tmp_path):
    """A TUM-layout folder (your own data) whose cam_params.json gives the lens's coefficients: frames come
    undistorted onto the same K (OpenCV's undistort of the recorded image), the camera without distortion;
    the Replica layout (pinhole renders) refuses a lens, naming the file."""
    from helpers_tum import replica_with_cam_params, tiny_tum

    k = [-0.3, 0.1, 0.0, 0.0, 0.0]
    root = tiny_tum(tmp_path / "mine", camera={"distortion": k})
    plain = TUMDataset(tiny_tum(tmp_path / "plain"), require_pose=False)
    ds = TUMDataset(root, require_pose=False)
    assert ds.camera == plain.camera and not ds.camera.distortion
    K = ds.camera.K
    expected = cv2.undistort(plain[1].rgb, K, np.array(k))
    np.testing.assert_allclose(ds[1].rgb, expected, atol=1e-5)
    assert np.abs(ds[1].rgb - plain[1].rgb).mean() > 0.05  # the lens moved the pixels
    replica = replica_with_cam_params(tmp_path / "replica", root / "cam_params.json")
    with pytest.raises(DatasetError, match=rf"{replica / 'cam_params.json'}: gives a lens distortion"):
        ReplicaDataset(replica)


def test_prefetch_iteration_equals_indexing(shared_data):
    ds = SevenScenesDataset(shared_data / "7scenes-redkitchen", stride=50, prefetch=3)
    frames = list(ds)
    assert len(frames) == len(ds) == 10
    for i in (0, 4, 9):
        np.testing.assert_array_equal(frames[i].rgb, ds[i].rgb)
        assert frames[i].index == i


@pytest.mark.parametrize("prefetch", [0, 3])
def test_frames_reads_any_indices_in_order(shared_data, prefetch):
    """``frames(indices)`` (the evaluation's scored frames and keyframes) gives ``ds[i]`` for each index in
    the given order, repeats included, read ahead or not."""
    ds = SevenScenesDataset(shared_data / "7scenes-redkitchen", stride=50, prefetch=prefetch)
    order = [7, 0, 9, 3, 3, 1]
    frames = list(ds.frames(order))
    assert [f.index for f in frames] == order
    for f, i in zip(frames, order, strict=True):
        np.testing.assert_array_equal(f.rgb, ds[i].rgb)
        np.testing.assert_array_equal(f.depth, ds[i].depth)
    assert list(ds.frames([])) == []


def _make_tum(tmp_path, shared_data, n=3, dt_depth=0.01):
    root = tmp_path / "rgbd_dataset_freiburg1_test"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines, depth_lines, gt_lines = (
        ["# color images"],
        ["# depth maps"],
        ["# timestamp tx ty tz qx qy qz qw"],
    )
    for k in range(n):
        t = 1305031102.175304 + 0.2 * k
        shutil.copy(shared_data / "tum-frame" / "TUM_color.png", root / "rgb" / f"{t:.6f}.png")
        shutil.copy(shared_data / "tum-frame" / "TUM_depth.png", root / "depth" / f"{t + dt_depth:.6f}.png")
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{t + dt_depth:.6f} depth/{t + dt_depth:.6f}.png")
        gt_lines.append(f"{t - 0.004:.4f} {0.1 * k} 0.2 0.3 0 0 0.3826834 0.9238795")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    return root


def test_tum_real_frame(tmp_path, shared_data):
    root = _make_tum(tmp_path, shared_data)
    ds = TUMDataset(root, undistort=False)
    assert len(ds) == 3
    c = ds.camera
    assert (c.fx, c.fy, c.cx, c.cy) == (517.3, 516.5, 318.6, 255.3)
    f = ds[1]
    raw = cv2.imread(str(shared_data / "tum-frame" / "TUM_depth.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(f.depth, raw.astype(np.float32) / np.float32(5000.0))
    np.testing.assert_allclose(f.pose_gt[:3, 3], [0.1, 0.2, 0.3])
    np.testing.assert_allclose(f.pose_gt[:3, :3] @ [1, 0, 0], [np.sqrt(0.5), np.sqrt(0.5), 0], atol=1e-6)
    assert f.timestamp == pytest.approx(1305031102.175304 + 0.2)

    und = TUMDataset(root, undistort=True)
    assert und.camera.distortion == ()
    K, dist = TUM_CAMERAS["fr1"].K, np.array(TUM_CAMERAS["fr1"].distortion)
    expected = cv2.undistort(f.rgb, K, dist, None, K)
    inner = (slice(40, -40), slice(40, -40))
    assert np.abs(und[1].rgb[inner] - expected[inner]).mean() < 2e-3
    assert np.abs(und[1].rgb[inner] - f.rgb[inner]).mean() > 5e-3  # undistortion did something


def test_tum_association_tolerance(tmp_path, shared_data):
    root = _make_tum(tmp_path, shared_data, dt_depth=0.05)
    assert len(TUMDataset(root, max_dt=0.08, undistort=False)) == 3
    with pytest.raises(DatasetError, match="max_dt"):
        TUMDataset(root, max_dt=0.02, undistort=False)


def test_associate_one_to_one():
    t_ref = np.array([0.0, 1.0, 2.0, 3.0])
    np.testing.assert_array_equal(associate(np.array([0.1, 1.6, 2.95, 5.0]), t_ref, 0.5), [0, 2, 3, -1])
    # Two queries near the same reference: the closer one gets it, the other the next within range.
    np.testing.assert_array_equal(associate(np.array([1.1, 0.95]), t_ref, 0.2), [-1, 1])


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(0, 100, allow_nan=False), min_size=1, max_size=30),
    st.lists(st.floats(0, 100, allow_nan=False), min_size=1, max_size=30),
    st.floats(0, 5),
)
def test_associate_properties(tq, tr, tol):
    tq, tr = np.array(tq), np.array(tr)
    got = associate(tq, tr, tol)
    matched = got[got >= 0]
    assert len(set(matched.tolist())) == len(matched)  # one-to-one
    for q, g in zip(tq, got, strict=True):
        if g >= 0:
            assert abs(tr[g] - q) <= tol
        else:  # unmatched only if every reference within range went to a closer query
            near = np.flatnonzero(np.abs(tr - q) <= tol)
            assert all(j in matched for j in near)


@settings(max_examples=80, deadline=None)
@given(st.text(max_size=200))
def test_parsers_never_crash_with_bare_errors(tmp_path_factory, text):
    """Arbitrary file contents either parse or raise a DatasetError naming the file."""
    path = tmp_path_factory.mktemp("fuzz") / "f.txt"
    path.write_text(text)
    for parse in (lambda: read_matrix_lines(path), lambda: read_tum_list(path, 7)):
        try:
            parse()
        except DatasetError as e:
            assert str(path) in str(e)


def _copy_replica(src, dst, n=2):
    (dst / "results").mkdir(parents=True)
    for k in range(n):
        shutil.copy(src / "results" / f"frame{k:06d}.jpg", dst / "results")
        shutil.copy(src / "results" / f"depth{k:06d}.png", dst / "results")
    lines = (src / "traj.txt").read_text().splitlines()[:n]
    (dst / "traj.txt").write_text("\n".join(lines) + "\n")
    return lines


def test_errors_name_file_and_problem(tmp_path, replica_root):
    with pytest.raises(DatasetError, match="does not exist.*\n.*expected layout.*\n.*obtain it from"):
        ReplicaDataset(tmp_path / "nope")
    empty = tmp_path / "empty"
    (empty / "results").mkdir(parents=True)
    (empty / "traj.txt").write_text("")
    with pytest.raises(DatasetError, match="no frames found"):
        ReplicaDataset(empty)

    root = tmp_path / "r1"
    lines = _copy_replica(replica_root, root)
    (root / "traj.txt").write_text(lines[0] + "\n" + lines[1].replace(lines[1].split()[3], "nan", 1) + "\n")
    with pytest.raises(DatasetError, match=r"traj.txt:2: pose: non-finite values"):
        ReplicaDataset(root)
    (root / "traj.txt").write_text(lines[0] + "\n1 2 3\n")
    with pytest.raises(DatasetError, match=r"traj.txt:2: expected 16 numbers"):
        ReplicaDataset(root)
    (root / "traj.txt").write_text(lines[0] + "\n")
    with pytest.raises(DatasetError, match="1 poses for 2 images"):
        ReplicaDataset(root)

    root = tmp_path / "r2"
    _copy_replica(replica_root, root)
    jpg = root / "results" / "frame000001.jpg"
    jpg.write_bytes(jpg.read_bytes()[:5000])
    ds = ReplicaDataset(root)
    with pytest.raises(DatasetError, match=r"frame000001.jpg: truncated JPEG"):
        ds[1]
    png = root / "results" / "depth000000.png"
    png.write_bytes(png.read_bytes()[:300])
    with pytest.raises(DatasetError, match=r"depth000000.png: not a readable depth image"):
        ds[0]

    root = tmp_path / "r3"
    _copy_replica(replica_root, root)
    d = cv2.imread(str(root / "results" / "depth000000.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(root / "results" / "depth000000.png"), d[::2, ::2])
    with pytest.raises(DatasetError, match="depth is 600x340 but colour is 1200x680"):
        ReplicaDataset(root)[0]
    cv2.imwrite(str(root / "results" / "depth000001.png"), d.astype(np.uint8))
    with pytest.raises(DatasetError, match="16-bit depth PNG"):
        ReplicaDataset(root)[1]


def test_downscale_depth_keeps_edges_invalid():
    d = np.zeros((4, 4), np.float32)
    d[:, :2] = 1.0
    d[:, 2:] = 3.0
    d[0, 0] = 0.0  # one invalid pixel: the block mean uses the valid ones
    d[2, 1] = 3.0  # a block straddling an edge becomes invalid
    out = downscale_depth(d, 2)
    np.testing.assert_allclose(out, [[1.0, 3.0], [0.0, 3.0]])
