"""The measurement-model protocol: what a sensor would measure in a scene (meas_v, seed eq. 14).

A measurement model names what each measurement refers to (:class:`Role`), the values it
measures, and predicts them for a :class:`Batch` of measurements from stacked scenes.  The
built-in models are in :mod:`mbcal.measurements.builtin`; :mod:`mbcal.measurements.registry`
finds them and third-party ones.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from mbcal._jax import jnp
from mbcal.modeling import Needs

if TYPE_CHECKING:
    from mbcal.scene import Scene

Array = Any

__all__ = ["Role", "Batch", "MeasurementModel", "frame_poses_with_world", "LOOKUPS"]

# What a role refers to → the model table it is looked up in.
LOOKUPS = ("camera", "point", "frame", "range", "object", "shape")


@dataclass(frozen=True)
class Role:
    """A named reference of a measurement to something in the model.

    Attributes
    ----------
    name : str
        The key in measurement files (a CSV column, a JSON key): ``camera``, ``point``, ``a``.
    lookup : str
        What it names: ``camera``, ``point``, ``frame``, ``range`` (a range sensor), ``object``
        (a frame and the shapes attached to it and its descendants) or ``shape``.
    default : str or None
        Used when a measurement leaves the role out (``world`` for a frame); None: required.
    """

    name: str
    lookup: str
    default: str | None = None


@dataclass(frozen=True)
class Batch:
    """All measurements of one kind, as index arrays (numpy constants inside the trace).

    Attributes
    ----------
    config : (n,) int
        Configuration (row of the stacked scenes) of each measurement.
    refs : dict of (n,) int
        Role name → index into the model's table (frames: −1 for the world).
    data : (n, d) float
        The model's extra numeric inputs (``MeasurementModel.data``).
    """

    config: np.ndarray
    refs: dict[str, np.ndarray]
    data: np.ndarray

    def __len__(self) -> int:
        return int(self.config.shape[0])


class MeasurementModel:
    """Base class (and protocol) of measurement models.

    Subclasses set the class attributes and implement :meth:`predict`.

    Attributes
    ----------
    kind : str
        The name measurement files use (``image_point``).
    roles : tuple of Role
        What each measurement refers to.
    values : tuple of str
        Names of the measured values, e.g. ``("u", "v")``.
    data : tuple of str
        Names of extra numeric inputs per measurement (``("ray",)``); not estimated.
    integer_data : tuple of str
        Those data that must be whole numbers (indices).
    unit_data : tuple of str or None
        Those data in the unit of the values (a measured point's coordinates): a file's ``unit``
        converts them with the values, the others (an index, a count) never.  None (the default):
        for a kind whose values are lengths, every datum that is not in ``integer_data`` (the rule
        before this attribute, less its converting of whole-number indices); none for other kinds.
    value_dimension : str
        ``pixel``, ``length``, ``angle`` or ``none``: the unit a file's ``unit`` column converts.
    implicit_value : float or None
        When set, files give no values and the measured value is this (``point_to_surface``
        measures a distance of 0).
    default_sigma : float
        σ used for candidate measurements when planning (in SI units of the value).
    description : str
        One line for ``--help`` and docs.
    """

    kind: ClassVar[str] = ""
    roles: ClassVar[tuple[Role, ...]] = ()
    values: ClassVar[tuple[str, ...]] = ()
    data: ClassVar[tuple[str, ...]] = ()
    integer_data: ClassVar[tuple[str, ...]] = ()
    unit_data: ClassVar[tuple[str, ...] | None] = None
    value_dimension: ClassVar[str] = "none"
    implicit_value: ClassVar[float | None] = None
    default_sigma: ClassVar[float] = 1.0
    description: ClassVar[str] = ""

    @property
    def size(self) -> int:
        """Number of values per measurement."""
        return len(self.values)

    @property
    def converted_data(self) -> tuple[str, ...]:
        """The data a file's ``unit`` converts (see ``unit_data``)."""
        if self.unit_data is not None:
            return self.unit_data
        if self.value_dimension != "length":
            return ()
        return tuple(k for k in self.data if k not in self.integer_data)

    def predict(self, scenes: Scene, batch: Batch) -> Array:
        """Predicted values (n, size) for a batch of measurements.

        Parameters
        ----------
        scenes : Scene
            One scene per configuration, stacked: every array has a leading axis C.
        batch : Batch
            The measurements; ``scenes.points[batch.config, batch.refs["point"]]`` gathers their
            points, for instance.
        """
        raise NotImplementedError

    def check(self, model, refs: dict[str, int], data: dict[str, float]) -> str | None:
        """Extra validation of one measurement; return an error message or None."""
        return None

    def needs(self, model, batch: Batch) -> Needs:
        """What :meth:`predict` reads from the scenes (a :class:`mbcal.modeling.Needs`).

        The modeler then skips everything else, which makes compiling and solving faster.  The
        default — everything — is always safe.
        """
        return Needs.everything()

    def candidates(self, model, configurations: list[str]) -> list[dict[str, Any]]:
        """Measurements of this kind that could be made in a model (records like a JSON file's).

        Used to suggest what to measure when parameters are unobservable.  Default: none.
        """
        return []

    def visible(self, scene: Scene, batch: Batch) -> Array:
        """Whether each measurement can be made (e.g. the point is in front of the camera).

        Used to mark impossible measurements and to choose candidate measurements.  Default:
        all visible.
        """
        return jnp.ones(len(batch), dtype=bool)


def frame_poses_with_world(scenes: Scene) -> tuple[Array, int]:
    """Frame poses (C, F + 1, 4, 4) with the world's identity appended, and its index F.

    Roles that look up frames give −1 for the world; map them with ``np.where(i < 0, F, i)``.
    """
    poses = scenes.frame_poses
    C = poses.shape[0]
    eye = jnp.broadcast_to(jnp.eye(4), (C, 1, 4, 4))
    return jnp.concatenate([poses, eye], axis=1), poses.shape[1]
