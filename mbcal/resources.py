"""Files that ship with mbcal: the example models and measurement plans.

In a wheel they are packaged under ``mbcal/data/``; in a source checkout (editable install)
they are the repository's ``models/`` and ``measurements/`` folders.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["bundled"]


def bundled(relative: str) -> Path:
    """The path of a bundled file, e.g. ``bundled("models/teleexistence.mdl")``."""
    packaged = resources.files("mbcal") / "data" / relative
    if packaged.is_file():
        return Path(str(packaged))
    checkout = Path(__file__).resolve().parents[1] / relative
    if checkout.is_file():
        return checkout
    raise FileNotFoundError(f"bundled file {relative} is missing from this mbcal installation")
