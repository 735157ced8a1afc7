"""GaussianMap <-> PLY in the standard 3DGS layout, so existing splat viewers open our maps.

Vertex properties (all float32): x y z, nx ny nz (zeros), f_dc_0..2, f_rest_0..3(K-1)-1
(channel-major: f_rest[c * (K-1) + k - 1] is coefficient k of channel c, as 3DGS flattens its
(N, 3, K-1) tensor), opacity (logit), scale_0..2 (log), rot_0..3 (w, x, y, z: 3DGS's order; the map
holds x, y, z, w).  Values are float32 on both sides, so a round trip is lossless.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from rgs_warp.types import GaussianMap


def _property_names(num_sh: int) -> list[str]:
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{j}" for j in range(3 * (num_sh - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def save_ply(path: str | Path, gmap: GaussianMap) -> None:
    fields = gmap.to_numpy()
    n = len(gmap)
    sh = fields["sh"]
    q = fields["rotations"]
    columns = [
        fields["means"],
        np.zeros((n, 3), np.float32),
        sh[:, 0, :],
        sh[:, 1:, :].transpose(0, 2, 1).reshape(n, -1),
        fields["opacity_logits"][:, None],
        fields["log_scales"],
        np.concatenate([q[:, 3:4], q[:, :3]], axis=1),
    ]
    data = np.concatenate(columns, axis=1).astype(np.float32)
    vertex = np.empty(n, dtype=[(name, "f4") for name in _property_names(gmap.num_sh)])
    for j, name in enumerate(vertex.dtype.names):
        vertex[name] = data[:, j]
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(path))


def load_ply(path: str | Path, device=None, requires_grad: bool = False) -> GaussianMap:
    v = PlyData.read(str(path))["vertex"]
    names = v.data.dtype.names
    num_rest = sum(1 for name in names if name.startswith("f_rest_"))
    num_sh = num_rest // 3 + 1
    n = len(v.data)

    def cols(prefix: str, count: int) -> np.ndarray:
        return np.stack([np.asarray(v[f"{prefix}{j}"], np.float32) for j in range(count)], axis=1)

    means = np.stack([np.asarray(v[c], np.float32) for c in "xyz"], axis=1)
    sh = np.empty((n, num_sh, 3), np.float32)
    sh[:, 0, :] = cols("f_dc_", 3)
    if num_sh > 1:
        sh[:, 1:, :] = cols("f_rest_", num_rest).reshape(n, 3, num_sh - 1).transpose(0, 2, 1)
    rot = cols("rot_", 4)
    quats = np.concatenate([rot[:, 1:], rot[:, :1]], axis=1)
    return GaussianMap.from_numpy(
        means,
        quats,
        cols("scale_", 3),
        np.asarray(v["opacity"], np.float32),
        sh,
        device=device,
        requires_grad=requires_grad,
    )
