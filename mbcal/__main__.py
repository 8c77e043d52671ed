"""``python -m mbcal`` is the ``mbcal`` command."""

import sys

from mbcal.cli import main

sys.exit(main())
