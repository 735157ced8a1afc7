"""The viewer: a viser web page that shows the Gaussian map rendered by our own
``Renderer`` from the browser's camera, the estimated and ground-truth trajectories, the keyframe
frustums, the current frame beside its render and residual, and the run's counters.

    python -m rgs_warp.slam ... viewer=true          # live, during a run (then waits for Ctrl-C)
    python -m rgs_warp.view RUN_DIR [--port 8080]    # a saved run (--host: the address it listens on)

``Viewer.update(slam, result, rgb, gt_poses, lost_frames)`` is the run loop's hook, called after each
frame.  It does all the viewer's work itself, in the caller's thread, between two frames: the
browsers' camera callbacks (on viser's event loop) only record the camera, so nothing renders while
the SLAM changes the map.  With no browser connected it returns at once (no render, no copy).  With one,
it renders each browser's view at most ``max_fps`` times a second when its camera moved (and every
``refresh_s`` while the map changes), at most ``max_width`` pixels wide; the JPEG encoding and the
sending happen on a worker thread, and a view waits while the previous one is still being sent.
Trajectories and frustums are redrawn every ``scene_every_s``, the frame | render | residual panel
every ``panel_every_s`` (rendered at ``panel_width``).

Cameras: viser's are OpenCV's as ours (x right, y down, z forward; ``wxyz`` and ``position`` are the
camera-to-world rotation and translation) with a vertical field of view over the browser's canvas:
``pose_from_viser`` and ``view_camera`` turn them into our ``T_WC`` and ``Camera``.

``SimulatedClient`` stands in for a browser where there is none (the GPU bench, the fast tests): it
connects over viser's websocket, moves its camera every ``1 / fps`` seconds around where the server
put it, and counts the rendered views it receives.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import io
import math
import sys
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rgs_warp.app.progress import quiet_warp
from rgs_warp.geometry import matrix_to_quat, quat_to_matrix
from rgs_warp.types import Camera

INSTALL_HINT = 'pip install "rgs_warp[viewer]"'
LOCAL_HOST = "127.0.0.1"  # not viser's default 0.0.0.0, which serves every interface with no access control
LOOPBACK_HOSTS = (LOCAL_HOST, "localhost", "::1")
MIN_VIEW_PX = 16  # a browser canvas folded to nothing still gets an image the renderer can make


def require_viser():
    """The ``viser`` module, or an ImportError that says how to install it."""
    try:
        import viser
    except ImportError as e:
        raise ImportError(f"the viewer needs viser, which is not installed: {INSTALL_HINT}") from e
    return viser


# ---- cameras ---------------------------------------------------------------------------------------
def pose_from_viser(wxyz, position) -> np.ndarray:
    """Our 4x4 camera-to-world pose of a viser camera (``wxyz``: scalar-first unit quaternion of the
    camera-to-world rotation; both OpenCV axes, so no axis change)."""
    w, x, y, z = (float(v) for v in wxyz)
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(np.array([x, y, z, w]))
    T[:3, 3] = np.asarray(position, dtype=np.float64)
    return T


def viser_from_pose(T_WC: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz, position) of a camera-to-world pose, as viser's scene nodes and cameras take them."""
    x, y, z, w = matrix_to_quat(np.asarray(T_WC, dtype=np.float64)[:3, :3])
    return np.array([w, x, y, z]), np.asarray(T_WC, dtype=np.float64)[:3, 3].copy()


def view_camera(fov_y: float, width: int, height: int, max_width: int) -> Camera:
    """Intrinsics of a browser camera (vertical field of view ``fov_y`` in radians over a
    ``width`` x ``height`` canvas), scaled down to at most ``max_width`` pixels wide.  Square pixels,
    principal point at the image centre ((w - 1) / 2 with pixel centres at integers)."""
    scale = min(1.0, max_width / max(width, 1))
    w = max(MIN_VIEW_PX, round(width * scale))
    h = max(MIN_VIEW_PX, round(height * scale))
    f = 0.5 * h / math.tan(0.5 * fov_y)
    return Camera(f, f, (w - 1) / 2.0, (h - 1) / 2.0, w, h)


def scaled_camera(camera: Camera, width: int) -> Camera:
    """``camera`` resampled to ``width`` pixels wide (pixel centres at integers: c' = (c + 0.5) s - 0.5)."""
    s = min(1.0, width / camera.width)
    w, h = max(MIN_VIEW_PX, round(camera.width * s)), max(MIN_VIEW_PX, round(camera.height * s))
    sx, sy = w / camera.width, h / camera.height
    return Camera(camera.fx * sx, camera.fy * sy, (camera.cx + 0.5) * sx - 0.5, (camera.cy + 0.5) * sy - 0.5, w, h)


def to_uint8(image: np.ndarray) -> np.ndarray:
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


@dataclass
class _View:
    """A browser's camera as its last message gave it."""

    T_WC: np.ndarray
    fov_y: float
    width: int
    height: int
    stamp: float  # time.perf_counter() when it arrived


@dataclass
class ViewerStats:
    """What the viewer did: ``updates`` (hook calls), ``busy_updates`` (calls with a browser
    connected), ``views`` (browser views rendered and sent), ``panels``, ``scenes`` (trajectory and
    frustum redraws), ``errors`` (updates that failed: the first is printed, the run goes on) and
    ``seconds`` (time spent in ``update``, all calls)."""

    updates: int = 0
    busy_updates: int = 0
    views: int = 0
    panels: int = 0
    scenes: int = 0
    errors: int = 0
    seconds: float = 0.0


class Viewer:
    """A viser server showing a SLAM (live: ``update`` per frame; saved: ``serve``).

    ``port``: the server's port (0: a free one; viser takes the next free port when it is in use:
    ``url`` says which); ``host``: the address it listens on (default: this machine only).  The other
    arguments bound the work per ``update`` (module docstring)."""

    def __init__(
        self,
        port: int = 8080,
        host: str = LOCAL_HOST,
        max_width: int = 640,
        max_fps: float = 15.0,
        refresh_s: float = 1.0,
        scene_every_s: float = 0.5,
        panel_every_s: float = 1.0,
        panel_width: int = 320,
        frustum_scale_m: float = 0.1,
        jpeg_quality: int = 85,
    ):
        viser = require_viser()
        self.max_width, self.max_fps, self.refresh_s = max_width, max_fps, refresh_s
        self.scene_every_s, self.panel_every_s, self.panel_width = scene_every_s, panel_every_s, panel_width
        self.frustum_scale_m, self.jpeg_quality = frustum_scale_m, jpeg_quality
        with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: open_viewer says where it is
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.gui.configure_theme(control_width="large")
        self.stats = ViewerStats()
        # browsers' cameras, written by viser's event loop, read by update (one dict assignment each)
        self._views: dict[int, _View] = {}
        self._placed: set[int] = set()  # clients whose camera update() has placed at the SLAM
        self._rendered: dict[int, tuple[float, float, int]] = {}  # client -> (view stamp, when, frames)
        self._sender = ThreadPoolExecutor(max_workers=1, thread_name_prefix="rgs-viewer-send")
        self._sending: Future | None = None
        self.last_view: np.ndarray | None = None  # the last view sent (H x W x 3 uint8), for tests
        self._slam = None
        self._rgb = None
        self._result = None
        self._gt_poses: list = []
        self._lost = 0
        self._frame_times: collections.deque[float] = collections.deque(maxlen=30)
        self._scene_key, self._scene_at = None, -math.inf
        self._panel_key, self._panel_at = None, -math.inf
        self._counters_at = -math.inf
        self._keyframes_drawn: set[int] = set()
        with self.server.gui.add_folder("Run"):
            self._counters = {
                name: self.server.gui.add_text(name, "-", disabled=True)
                for name in ("frame", "frames/s", "Gaussians", "keyframes", "lost frames")
            }
        with self.server.gui.add_folder("Current frame"):
            blank = np.zeros((MIN_VIEW_PX, 3 * MIN_VIEW_PX, 3), dtype=np.uint8)
            self._panel = self.server.gui.add_image(blank, label="frame | render | residual (x4)", format="jpeg")
        self.server.on_client_connect(self._connected)
        self.server.on_client_disconnect(self._disconnected)

    # ---- viser's callbacks, on its event loop (in message order): record, never render ---------------
    async def _connected(self, client) -> None:
        client.camera.on_update(self._camera_moved)  # called for this first camera message too

    async def _disconnected(self, client) -> None:
        self._views.pop(client.client_id, None)
        self._placed.discard(client.client_id)
        self._rendered.pop(client.client_id, None)

    async def _camera_moved(self, camera) -> None:
        view = _View(
            pose_from_viser(camera.wxyz, camera.position),
            float(camera.fov),
            int(camera.image_width),
            int(camera.image_height),
            time.perf_counter(),
        )
        self._views[camera.client.client_id] = view

    # ---- public ----------------------------------------------------------------------------------
    @property
    def port(self) -> int:
        return self.server.get_port()

    @property
    def url(self) -> str:
        host = self.server.get_host()
        return f"http://{'localhost' if host in ('0.0.0.0', '::', '') else host}:{self.port}"

    @property
    def slam(self):
        """The SLAM shown: the last one ``update`` saw."""
        return self._slam

    @property
    def clients(self) -> int:
        """Browsers connected (that sent their camera)."""
        return len(self._views)

    def update(self, slam, result=None, rgb=None, gt_poses=None, lost_frames: int | None = None) -> None:
        """The run loop's hook after each frame: ``result`` the frame's ``FrameResult``, ``rgb`` its
        colour image (H x W x 3 in [0, 1]), ``gt_poses`` the ground-truth poses of the frames so far
        (None where unknown; the list is read, not copied), ``lost_frames`` the count so far.  Returns
        at once when no browser is connected.  Called without ``result``: the saved-run view (the panel
        shows the newest keyframe)."""
        t0 = time.perf_counter()
        self.stats.updates += 1
        self._slam = slam
        if result is not None:
            self._result, self._rgb = result, rgb
            self._frame_times.append(t0)
        if gt_poses is not None:
            self._gt_poses = gt_poses
        if lost_frames is not None:
            self._lost = lost_frames
        if not self._views:
            self.stats.seconds += time.perf_counter() - t0
            return
        self.stats.busy_updates += 1
        views = dict(self._views)
        try:
            self._place_new_clients(slam, views)
            if t0 - self._counters_at >= 0.25:
                self._counters_at = t0
                self._update_counters(slam)
            self._update_scene(slam, t0)
            self._update_panel(slam, t0)
            self._update_views(slam, views, t0)
        except Exception as e:  # noqa: BLE001 (what the viewer shows never stops the run)
            if not self.stats.errors:
                print(f"warning: viewer: {type(e).__name__}: {e} (the run goes on)", file=sys.stderr)
            self.stats.errors += 1
        self.stats.seconds += time.perf_counter() - t0

    def serve(self, slam=None, stop: threading.Event | None = None, poll_s: float = 0.02) -> None:
        """Keep showing ``slam`` (default: the last one ``update`` saw), answering camera moves,
        until ``stop`` is set (or Ctrl-C)."""
        slam = self._slam if slam is None else slam
        stop = stop or threading.Event()
        while not stop.wait(poll_s):
            self.update(slam)

    def close(self) -> None:
        self._sender.shutdown(wait=True)
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- the work with a browser connected -------------------------------------------------------
    def _place_new_clients(self, slam, views: dict[int, _View]) -> None:
        """A new browser's camera starts behind and above the newest pose, looking where it looks."""
        new = [cid for cid in views if cid not in self._placed]
        if not new or not slam.poses:
            return
        T = np.asarray(slam.poses[-1], dtype=np.float64)
        forward, up, centre = T[:3, 2], -T[:3, 1], T[:3, 3]
        # the camera's up, not the scene's (set_up_direction): a browser applies a new scene up after
        # the camera messages of the same batch, and then reports its camera in the other frame
        clients = self.server.get_clients()
        for cid in new:
            client = clients.get(cid)
            if client is None:
                continue
            client.camera.up_direction = up
            client.camera.position = centre - 0.5 * forward + 0.2 * up
            client.camera.look_at = centre + 1.5 * forward
            self._placed.add(cid)

    def _update_counters(self, slam) -> None:
        times = self._frame_times
        fps = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 and times[-1] > times[0] else None
        values = {
            "frame": str(len(slam.poses)),
            "frames/s": "-" if fps is None else f"{fps:.1f}",
            "Gaussians": f"{len(slam.map):,}",
            "keyframes": str(len(slam.keyframe_indices)),
            "lost frames": str(self._lost),
        }
        for name, value in values.items():
            if self._counters[name].value != value:
                self._counters[name].value = value

    def _update_scene(self, slam, now: float) -> None:
        """Trajectories (estimate orange, ground truth blue), keyframe frustums (green) and the current
        camera (red), when something changed and ``scene_every_s`` passed."""
        key = (len(slam.poses), len(slam.keyframe_indices), len(self._gt_poses))
        if key == self._scene_key or now - self._scene_at < self.scene_every_s or not slam.poses:
            return
        self._scene_key, self._scene_at = key, now
        self.stats.scenes += 1
        scene, cam = self.server.scene, slam.camera
        fov_y, aspect = 2.0 * math.atan(0.5 * cam.height / cam.fy), cam.width / cam.height
        poses = np.asarray(slam.poses, dtype=np.float64)
        self._draw_path("/trajectory/estimate", poses[:, :3, 3], (255, 110, 0))
        gt = [np.asarray(T)[:3, 3] for T in self._gt_poses if T is not None]
        if len(gt) >= 2:
            self._draw_path("/trajectory/ground_truth", np.array(gt), (0, 140, 255))
        for i in slam.keyframe_indices:
            if i in self._keyframes_drawn or i >= len(poses):
                continue
            wxyz, position = viser_from_pose(poses[i])
            scene.add_camera_frustum(
                f"/keyframes/{i:06d}",
                fov_y,
                aspect,
                scale=self.frustum_scale_m,
                thickness=1.5,
                thickness_units="screen",
                color=(40, 200, 60),
                wxyz=wxyz,
                position=position,
            )
            self._keyframes_drawn.add(i)
        wxyz, position = viser_from_pose(poses[-1])
        scene.add_camera_frustum(
            "/current",
            fov_y,
            aspect,
            scale=1.5 * self.frustum_scale_m,
            thickness=2.5,
            thickness_units="screen",
            color=(230, 30, 30),
            wxyz=wxyz,
            position=position,
        )

    def _draw_path(self, name: str, points: np.ndarray, color: tuple[int, int, int]) -> None:
        if len(points) < 2:
            return
        segments = np.stack([points[:-1], points[1:]], axis=1).astype(np.float32)
        self.server.scene.add_line_segments(name, segments, color, thickness=2.0, thickness_units="screen")

    def _render(self, slam, camera: Camera, T_WC: np.ndarray):
        """``slam.render``: with asynchronous mapping it renders the published map in tracking's turn,
        never the map the worker is writing."""
        return slam.render(T_WC, camera)  # whole even after a smaller view (SLAM.render renders again)

    def _update_panel(self, slam, now: float) -> None:
        """Frame | render | residual of the newest frame (live) or keyframe (saved run)."""
        if self._result is not None and self._rgb is not None:
            key, T_WC, rgb = self._result.index, self._result.T_WC, self._rgb
        elif len(slam.keyframes):
            slot = slam.keyframes.slots()[-1]
            key, T_WC, rgb = ("keyframe", int(slam.keyframes.frame_ids[slot])), slam.keyframes.poses[slot], None
        else:
            return
        if key == self._panel_key or now - self._panel_at < self.panel_every_s:
            return
        import cv2

        from rgs_warp.app.evaluate import error_image

        self._panel_key, self._panel_at = key, now
        self.stats.panels += 1
        if rgb is None:
            rgb = slam.keyframes.rgb[slot]
        rgb = rgb.numpy() if hasattr(rgb, "numpy") else np.asarray(rgb)
        camera = scaled_camera(slam.camera, self.panel_width)
        frame = cv2.resize(rgb.astype(np.float32), (camera.width, camera.height), interpolation=cv2.INTER_AREA)
        res = self._render(slam, camera, T_WC)
        render = np.clip(res.color.numpy(), 0.0, 1.0)
        error = error_image(render, frame, res.alpha.numpy())
        self._panel.image = to_uint8(np.concatenate([frame, render, error], axis=1))

    def _update_views(self, slam, views: dict[int, _View], now: float) -> None:
        """One browser's view per update, rendered when its camera moved (at most ``max_fps``) or, the
        map having changed, every ``refresh_s`` (of those due, the one waiting longest); none while
        the previous image is still being sent."""
        if self._sending is not None and not self._sending.done():
            return
        due = []
        for cid, view in views.items():
            stamp, at, frames = self._rendered.get(cid, (None, -math.inf, -1))
            if now - at < 1.0 / self.max_fps:
                continue
            if view.stamp != stamp or (frames != len(slam.poses) and now - at >= self.refresh_s):
                due.append((at, cid))
        if not due:
            return
        cid = min(due)[1]
        client, view = self.server.get_clients().get(cid), views[cid]
        if client is None:
            return
        camera = view_camera(view.fov_y, view.width, view.height, self.max_width)
        color = self._render(slam, camera, view.T_WC).color.numpy()
        if not slam.device.is_cuda:  # a CPU array's numpy() is a view of the buffer the next render reuses
            color = color.copy()
        self._rendered[cid] = (view.stamp, now, len(slam.poses))
        self.stats.views += 1
        self._sending = self._sender.submit(self._send, client, color)

    def _send(self, client, color: np.ndarray) -> None:
        """On the worker thread: the 8-bit conversion, the JPEG encoding (viser's) and the sending."""
        image = to_uint8(color)
        self.last_view = image
        if client.client_id not in self._views:  # it left meanwhile
            return
        client.scene.set_background_image(image, format="jpeg", jpeg_quality=self.jpeg_quality)
        client.flush()


def open_viewer(port: int, host: str = LOCAL_HOST) -> Viewer:
    """The viewer of ``viewer=true`` (``viewer_port``, ``viewer_host``), announced on the console: its
    URL, the port it took instead of a busy ``port``, and a warning when it listens beyond this machine."""
    viewer = Viewer(port=port, host=host)
    if port and viewer.port != port:
        print(f"viewer: port {port} is in use; serving on port {viewer.port} instead", file=sys.stderr)
    if host not in LOOPBACK_HOSTS:
        print(
            f"warning: the viewer listens on {host}: anyone who reaches this machine on port {viewer.port} sees "
            f"the run (no access control); viewer_host={LOCAL_HOST} keeps it to this machine",
            file=sys.stderr,
        )
    tunnel = f"ssh -L {viewer.port}:localhost:{viewer.port} HOST"
    print(f"viewer: {viewer.url} (open it in a browser; from another machine: {tunnel})", file=sys.stderr)
    return viewer


# ---- a browser stand-in ------------------------------------------------------------------------------
class SimulatedClient:
    """A viser client without a browser: a thread on viser's websocket that answers the server's
    camera placement, then moves its camera (a slow orbit around where it was put) every ``1 / fps``
    seconds, sending ``width`` x ``height`` as its canvas, and counts the background images (rendered
    views) it receives in ``views``.  ``close()`` ends it."""

    def __init__(self, url: str, fps: float = 30.0, width: int = 1280, height: int = 720, fov_deg: float = 60.0):
        viser = require_viser()
        from websockets.sync.client import connect

        self.views = 0
        self.fps, self.size, self.fov = fps, (width, height), math.radians(fov_deg)
        self._position, self._look_at, self._up = np.array([0.0, 0.0, -1.0]), np.zeros(3), np.array([0.0, -1.0, 0.0])
        self._ws = connect(url.replace("http", "ws", 1), subprotocols=[f"viser-v{viser.__version__}"], max_size=None)
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=f, daemon=True) for f in (self._receive, self._move)]
        for t in self._threads:
            t.start()

    def _receive(self) -> None:
        import msgspec
        import zstandard

        zstd = zstandard.ZstdDecompressor()
        while not self._stop.is_set():
            try:
                raw = self._ws.recv(timeout=0.1)
            except TimeoutError:
                continue
            except Exception:  # noqa: BLE001 (the server went away: nothing more to receive)
                return
            size, compressed = int.from_bytes(raw[:8], "little"), int.from_bytes(raw[8:16], "little")
            inner = msgspec.msgpack.decode(zstd.decompress(raw[16 : 16 + compressed], max_output_size=size))
            for message in inner["messages"]:
                kind = message["type"]
                if kind == "BackgroundImageMessage" and message.get("rgb_data") is not None:
                    self.views += 1
                elif kind == "SetCameraPositionMessage":
                    self._position = np.array(message["position"], dtype=np.float64)
                elif kind == "SetCameraLookAtMessage":
                    self._look_at = np.array(message["look_at"], dtype=np.float64)
                elif kind == "SetCameraUpDirectionMessage":
                    self._up = np.array(message["position"], dtype=np.float64)

    def _move(self) -> None:
        import msgspec

        t0 = time.perf_counter()
        while not self._stop.wait(1.0 / self.fps):
            angle = 0.2 * math.sin(time.perf_counter() - t0)  # radians about the up axis, through look_at
            T = look_at_pose(
                self._look_at + _rotate(self._position - self._look_at, self._up, angle), self._look_at, self._up
            )
            wxyz, position = viser_from_pose(T)
            message = {
                "type": "ViewerCameraMessage",
                "wxyz": [float(v) for v in wxyz],
                "position": [float(v) for v in position],
                "fov": self.fov,
                "near": 0.01,
                "far": 1000.0,
                "image_height": self.size[1],
                "image_width": self.size[0],
                "look_at": [float(v) for v in self._look_at],
                "up_direction": [float(v) for v in self._up],
            }
            try:
                self._ws.send(msgspec.msgpack.encode(message))
            except Exception:  # noqa: BLE001 (the server went away)
                return

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        self._ws.close()


def look_at_pose(position: np.ndarray, look_at: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) at ``position`` looking at ``look_at`` with ``up`` up."""
    z = look_at - position
    z = z / np.linalg.norm(z)
    y = -(up - np.dot(up, z) * z)
    y = y / np.linalg.norm(y)
    T = np.eye(4)
    T[:3, :3] = np.stack([np.cross(y, z), y, z], axis=1)
    T[:3, 3] = position
    return T


def _rotate(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    k = axis / np.linalg.norm(axis)
    return v * math.cos(angle) + np.cross(k, v) * math.sin(angle) + k * np.dot(k, v) * (1 - math.cos(angle))


# ---- python -m rgs_warp.view RUN_DIR -----------------------------------------------------------------
def ground_truth_poses(slam, device: str, data_root: str | None = None) -> list | None:
    """The ground-truth poses of a loaded run's frames, from its dataset (``slam.cfg``'s); None, with
    a warning, when the dataset cannot be opened or has none.  The run started at the first frame's
    ground-truth pose, so they share its world frame."""
    from rgs_warp.datasets import DatasetError, open_dataset

    cfg = slam.cfg
    if data_root is not None:
        cfg.data_root = data_root
    try:
        poses = open_dataset(cfg, device=device).gt_poses()
    except (DatasetError, ValueError, OSError) as e:
        print(f"warning: no ground truth drawn: {e}", file=sys.stderr)
        return None
    if poses is None:
        print("warning: no ground truth drawn: the dataset has no poses for every frame", file=sys.stderr)
        return None
    return list(poses[: len(slam.poses)])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m rgs_warp.view", description="Show a saved run in the browser.")
    ap.add_argument("run_dir", type=Path, help="a run folder (python -m rgs_warp.slam writes one under runs/)")
    ap.add_argument("--port", type=int, default=8080, help="the server's port (default 8080; 0: a free one)")
    ap.add_argument(
        "--host",
        default=LOCAL_HOST,
        help=f"the address it listens on (default {LOCAL_HOST}: this machine only; 0.0.0.0: every interface, "
        "with no access control)",
    )
    ap.add_argument("--device", default="auto", help="where to render (default: cuda:0 when there is one, else cpu)")
    ap.add_argument(
        "--ground-truth",
        action="store_true",
        help="also draw the ground-truth trajectory, read from the run's dataset (a synthetic one not in the "
        "cache is generated first)",
    )
    ap.add_argument("--data-root", help="where the run's dataset is, as data_root= of the run")
    args = ap.parse_args(argv)
    quiet_warp()
    from rgs_warp.config import resolve_device
    from rgs_warp.slam import SLAM

    try:
        require_viser()
        device = resolve_device(args.device)
        slam = SLAM.load(args.run_dir, device=device)
    except (ImportError, ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    gt_poses = ground_truth_poses(slam, device, args.data_root) if args.ground_truth else None
    viewer = open_viewer(args.port, args.host)
    viewer.update(slam, gt_poses=gt_poses)
    print(
        f"showing {args.run_dir}: {len(slam.poses)} frames, {len(slam.keyframe_indices)} keyframes, "
        f"{len(slam.map):,} Gaussians; Ctrl-C to stop",
        file=sys.stderr,
    )
    try:
        viewer.serve(slam)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.close()
    return 0
