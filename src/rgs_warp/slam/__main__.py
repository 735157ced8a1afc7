"""``python -m rgs_warp.slam``: SLAM on a dataset, evaluated, into a run folder (``rgs_warp.run.main``)."""

import signal
import sys
import warnings

from rgs_warp.datasets import DatasetWarning
from rgs_warp.run import main

# a job scheduler stops a run with SIGTERM: leave through the run's `finally`, which saves what was
# tracked (as Ctrl-C does), with the shell's exit status for it
signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
_format_warning = warnings.formatwarning


def _one_line(message, category, filename, lineno, line=None):
    """A dataset's warning (e.g. frames dropped) as one line, as the command's own warnings."""
    if issubclass(category, DatasetWarning):
        return f"warning: {message}\n"
    return _format_warning(message, category, filename, lineno, line)


warnings.formatwarning = _one_line
sys.exit(main())
