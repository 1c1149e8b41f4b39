"""``python -m gtsam_sphere``."""

import sys

from .cli import main

sys.exit(main())
