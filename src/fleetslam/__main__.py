"""``python -m fleetslam``: the ``fleetslam`` command, for an environment whose scripts
directory is not on PATH."""

import sys

from fleetslam.cli import main

sys.exit(main())
