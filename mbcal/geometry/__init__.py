"""Geometry in JAX: rigid transforms, camera projection, the shape registry and ray casting.

Nothing here knows the model language: these are the kernels the modeler, the measurement
models, the renderer and the URDF importer share.
"""

from typing import Any

from mbcal import _submodule


def __getattr__(name: str) -> Any:  # the modules on first use: a dotted name works after 'import mbcal'
    return _submodule(__name__, name)
