"""Complete tasks built on the library: camera calibration from target images (Zhang's
initialisation, OpenCV-compatible results), target detection, and the seed's demo."""

from typing import Any

from mbcal import _submodule


def __getattr__(name: str) -> Any:  # the modules on first use: a dotted name works after 'import mbcal'
    return _submodule(__name__, name)
