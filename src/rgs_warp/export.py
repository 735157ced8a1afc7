"""``python -m rgs_warp.export RUN_DIR``: the run's coloured mesh as PLY (``rgs_warp.app.export``)."""

import sys

if __name__ == "__main__":
    from rgs_warp.app.export import main

    sys.exit(main())
