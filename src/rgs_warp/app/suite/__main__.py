"""``python -m rgs_warp.app.suite``: the evaluation suite's command (``nox -s eval``)."""

import sys

from rgs_warp.app.suite.cli import main

sys.exit(main())
