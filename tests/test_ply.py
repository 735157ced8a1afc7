"""PLY in the 3DGS layout: header fields and a lossless round trip."""

import numpy as np
from plyfile import PlyData

from rgs_warp.io.ply import load_ply, save_ply
from rgs_warp.types import GaussianMap


def test_ply_round_trip_and_header(tmp_path, device):
    rng = np.random.default_rng(3)
    n = 25
    q = rng.normal(size=(n, 4))
    rows = (rng.normal(size=(n, 3)), q, rng.normal(size=(n, 3)), rng.normal(size=n), rng.normal(size=(n, 9, 3)))
    gmap = GaussianMap.from_numpy(*rows, device=device)
    path = tmp_path / "map.ply"
    save_ply(path, gmap)

    names = PlyData.read(str(path))["vertex"].data.dtype.names
    expected = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    expected += [f"f_rest_{j}" for j in range(24)]
    expected += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert list(names) == expected
    v = PlyData.read(str(path))["vertex"]
    # 3DGS order: rot_0 is w; f_rest is channel-major
    np.testing.assert_array_equal(v["rot_0"], q[:, 3].astype(np.float32))
    np.testing.assert_array_equal(v["f_rest_8"], rows[4][:, 1, 1].astype(np.float32))

    loaded = load_ply(path, device=device)
    assert len(loaded) == n and loaded.sh_degree == 2
    for name, value in gmap.to_numpy().items():
        np.testing.assert_array_equal(loaded.to_numpy()[name], value)
