"""Keyframe scheduling by co-visibility (supplement §4.3) and the bounded keyframe buffer."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import warp as wp

from rgs_warp.config import KeyframeConfig
from rgs_warp.geometry import invert_pose, rotation_angle_deg
from rgs_warp.kernels.covisibility import reprojected_iou, visibility_iou
from rgs_warp.types import Camera


@dataclass
class KeyframeDecision:
    is_keyframe: bool
    iou: float  # Eq. 9 against the last keyframe (1.0 before the first keyframe has a mask)
    translation_m: float  # relative to the last keyframe
    rotation_deg: float
    reason: str
    coverage: float = 1.0  # fraction of the frame's pixels the map covers (accumulated opacity > threshold)


class KeyframeSelector:
    """A frame becomes a keyframe when its visibility IoU with the last keyframe falls below
    ``iou_threshold`` AND it moved by more than ``min_translation_m`` or ``min_rotation_deg``
    (the bounds keep near-duplicate viewpoints out, which would add cost but no baseline).
    The first frame is always a keyframe.  With ``max_loss_ratio`` > 0, a frame whose tracking loss
    exceeds that multiple of the first loss after the last keyframe is one too (motion bounds
    still apply).

    ``covisibility``: "pixels" compares the two visibility masks pixel by pixel (Eq. 9 as written);
    "reprojected" lifts each visible pixel with its rendered depth into the last keyframe and counts
    it shared where the keyframe saw the same surface (``reprojected_iou``): a view that turns within
    a mapped room keeps a full mask, so only this one sees that it shows other surface."""

    def __init__(self, cfg: KeyframeConfig, camera: Camera, device: str):
        if cfg.covisibility not in ("pixels", "reprojected"):
            raise ValueError(f"keyframes.covisibility must be pixels or reprojected, got {cfg.covisibility!r}")
        self.cfg = cfg
        self.camera = camera
        self.device = device
        shape = (camera.height, camera.width)
        self._last_mask = wp.zeros(shape, dtype=wp.uint8, device=device)
        self._mask = wp.zeros(shape, dtype=wp.uint8, device=device)
        self._last_depth = wp.zeros(shape, dtype=wp.float32, device=device)
        self._depth = wp.zeros(shape, dtype=wp.float32, device=device)
        self._counts = wp.zeros(3, dtype=wp.int32, device=device)
        self._loss_ref: float | None = None  # tracking loss of the first frame after the last keyframe
        self._last_pose: np.ndarray | None = None

    def _iou(self, alpha: wp.array2d, depth: wp.array2d | None, T_ref_cur: np.ndarray) -> tuple[float, float]:
        """(IoU with the last keyframe, coverage); writes the frame's mask (and depth) for ``accept``.
        ``T_ref_cur``: this frame's camera in the last keyframe's."""
        n_pixels = float(alpha.shape[0] * alpha.shape[1])
        if self.cfg.covisibility == "pixels":
            visibility_iou(alpha, self._last_mask, self.cfg.alpha_threshold, self._mask, self._counts)
            inter, union, visible = self._counts.numpy()
            return (float(inter) / float(union) if union > 0 else 0.0), float(visible) / n_pixels
        if depth is None:
            raise ValueError("keyframes.covisibility=reprojected needs the frame's rendered depth")
        c = self.camera
        reprojected_iou(
            alpha, depth, self._last_mask, self._last_depth, self.cfg.alpha_threshold, T_ref_cur,
            (c.fx, c.fy, c.cx, c.cy), self.cfg.depth_tol, self._mask, self._depth, self._counts,
        )  # fmt: skip
        shared, visible, last_visible = self._counts.numpy()
        union = int(visible) + int(last_visible) - int(shared)
        return (float(shared) / float(union) if union > 0 else 0.0), float(visible) / n_pixels

    def should_add(
        self, alpha: wp.array2d, T_WC: np.ndarray, loss: float | None = None, depth: wp.array2d | None = None
    ) -> KeyframeDecision:
        """Decide on a tracked frame from its rendered accumulated opacity, pose, (optional) tracking
        loss and rendered depth (needed by ``covisibility=reprojected``)."""
        if alpha.shape != self._mask.shape:
            raise ValueError(f"alpha is {alpha.shape}, the selector was built for {self._mask.shape}")
        rel = np.eye(4) if self._last_pose is None else invert_pose(self._last_pose) @ T_WC
        iou, coverage = self._iou(alpha, depth, rel)
        if self._last_pose is None:
            return KeyframeDecision(True, 1.0, 0.0, 0.0, "first frame")
        dt = float(np.linalg.norm(rel[:3, 3]))
        drot = rotation_angle_deg(rel[:3, :3])
        moved = dt > self.cfg.min_translation_m or drot > self.cfg.min_rotation_deg
        if iou < self.cfg.iou_threshold and moved:
            return KeyframeDecision(True, iou, dt, drot, f"IoU {iou:.3f} < {self.cfg.iou_threshold}", coverage)
        ratio = self.cfg.max_loss_ratio
        if ratio > 0.0 and loss is not None and np.isfinite(loss):
            if self._loss_ref is None:
                self._loss_ref = float(loss)
            elif moved and loss > ratio * self._loss_ref:
                reason = f"tracking loss {loss:.4f} > {ratio} x {self._loss_ref:.4f}"
                return KeyframeDecision(True, iou, dt, drot, reason, coverage)
        reason = "overlap high" if iou >= self.cfg.iou_threshold else "motion below bounds"
        return KeyframeDecision(False, iou, dt, drot, reason, coverage)

    def accept(self, T_WC: np.ndarray) -> None:
        """Make the frame last passed to ``should_add`` the reference keyframe."""
        wp.copy(self._last_mask, self._mask)
        wp.copy(self._last_depth, self._depth)
        self._last_pose = np.array(T_WC, dtype=np.float64)
        self._loss_ref = None

    def state_dict(self) -> dict[str, np.ndarray]:
        """What the selector carries from frame to frame: the reference keyframe's visibility mask,
        depth and pose (none before the first), and the loss reference (NaN: none); ``load_state_dict``
        restores it."""
        pose = np.zeros((0, 4, 4)) if self._last_pose is None else self._last_pose[None]
        loss_ref = np.nan if self._loss_ref is None else self._loss_ref
        return {
            "last_mask": self._last_mask.numpy().copy(),
            "last_depth": self._last_depth.numpy().copy(),
            "last_pose": pose,
            "loss_ref": np.array(loss_ref),
        }

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self._last_mask.assign(np.asarray(state["last_mask"], dtype=np.uint8))
        if "last_depth" in state:  # states saved before it was kept: the next keyframe sets it
            self._last_depth.assign(np.asarray(state["last_depth"], dtype=np.float32))
        self._last_pose = np.array(state["last_pose"][0], dtype=np.float64) if len(state["last_pose"]) else None
        loss_ref = float(state["loss_ref"])
        self._loss_ref = None if np.isnan(loss_ref) else loss_ref


class KeyframeBuffer:
    """Bounded buffer of the most recent keyframes (§4.3: 8-12), in preallocated device slots.

    Eviction: when full, the oldest keyframe leaves (first in, first out). The buffer serves
    triangulation baselines and the local mapping window, both of which want recent viewpoints;
    long-range revisits are the map's job, not the buffer's.
    """

    def __init__(self, capacity: int, width: int, height: int, device: str, lazy: bool = False):
        """``lazy``: each slot's images are allocated when a keyframe is first stored there, and ``rgb`` /
        ``depth`` are indexable by slot only (a buffer that may never fill: the history); else one array
        of all slots each, which kernels index by slot."""
        if not 1 <= capacity:
            raise ValueError(f"keyframe buffer capacity must be >= 1, got {capacity}")
        self.capacity = capacity
        self.device = device
        images = _SlotImages if lazy else _slot_array
        self.rgb = images((capacity, height, width), wp.vec3, device)
        self.depth = images((capacity, height, width), wp.float32, device)
        self.poses = np.tile(np.eye(4), (capacity, 1, 1))  # camera-to-world, as tracked
        self.exposure = np.tile(np.array([1.0, 0.0]), (capacity, 1))  # (g, b) of Eq. 3
        self.frame_ids = np.full(capacity, -1, dtype=np.int64)
        self.descriptors: list = [None] * capacity  # filled by the DenseMatcher
        self._order: list[int] = []  # slots, oldest first

    def __len__(self) -> int:
        return len(self._order)

    def slots(self) -> list[int]:
        """Occupied slots, oldest first."""
        return list(self._order)

    def add(
        self, frame_id: int, T_WC: np.ndarray, rgb, depth=None, exposure=(1.0, 0.0), slot: int | None = None
    ) -> int:
        """Store a keyframe (rgb HxWx3 / depth HxW as NumPy or device arrays); returns its slot:
        ``slot`` if given (a free one: restoring a saved buffer as it was), else a free slot or the
        oldest keyframe's."""
        if slot is not None:
            if not 0 <= slot < self.capacity or slot in self._order:
                raise ValueError(f"slot {slot} is not a free slot of a buffer of {self.capacity}")
        elif len(self._order) == self.capacity:
            slot = self._order.pop(0)
        else:
            slot = next(s for s in range(self.capacity) if s not in self._order)
        _copy_into(self.rgb, slot, rgb, wp.vec3)
        if depth is not None:
            _copy_into(self.depth, slot, depth, wp.float32)
        else:
            self.depth[slot].zero_()
        self.poses[slot] = T_WC
        self.exposure[slot] = exposure
        self.frame_ids[slot] = frame_id
        self.descriptors[slot] = None
        self._order.append(slot)
        return slot

    def remove(self, slot: int) -> None:
        """Free ``slot`` (its images stay until a keyframe is added there)."""
        self._order.remove(slot)


def _slot_array(shape: tuple[int, int, int], dtype, device) -> wp.array:
    return wp.zeros(shape, dtype=dtype, device=device)


class _SlotImages:
    """A lazy buffer's images: ``[slot]`` gives slot's (height, width) array, allocated at its first use."""

    def __init__(self, shape: tuple[int, int, int], dtype, device):
        self.shape, self.dtype, self.device = shape, dtype, device
        self._slots: dict[int, wp.array] = {}

    def __getitem__(self, slot: int) -> wp.array:
        if slot not in self._slots:
            if not 0 <= slot < self.shape[0]:
                raise IndexError(f"slot {slot} of a buffer of {self.shape[0]}")
            self._slots[slot] = wp.zeros(self.shape[1:], dtype=self.dtype, device=self.device)
        return self._slots[slot]

    @property
    def allocated(self) -> int:
        """Slots whose images exist on the device."""
        return len(self._slots)


class ViewSample:
    """Views on the device for mapping, up to ``capacity``; when full, each new one replaces a random one
    with probability capacity / offered so far (reservoir sampling), so that the kept ones are a uniform
    sample of the whole run rather than its latest part.  Device memory for the views kept, not for all
    it could keep (a 1200x680 view: 13 MB)."""

    def __init__(self, capacity: int, width: int, height: int, device: str, seed: int = 0):
        self.buffer = KeyframeBuffer(capacity, width, height, device, lazy=True)
        self.offered = 0
        self.rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return len(self.buffer)

    def add(self, frame_id: int, T_WC: np.ndarray, rgb, depth, exposure) -> None:
        """A view offered: kept or not (see above)."""
        buf, self.offered = self.buffer, self.offered + 1
        if len(buf) == buf.capacity:
            j = int(self.rng.integers(self.offered))
            if j >= buf.capacity:
                return
            target = buf.slots()[j]
            buf.remove(target)
        else:
            target = None
        buf.add(frame_id, T_WC, rgb, depth, exposure, slot=target)

    def views(self) -> list[tuple[KeyframeBuffer, int]]:
        return [(self.buffer, s) for s in self.buffer.slots()]

    def state_dict(self) -> dict[str, np.ndarray]:
        state = {"offered": np.array(self.offered), "rng": np.array(json.dumps(self.rng.bit_generator.state))}
        return state | _buffer_state(self.buffer)

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        """What ``state_dict`` saved; also an earlier version's (the count named "evicted"; frame views that
        kept the latest, without a count or a generator)."""
        self.offered = int(state.get("offered", state.get("evicted", len(state["slots"]))))
        if "rng" in state:
            self.rng.bit_generator.state = json.loads(str(state["rng"]))
        _load_buffer(self.buffer, state)


class KeyframeHistory(ViewSample):
    """Older keyframes on the device for mapping (``mapping.history``): a sample of those the keyframe
    buffer evicts (``ViewSample``)."""

    def keep(self, source: KeyframeBuffer, slot: int) -> None:
        """The keyframe in ``source`` slot ``slot`` (about to be evicted), kept or not."""
        self.add(
            source.frame_ids[slot], source.poses[slot], source.rgb[slot], source.depth[slot], source.exposure[slot]
        )


class FrameViews(ViewSample):
    """Frames between keyframes kept as mapping views (``mapping.frame_views``): one every
    ``mapping.frame_view_every`` frames after a keyframe, a sample of the whole run on the device
    (``ViewSample``), so that mapping also fits the viewpoints between keyframes.  ``frame_ids`` lists every
    frame ever kept (the evaluation holds them out of its held-out frames, as it does the keyframes)."""

    def __init__(self, capacity: int, every: int, width: int, height: int, device: str, seed: int = 0):
        super().__init__(capacity, width, height, device, seed)
        self.every = every
        self.frame_ids: list[int] = []

    def wants(self, index: int, last_keyframe: int) -> bool:
        """Whether frame ``index``, tracked after the keyframe ``last_keyframe``, is to be kept."""
        return index > last_keyframe and (index - last_keyframe) % self.every == 0

    def keep(self, index: int, T_WC: np.ndarray, rgb, depth, exposure) -> None:
        self.add(index, T_WC, rgb, depth, exposure)
        self.frame_ids.append(int(index))

    def state_dict(self) -> dict[str, np.ndarray]:
        return {"kept": np.array(self.frame_ids, dtype=np.int64)} | super().state_dict()

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self.frame_ids = [int(i) for i in state["kept"]]
        super().load_state_dict(state)


def _buffer_state(buf: KeyframeBuffer) -> dict[str, np.ndarray]:
    """A buffer's keyframes in host arrays (slots, frame ids, poses, exposures, images), oldest first."""
    slots = buf.slots()
    state = {"slots": np.array(slots, dtype=np.int64)}
    if slots:
        state.update(frame_ids=buf.frame_ids[slots], poses=buf.poses[slots], exposure=buf.exposure[slots])
        state["rgb"] = np.stack([buf.rgb[s].numpy() for s in slots])
        state["depth"] = np.stack([buf.depth[s].numpy() for s in slots])
    return state


def _load_buffer(buf: KeyframeBuffer, state: dict[str, np.ndarray]) -> None:
    """``buf`` holding what ``_buffer_state`` saved, in the same slots."""
    for slot in buf.slots():
        buf.remove(slot)
    for k, slot in enumerate(state["slots"]):
        buf.add(
            int(state["frame_ids"][k]),
            state["poses"][k],
            state["rgb"][k],
            state["depth"][k],
            state["exposure"][k],
            slot=int(slot),
        )


def _copy_into(dst: wp.array | _SlotImages, slot: int, src, dtype) -> None:
    if isinstance(src, np.ndarray):
        src = wp.array(np.ascontiguousarray(src, dtype=np.float32), dtype=dtype, device=dst.device)
    if src.shape != dst.shape[1:]:  # wp.copy would copy the overlap of any two sizes silently
        raise ValueError(f"keyframe image of shape {src.shape}, the buffer holds {dst.shape[1:]}")
    wp.copy(dst[slot], src)
