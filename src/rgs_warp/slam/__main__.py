"""``python -m rgs_warp.slam``: SLAM on a dataset, evaluated, into a run folder (``rgs_warp.app.cli``)."""

import sys

if __name__ == "__main__":
    from rgs_warp.app.cli import command

    sys.exit(command())
