"""``python -m mbcal`` is the ``mbcal`` command, and :func:`run` its console script: the command
line's start-up runs without garbage collections from its first import (mbcal._collector), then
:func:`mbcal.cli.entry` (its fast exit)."""

from mbcal._collector import pause_start_up


def run() -> None:  # pragma: no cover - the console script
    pause_start_up()
    from mbcal.cli import entry

    entry()


if __name__ == "__main__":  # pragma: no cover
    run()
