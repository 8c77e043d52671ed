"""Writing calibrated models: the .mdl text with estimates as nominal values, calibrated URDFs."""

from typing import Any

from mbcal import _submodule


def __getattr__(name: str) -> Any:  # the modules on first use: a dotted name works after 'import mbcal'
    return _submodule(__name__, name)
