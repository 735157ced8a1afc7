"""Synthetic sequences: determinism, multi-view consistency, depth on the mesh, file formats, texture."""

from __future__ import annotations

import json
import re

import cv2
import numpy as np
import plyfile
import pytest

from helpers_open3d import import_open3d
from rgs_warp.datasets.base import DatasetError
from rgs_warp.datasets.synthetic import SequenceRenderer, SyntheticConfig, SyntheticDataset, build_scene, write_sequence
from rgs_warp.datasets.synthetic import dataset as synthetic_dataset
from rgs_warp.datasets.synthetic.render import SceneRenderer
from rgs_warp.datasets.tum import TUMDataset, associate, read_tum_list
from rgs_warp.geometry import invert_pose, quat_to_matrix, rotation_angle_deg

SMALL = dict(width=96, height=54)


@pytest.fixture(scope="module")
def room(device):
    """room0 at the default 240x136, 100 frames; a few frames rendered once for several tests."""
    seq = SequenceRenderer(SyntheticConfig(scene="room0"), device)
    frames = {i: seq.render(i) for i in (30, 32, 60, 63, 90)}
    return seq, frames


def _raycasting_scene(o3d, seq: SequenceRenderer):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(seq.scene.positions.reshape(-1, 3).astype(np.float32)),
        o3d.core.Tensor(np.arange(seq.scene.positions.shape[0] * 3, dtype=np.uint32).reshape(-1, 3)),
    )
    return scene


def _backproject(depth: np.ndarray, cam, T_wc: np.ndarray) -> np.ndarray:
    v, u = np.mgrid[0 : depth.shape[0], 0 : depth.shape[1]].astype(np.float64)
    X = np.stack([(u - cam.cx) / cam.fx * depth, (v - cam.cy) / cam.fy * depth, depth], -1)
    return X @ T_wc[:3, :3].T + T_wc[:3, 3]


def _project(Xw: np.ndarray, cam, T_wc: np.ndarray):
    Xc = (Xw - T_wc[:3, 3]) @ T_wc[:3, :3]
    z = Xc[..., 2]
    return cam.fx * Xc[..., 0] / z + cam.cx, cam.fy * Xc[..., 1] / z + cam.cy, z


def _warp_error(rgb_i, rgb_j, u, v, mask) -> float:
    """Mean absolute difference between frame i and frame j sampled bilinearly at (u, v)."""
    warped = cv2.remap(rgb_j, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR)
    return float(np.abs(warped - rgb_i)[mask].mean())


@pytest.mark.slow  # each builds the scene again (1.5 s a renderer on the CPU)
def test_same_seed_same_arrays_other_seed_differs(device):
    cfg = SyntheticConfig(scene="office0", n_frames=20, exposure_drift=True, depth_noise_m=0.002, **SMALL)
    a, b = SequenceRenderer(cfg, device), SequenceRenderer(cfg, device)
    for i in (0, 7):
        (ra, da), (rb, db) = a.render(i), b.render(i)
        np.testing.assert_array_equal(ra, rb)
        np.testing.assert_array_equal(da, db)
    np.testing.assert_array_equal(a.poses, b.poses)
    c = SequenceRenderer(SyntheticConfig(**{**cfg.__dict__, "seed": 1}), device)
    rc, dc = c.render(7)
    assert np.abs(rc - ra).max() > 1e-3 and np.abs(dc - da).max() > 1e-3


@pytest.mark.slow  # each builds the scene again (1.5 s a renderer on the CPU)
def test_exposure_drift_is_an_affine_map_of_the_undrifted_image(device):
    base = SyntheticConfig(scene="office0", n_frames=30, **SMALL)
    drift = SyntheticConfig(**{**base.__dict__, "exposure_drift": 0.15})
    plain, drifted = SequenceRenderer(base, device), SequenceRenderer(drift, device)
    gains = drifted.exposure[:, 0]
    assert gains.std() > 0.02 and np.abs(np.diff(gains)).max() < 0.2  # drifts, but smoothly
    i = int(np.argmax(np.abs(gains - 1)))
    (r0, _), (r1, _) = plain.render(i), drifted.render(i)
    g, b = drifted.exposure[i]
    ok = (r1 > 0.01) & (r1 < 0.99)
    np.testing.assert_allclose(r1[ok], g * r0[ok] + b, atol=1e-5)


def test_warping_frame_j_into_i_reproduces_frame_i(room):
    seq, frames = room
    cam = seq.cfg.camera
    for i, j in ((30, 32), (60, 63)):
        (rgb_i, depth_i), (rgb_j, depth_j) = frames[i], frames[j]
        Xw = _backproject(depth_i, cam, seq.poses[i])
        u, v, z = _project(Xw, cam, seq.poses[j])
        inside = (u > 1) & (u < cam.width - 2) & (v > 1) & (v < cam.height - 2) & (depth_i > 0)
        seen_j = cv2.remap(depth_j, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR)
        visible = inside & (np.abs(seen_j - z) < 0.01 * z)  # not occluded in frame j
        # pixels on depth edges average two surfaces in colour but not in depth: leave them out
        edge = cv2.dilate(
            (cv2.morphologyEx(depth_i, cv2.MORPH_GRADIENT, np.ones((3, 3))) > 0.03 * depth_i).astype(np.uint8),
            np.ones((3, 3)),
        ).astype(bool)
        mask = visible & ~edge
        assert mask.mean() > 0.4

        no_motion = np.abs(rgb_j - rgb_i)[mask].mean()
        e = _warp_error(rgb_i, rgb_j, u, v, mask)
        assert e < 0.02, (i, j, e)
        assert e < no_motion / 4, (i, j, e, no_motion)
        assert e < 0.8 * _warp_error(rgb_i, rgb_j, u + 0.5, v, mask)  # sensitive to a half-pixel shift


def test_reprojection_agrees_with_an_independent_ray_cast(room):
    """Frame i's depth, reprojected into frame j at (u', v'): an Open3D ray through (u', v') from
    camera j must hit the same 3D point, and that point must project back onto frame i's pixel."""
    o3d = import_open3d()
    seq, frames = room
    cam = seq.cfg.camera
    rc = _raycasting_scene(o3d, seq)
    i, j = 60, 63
    depth_i = frames[i][1]
    Xw = _backproject(depth_i, cam, seq.poses[i])
    u, v, _ = _project(Xw, cam, seq.poses[j])
    inside = (u > 0) & (u < cam.width - 1) & (v > 0) & (v < cam.height - 1)
    uu, vv, X = u[inside], v[inside], Xw[inside]
    T = seq.poses[j]
    d = np.stack([(uu - cam.cx) / cam.fx, (vv - cam.cy) / cam.fy, np.ones_like(uu)], -1) @ T[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rays = np.concatenate([np.broadcast_to(T[:3, 3], d.shape), d], 1).astype(np.float32)
    t_hit = rc.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
    hit = T[:3, 3] + d * t_hit[:, None]
    same = np.linalg.norm(hit - X, axis=1) < 0.01  # else occluded in frame j
    assert same.mean() > 0.8
    ui, vi, _ = _project(hit[same], cam, seq.poses[i])
    v0, u0 = np.nonzero(inside)
    px_err = np.hypot(ui - u0[same], vi - v0[same])
    assert np.median(px_err) < 0.01 and np.percentile(px_err, 99) < 0.1, (np.median(px_err), px_err.max())


@pytest.mark.slow  # each builds the scene again (1.5 s a renderer on the CPU)
def test_depth_lies_on_the_ground_truth_mesh(tmp_path, device):
    o3d = import_open3d()
    ds = SyntheticDataset(
        "office0", n_frames=12, cache_root=tmp_path, device=device, prefetch=0, progress=False, **SMALL
    )
    ply = o3d.t.io.read_triangle_mesh(str(ds.mesh_path))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(ply)
    dists = []
    for k in (0, 5, 11):
        f = ds[k]
        X = _backproject(f.depth, ds.camera, f.pose_gt)[f.depth > 0]
        dists.append(scene.compute_distance(o3d.core.Tensor(X.astype(np.float32))).numpy())
    dists = np.concatenate(dists)
    assert np.median(dists) < 2e-4 and np.percentile(dists, 99.5) < 1e-3, np.percentile(dists, [50, 99.5, 100])


def test_replica_layout_files_and_cache(tmp_path, device, monkeypatch):
    kw = dict(n_frames=5, cache_root=tmp_path, device=device, progress=False, **SMALL)
    ds = SyntheticDataset("room0", **kw)
    root = ds.root
    assert len(ds) == 5 and ds.config.n_frames == 5 and ds.mesh_path == root / "mesh.ply"
    assert sorted(p.name for p in (root / "results").iterdir()) == [
        f"{kind}{i:06d}.{ext}" for kind, ext in (("depth", "png"), ("frame", "jpg")) for i in range(5)
    ]
    params = json.loads((root / "cam_params.json").read_text())
    assert params == {"camera": {"w": 96, "h": 54, "fx": 48.0, "fy": 48.0, "cx": 47.5, "cy": 26.5, "scale": 6553.5}}
    lines = (root / "traj.txt").read_text().splitlines()
    number = re.compile(r"^-?\d\.\d{18}e[+-]\d{2}$")
    assert len(lines) == 5 and all(
        len(ln.split(" ")) == 16 and all(number.match(t) for t in ln.split(" ")) for ln in lines
    )
    seq = SequenceRenderer(ds.config, device)
    rgb, depth = seq.render(3)
    raw = cv2.imread(str(root / "results" / "depth000003.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw.shape == (54, 96)
    np.testing.assert_array_equal(raw, np.round(depth.astype(np.float64) * 6553.5).astype(np.uint16))
    f = ds[3]
    np.testing.assert_allclose(f.depth, depth, atol=0.6 / 6553.5)
    assert np.abs(f.rgb - rgb).mean() < 0.02  # JPEG quality 95
    np.testing.assert_allclose(f.pose_gt, seq.poses[3], atol=1e-15)
    head = plyfile.PlyData.read(str(ds.mesh_path))
    assert head.text is False and head.byte_order == "<"
    assert [p.name for p in head["vertex"].properties] == ["x", "y", "z", "red", "green", "blue", "alpha"]
    assert head["face"]["vertex_indices"].shape[0] == seq.scene.positions.shape[0]

    # reused, not regenerated; an interrupted generation leaves nothing that would be reused
    def boom(*a, **k):
        raise RuntimeError("interrupted")

    monkeypatch.setattr(synthetic_dataset, "write_sequence", boom)
    assert SyntheticDataset("room0", **kw).root == root
    with pytest.raises(RuntimeError, match="interrupted"):
        SyntheticDataset("room0", **{**kw, "seed": 3})
    assert sorted(p.name for p in tmp_path.iterdir()) == [root.name]


@pytest.mark.slow  # each builds the scene again (1.5 s a renderer on the CPU)
def test_tum_layout_parses_and_associates(tmp_path, device):
    cfg = SyntheticConfig(scene="office0", n_frames=8, **SMALL)
    write_sequence(cfg, tmp_path, "tum", device=device, progress=False)
    t_rgb, rgb_rows = read_tum_list(tmp_path / "rgb.txt", 1)
    t_depth, depth_rows = read_tum_list(tmp_path / "depth.txt", 1)
    t_gt, gt_rows = read_tum_list(tmp_path / "groundtruth.txt", 7)
    assert len(t_rgb) == len(t_depth) == 8
    offsets = t_depth - t_rgb
    assert np.all(np.abs(offsets) <= 0.0125) and np.all(np.abs(offsets) > 0) and len(set(np.round(offsets, 6))) > 4
    np.testing.assert_array_equal(associate(t_rgb, t_depth, 0.02), np.arange(8))
    assert np.all(np.diff(t_gt) > 0) and t_gt[0] <= t_rgb[0] and t_gt[-1] >= t_rgb[-1]
    for text in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        assert (tmp_path / text).read_text().startswith("#")
    depth = cv2.imread(str(tmp_path / depth_rows[4][0]), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and depth.shape == (54, 96) and 0.5 < np.median(depth) / 5000.0 < 6.0
    assert cv2.imread(str(tmp_path / rgb_rows[4][0])).shape == (54, 96, 3)
    seq = SequenceRenderer(cfg, device)
    gt = np.array(gt_rows, float)
    k = int(np.argmin(np.abs(t_gt - t_rgb[4])))
    assert abs(t_gt[k] - t_rgb[4]) <= 0.005 + 1e-6
    np.testing.assert_allclose(np.linalg.norm(gt[:, 3:], axis=1), 1.0, atol=1e-6)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = quat_to_matrix(gt[k, 3:]), gt[k, :3]
    rel = invert_pose(T) @ seq.poses[4]
    assert np.linalg.norm(rel[:3, 3]) < 0.02 and rotation_angle_deg(rel[:3, :3]) < 1.0

    # The real loader reads the folder: camera from cam_params.json, depth / 5000, associated poses.
    ds = TUMDataset(tmp_path, max_dt=0.02)
    assert len(ds) == 8 and (ds.camera.width, ds.camera.height, ds.camera.cx) == (96, 54, cfg.cx or 47.5)
    np.testing.assert_allclose(ds[4].depth, depth.astype(np.float32) / 5000.0)
    np.testing.assert_allclose(ds[4].pose_gt, T, atol=1e-9)

    # Your own data: no groundtruth.txt, depth in millimetres (cam_params.json "scale": 1000), and for
    # monocular no depth at all.
    (tmp_path / "groundtruth.txt").unlink()
    with pytest.raises(DatasetError, match="require_pose=false"):
        TUMDataset(tmp_path, max_dt=0.02)
    for _, (name,) in zip(t_depth, depth_rows, strict=True):
        raw = cv2.imread(str(tmp_path / name), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(tmp_path / name), np.round(raw.astype(np.float64) / 5.0).astype(np.uint16))
    params = json.loads((tmp_path / "cam_params.json").read_text())
    params["camera"]["scale"] = 1000.0
    (tmp_path / "cam_params.json").write_text(json.dumps(params))
    own = TUMDataset(tmp_path, max_dt=0.02, require_pose=False)
    assert len(own) == 8 and own[4].pose_gt is None
    np.testing.assert_allclose(own[4].depth, depth.astype(np.float32) / 5000.0, atol=0.6e-3)
    (tmp_path / "depth.txt").unlink()
    mono = TUMDataset(tmp_path, max_dt=0.02, require_pose=False, require_depth=False)
    assert len(mono) == 8 and mono[4].depth is None
    with pytest.raises(DatasetError, match="depth.txt"):
        TUMDataset(tmp_path, max_dt=0.02, require_pose=False)


def test_images_have_texture_and_textureless_regions(room):
    _, frames = room
    for rgb, _ in frames.values():
        grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        grad = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1)) / 8
        assert (grad > 0.01).mean() > 0.3  # most of the image has structure a tracker can use
    flat_share = []
    for rgb, _ in frames.values():
        grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        mean = cv2.blur(grey, (9, 9))
        std = np.sqrt(np.maximum(cv2.blur(grey * grey, (9, 9)) - mean * mean, 0))
        flat_share.append((std < 0.004).mean())
    assert max(flat_share) > 0.1  # and some views have large plain areas


@pytest.mark.parametrize("name", ["room0", "office0"])
def test_trajectory_is_smooth_clear_of_obstacles_and_revisits(name, device):
    scene = build_scene(name)
    traj = scene.trajectory()
    t = np.linspace(0, traj.duration, 400)
    P = traj.poses(t)
    R = P[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    step_deg = np.array([rotation_angle_deg(a.T @ b) for a, b in zip(R[:-1], R[1:], strict=True)])
    step_m = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)
    assert step_deg.max() < 4.0 and step_m.max() < 0.04  # at 400 frames: no jumps anywhere
    assert np.abs(np.diff(step_deg)).max() < 0.5  # smooth angular speed
    assert step_deg.max() > 3 * np.median(step_deg)  # rapid turns as well as slow pans
    assert min(scene.clearance_m(p) for p in P[:, :3, 3]) > 0.5
    assert np.linalg.norm(P[-1, :3, 3] - P[0, :3, 3]) < 0.3 and rotation_angle_deg(R[0].T @ R[-1]) < 15
    renderer = SceneRenderer(scene, device, light_samples=1, ao_samples=1)
    cam = SyntheticConfig(width=48, height=27).camera
    for T in P[::8]:
        _, depth = renderer.render(cam, T[None], T, n_ss=0)
        assert depth.min() > 0 and np.percentile(depth, 5) > 0.4  # never staring at a wall up close
