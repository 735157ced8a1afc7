"""Monocular keypoint odometry with a windowed local bundle adjustment: the SLAM's monocular front
end.  Photometric tracking against the SLAM's own Gaussian map loses the scale in monocular mode;
this odometry shares nothing with the map and held it over the synthetic office's first 150 frames
(0.40 cm Sim(3) ATE at 1200x680; not yet over 300: experiments/results/mono.md).

Host only (NumPy / OpenCV / SciPy), float64:

- tracks: Shi-Tomasi corners followed frame to frame by pyramidal KLT, forward-backward checked, started
  from the motion model's prediction (landmarks at their projection, other tracks moved by the rotation);
- pose: PnP (AP3P RANSAC) and the prediction compete by inliers, Levenberg-Marquardt on the inliers;
  landmark tracks that do not fit the pose are dropped (they slide).  Too few inliers, or a pose far
  from the prediction: the rotation alone from all tracks, the centre from the epipolar planes to the
  last keyframe, the landmarks left and the motion model's step length; with too few tracks even for
  that the frame is lost and leaves no trace;
- keyframes by tracked fraction, usable landmarks and parallax; landmarks triangulated from all of a
  track's keyframe observations;
- local BA (bundle_adjustment.py) over the last keyframes' poses and their landmarks, older keyframes
  that see them held (the gauge and the scale: the first start keyframe never moves; the second is
  refined by the first BAs with the start's baseline length kept).

Poses are camera-to-world at the interface (the SLAM's), world-to-camera (``T_CW``) inside.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

import cv2
import numpy as np

from rgs_warp.bundle_adjustment import (
    bundle_adjust,
    centre,
    centres,
    cross_matrices,
    project,
    rescaled_to_baseline,
    rigid,
    shifted,
)
from rgs_warp.config import KeypointsConfig
from rgs_warp.geometry import invert_pose, rotation_angle_deg
from rgs_warp.types import Camera

# The pixel quantities of KeypointsConfig were measured at 640 px of image width; they scale with the
# width, but not below half of it (a 1-px KLT or PnP limit is below what KLT delivers)
REFERENCE_WIDTH_PX = 640.0
MIN_PIXEL_SCALE = 0.5
# KLT's window (21 px at 640, OpenCV's default) grows with larger images only: the window must hold
# texture, which a smaller image has less of per pixel
KLT_WINDOW_PX = 21
MIN_CORNER_DISTANCE_PX = 5
BORDER_PX = 4  # a track closer to the border loses part of its KLT window
# After a BA an observation whose residual exceeds this many Huber widths is removed (mono.md)
BA_OUTLIER_HUBER_WIDTHS = 3.0
# A BA needs enough landmarks for the free poses to be determined at all
BA_MIN_LANDMARKS = 10
# The constant-velocity prediction is one PnP candidate; AP3P RANSAC the other
PNP_RANSAC_ITERS = 200
PNP_REFINEMENTS = 3  # LM on the inliers, inliers re-selected after each
KABSCH_TRIMS = 3  # rotation-only: Kabsch, dropping tracks beyond 3x the median angle, 3 times
# A rotation-only frame's centre: the weight of the motion model's centre against epipolar rows of
# unit bearings (about the parallax in radians, 0.01-0.05) and landmark rows (about 1): it only fills
# what those leave free
CENTRE_PRIOR_WEIGHT = 1e-4
CENTRE_TRIMS = 3  # rotation-only centre: rows beyond 3x their kind's median residual dropped, 3 times


@dataclass
class OdometryResult:
    T_WC: np.ndarray | None  # 4x4 camera-to-world in the SLAM's gauge, None when the frame is lost
    inliers: int  # landmarks agreeing with the pose (within keypoints.pnp_px)
    rotation_only: bool  # too few landmarks for PnP: rotation from all tracks, centre from epipolar planes
    keyframe: bool  # the odometry made this frame one of its keyframes (and ran its local BA)
    reason: str = ""  # why lost / rotation-only, empty otherwise


class KeypointOdometry:
    """Monocular odometry from KLT tracks, PnP and a windowed local BA, in the gauge and scale of the
    two poses that ``start`` is given."""

    def __init__(self, cfg: KeypointsConfig, camera: Camera):
        self.cfg = cfg
        self.K = camera.K.astype(np.float64)
        self.width, self.height = camera.width, camera.height
        scale = camera.width / REFERENCE_WIDTH_PX
        self._px = max(scale, MIN_PIXEL_SCALE)  # image px per px at 640
        self._max_features = int(cfg.max_features * self._px)
        self._min_distance = max(int(round(cfg.min_distance_px * scale)), MIN_CORNER_DISTANCE_PX)
        window = int(round(KLT_WINDOW_PX * max(scale, 1.0))) | 1
        self._klt = dict(
            winSize=(window, window),
            maxLevel=4 if scale > 1.5 else 3,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
        )
        self._clear()

    def __len__(self) -> int:
        return len(self._landmarks)

    def _clear(self) -> None:
        self._next_id = 0
        self._pts = np.zeros((0, 2), np.float32)  # current tracks' pixels
        self._ids = np.zeros(0, np.int64)
        self._obs: dict[int, list[tuple[int, np.ndarray]]] = {}  # track -> [(keyframe, uv)]
        self._landmarks: dict[int, np.ndarray] = {}  # track -> world point
        self._kf_T: list[np.ndarray] = []  # T_CW of each keyframe
        self._kf_frame: list[int] = []
        self._kf_tracks: set[int] = set()  # tracks alive at the last keyframe
        self._kf_landmarks = 0  # landmarks usable at the last keyframe
        self._frame = 0
        self._prev: np.ndarray | None = None
        # the last two frames' T_CW for the motion model, with their keyframe index (None: not one);
        # a keyframe's pose is read from _kf_T, so the motion model sees what the BA made of it
        self._recent: list[tuple[np.ndarray, int | None]] = []
        self._scene_depth = 1.0

    # ------------------------------------------------------------------------------------- public
    def start(self, images: list, T_first_WC: np.ndarray, T_last_WC: np.ndarray) -> list[np.ndarray]:
        """Begin at the monocular bootstrap: images = the frames 0..k in order (HxWx3 float32 RGB in
        [0, 1], or None for a frame whose input was unusable), T_first_WC / T_last_WC the bootstrap's
        poses of frames 0 and k (the SLAM's gauge and scale: the first pose and the distance between
        the two are kept; the second pose is refined by the first local BAs).  Tracks run through all
        of them, landmarks are triangulated from the two poses, the frames between get PnP poses (a
        frame without an image, or where PnP fails, the pose of the frame before); returns the poses
        of frames 0..k.  ValueError when frame 0 or k has no image or the two poses triangulate no
        landmark (too little parallax)."""
        if len(images) < 2 or images[0] is None or images[-1] is None:
            raise ValueError("start needs at least two frames, the first and the last with images")
        self._clear()
        T_first, T_last = (
            invert_pose(np.asarray(T_first_WC, np.float64)),
            invert_pose(np.asarray(T_last_WC, np.float64)),
        )
        prev = _grey(images[0])
        self._detect(prev)
        history: list[tuple[np.ndarray, np.ndarray] | None] = [(self._pts.copy(), self._ids.copy())]
        for rgb in images[1:]:
            if rgb is None:
                history.append(None)
                continue
            img = _grey(rgb)
            self._follow(prev, img, None)
            history.append((self._pts.copy(), self._ids.copy()))
            prev = img
        self._kf_T.append(T_first)
        self._kf_frame.append(0)
        for uv, t in zip(history[0][0].astype(np.float64), history[0][1].tolist(), strict=True):
            self._obs[t] = [(0, uv)]
        self._frame = len(images) - 1
        self._add_keyframe(prev, T_last)
        if not self._landmarks:
            raise ValueError("the two start poses triangulate no landmark: too little parallax between them")
        self._local_ba()  # the two-view start refined (experiments/results/mono.md)
        self._forget()
        T_last = self._kf_T[1]
        depth = [(T_last[:3, :3] @ X + T_last[:3, 3])[2] for X in self._landmarks.values()]
        self._scene_depth = float(np.median(depth))
        poses = [T_first]
        for tracks in history[1:-1]:
            poses.append(self._pnp_between(tracks, poses[-1]))
        poses.append(T_last)
        self._recent = [(poses[-2], 0 if len(images) == 2 else None), (T_last, 1)]
        self._prev = prev
        return [invert_pose(T) for T in poses]

    def track(self, rgb: np.ndarray, T_pred_WC: np.ndarray | None = None) -> OdometryResult:
        """The next frame (HxWx3 float32 RGB in [0, 1]); T_pred_WC an optional prediction (else the
        odometry's own constant-velocity model).  A lost frame changes nothing: the next one is tracked
        from the last frame that had a pose."""
        if self._prev is None:
            raise RuntimeError("KeypointOdometry.track before start")
        cfg = self.cfg
        img = _grey(rgb)
        T_prev = self._recent_pose(-1)
        if T_pred_WC is None:
            T_pred = self._motion_prediction()
        else:
            T_pred = invert_pose(np.asarray(T_pred_WC, np.float64))
        prev_uv = dict(zip(self._ids.tolist(), self._pts.astype(np.float64), strict=True))
        kept = (self._pts, self._ids)
        self._follow(self._prev, img, self._predicted_flow(T_pred, T_prev))
        T, status, inliers, reason = self._estimate_pose(T_pred, T_prev, prev_uv)
        if T is None:
            self._pts, self._ids = kept
            return OdometryResult(None, 0, False, False, reason)
        self._frame += 1
        # new tracks every frame (not only at keyframes): they have parallax by the next keyframe
        if len(self._pts) < cfg.redetect_fraction * self._max_features:
            self._detect(img)
        n_landmarks = self._usable().sum()
        alive = len(self._kf_tracks.intersection(self._ids.tolist())) / max(len(self._kf_tracks), 1)
        need = (
            alive < cfg.kf_tracked_fraction
            or n_landmarks < cfg.kf_landmark_fraction * max(self._kf_landmarks, 1)
            or n_landmarks < cfg.kf_min_landmarks
            or self._parallax_deg(self._kf_T[-1], T) > cfg.kf_parallax_deg
            or status != "ok"
        )
        keyframe = need and self._frame - self._kf_frame[-1] >= cfg.kf_min_gap
        if keyframe:
            self._add_keyframe(img, T)
            self._local_ba()
            self._forget()
            T = self._kf_T[-1]
        self._recent = [self._recent[-1], (T, len(self._kf_T) - 1 if keyframe else None)]
        self._prev = img
        return OdometryResult(invert_pose(T), inliers, status == "rotation", keyframe, reason)

    def _motion_prediction(self) -> np.ndarray:
        """T_CW of the next frame by the constant-velocity model: the last step repeated."""
        T_prev, T_before = self._recent_pose(-1), self._recent_pose(-2)
        return (T_prev @ invert_pose(T_before)) @ T_prev

    def move_to(self, T_WC: np.ndarray, T_prev_WC: np.ndarray | None = None) -> None:
        """The frame last tracked is at T_WC in the caller's world (the caller turned its pose down): the
        odometry's world moves rigidly to put it there (landmarks, keyframe poses, motion model), so the
        frames after go on from T_WC with the odometry's own steps instead of from the pose turned down.
        T_prev_WC: the caller's pose of the frame before, the motion model's velocity (else the odometry's,
        which would repeat the step turned down)."""
        if self._prev is None:
            raise RuntimeError("KeypointOdometry.move_to before start")
        C = np.asarray(T_WC, np.float64) @ self._recent_pose(-1)  # the odometry's world -> the caller's
        C_inv = invert_pose(C)
        self._kf_T = [T @ C_inv for T in self._kf_T]
        R, t = C[:3, :3], C[:3, 3]
        self._landmarks = {k: R @ X + t for k, X in self._landmarks.items()}
        self._recent = [(T @ C_inv, kf) for T, kf in self._recent]
        if T_prev_WC is not None:
            self._recent[0] = (invert_pose(np.asarray(T_prev_WC, np.float64)), None)

    def predict(self) -> np.ndarray:
        """The constant-velocity prediction of the next frame's camera-to-world pose (where ``track`` starts
        without ``T_pred_WC``)."""
        return invert_pose(self._motion_prediction())

    def recent_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """The camera-to-world poses of the two frames last tracked, oldest first, that the motion model
        repeats the step of (a keyframe's as its BA left it)."""
        return invert_pose(self._recent_pose(-2)), invert_pose(self._recent_pose(-1))

    def tracked_landmarks(self) -> tuple[np.ndarray, np.ndarray]:
        """The landmarks followed into the frame last tracked: their world points (n, 3) and their tracks'
        pixels in that frame (n, 2)."""
        use = self._usable()
        X = np.array([self._landmarks[t] for t in self._ids[use].tolist()]).reshape(-1, 3)
        return X, self._pts[use].astype(np.float64)

    @property
    def landmarks(self) -> Mapping[int, np.ndarray]:
        """Track id -> world point of every landmark held (read-only)."""
        return MappingProxyType(self._landmarks)

    @property
    def observations(self) -> Mapping[int, list[tuple[int, np.ndarray]]]:
        """Track id -> its keyframe observations [(keyframe index, pixel)] of every track held (read-only)."""
        return MappingProxyType(self._obs)

    @property
    def keyframe_count(self) -> int:
        return len(self._kf_T)

    @property
    def keyframe_tracks(self) -> frozenset[int]:
        """The tracks alive at the last keyframe."""
        return frozenset(self._kf_tracks)

    @property
    def pixel_scale(self) -> float:
        """Image px per px at ``REFERENCE_WIDTH_PX``: the factor KeypointsConfig's pixel quantities are scaled by."""
        return self._px

    # ------------------------------------------------------------------------------------- tracks
    def _detect(self, img: np.ndarray) -> None:
        want = self._max_features - len(self._pts)
        if want <= 0:
            return
        mask = np.full(img.shape, 255, np.uint8)
        for p in self._pts:
            cv2.circle(mask, (int(p[0]), int(p[1])), self._min_distance, 0, -1)
        corners = cv2.goodFeaturesToTrack(img, want * 2, 0.01, self._min_distance, mask=mask, blockSize=3)
        if corners is None:
            return
        corners = cv2.cornerSubPix(
            img, corners, (3, 3), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.01)
        )
        corners = corners.reshape(-1, 2).astype(np.float32)[:want]
        self._pts = np.vstack([self._pts, corners])
        self._ids = np.concatenate([self._ids, np.arange(self._next_id, self._next_id + len(corners))])
        self._next_id += len(corners)

    def _follow(self, prev: np.ndarray, img: np.ndarray, guess: np.ndarray | None) -> None:
        """KLT from prev to img (from guess where given), kept where the way back returns within fb_px."""
        if len(self._pts) == 0:
            return
        if guess is None:
            p1, st, _ = cv2.calcOpticalFlowPyrLK(prev, img, self._pts, None, **self._klt)
        else:
            p1, st, _ = cv2.calcOpticalFlowPyrLK(
                prev, img, self._pts, guess.astype(np.float32), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **self._klt
            )
        back, st_back, _ = cv2.calcOpticalFlowPyrLK(
            img, prev, p1, self._pts.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **self._klt
        )
        good = (
            (st.ravel() == 1)
            & (st_back.ravel() == 1)
            & (np.linalg.norm(back - self._pts, axis=1) < self.cfg.fb_px * self._px)
            & (p1[:, 0] >= BORDER_PX)
            & (p1[:, 0] < self.width - BORDER_PX)
            & (p1[:, 1] >= BORDER_PX)
            & (p1[:, 1] < self.height - BORDER_PX)
        )
        self._pts, self._ids = p1[good], self._ids[good]

    def _predicted_flow(self, T_pred: np.ndarray, T_prev: np.ndarray) -> np.ndarray | None:
        """KLT's start: landmarks at their projection in the predicted pose, other tracks moved by the
        predicted rotation (their depth is unknown)."""
        if len(self._pts) == 0:
            return None
        H = self.K @ (T_pred @ invert_pose(T_prev))[:3, :3] @ np.linalg.inv(self.K)
        q = np.c_[self._pts, np.ones(len(self._pts))] @ H.T
        guess = q[:, :2] / q[:, 2:3]
        has = self._usable()
        if has.any():
            uv, z = project(self.K, T_pred, np.array([self._landmarks[t] for t in self._ids[has].tolist()]))
            uv[z <= 0] = guess[has][z <= 0]
            guess[has] = uv
        return guess

    def _drop_tracks(self, tracks) -> None:
        tracks = np.asarray(list(tracks), np.int64)
        if len(tracks) == 0:
            return
        keep = ~np.isin(self._ids, tracks)
        self._pts, self._ids = self._pts[keep], self._ids[keep]
        for t in tracks.tolist():
            self._landmarks.pop(t, None)

    def _usable(self) -> np.ndarray:
        return np.array([t in self._landmarks for t in self._ids.tolist()], bool)

    # ------------------------------------------------------------------------------------- pose
    def _recent_pose(self, j: int) -> np.ndarray:
        T, kf = self._recent[j]
        return T if kf is None else self._kf_T[kf]

    def _pnp_between(self, tracks, T_before: np.ndarray) -> np.ndarray:
        """A start frame's pose from its tracks of the start landmarks (T_before where that fails)."""
        if tracks is None:
            return T_before
        uv, ids = tracks
        sel = np.array([t in self._landmarks for t in ids.tolist()], bool)
        if sel.sum() < 6:
            return T_before
        origin = centre(T_before)  # PnP about the camera, not a world origin metres away
        obj = np.array([self._landmarks[t] for t in ids[sel].tolist()]) - origin
        ok, rv, tv, _ = cv2.solvePnPRansac(
            obj,
            uv[sel].astype(np.float64),
            self.K,
            None,
            reprojectionError=self.cfg.pnp_px * self._px,
            flags=cv2.SOLVEPNP_AP3P,
        )
        return shifted(rigid(cv2.Rodrigues(rv)[0], tv)[None], -origin)[0] if ok else T_before

    def _estimate_pose(self, T_pred, T_prev, prev_uv) -> tuple[np.ndarray | None, str, int, str]:
        """(T_CW, 'ok' | 'rotation' | 'lost', landmarks agreeing, reason)."""
        cfg = self.cfg
        use = self._usable()
        # PnP about the last camera's centre, not a world origin metres away (conditioning; the poses then do
        # not depend on where the world's origin is): landmarks and poses in that frame, the pose moved back
        origin = centre(T_prev)
        obj = np.array([self._landmarks[t] for t in self._ids[use].tolist()]).reshape(-1, 3) - origin
        uv = self._pts[use].astype(np.float64)
        limit = cfg.pnp_px * self._px

        def agreeing(T):
            p, z = project(self.K, T, obj)
            return (np.linalg.norm(p - uv, axis=1) < limit) & (z > 0)

        T, reason = None, f"{len(obj)} landmarks tracked, fewer than {cfg.min_inliers}"
        if len(obj) >= cfg.min_inliers:
            candidates = [shifted(T_pred[None], origin)[0]]
            ok, rv, tv, _ = cv2.solvePnPRansac(
                obj,
                uv,
                self.K,
                None,
                iterationsCount=PNP_RANSAC_ITERS,
                reprojectionError=limit,
                confidence=0.999,
                flags=cv2.SOLVEPNP_AP3P,
            )
            if ok:
                candidates.append(rigid(cv2.Rodrigues(rv)[0], tv))
            best = max(candidates, key=lambda c: agreeing(c).sum())
            inl = agreeing(best)
            for _ in range(PNP_REFINEMENTS):
                if inl.sum() < 6:
                    break
                rv, tv = cv2.solvePnPRefineLM(
                    obj[inl], uv[inl], self.K, None, cv2.Rodrigues(best[:3, :3])[0], best[:3, 3].reshape(3, 1).copy()
                )
                best = rigid(cv2.Rodrigues(rv)[0], tv)
                inl = agreeing(best)
            if inl.sum() >= cfg.min_inliers:
                T = shifted(best[None], -origin)[0]
            else:
                reason = f"{int(inl.sum())} of {len(obj)} landmarks agree on a pose, fewer than {cfg.min_inliers}"
        if T is not None:
            # a pose far from the motion model is a wrong PnP solution more often than a real jump
            step = np.linalg.norm(centre(T_prev) - centre(T_pred))
            dt = np.linalg.norm(centre(T) - centre(T_pred))
            dr = rotation_angle_deg(T[:3, :3] @ T_pred[:3, :3].T)
            if dr > cfg.max_dev_deg or dt > cfg.max_dev_step * step + cfg.max_dev_depth * self._scene_depth:
                T, reason = None, f"PnP pose {dt:.3g} / {dr:.1f} deg from the motion model's"
        if T is not None:
            # landmark tracks that do not fit the pose slide (stripes, occlusion edges): drop them
            r = np.linalg.norm(project(self.K, T, obj + origin)[0] - uv, axis=1)
            cut = cfg.residual_px * self._px if cfg.residual_px > 0 else limit
            self._drop_tracks(self._ids[use][r > cut])
            return T, "ok", int((r <= cut).sum()), ""
        R = self._rotation(prev_uv)
        if R is None:
            return None, "lost", 0, reason + f"; fewer than {cfg.rotation_min_tracks} tracks for a rotation"
        T = rigid(R, -R @ self._centre_given_rotation(R, centre(T_pred), obj + origin, uv))
        return T, "rotation", int(agreeing(shifted(T[None], origin)[0]).sum()), reason

    def _centre_given_rotation(self, R: np.ndarray, c_pred: np.ndarray, obj: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """The camera centre of a rotation-only frame: the landmarks still tracked and the epipolar planes
        of the tracks seen at the last keyframe fix it where they can, the motion model's centre the rest
        (the baseline's length where no landmark is left).  The motion model's centre alone keeps its
        direction for every later frame: the keyframes made from it triangulate nothing and the odometry
        never leaves rotation-only (frames 218-299 of the office, mono.md, "Holding the 300-frame path")."""
        k = len(self._kf_T) - 1
        T_kf = self._kf_T[k]
        at_kf = {t: obs[-1][1] for t in self._ids.tolist() if (obs := self._obs.get(t)) and obs[-1][0] == k}
        now = [j for j, t in enumerate(self._ids.tolist()) if t in at_kf]
        b_kf = self._bearings(np.array([at_kf[t] for t in self._ids[now].tolist()]).reshape(-1, 2)) @ T_kf[:3, :3]
        b_now = self._bearings(self._pts[now].astype(np.float64).reshape(-1, 2)) @ R
        b_obj = self._bearings(uv) @ R
        return centre_from_bearings(centre(T_kf), b_kf, b_now, obj, b_obj, c_pred)

    def _rotation(self, prev_uv: dict) -> np.ndarray | None:
        """The rotation from the previous frame (Kabsch on the bearings of the tracks seen in both),
        composed with the previous rotation; None with too few tracks."""
        common = [j for j, t in enumerate(self._ids.tolist()) if t in prev_uv]
        if len(common) < self.cfg.rotation_min_tracks:
            return None
        b1 = self._bearings(self._pts[common].astype(np.float64))
        b0 = self._bearings(np.array([prev_uv[t] for t in self._ids[common].tolist()]))
        mask = np.ones(len(b0), bool)
        for _ in range(KABSCH_TRIMS):
            U, _, Vt = np.linalg.svd(b1[mask].T @ b0[mask])
            R_rel = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
            angle = np.degrees(np.arccos(np.clip(np.sum((b0 @ R_rel.T) * b1, axis=1), -1, 1)))
            mask = angle < max(3 * np.median(angle), 0.2)
        return R_rel @ self._recent_pose(-1)[:3, :3]

    def _bearings(self, uv: np.ndarray) -> np.ndarray:
        b = np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(self.K).T
        return b / np.linalg.norm(b, axis=1, keepdims=True)

    def _parallax_deg(self, T_kf: np.ndarray, T: np.ndarray) -> float:
        """Median angle at the landmarks seen now (the first 300) between the rays from T_kf and T."""
        seen = [t for t in self._ids.tolist() if t in self._landmarks][:300]
        if not seen:
            return 0.0
        X = np.array([self._landmarks[t] for t in seen])
        r0, r1 = X - centre(T_kf), X - centre(T)
        cos = np.sum(r0 * r1, axis=1) / np.linalg.norm(r0, axis=1) / np.linalg.norm(r1, axis=1)
        return float(np.degrees(np.median(np.arccos(np.clip(cos, -1, 1)))))

    # ------------------------------------------------------------------------------------- keyframes
    def _add_keyframe(self, img: np.ndarray, T: np.ndarray) -> None:
        k = len(self._kf_T)
        self._kf_T.append(T.copy())
        self._kf_frame.append(self._frame)
        for uv, t in zip(self._pts.astype(np.float64), self._ids.tolist(), strict=True):
            self._obs.setdefault(t, []).append((k, uv))
        self._triangulate_tracks()
        self._detect(img)
        for uv, t in zip(self._pts.astype(np.float64), self._ids.tolist(), strict=True):
            if t not in self._obs:
                self._obs[t] = [(k, uv)]
        self._kf_tracks = set(self._ids.tolist())
        self._kf_landmarks = int(self._usable().sum())

    def _forget(self) -> None:
        """After a keyframe's BA: drop the tracks no longer followed that no BA can use again (no
        landmark, or a landmark whose newest view is older than the window): KLT never takes a lost
        track back, so they would only grow the odometry's memory and each BA's search over a long run."""
        alive = set(self._ids.tolist())
        oldest = len(self._kf_T) - self.cfg.ba_window
        gone = [
            t for t, obs in self._obs.items() if t not in alive and (t not in self._landmarks or obs[-1][0] < oldest)
        ]
        for t in gone:
            del self._obs[t]
            self._landmarks.pop(t, None)

    def _triangulate_tracks(self) -> None:
        cfg = self.cfg
        for t in self._ids.tolist():
            obs = self._obs.get(t, ())
            if t in self._landmarks or len(obs) < 2:
                continue
            X = triangulate(
                np.stack([self._kf_T[k] for k, _ in obs]),
                np.array([uv for _, uv in obs]),
                self.K,
                cfg.min_parallax_deg,
                cfg.max_reproj_px * self._px,
            )
            if X is not None:
                self._landmarks[t] = X

    def _local_ba(self) -> None:
        """BA over the last ba_window keyframes and their landmarks; the older keyframes that see
        those landmarks (the last ba_held_max of them) enter held, at least two (gauge and scale):
        the window's oldest make up the two where fewer older ones exist, except the start's second
        keyframe (below)."""
        cfg = self.cfg
        n_kf = len(self._kf_T)
        # the first start keyframe and the start's baseline are the SLAM's gauge and scale
        if cfg.ba_window == 0 or n_kf < 2:
            return
        window = list(range(max(0, n_kf - cfg.ba_window), n_kf))
        in_window = set(window)
        tracks = [t for t in self._landmarks if any(k in in_window for k, _ in self._obs[t])]
        if len(tracks) < BA_MIN_LANDMARKS:
            return
        held = sorted({k for t in tracks for k, _ in self._obs[t] if k not in in_window})[-cfg.ba_held_max :]
        free = window
        # while the start's two keyframes are both in the window, only the first is held: the second
        # pose (the bootstrap's two-view estimate) is refined with the rest, and the solution is then
        # scaled about the first keyframe to the start's baseline, the SLAM's scale (refining the
        # start: 2.8 -> 1.1 cm Sim(3) ATE at 640x360 in the harness, experiments/results/mono.md)
        refine_start = not held and free[:2] == [0, 1]
        while len(held) < (1 if refine_start else 2) and free:
            held.append(free.pop(0))
        if not free:
            return
        cams = free + held
        cam_of = {k: j for j, k in enumerate(cams)}
        cam, land, uv = [], [], []
        for j, t in enumerate(tracks):
            for k, u in self._obs[t]:
                if k in cam_of:
                    cam.append(cam_of[k])
                    land.append(j)
                    uv.append(u)
        cam, land, uv = np.array(cam), np.array(land), np.array(uv)
        huber_px = cfg.ba_huber_px * self._px
        T_free, X, residual = bundle_adjust(
            np.stack([self._kf_T[k] for k in cams]),
            len(free),
            np.stack([self._landmarks[t] for t in tracks]),
            cam,
            land,
            uv,
            self.K,
            huber_px,
            cfg.ba_iters,
        )
        if refine_start:
            T_free, X = rescaled_to_baseline(self._kf_T[0], self._kf_T[1], T_free, free.index(1), X)
        for k, T in zip(free, T_free, strict=True):
            self._kf_T[k] = T
        for t, x in zip(tracks, X, strict=True):
            self._landmarks[t] = x
        bad = np.linalg.norm(residual, axis=1) > BA_OUTLIER_HUBER_WIDTHS * huber_px
        if not bad.any():
            return
        outliers: dict[int, set[int]] = {}
        for c, j in zip(cam[bad], land[bad], strict=True):
            outliers.setdefault(tracks[j], set()).add(cams[c])
        drop = []
        for t, ks in outliers.items():
            self._obs[t] = [(k, u) for k, u in self._obs[t] if k not in ks]
            if len(self._obs[t]) < 2:
                drop.append(t)
        self._drop_tracks(drop)


# ----------------------------------------------------------------------------------------- geometry
def centre_from_bearings(
    c_kf: np.ndarray, b_kf: np.ndarray, b_now: np.ndarray, X: np.ndarray, b_X: np.ndarray, c_prior: np.ndarray
) -> np.ndarray:
    """A camera centre of known rotation by linear least squares: world bearings b_now (n, 3) of points
    seen along b_kf from the keyframe centre c_kf (the baseline lies in each pair's epipolar plane:
    (b_kf x b_now) . (c - c_kf) = 0, a row weighted by the pair's parallax), world bearings b_X of the
    landmarks X (m, 3) (b_X x (X - c) = 0), and c_prior with a weight small against both (it decides
    only what they leave free; without two landmarks c_prior's distance from c_kf is the baseline's
    length).  Pairs and landmarks beyond 3x their kind's median residual are dropped, CENTRE_TRIMS times."""
    n = np.cross(b_kf, b_now)
    S = cross_matrices(b_X)
    A = np.concatenate([n, S.reshape(-1, 3), CENTRE_PRIOR_WEIGHT * np.eye(3)])
    b = np.concatenate([n @ c_kf, np.einsum("nij,nj->ni", S, X).ravel(), CENTRE_PRIOR_WEIGHT * c_prior])
    # a landmark's two independent rows of its three are dropped together with it
    group = np.concatenate([np.arange(len(n)), len(n) + np.repeat(np.arange(len(X)), 3), [-1, -1, -1]])
    data = group >= 0
    # the two kinds of rows differ in units (epipolar rows scale with the parallax): a median each
    epipolar = np.arange(len(n) + len(X)) < len(n)
    keep = np.ones(len(A), bool)
    for _ in range(CENTRE_TRIMS):
        c = np.linalg.lstsq(A[keep], b[keep], rcond=None)[0]
        worst = np.zeros(len(n) + len(X))
        np.maximum.at(worst, group[data], np.abs(A @ c - b)[data])
        ok = np.ones(len(worst), bool)
        for kind in (epipolar, ~epipolar):
            if kind.any():
                ok[kind] = worst[kind] <= 3 * np.median(worst[kind])
        keep = ~data | ok[np.maximum(group, 0)]
    c = np.linalg.lstsq(A[keep], b[keep], rcond=None)[0]
    if len(X) >= 2:
        return c
    # without landmarks the prior's projection onto the baseline shortens every step and the steps shrink
    # to nothing over a few frames: the prior's baseline length along the direction found
    step = np.linalg.norm(c - c_kf)
    return c if step < 1e-12 else c_kf + (c - c_kf) * np.linalg.norm(c_prior - c_kf) / step


def _grey(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.clip(np.asarray(rgb) * 255 + 0.5, 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)


def triangulate(
    T_CW: np.ndarray, uv: np.ndarray, K: np.ndarray, min_parallax_deg: float, max_reproj_px: float
) -> np.ndarray | None:
    """The world point seen at pixels uv (n, 2) from the cameras T_CW (n, 4, 4): linear multi-view
    triangulation (DLT in normalised coordinates).  None when no two rays (the first or the last against
    all) span min_parallax_deg, or the point is behind a camera or reprojects beyond max_reproj_px."""
    Kinv = np.linalg.inv(K)
    x = np.c_[uv, np.ones(len(uv))] @ Kinv.T
    rays = np.einsum("nji,nj->ni", T_CW[:, :3, :3], x / np.linalg.norm(x, axis=1, keepdims=True))
    cos_min = np.cos(np.radians(min_parallax_deg))
    if np.min(rays @ rays[-1]) > cos_min and np.min(rays @ rays[0]) > cos_min:
        return None
    # solved about the cameras' mean centre: the homogeneous DLT is not invariant to where the world's
    # origin is, and a world metres from the cameras conditions it poorly
    origin = centres(T_CW).mean(axis=0)
    P = shifted(T_CW, origin)[:, :3]
    A = np.concatenate([x[:, :1] * P[:, 2] - P[:, 0], x[:, 1:2] * P[:, 2] - P[:, 1]])
    Xh = np.linalg.svd(A)[2][-1]
    if abs(Xh[3]) < 1e-12:
        return None
    X = Xh[:3] / Xh[3] + origin
    for T, u in zip(T_CW, uv, strict=True):
        p, z = project(K, T, X[None])
        if z[0] <= 0 or np.linalg.norm(p[0] - u) > max_reproj_px:
            return None
    return X
