"""Measurements + model + unknowns → h(p, x) and the whitened residual the solver minimises.

``h(p, x) = meas_v(modeler(D, param(p, x)))`` (seed, eq. 14): the parameter set maps the
unknowns into one parameter row per configuration, the modeler builds one scene per
configuration (vmapped), and every measurement model predicts its measurements from the
stacked scenes.  The residual is ``r = W^½ (h − y)`` with W the inverse covariance of each
measurement, followed by one row ``(x_j − nominal_j) / σ_j`` per unknown with a prior σ.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mbcal._jax import jax, jnp
from mbcal.cache import Hasher, code_fingerprint, enable_compilation_cache
from mbcal.errors import SolverError
from mbcal.geometry.shapes import runtime_shapes
from mbcal.language.functions import runtime_functions
from mbcal.language.model import Model
from mbcal.measurements.protocol import Batch, MeasurementModel
from mbcal.measurements.registry import get_model
from mbcal.measurements.sets import MeasurementSet
from mbcal.modeling import Needs, modeler
from mbcal.params import ParameterSet

Array = Any

__all__ = ["Problem", "Group"]


@dataclass(frozen=True)
class Group:
    """The measurements of one kind: their model, batch, rows in h and whitening."""

    model: MeasurementModel
    batch: Batch
    members: np.ndarray  # indices into MeasurementSet.measurements
    start: int  # first row in h
    whiten: np.ndarray  # (n, s, s) inverse Cholesky factors of the covariances, or (n, s) 1/σ
    diagonal: bool

    @property
    def rows(self) -> int:
        return len(self.members) * self.model.size


class Problem:
    """One calibration problem.

    Parameters
    ----------
    model : Model
    measurements : MeasurementSet
        Values may be absent (a plan) for prediction, simulation and observability analysis.
    estimate : sequence of str
        Names or glob patterns of the unknowns (``room.*``).
    known : mapping, optional
        Extra known values (SI) that override the model's nominal values and the file's.
    priors : bool
        Add a residual row for every unknown with a prior σ in the model.
    """

    def __init__(
        self,
        model: Model,
        measurements: MeasurementSet,
        estimate: Sequence[str],
        *,
        known: Mapping[str, float] | None = None,
        priors: bool = True,
    ):
        self.model = model
        self.measurements = measurements
        self.params = ParameterSet(
            model,
            list(estimate),
            known={**measurements.known, **(known or {})},
            configurations=measurements.config_names,
            per_configuration=measurements.configurations,
        )
        config_index = {c: i for i, c in enumerate(self.params.configurations)}
        by_kind: dict[str, list[int]] = {}
        for i, m in enumerate(measurements.measurements):
            by_kind.setdefault(m.kind, []).append(i)
        groups: list[Group] = []
        start = 0
        for kind, members in by_kind.items():
            mm = get_model(kind)
            ms = [measurements.measurements[i] for i in members]
            refs = {}
            for role in mm.roles:
                table = "frame" if role.lookup == "object" else role.lookup
                if table == "frame":
                    refs[role.name] = np.array([model.frame_index(m.refs[role.name]) for m in ms], dtype=np.int64)
                else:
                    refs[role.name] = np.array([model._lookup(table, m.refs[role.name]) for m in ms], dtype=np.int64)
            data = np.array([[m.data[k] for k in mm.data] for m in ms], dtype=float).reshape(len(ms), len(mm.data))
            batch = Batch(np.array([config_index[m.config] for m in ms], dtype=np.int64), refs, data)
            covs = np.stack([m.cov for m in ms])
            diagonal = bool(np.all(covs == np.einsum("nii->ni", covs)[:, :, None] * np.eye(mm.size)))
            if diagonal:
                whiten = 1.0 / np.sqrt(np.einsum("nii->ni", covs))
            else:
                whiten = np.linalg.inv(np.linalg.cholesky(covs))
            groups.append(Group(mm, batch, np.asarray(members), start, whiten, diagonal))
            start += len(members) * mm.size
        self.groups: tuple[Group, ...] = tuple(groups)
        needs = Needs()
        for g in self.groups:
            needs = needs.union(g.model.needs(model, g.batch))
        self.needs = needs  # what the measurements read: the modeler skips the rest
        self.size = start  # rows of h
        # Which measurement and which value each row of h belongs to, and the reverse: the rows
        # of h (and of the residual and Jacobian) of each measurement, in the set's order.
        self.row_measurement = np.zeros(self.size, dtype=np.int64)
        self.row_component = np.zeros(self.size, dtype=np.int64)
        self.measurement_rows: list[slice] = [slice(0, 0)] * len(measurements.measurements)
        for g in self.groups:
            s = g.model.size
            self.row_measurement[g.start : g.start + g.rows] = np.repeat(g.members, s)
            self.row_component[g.start : g.start + g.rows] = np.tile(np.arange(s), len(g.members))
            for k, i in enumerate(g.members):
                self.measurement_rows[int(i)] = slice(g.start + k * s, g.start + (k + 1) * s)
        sigma = self.params.prior_sigma
        self.prior_index = np.nonzero(np.isfinite(sigma))[0] if priors else np.zeros(0, dtype=np.int64)
        self.prior_sigma = sigma[self.prior_index]
        self.prior_mean = self.params.prior_mean[self.prior_index]
        enable_compilation_cache()
        self._fun = self._make_residual()
        self._predict_jit = jax.jit(self._predict)
        self._residual_jit = jax.jit(self._fun)
        self._jacobian_jit = jax.jit(jax.jacfwd(self._fun))
        self._visible_jit = jax.jit(self._visible)
        self._origins_jit = jax.jit(lambda x, known: self.scenes(x, known, Needs.everything()).frame_poses[..., :3, 3])
        self._point_cache: dict[Any, Any] = {}

    # ---- values ---------------------------------------------------------------------------------

    @property
    def y(self) -> np.ndarray:
        """The measured values stacked like h (NaN where a plan has none)."""
        y = np.full(self.size, np.nan)
        for m, rows in zip(self.measurements.measurements, self.measurement_rows):
            if m.value is not None:
                y[rows] = m.value
        return y

    @property
    def unknown_names(self) -> list[str]:
        return self.params.names

    @property
    def n_residuals(self) -> int:
        """Rows of the residual: measurements plus priors."""
        return self.size + len(self.prior_index)

    # ---- the functions the solver sees ------------------------------------------------------------

    def scenes(self, x: Array, known: Array | None = None, needs=None):
        """The stacked scenes (one per configuration) for unknowns x, with what the measurements need
        (``needs`` overrides it; ``Needs.everything()`` for a whole scene)."""
        needs = self.needs if needs is None else needs
        rows, configs = self.params.views(x, known)
        return jax.vmap(lambda row, c: modeler(self.model, self.params.view(x, row, c), needs))(rows, configs)

    def _predict(self, x: Array, known: Array) -> Array:
        scenes = self.scenes(x, known)
        parts = [jnp.reshape(g.model.predict(scenes, g.batch), (-1,)) for g in self.groups]
        return jnp.concatenate(parts) if parts else jnp.zeros(0)

    def _whitened(self, h: Array, y: Array) -> Array:
        parts = []
        for g in self.groups:
            e = jnp.reshape(h[g.start : g.start + g.rows] - y[g.start : g.start + g.rows], (-1, g.model.size))
            if g.diagonal:
                parts.append(jnp.reshape(e * g.whiten, (-1,)))
            else:
                parts.append(jnp.reshape(jnp.sum(g.whiten * e[:, None, :], axis=2), (-1,)))
        return jnp.concatenate(parts) if parts else jnp.zeros(0)

    def _make_residual(self):
        prior_index, prior_sigma, prior_mean = self.prior_index, self.prior_sigma, self.prior_mean

        def residual(x, y, known):
            r = self._whitened(self._predict(x, known), y)
            if len(prior_index):
                r = jnp.concatenate([r, (x[prior_index] - prior_mean) / prior_sigma])
            return r

        return residual

    @property
    def residual_function(self):
        """``f(x, y, known) -> r``: the function handed to :func:`mbcal.solver.least_squares`."""
        return self._fun

    def predict(self, x: Array | None = None) -> np.ndarray:
        """h(p, x) as numpy (default x: the initial values)."""
        x = self.params.x0 if x is None else x
        return np.asarray(self._predict_jit(jnp.asarray(x, dtype=float), jnp.asarray(self.params.known)))

    def residual(self, x: Array, y: Array | None = None) -> np.ndarray:
        """The whitened residual r(x) (measurements, then priors)."""
        y = self.y if y is None else y
        return np.asarray(
            self._residual_jit(jnp.asarray(x, dtype=float), jnp.asarray(y), jnp.asarray(self.params.known))
        )

    def jacobian(self, x: Array, y: Array | None = None) -> np.ndarray:
        """J = ∂r/∂x (whitened; rows like :meth:`residual`), by forward-mode autodiff."""
        y = jnp.asarray(self.y if y is None else np.nan_to_num(y))
        J = self._jacobian_jit(jnp.asarray(x, dtype=float), y, jnp.asarray(self.params.known))
        return np.asarray(J)

    def _visible(self, x: Array, known: Array) -> list[Array]:
        scenes = self.scenes(x, known)
        return [g.model.visible(scenes, g.batch) for g in self.groups]

    def visible(self, x: Array | None = None) -> np.ndarray:
        """Per measurement: whether it can be made (point in front of the camera and in the image, ...)."""
        x = self.params.x0 if x is None else x
        flags = self._visible_jit(jnp.asarray(x, dtype=float), jnp.asarray(self.params.known))
        out = np.ones(len(self.measurements), dtype=bool)
        for g, f in zip(self.groups, flags):
            out[g.members] = np.asarray(f)
        return out

    def point_jacobian(self, x: Array, configs: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World positions (k, 3) of points in configurations, and their Jacobians (k, 3, n) ∂p/∂x."""
        key = (configs.tobytes(), points.tobytes())
        fn = self._point_cache.get(key)
        if fn is None:
            wanted = Needs(points=frozenset(int(p) for p in points))

            def positions(xx, known):
                return self.scenes(xx, known, wanted).points[configs, points]

            fn = jax.jit(lambda xx, known: (positions(xx, known), jax.jacfwd(positions)(xx, known)))
            self._point_cache = {key: fn}
        P, J = fn(jnp.asarray(x, dtype=float), jnp.asarray(self.params.known))
        return np.asarray(P), np.asarray(J)

    def frame_origins(self, x: Array) -> np.ndarray:
        """World origin (C, F, 3) of every frame in every configuration."""
        return np.asarray(self._origins_jit(jnp.asarray(x, dtype=float), jnp.asarray(self.params.known)))

    def fingerprint(self) -> str | None:
        """A hash of everything the residual function depends on besides y and the known values:
        the model's files and meshes, the measurement structure and σ, the unknowns, mbcal's code.

        None — do not cache the compiled program across processes — while shape kinds or language
        functions registered at run time exist: their code is not part of mbcal's fingerprint, and
        a changed implementation must never reuse an old program."""
        if runtime_shapes() or runtime_functions():
            return None
        h = Hasher().add(code_fingerprint(), self.size, self.params.names, self.params._source)
        for path in self.model.files:
            h.add(str(path)).add_file(path)
        for shape in self.model.shapes:
            if shape.mesh is not None:
                h.add(shape.mesh.path).add_file(shape.mesh.path)
        for g in self.groups:
            b = g.batch
            h.add(
                g.model.kind,
                type(g.model).__module__,
                type(g.model).__qualname__,
                b.config,
                b.data,
                g.whiten,
                g.diagonal,
                sorted((k, v.tobytes()) for k, v in b.refs.items()),
            )
        h.add(self.prior_index, self.prior_sigma, self.prior_mean, self.params.known.shape)
        return h.hexdigest()

    def check_ready(self) -> None:
        """Refuse problems the solver cannot start on (no unknowns, no values)."""
        if self.params.size == 0:
            raise SolverError("nothing to estimate: name the unknowns (--estimate NAME|GLOB)")
        self.measurements.require_values()
