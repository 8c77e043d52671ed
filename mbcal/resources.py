"""Files that ship with mbcal: the grammar, the example models and measurement plans.

The one place that knows where they are.  In a wheel they are packaged inside ``mbcal/``
(``mbcal/grammar/mdl.lark``, ``mbcal/data/models/…``, ``mbcal/data/measurements/…``; see
``[tool.hatch.build.targets.wheel.force-include]`` in pyproject.toml); in a source checkout
(an editable install) they are the repository's ``grammar/``, ``models/`` and
``measurements/`` folders.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["bundled", "find_bundled", "grammar_path", "package_root"]

# Top folder in the checkout → where the wheel packages it, relative to the mbcal package.
_PACKAGED = {"grammar": "grammar", "models": "data/models", "measurements": "data/measurements"}


def package_root() -> Path:
    """The folder of the installed ``mbcal`` package."""
    return Path(__file__).resolve().parent


def find_bundled(relative: str) -> Path | None:
    """The path of a bundled file (``"models/teleexistence.mdl"``), or None when it is missing."""
    top, _, rest = relative.partition("/")
    packaged = resources.files("mbcal") / _PACKAGED.get(top, top) / rest
    if packaged.is_file():
        return Path(str(packaged))
    checkout = package_root().parent / relative
    if checkout.is_file():
        return checkout
    return None


def bundled(relative: str) -> Path:
    """The path of a bundled file, e.g. ``bundled("models/teleexistence.mdl")``.

    Raises
    ------
    FileNotFoundError
        The file is neither in the package nor in the source checkout.
    """
    found = find_bundled(relative)
    if found is None:
        raise FileNotFoundError(
            f"bundled file {relative} is missing from this mbcal installation (looked in the package and in "
            f"the source checkout {package_root().parent}); reinstall mbcal"
        )
    return found


def grammar_path() -> Path:
    """Where the model language's grammar ``mdl.lark`` is."""
    return bundled("grammar/mdl.lark")
