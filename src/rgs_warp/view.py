"""``python -m rgs_warp.view RUN_DIR``: a saved run in the browser (``rgs_warp.app.view``)."""

import sys

if __name__ == "__main__":
    from rgs_warp.app.view import main

    sys.exit(main())
