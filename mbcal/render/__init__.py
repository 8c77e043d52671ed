"""Pictures: headless rendering of model views (pyrender), overlays on photos, residual plots.

Optional at import time: pyrender and matplotlib are loaded when a picture is made.
"""

from typing import Any

from mbcal import _submodule


def __getattr__(name: str) -> Any:  # the modules on first use: a dotted name works after 'import mbcal'
    return _submodule(__name__, name)
