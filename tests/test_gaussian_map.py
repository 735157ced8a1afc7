"""GaussianMap: construction, growth by doubling, append, in-place compaction."""

import numpy as np
import warp as wp

from rgs_warp.types import GaussianMap


def _rows(rng, n, num_sh=9):
    q = rng.normal(size=(n, 4))
    return (
        rng.normal(size=(n, 3)),
        q / np.linalg.norm(q, axis=1, keepdims=True),
        rng.normal(size=(n, 3)),
        rng.normal(size=n),
        rng.normal(size=(n, num_sh, 3)),
    )


def _assert_rows(gmap, rows):
    fields = gmap.to_numpy()
    for name, expected in zip(fields, rows, strict=True):
        np.testing.assert_array_equal(fields[name], np.asarray(expected, np.float32))


def test_from_numpy_round_trip(device):
    rows = _rows(np.random.default_rng(0), 7)
    gmap = GaussianMap.from_numpy(*rows, device=device)
    assert len(gmap) == 7 and gmap.sh_degree == 2 and gmap.sh.shape == (7, 9)
    _assert_rows(gmap, rows)


def test_append_grows_by_doubling(device):
    rng = np.random.default_rng(1)
    gmap = GaussianMap(capacity=4, sh_degree=1, device=device)
    a, b = _rows(rng, 3, 4), _rows(rng, 6, 4)
    gmap.append(*a)
    assert gmap.capacity == 4
    gmap.append(wp.array(b[0].astype(np.float32), dtype=wp.vec3, device=device), *b[1:])
    assert len(gmap) == 9 and gmap.capacity == 16
    _assert_rows(gmap, [np.concatenate([x, y]) for x, y in zip(a, b, strict=True)])


def test_remove_compacts_in_place(device):
    rng = np.random.default_rng(2)
    rows = _rows(rng, 50)
    gmap = GaussianMap.from_numpy(*rows, device=device, capacity=64)
    means_array = gmap.means
    mask = rng.random(50) < 0.4
    gmap.remove(mask)
    assert len(gmap) == (~mask).sum() and gmap.means is means_array
    _assert_rows(gmap, [x[~mask] for x in rows])
    gmap.remove(wp.array(np.r_[1, np.zeros(len(gmap) - 1)].astype(np.int32), device=device))
    _assert_rows(gmap, [x[~mask][1:] for x in rows])
