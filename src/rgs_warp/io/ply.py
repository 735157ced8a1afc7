"""GaussianMap <-> PLY in the standard 3DGS layout, so existing splat viewers open our maps.

Vertex properties (all float32): x y z, nx ny nz (zeros), f_dc_0..2, f_rest_0..3(K-1)-1
(channel-major: f_rest[c * (K-1) + k - 1] is coefficient k of channel c, as 3DGS flattens its
(N, 3, K-1) tensor), opacity (logit), scale_0..2 (log), rot_0..3 (w, x, y, z: 3DGS's order; the map
holds x, y, z, w).  Values are float32 on both sides, so a round trip is lossless.  A map without
Gaussians is a PLY with 0 vertices.  ``save_ply`` writes atomically (``rgs_warp.io.atomic``);
``load_ply`` names the file in every error (``PlyFormatError``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement, PlyParseError

from rgs_warp.io.atomic import atomic_write
from rgs_warp.types import GaussianMap


class PlyFormatError(ValueError):
    """A PLY file that is not a readable map (truncated, not PLY, properties missing); the message
    names the file."""


def _property_names(num_sh: int) -> list[str]:
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{j}" for j in range(3 * (num_sh - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def save_ply(path: str | Path, gmap: GaussianMap) -> None:
    write_ply(path, gmap.to_numpy(), gmap.num_sh)


def write_ply(path: str | Path, fields: dict[str, np.ndarray], num_sh: int) -> None:
    """``save_ply`` from the map's fields (``GaussianMap.to_numpy``) and its SH coefficients per channel."""
    n = len(fields["means"])
    sh = fields["sh"]
    q = fields["rotations"]
    columns = [
        fields["means"],
        np.zeros((n, 3), np.float32),
        sh[:, 0, :],
        sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (num_sh - 1)),
        fields["opacity_logits"][:, None],
        fields["log_scales"],
        np.concatenate([q[:, 3:4], q[:, :3]], axis=1),
    ]
    data = np.concatenate(columns, axis=1).astype(np.float32)
    vertex = np.empty(n, dtype=[(name, "f4") for name in _property_names(num_sh)])
    for j, name in enumerate(vertex.dtype.names):
        vertex[name] = data[:, j]
    with atomic_write(path) as f:
        PlyData([PlyElement.describe(vertex, "vertex")]).write(f)


def load_ply(path: str | Path, device=None, requires_grad: bool = False) -> GaussianMap:
    try:
        v = PlyData.read(str(path))["vertex"]
    except (PlyParseError, KeyError, ValueError, UnicodeDecodeError) as e:
        what = "no 'vertex' element" if isinstance(e, KeyError) else f"{type(e).__name__}: {e}"
        raise PlyFormatError(f"{path}: not a readable PLY map (truncated or damaged?): {what}") from e
    names = v.data.dtype.names
    num_rest = sum(1 for name in names if name.startswith("f_rest_"))
    num_sh = num_rest // 3 + 1
    missing = [name for name in _property_names(num_sh) if name not in names and name not in ("nx", "ny", "nz")]
    if missing or num_rest % 3 or round(num_sh**0.5) ** 2 != num_sh:
        detail = f"properties {', '.join(missing)} missing" if missing else f"{num_rest} f_rest_ properties"
        raise PlyFormatError(f"{path}: not a 3DGS map: {detail}")
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
