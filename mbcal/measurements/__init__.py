"""Measurement models meas_v: what a sensor would measure in a scene (seed, eq. 14).

A measurement model is a plugin.  mbcal's built-ins (image points, 3-D points, distances,
angles, ranges, point-to-surface distances) and third-party models are all found the same way:
through the ``mbcal.measurements`` entry-point group.  A plugin package declares, in its
``pyproject.toml``::

    [project.entry-points."mbcal.measurements"]
    my_kind = "my_package.module:MyModel"

where ``MyModel`` follows :class:`MeasurementModel`.  See docs/plugins.md.

The package's modules:

- :mod:`~mbcal.measurements.protocol` — :class:`Role`, :class:`Batch`, :class:`MeasurementModel`;
- :mod:`~mbcal.measurements.registry` — the built-ins and the plugins, by kind;
- :mod:`~mbcal.measurements.builtin` — the built-in models;
- :mod:`~mbcal.measurements.sets` — :class:`Measurement`, :class:`MeasurementSet`, building them;
- :mod:`~mbcal.measurements.io` — measurement files (CSV, JSON).

This module only re-exports the protocol and the registry.
"""

from __future__ import annotations

from typing import Any

from mbcal import _submodule
from mbcal.measurements.protocol import Batch, MeasurementModel, Role, frame_poses_with_world
from mbcal.measurements.registry import (
    ENTRY_POINT_GROUP,
    get_model,
    register,
    register_measurement_model,
    registry,
)

__all__ = [
    "Role",
    "Batch",
    "MeasurementModel",
    "registry",
    "get_model",
    "register",
    "register_measurement_model",
    "ENTRY_POINT_GROUP",
    "frame_poses_with_world",
]


def __getattr__(name: str) -> Any:  # the modules on first use: a dotted name works after 'import mbcal'
    return _submodule(__name__, name)
