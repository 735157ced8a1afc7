"""The viewer (``rgs_warp.app.view``): viser's camera against our pose and intrinsics, the hook's cost
without a browser, a simulated browser that receives rendered views, and (slow) a real headless
chromium driven by Playwright that shows the rendered map and follows a camera move."""

from __future__ import annotations

import math
import shutil
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from rgs_warp.config import load_config
from rgs_warp.geometry import invert_pose
from rgs_warp.slam import SLAM
from rgs_warp.types import Camera

viser = pytest.importorskip("viser", reason='the viewer needs viser: pip install "rgs_warp[viewer]"')
from viser import transforms as vtf  # noqa: E402  (viser's own SO(3), the reference)

from rgs_warp.app.view import (  # noqa: E402
    SimulatedClient,
    Viewer,
    look_at_pose,
    pose_from_viser,
    view_camera,
    viser_from_pose,
)

SH_C0 = 0.28209479177387814
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def tiny_slam(device, width: int = 160, height: int = 90) -> SLAM:
    """A SLAM whose map is a textured wall 2 m in front of the first camera (a checkerboard of
    coloured tiles under a gradient: every view of it differs), with a short trajectory and two
    keyframes; nothing tracked, nothing compiled but the renderer."""
    cfg = load_config([f"device={device}", f"dataset.width={width}", f"dataset.height={height}"])
    camera = Camera(0.8 * width, 0.8 * width, (width - 1) / 2, (height - 1) / 2, width, height)
    slam = SLAM(cfg, camera, device=device)
    ys, xs = np.mgrid[-1.0:1.0:48j, -1.6:1.6:80j]
    n = xs.size
    means = np.stack([xs.ravel(), ys.ravel(), np.full(n, 2.0)], axis=1)
    tile = (np.floor(xs / 0.4) + np.floor(ys / 0.4)).ravel() % 2
    colour = np.stack([0.2 + 0.6 * tile, 0.5 + 0.3 * xs.ravel() / 1.6, 0.5 - 0.4 * ys.ravel()], axis=1)
    sh = np.zeros((n, slam.map.num_sh, 3))
    sh[:, 0] = (colour - 0.5) / SH_C0
    quats = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    log_scales = np.log(np.tile([0.03, 0.03, 0.003], (n, 1)))
    slam.map.append(means, quats, log_scales, np.full(n, 4.0), sh)
    for k in range(6):
        T = np.eye(4)
        T[:3, 3] = [0.05 * k, 0.0, 0.0]
        slam.poses.append(T)
        slam.timestamps.append(float(k))
    slam.keyframe_indices = [0, 4]
    for i in slam.keyframe_indices:  # the panel shows the newest keyframe of a saved run
        rgb = np.clip(slam.render(slam.poses[i]).color.numpy(), 0.0, 1.0)
        slam.keyframes.add(i, slam.poses[i], rgb, np.full((height, width), 2.0, np.float32), (1.0, 0.0))
    return slam


# ---- cameras --------------------------------------------------------------------------------------
def test_viser_pose_round_trips_and_matches_viser_rotation():
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        wxyz = q / np.linalg.norm(q)
        position = rng.normal(size=3)
        T = pose_from_viser(wxyz, position)
        # viser's own SO(3) (its R_world_camera) is the reference rotation
        np.testing.assert_allclose(T[:3, :3], vtf.SO3(wxyz).as_matrix(), atol=1e-12)
        np.testing.assert_allclose(T[:3, 3], position)
        wxyz2, position2 = viser_from_pose(T)
        assert min(np.abs(wxyz2 - wxyz).max(), np.abs(wxyz2 + wxyz).max()) < 1e-9  # q and -q are one rotation
        np.testing.assert_allclose(pose_from_viser(wxyz2, position2), T, atol=1e-12)


def test_view_camera_projects_as_the_browser_camera():
    """A camera placed as viser places it (position, look-at point, up direction: z towards the
    look-at point, y down) sees the look-at point at the image centre, the up direction upwards and
    its right to the right; the vertical field of view spans the image height."""
    position, look_at, up = np.array([1.0, -2.0, 0.5]), np.array([0.0, 1.0, 0.2]), np.array([0.0, 0.0, 1.0])
    T_WC = look_at_pose(position, look_at, up)
    fov_y = math.radians(50.0)
    cam = view_camera(fov_y, 1200, 800, max_width=600)
    assert (cam.width, cam.height) == (600, 400)

    def project(p_world):
        p = invert_pose(T_WC) @ np.append(p_world, 1.0)
        return cam.fx * p[0] / p[2] + cam.cx, cam.fy * p[1] / p[2] + cam.cy

    u, v = project(look_at)
    assert abs(u - (cam.width - 1) / 2) < 1e-9 and abs(v - (cam.height - 1) / 2) < 1e-9
    forward = (look_at - position) / np.linalg.norm(look_at - position)
    assert project(look_at + 0.1 * up)[1] < v  # up is up in the image
    right = np.cross(forward, up)  # the viewer's right: forward x up in a right-handed world
    assert project(look_at + 0.1 * right)[0] > u
    # the top edge of the field of view lies on the image's top edge (pixel centres at integers: -0.5)
    d = np.linalg.norm(look_at - position)
    top = up - np.dot(up, forward) * forward
    edge = position + d * forward + d * math.tan(fov_y / 2) * top / np.linalg.norm(top)
    assert abs(project(edge)[1] - (-0.5)) < 1e-6


# ---- the hook ---------------------------------------------------------------------------------------
@pytest.fixture
def viewer():
    v = Viewer(port=0, host="127.0.0.1")
    yield v
    v.close()


def test_hook_without_a_browser_does_nothing(viewer, device, monkeypatch):
    slam = tiny_slam(device)

    def forbidden(*args, **kwargs):
        raise AssertionError("the viewer worked without a browser")

    for name in ("_render", "_update_scene", "_update_panel", "_update_views", "_update_counters"):
        monkeypatch.setattr(viewer, name, forbidden)
    rgb = np.zeros((90, 160, 3), dtype=np.float32)
    t0 = time.perf_counter()
    for _ in range(1000):
        viewer.update(slam, None, rgb, [None], 0)
    per_call_s = (time.perf_counter() - t0) / 1000
    assert viewer.stats.busy_updates == 0 and viewer.stats.views == 0
    assert per_call_s < 1e-4, per_call_s  # measured ~2 us on a shared 2-core CPU


def test_simulated_clients_receive_rendered_views(viewer, device):
    """Two browsers whose cameras keep moving both get their views (one render per update, the one
    waiting longest first)."""
    slam = tiny_slam(device)
    clients = [SimulatedClient(viewer.url, fps=20.0, width=320, height=180) for _ in range(2)]
    try:
        deadline = time.monotonic() + 30.0
        while min(c.views for c in clients) < 3 and time.monotonic() < deadline:
            viewer.update(slam)
            time.sleep(0.02)
        assert min(c.views for c in clients) >= 3, viewer.stats
        assert viewer.clients == 2 and viewer.stats.views >= 6 and viewer.stats.scenes >= 1
        assert viewer.stats.errors == 0
    finally:
        for c in clients:
            c.close()


def test_views_render_whole_after_a_smaller_view(device):
    """A view that needs more tile intersections than the viewer's previous one is rendered whole
    (``SLAM.render``, which the viewer renders with: the renderer drops what exceeds its capacity and
    grows it for the next render)."""
    from rgs_warp.render import Renderer

    slam = tiny_slam(device)
    camera = view_camera(math.radians(60.0), 320, 180, 320)
    far, near = np.eye(4), np.eye(4)
    far[2, 3], near[2, 3] = -8.0, 1.2
    slam.render(far, camera)
    got = slam.render(near, camera).color.numpy()
    np.testing.assert_allclose(got, Renderer(device).forward(slam.map, camera, near).color.numpy(), atol=1e-5)


def test_viewer_config_and_missing_viser(monkeypatch, capsys, tmp_path):
    from rgs_warp.app.cli import main
    from rgs_warp.app.view import require_viser
    from rgs_warp.config import ConfigError

    assert load_config(["viewer=true", "viewer_port=0"]).viewer
    with pytest.raises(ConfigError, match="viewer_port"):
        load_config(["viewer_port=70000"])
    monkeypatch.setitem(sys.modules, "viser", None)  # import viser now fails
    with pytest.raises(ImportError, match=r"pip install \"rgs_warp\[viewer\]\""):
        require_viser()
    assert main(["viewer=true", "cpu_sized=false", f"output_dir={tmp_path}"]) == 1  # refused before the run
    err = capsys.readouterr().err
    assert 'pip install "rgs_warp[viewer]"' in err and len(err.strip().splitlines()) == 1
    assert not list(tmp_path.iterdir())


def test_resume_may_turn_the_viewer_on(tmp_path):
    from rgs_warp.app.runner import resume_config
    from rgs_warp.config import ConfigError, save_config

    save_config(load_config([]), tmp_path / "config.yaml")
    (tmp_path / "checkpoint.json").write_text("{}")
    cfg = resume_config(tmp_path, ["viewer=true", "viewer_port=9000", "device=cuda:1"])
    assert (cfg.viewer, cfg.viewer_port, cfg.device) == (True, 9000, "cuda:1")
    with pytest.raises(ConfigError, match="viewer"):
        resume_config(tmp_path, ["viewer=sometimes"])


def test_view_command_refuses_what_is_not_a_run(tmp_path, capsys):
    from rgs_warp.app.view import main

    (tmp_path / "empty").mkdir()
    assert main([str(tmp_path / "empty"), "--port", "0", "--device", "cpu"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "map.ply: missing" in err and len(err.strip().splitlines()) == 1
    assert main([str(tmp_path / "nothing"), "--port", "0", "--device", "cpu"]) == 1
    assert capsys.readouterr().err == f"error: {tmp_path / 'nothing'}: no such folder\n"


@pytest.mark.slow
def test_live_run_feeds_the_viewer(tmp_path, device, monkeypatch, capsys):
    """``python -m rgs_warp.slam ... viewer=true`` with a (simulated) browser: the viewer opens before
    the run, its hook runs after every frame (the browser gets rendered views, the panel and the scene
    are drawn, log.jsonl has the hook's time), it keeps serving after the run until Ctrl-C, then
    closes."""
    import json

    import rgs_warp.app.view
    from rgs_warp.app.cli import main

    viewer = Viewer(port=0, host="127.0.0.1", panel_every_s=0.0, scene_every_s=0.0)
    client = SimulatedClient(viewer.url, fps=30.0, width=320, height=180)
    served, closed = [], []

    def serve(slam=None, stop=None, poll_s=0.02):
        served.append(viewer.slam)
        raise KeyboardInterrupt  # Ctrl-C while it serves the finished run

    monkeypatch.setattr(rgs_warp.app.view, "open_viewer", lambda port, host: viewer)
    monkeypatch.setattr(viewer, "serve", serve)
    monkeypatch.setattr(viewer, "close", lambda: closed.append(True))
    # a small run: 3 keyframes (the keyframe ATE needs 3), 2 tracked frames; accuracy is test_slam's business
    argv = ["dataset=synthetic/office0", "dataset.width=160", "dataset.height=90", "dataset.max_frames=5"]
    argv += ["mapping.init_window=3", "mapping.init_iters=9", "mapping.iters_per_frame=2", "tracking.iters=3"]
    argv += ["checkpoint_every=0", f"device={device}", f"output_dir={tmp_path}", "run_name=live", "viewer=true"]
    try:
        deadline = time.monotonic() + 20.0
        while viewer.clients == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert main(argv) == 0
        assert "still serving the run at " + viewer.url in capsys.readouterr().err
        assert len(served) == 1 and len(served[0].poses) == 5 and closed == [True]
        log = [json.loads(line) for line in (tmp_path / "live" / "log.jsonl").read_text().splitlines()]
        assert len(log) == 5 and all("viewer_seconds" in e for e in log)
        assert viewer.stats.updates == 5 and viewer.stats.busy_updates == 5
        assert viewer.stats.views >= 1 and viewer.stats.panels >= 1 and viewer.stats.scenes >= 1
        assert client.views >= 1 and viewer.stats.errors == 0
    finally:
        client.close()
        Viewer.close(viewer)


# ---- a real browser -------------------------------------------------------------------------------------
def _image_from_png(png: bytes) -> np.ndarray:
    import cv2

    return cv2.imdecode(np.frombuffer(png, dtype=np.uint8), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32)


@pytest.mark.slow
def test_chromium_shows_the_rendered_map_and_follows_the_camera(device, tmp_path):
    """Headless chromium on the viewer's page: the canvas shows the map as our renderer drew it from
    the browser's camera (the page's pixels are the image the viewer sent: not a blank page, not one
    colour), and a mouse drag (viser's orbit controls) moves the camera, which brings a new render."""
    if CHROMIUM is None:
        pytest.skip("no chromium on this machine (Debian: apt-get install -y chromium); .ci/run installs it")
    playwright = pytest.importorskip("playwright.sync_api", reason="playwright not installed (the dev extra has it)")
    slam = tiny_slam(device)
    stop = threading.Event()
    with Viewer(port=0, host="127.0.0.1", max_width=480) as viewer:
        server = threading.Thread(target=viewer.serve, args=(slam, stop), daemon=True)
        server.start()
        try:
            with playwright.sync_playwright() as p:
                # software WebGL (SwiftShader): CI has no GPU
                args = [
                    "--no-sandbox",
                    "--disable-dev-shm-usage",
                    "--use-angle=swiftshader",
                    "--enable-unsafe-swiftshader",
                ]
                browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=args)
                try:
                    page = browser.new_page(viewport={"width": 960, "height": 600})
                    page.goto(viewer.url, timeout=30_000)
                    canvas = page.locator("canvas").first
                    canvas.wait_for(timeout=30_000)
                    before, sent = _wait_for_view(page, canvas, viewer, tmp_path / "before.png")
                    assert _varied(sent), "the rendered view is blank or one colour"
                    # drag across the canvas: the orbit controls turn the camera, the browser sends it,
                    # the viewer renders the new view
                    box = canvas.bounding_box()
                    x, y = box["x"] + 0.3 * box["width"], box["y"] + 0.6 * box["height"]
                    page.mouse.move(x, y)
                    page.mouse.down()
                    for k in range(1, 11):
                        page.mouse.move(x + 15 * k, y + 4 * k)
                    page.mouse.up()
                    after, _ = _wait_for_view(page, canvas, viewer, tmp_path / "after.png", unlike=before)
                    assert np.abs(after - before).mean() > 5.0
                    assert viewer.stats.errors == 0 and viewer.stats.panels >= 1 and viewer.stats.scenes >= 1
                finally:
                    browser.close()
        finally:
            stop.set()
            server.join(timeout=10)


def _varied(img: np.ndarray) -> bool:
    """Not blank and not one colour: the rendered wall's tiles and gradient."""
    return img.std(axis=(0, 1)).max() > 20.0 and len(np.unique((img // 32).reshape(-1, 3), axis=0)) >= 6


def _shows(page_img: np.ndarray, sent: np.ndarray) -> bool:
    """The page shows the sent view: where the view has the map, at least 60 % of the page's pixels are
    within 40 grey levels of it (the GUI panel and the frustums' lines cover the rest)."""
    import cv2

    h, w = page_img.shape[:2]
    view = cv2.resize(sent, (w, h), interpolation=cv2.INTER_LINEAR).astype(np.float32)
    mapped = view.max(axis=2) > 30
    close = np.abs(page_img - view).max(axis=2) < 40
    return mapped.mean() > 0.05 and close[mapped].mean() > 0.6


def _wait_for_view(page, canvas, viewer, path: Path, unlike: np.ndarray | None = None, timeout_s: float = 40.0):
    """The canvas once it shows the viewer's latest view (and, with ``unlike``, differs from it); the
    screenshot is kept at ``path``.  Returns (screenshot, the view) as float arrays."""
    deadline = time.monotonic() + timeout_s
    while True:
        png = canvas.screenshot(timeout=10_000)
        path.write_bytes(png)
        img = _image_from_png(png)
        sent = viewer.last_view
        if sent is not None and _shows(img, sent) and (unlike is None or np.abs(img - unlike).mean() > 5.0):
            return img, sent.astype(np.float32)
        if time.monotonic() > deadline:
            raise AssertionError(
                f"the page did not show the viewer's view within {timeout_s:.0f} s ({viewer.stats}; "
                f"last screenshot: {path})"
            )
        page.wait_for_timeout(250)


# ---- where it listens -------------------------------------------------------------------------------
def test_the_viewer_listens_on_this_machine_only_by_default():
    """viser's default, 0.0.0.0, served the run to every network the machine is on, with no access
    control; the viewer's default is the loopback address (the ssh tunnel it prints reaches it)."""
    from rgs_warp.config import Config

    with Viewer(port=0) as viewer:
        assert viewer.server.get_host() == "127.0.0.1" and viewer.url.startswith("http://127.0.0.1:")
    assert Config().viewer_host == "127.0.0.1"


def test_open_viewer_warns_when_it_listens_beyond_this_machine(capsys):
    from rgs_warp.app.view import open_viewer

    with open_viewer(0) as viewer:
        err = capsys.readouterr().err
        assert "warning" not in err and f"ssh -L {viewer.port}:localhost:{viewer.port}" in err
    with open_viewer(0, "0.0.0.0") as viewer:
        err = capsys.readouterr().err
        assert f"warning: the viewer listens on 0.0.0.0: anyone who reaches this machine on port {viewer.port}" in err


def test_open_viewer_says_when_its_port_was_taken(capsys):
    """viser moves to the next free port without a word; the viewer names both."""
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        from rgs_warp.app.view import open_viewer

        with open_viewer(port) as viewer:
            assert viewer.port != port
            assert f"viewer: port {port} is in use; serving on port {viewer.port} instead" in capsys.readouterr().err


def test_the_command_prints_its_error_alone(tmp_path):
    # in a process of its own (Warp starts there): its start-up banner is not printed before the error
    import subprocess

    proc = subprocess.run(
        [sys.executable, "-m", "rgs_warp.view", str(tmp_path / "nothere")], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 1
    assert f"error: {tmp_path / 'nothere'}: no such folder" in proc.stderr
    printed = proc.stdout + proc.stderr
    assert "initialized" not in printed and "Kernel cache" not in printed, printed
