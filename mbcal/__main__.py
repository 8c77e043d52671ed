"""``python -m mbcal`` is the ``mbcal`` command (the same fast exit as the console script)."""

from mbcal.cli import entry

entry()
