"""``rgs_warp.io.atomic``: a write that fails leaves the old file whole and no temporary beside it."""

import pytest


def test_atomic_write_leaves_the_old_file_when_writing_fails(tmp_path):
    from rgs_warp.io.atomic import atomic_write

    path = tmp_path / "a.txt"
    path.write_text("old")
    with pytest.raises(RuntimeError), atomic_write(path, text=True) as f:
        f.write("half of the new")
        raise RuntimeError("killed mid-write")
    assert path.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]
    with atomic_write(path, text=True) as f:
        f.write("new")
    assert path.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]
