"""``python -m gtsam_sphere.cli``."""

import sys

from . import main

sys.exit(main())
