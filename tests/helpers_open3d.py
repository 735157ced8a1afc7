"""open3d (the optional extra ``mesh``, in ``dev``) for the tests that need it: skipped, with the reason
and the fix, where it cannot be imported (not installed, or its library misses the system libusb)."""

import pytest


def import_open3d():
    try:
        import open3d
    except ImportError as e:  # e.g. "libusb-1.0.so.0: cannot open shared object file"
        pytest.skip(
            f"open3d cannot be imported ({e}); install the mesh extra (pip install -e '.[mesh]', part of dev) "
            "and on Linux the system libusb: apt-get install libusb-1.0-0",
            allow_module_level=True,
        )
    return open3d
