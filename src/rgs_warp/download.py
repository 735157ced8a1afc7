"""``python -m rgs_warp.download NAME...``: datasets fetched, checked and unpacked under data_root in the
layout the loaders read (``rgs_warp.app.download``)."""

import sys

if __name__ == "__main__":
    from rgs_warp.app.download import main

    sys.exit(main())
