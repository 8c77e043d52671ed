"""An example mbcal measurement model: the height of a named point above a frame's xy-plane.

It stands for what a surveyor's level or a tape measure from the floor gives: one number per
point, in metres.  Install the package and mbcal finds the model through its entry point::

    [project.entry-points."mbcal.measurements"]
    height = "mbcal_example_plugin:Height"
"""

from __future__ import annotations

import numpy as np

from mbcal._jax import jnp
from mbcal.measurements import Batch, MeasurementModel, Role, frame_poses_with_world


class Height(MeasurementModel):
    """Height (m) of ``point`` above the xy-plane of ``frame`` (default: the world)."""

    kind = "height"
    roles = (Role("point", "point"), Role("frame", "frame", default="world"))
    values = ("value",)
    value_dimension = "length"
    default_sigma = 1e-3
    description = "height of a point above a frame's xy-plane (a level or a tape from the floor)"

    def predict(self, scenes, batch: Batch):
        poses, world = frame_poses_with_world(scenes)
        frames = np.where(batch.refs["frame"] < 0, world, batch.refs["frame"])
        T = poses[batch.config, frames]  # (n, 4, 4) world pose of each measurement's frame
        p = scenes.points[batch.config, batch.refs["point"]]  # (n, 3) world positions
        z_axis = T[:, :3, 2]
        return jnp.sum((p - T[:, :3, 3]) * z_axis, axis=1)[:, None]

    def candidates(self, model, configurations):
        return [{"kind": self.kind, "point": p.name, "config": c} for c in configurations for p in model.points]
