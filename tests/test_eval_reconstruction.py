"""Mesh metrics and TSDF fusion on the real Replica office0 ground-truth mesh."""

import copy

import cv2
import numpy as np
import pytest

from helpers_open3d import import_open3d
from rgs_warp.eval import depth_l1_cm, mesh_metrics, tsdf_fuse
from rgs_warp.types import Camera

o3d = import_open3d()  # every test here needs it: the module is skipped, with the reason, without it

REPLICA_CAMERA = Camera(fx=600.0, fy=600.0, cx=599.5, cy=339.5, width=1200, height=680)


@pytest.fixture(scope="module")
def replica(shared_data):
    folder = shared_data / "replica-office0-sample"
    mesh = o3d.io.read_triangle_mesh(str(folder / "office0_mesh.ply"))
    poses_c2w = np.loadtxt(folder / "office0" / "traj.txt").reshape(-1, 4, 4)
    return mesh, poses_c2w, folder


def _offset_along_normals(mesh: o3d.geometry.TriangleMesh, offset_m: float) -> o3d.geometry.TriangleMesh:
    out = copy.deepcopy(mesh)
    out.compute_vertex_normals()
    out.vertices = o3d.utility.Vector3dVector(np.asarray(out.vertices) + offset_m * np.asarray(out.vertex_normals))
    return out


def _render_depth_m(mesh, T_wc: np.ndarray, camera: Camera) -> np.ndarray:
    """Ground-truth depth through each pixel centre (u, v) (the project's convention, types.py)."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    # Camera-frame directions with z = 1, so the hit distance along them is the depth.
    dirs_c = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u, float)], -1)
    dirs_w = dirs_c @ T_wc[:3, :3].T
    rays = np.concatenate([np.broadcast_to(T_wc[:3, 3], dirs_w.shape), dirs_w], -1).astype(np.float32)
    depth_m = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return np.where(np.isfinite(depth_m), depth_m, 0.0).astype(np.float32)


def test_sample_floor_against_itself(replica):
    mesh, _, _ = replica
    n = 50_000
    m = mesh_metrics(mesh, mesh, n_samples=n)
    # Nearest neighbour in a uniform 2D sampling of density n / A lies 0.5 * sqrt(A / n) away on average.
    floor_cm = 100.0 * 0.5 * np.sqrt(mesh.get_surface_area() / n)
    assert m["acc_cm"] == pytest.approx(floor_cm, rel=0.05)
    assert m["comp_cm"] == pytest.approx(floor_cm, rel=0.05)
    assert m == mesh_metrics(mesh, mesh, n_samples=n)
    assert m != mesh_metrics(mesh, mesh, n_samples=n, seed=1)

    exact = mesh_metrics(mesh, mesh, n_samples=n, to_surface=True)
    assert exact["acc_cm"] < 1e-4 and exact["comp_cm"] < 1e-4
    assert exact["comp_ratio_pct"] == 100.0


def test_offset_copy_gives_the_offset(replica):
    mesh, _, _ = replica
    n = 20_000
    # Every point of the offset surface is a convex combination of vertices moved by 2 cm along unit
    # normals, so it lies at most 2 cm from the original; on the (mostly planar) room exactly 2 cm.
    shifted = _offset_along_normals(mesh, 0.02)
    exact = mesh_metrics(shifted, mesh, n_samples=n, to_surface=True)
    for key in ("acc_cm", "comp_cm"):
        assert 1.85 < exact[key] <= 2.0 + 1e-4, key
    assert exact["comp_ratio_pct"] == 100.0
    # Samples lie on the surface, so distances to samples can only be longer than to the surface.
    sampled = mesh_metrics(shifted, mesh, n_samples=n)
    assert sampled["acc_cm"] > exact["acc_cm"] and sampled["comp_cm"] > exact["comp_cm"]
    # The completion threshold: all 2 cm away, a few percent (corners, thin objects) under 1.5 cm.
    assert mesh_metrics(shifted, mesh, n_samples=n, threshold_m=0.0201, to_surface=True)["comp_ratio_pct"] == 100.0
    assert mesh_metrics(shifted, mesh, n_samples=n, threshold_m=0.015, to_surface=True)["comp_ratio_pct"] < 10.0


def test_rendered_depth_matches_real_frame(replica):
    # Checks this test's renderer (and so the conventions the TSDF test relies on) on real data.
    mesh, poses_c2w, folder = replica
    real_m = cv2.imread(str(folder / "office0" / "results" / "depth000000.png"), cv2.IMREAD_UNCHANGED) / 6553.5
    rendered_m = _render_depth_m(mesh, poses_c2w[0], REPLICA_CAMERA)
    assert depth_l1_cm(rendered_m, real_m) < 0.5
    shifted_pose = poses_c2w[0].copy()
    shifted_pose[:3, 3] += shifted_pose[:3, 0] * 0.05
    assert depth_l1_cm(_render_depth_m(mesh, shifted_pose, REPLICA_CAMERA), real_m) > 2.0


@pytest.mark.slow  # 7 s of open3d fusion on the CPU
def test_tsdf_of_rendered_depth_is_accurate(replica):
    mesh, poses_c2w, _ = replica
    camera = REPLICA_CAMERA.scaled(4)
    poses = poses_c2w[::250]
    depths_m = [_render_depth_m(mesh, T, camera) for T in poses]
    rec = tsdf_fuse(depths_m, poses, camera, voxel_m=0.01, trunc_m=0.04, max_depth_m=6.0)
    m = mesh_metrics(rec, mesh, n_samples=20_000, to_surface=True)
    # Measured 0.15 cm; a half-pixel error in the pixel-centre convention gives 0.54 cm, a wrong
    # pose convention metres.
    assert m["acc_cm"] < 0.3
    # Eight views see most of one room, not all of it.
    assert 30.0 < m["comp_ratio_pct"] < 100.0
    assert len(tsdf_fuse(depths_m[:1], poses[:1], camera, min_observations=2).triangles) == 0
    with pytest.raises(ValueError, match="does not match camera"):
        tsdf_fuse([depths_m[0][:-1]], poses[:1], camera)


@pytest.mark.slow
def test_mesh_export_of_a_saved_run(tmp_path, device):
    """``python -m rgs_warp.export RUN_DIR`` on a saved run: a coloured mesh.ply that Open3D reads back,
    on the ground-truth surface of the synthetic scene (to-surface accuracy, the metrics' code)."""
    from rgs_warp import SLAM, load_config, open_dataset
    from rgs_warp.app.export import main as export_main

    cfg = load_config(
        ["dataset=synthetic/office0", "dataset.width=160", "dataset.height=90", "dataset.max_frames=6"]
        + ["mapping.init_iters=60", "mapping.iters_per_frame=5", f"device={device}"]
    )
    ds = open_dataset(cfg, device="cpu")
    slam = SLAM(cfg, ds.camera, device=device)
    for f in ds:
        slam.process(f.rgb, f.depth, f.timestamp, T_WC=f.pose_gt)
    slam.finish()
    run_dir = slam.save(tmp_path / "run")
    assert export_main([str(run_dir), "--voxel-m", "0.02"]) == 0
    mesh = o3d.io.read_triangle_mesh(str(run_dir / "mesh.ply"))
    assert len(mesh.triangles) > 1000 and mesh.has_vertex_colors()
    colours = np.asarray(mesh.vertex_colors)
    assert colours.std(axis=0).min() > 0.05  # the scene's colours, not one flat colour
    metrics = mesh_metrics(mesh, o3d.io.read_triangle_mesh(str(ds.mesh_path)), n_samples=20_000, to_surface=True)
    assert metrics["acc_cm"] < 3.0, metrics
    assert export_main([str(tmp_path / "missing")]) == 1  # not a run folder: an error line, no traceback


def test_samples_do_not_depend_on_the_triangles_order():
    """Open3D's TSDF extraction lists the same triangles in another order from run to run; the same
    surface must give the same samples (and metrics), whatever the order of its triangles."""
    from rgs_warp.eval.reconstruction import sample_surface

    mesh = o3d.geometry.TriangleMesh.create_box(1.0, 2.0, 0.5)
    shuffled = copy.deepcopy(mesh)
    triangles = np.asarray(mesh.triangles)
    shuffled.triangles = o3d.utility.Vector3iVector(triangles[np.random.default_rng(3).permutation(len(triangles))])
    assert not np.array_equal(np.asarray(shuffled.triangles), triangles)
    a = sample_surface(mesh, 1000, np.random.default_rng(0))
    b = sample_surface(shuffled, 1000, np.random.default_rng(0))
    assert np.array_equal(a, b)
