"""``python -m perchpose``."""

import sys

from perchpose.cli import main

sys.exit(main())
