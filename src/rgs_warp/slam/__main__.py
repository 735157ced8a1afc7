"""``python -m rgs_warp.slam``: SLAM on a dataset, evaluated, into a run folder (``rgs_warp.run.main``)."""

import signal
import sys

from rgs_warp.run import main

# a job scheduler stops a run with SIGTERM: leave through the run's `finally`, which saves what was
# tracked (as Ctrl-C does), with the shell's exit status for it
signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
sys.exit(main())
