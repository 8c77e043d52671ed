"""Measurements + model + unknowns → h(p, x) and the whitened residual the solver minimises.

``h(p, x) = meas_v(modeler(D, param(p, x)))`` (seed, eq. 14): the parameter set maps the
unknowns into one parameter row per configuration, the modeler builds one scene per
configuration (vmapped), and every measurement model predicts its measurements from the
stacked scenes.  The residual is ``r = W^½ (h − y)`` with W the inverse covariance of each
measurement, followed by one row ``(x_j − nominal_j) / σ_j`` per unknown with a prior σ.

Orientations whose roll, pitch and yaw are all unknown (:func:`mbcal.modeling.rpy_triples`)
also get a local parameterisation for the solver (:attr:`Problem.local`): the rotation
R(rpy₀)·exp([δ]×) with a rotation vector δ about the current orientation, which has no gimbal
lock; after each step the angles are read back from the rotation.
"""

from __future__ import annotations

import copy
import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mbcal._jax import jax, jit, jnp, release_memory
from mbcal.cache import PROGRAMS, Hasher, code_fingerprint, enable_compilation_cache, exported, source_fingerprint
from mbcal.errors import MeasurementModelError, SolverError
from mbcal.geometry.shapes import runtime_shapes
from mbcal.language import soa_math as sm
from mbcal.language.functions import runtime_functions
from mbcal.language.model import Model
from mbcal.measurements.protocol import Batch, MeasurementModel
from mbcal.measurements.registry import call_model, declared_models, describe, get_model
from mbcal.measurements.sets import MeasurementSet
from mbcal.modeling import Needs, RpyTriple, modeler, rpy_triples
from mbcal.params import ParameterSet
from mbcal.scene import Scene

Array = Any

__all__ = ["Problem", "Group", "OrientationSteps", "RowBlocks", "blocks_by_size"]


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


@dataclass(frozen=True)
class RowBlocks:
    """Each measurement's rows of h as (start, size): block ``i`` is rows
    ``starts[i] … starts[i] + sizes[i] − 1`` (size 0: a measurement without rows).  The arrays a
    fit verdict works from, without a NumPy range per measurement (issue 16)."""

    starts: np.ndarray
    sizes: np.ndarray

    def __len__(self) -> int:
        return len(self.starts)

    def __getitem__(self, i: int) -> np.ndarray:
        return np.arange(self.starts[i], self.starts[i] + self.sizes[i])

    def __iter__(self):
        return (np.arange(a, a + b) for a, b in zip(self.starts.tolist(), self.sizes.tolist()))

    def take(self, index: np.ndarray | Sequence[int]) -> RowBlocks:
        index = np.asarray(index, dtype=np.int64)
        return RowBlocks(self.starts[index], self.sizes[index])


def blocks_by_size(blocks: RowBlocks | Sequence[np.ndarray]):
    """``(size, positions, rows)`` for the blocks of each size > 0: their positions in
    ``blocks`` and their rows as an (N, size) array — what batched deletions work from."""
    if isinstance(blocks, RowBlocks):
        for size in np.unique(blocks.sizes).tolist():
            if size:
                members = np.nonzero(blocks.sizes == size)[0]
                yield size, members, blocks.starts[members, None] + np.arange(size)
        return
    by_size: dict[int, list[int]] = {}
    for k, b in enumerate(blocks):
        by_size.setdefault(len(b), []).append(k)
    for size, listed in by_size.items():
        if size:
            yield size, np.asarray(listed, dtype=np.int64), np.stack([blocks[k] for k in listed])


def _called(g: Group, method: str, scenes: Scene, width: int) -> Array:
    """A group's ``predict`` (``width`` = its number of values) or ``visible`` (``width`` 0: one
    flag each), its shape checked as it is traced — (n, width), or (n,) for one value or a flag —
    static, so no cost in the compiled program.  Flattened unchecked, an (n, 2) from a model of
    one value, or a (2, n) for (n, 2), would shift or transpose the rows of h against y, and every
    later kind's with them: a wrong fit that the verdict could call trustworthy."""
    mm, n = g.model, len(g.batch)
    out = call_model(mm, method, scenes, g.batch)
    shape = tuple(jnp.shape(out))
    allowed = {(n,)} if width == 0 else {(n, width), (n,)} if width == 1 else {(n, width)}
    if shape not in allowed:
        if width:
            values = ", ".join(repr(v) for v in mm.values)
            either = f" or ({n},)" if width == 1 else ""
            expected = f"({n}, {width}){either}: one row per measurement, one column per value ({values})"
        else:
            expected = f"({n},): one flag per measurement"
        raise MeasurementModelError(
            f"{describe(mm)}: {method} returned an array of shape {shape} for {n} measurements; expected {expected}",
            hint="see 'The protocol' in docs/plugins.md",
        )
    return out


def _predicted(g: Group, scenes: Scene) -> Array:
    """The predictions of a group, flat (n · size,) as h stacks them (:func:`_called`)."""
    return jnp.reshape(_called(g, "predict", scenes, g.model.size), (-1,))


def _visible(g: Group, scenes: Scene) -> Array:
    """A group's visibility flags (n,) (:func:`_called`)."""
    return _called(g, "visible", scenes, 0)


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
        if not isinstance(model, Model):
            raise SolverError(f"model must be a Model (mbcal.load_model), got {type(model).__name__}")
        if not isinstance(measurements, MeasurementSet):
            raise SolverError(
                f"measurements must be a MeasurementSet (mbcal.read_measurements, measurements_from_records), "
                f"got {type(measurements).__name__}"
            )
        declared_models(model)  # a 'measure' kind no installed model provides: located at the statement
        self.model = model
        self.measurements = measurements
        # the caller's values (--set), for problems made from this one (the candidate measurements')
        self.known_given: dict[str, float] = dict(known or {})
        self._fingerprint: str | None = None
        columns = measurements.columns()  # the set as arrays, built once per set (issue 15)
        self._columns = columns
        self.params = ParameterSet(
            model,
            [estimate] if isinstance(estimate, str) else list(estimate),  # one name, not its letters
            known=measurements.known,
            configurations=columns.config_names,
            per_configuration=measurements.configurations,
            overrides=known,  # the caller's values win over the file's, per configuration too
        )
        groups: list[Group] = []
        start = 0
        for kind, col in columns.kinds.items():
            mm = get_model(kind)
            refs = {}
            for role in mm.roles:
                table = "frame" if role.lookup == "object" else role.lookup
                distinct, code = col.refs[role.name]
                # each distinct name looked up once (thousands of measurements name a few dozen things)
                if table == "frame":
                    index = [model.frame_index(name) for name in distinct]
                else:
                    index = [model._lookup(table, name) for name in distinct]
                refs[role.name] = np.asarray(index, dtype=np.int64)[code]
            batch = Batch(col.config, refs, col.data)
            covs = col.cov
            diagonal = bool(np.all(covs == np.einsum("nii->ni", covs)[:, :, None] * np.eye(mm.size)))
            if diagonal:
                whiten = 1.0 / np.sqrt(np.einsum("nii->ni", covs))
            else:
                whiten = np.linalg.inv(np.linalg.cholesky(covs))
            groups.append(Group(mm, batch, col.members, start, whiten, diagonal))
            start += len(col.members) * mm.size
        self.groups: tuple[Group, ...] = tuple(groups)
        needs = Needs()
        for g in self.groups:
            needs = needs.union(call_model(g.model, "needs", model, g.batch))
        self.needs = needs  # what the measurements read: the modeler skips the rest
        self.size = start  # rows of h
        # Which measurement and which value each row of h belongs to (the reverse,
        # measurement_rows, is built when first asked for).
        self.row_measurement = np.zeros(self.size, dtype=np.int64)
        self.row_component = np.zeros(self.size, dtype=np.int64)
        for g in self.groups:
            s = g.model.size
            self.row_measurement[g.start : g.start + g.rows] = np.repeat(g.members, s)
            self.row_component[g.start : g.start + g.rows] = np.tile(np.arange(s), len(g.members))
        sigma = self.params.prior_sigma
        self.prior_index = np.nonzero(np.isfinite(sigma))[0] if priors else np.zeros(0, dtype=np.int64)
        self.prior_sigma = sigma[self.prior_index]
        self.prior_mean = self.params.prior_mean[self.prior_index]
        self.orientations = self._orientations()
        # The solver's rotation step for them (None: no such orientation, plain steps only).
        self.local: OrientationSteps | None = OrientationSteps(self) if self.orientations else None
        enable_compilation_cache()
        # The jitted functions, shared with the earlier problems of the same structure (issue 16:
        # a warm calibration neither traces nor compiles); the solver's rotation steps with them.
        programs = _shared_programs(self)
        self._programs = programs
        self._last_values: tuple[Any, tuple[np.ndarray, list[np.ndarray], np.ndarray]] | None = None
        self.local = programs.local
        self._fun = programs.fun
        release_memory(64 * self.size)  # the temporaries of a large set's groups and row tables

    def _orientations(self) -> list[tuple[RpyTriple, np.ndarray]]:
        """The roll-pitch-yaw triples stepped as rotations, each with the positions (k, 3) of its
        unknowns in x (one row per configuration for a per-configuration orientation).

        A triple qualifies when its three angles are unknown together (in the same
        configurations, all per configuration or all not), none has hard limits, and none has a
        prior σ in use: limits and priors act on the angles themselves, so those orientations
        keep plain steps.
        """
        source = self.params._source  # (C, n_params): position in x, -1 when known
        out = []
        for triple in rpy_triples(self.model):
            infos = [self.model.params[i] for i in triple.params]
            if any(p.limited for p in infos) or (len(self.prior_index) and any(p.sigma is not None for p in infos)):
                continue
            columns = source[:, list(triple.params)]
            unknown = columns >= 0
            if not unknown.any() or not np.all(unknown.all(axis=1) | ~unknown.any(axis=1)):
                continue
            positions = np.unique(columns[unknown.all(axis=1)], axis=0)
            if len(np.unique(positions)) != positions.size:
                continue  # per configuration and global angles mixed: one unknown in several rotations
            out.append((triple, positions.astype(np.int64)))
        return out

    @property
    def orientation_names(self) -> list[tuple[str, str, str]]:
        """The unknowns (roll, pitch, yaw) that the solver steps as rotations (see :attr:`local`)."""
        names = self.params.names
        return [tuple(names[j] for j in row) for _, positions in self.orientations for row in positions]  # type: ignore[misc]

    # ---- values ---------------------------------------------------------------------------------

    @functools.cached_property
    def measurement_rows(self) -> list[slice]:
        """The rows of h (and of the residual and Jacobian) of each measurement, in the set's order."""
        spans = self.row_blocks
        return [slice(a, a + b) for a, b in zip(spans.starts.tolist(), spans.sizes.tolist())]

    @functools.cached_property
    def row_blocks(self) -> RowBlocks:
        """:attr:`measurement_rows` as arrays (:class:`RowBlocks`)."""
        starts = np.zeros(len(self.measurements.measurements), dtype=np.int64)
        sizes = np.zeros(len(starts), dtype=np.int64)
        for g in self.groups:
            starts[g.members] = g.start + np.arange(len(g.members)) * g.model.size
            sizes[g.members] = g.model.size
        return RowBlocks(starts, sizes)

    @property
    def y(self) -> np.ndarray:
        """The measured values stacked like h (NaN where a plan has none)."""
        y = np.full(self.size, np.nan)
        for g, col in zip(self.groups, self._columns.kinds.values()):
            y[g.start : g.start + g.rows] = col.values.ravel()
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
        (``needs`` overrides it; ``Needs.everything()`` for a whole scene).  ``known`` gives the
        known values; those the model alone gives (:attr:`ParameterSet.model_constants`) are its
        nominal values, constants of the traced programs."""
        needs = self.needs if needs is None else needs
        rows, configs = self.params.views(x, known)
        params = self.params
        return jax.vmap(lambda row, c: modeler(self.model, params.view(x, row, c, model_constants=True), needs))(
            rows, configs
        )

    def _predict(self, x: Array, known: Array) -> Array:
        scenes = self.scenes(x, known)
        parts = [_predicted(g, scenes) for g in self.groups]
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
            return self._unless_constants_changed(r, known)

        return residual

    @property
    def residual_function(self):
        """``f(x, y, known) -> r``: the function handed to :func:`mbcal.solver.least_squares`.

        ``known`` (C, n_params) may change between calls without a new compile, except in the
        columns of :attr:`ParameterSet.model_constants` (the values only the model gives), which
        the programs hold as constants: another value there makes r NaN (never silently
        ignored); build a :class:`Problem` with ``known=`` to change one."""
        return self._fun

    def predict(self, x: Array | None = None) -> np.ndarray:
        """h(p, x) as numpy (default x: the initial values)."""
        return self._values(self.params.x0 if x is None else x)[0]

    def _values(self, x: Array) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
        """h, the visibility flags of each group and the frame origins at x, from one compiled
        program (one compile and one run where the analysis asks for all three); the last x's
        values are kept."""
        x = np.asarray(x, dtype=float)
        key = (x.tobytes(), self.params.known.tobytes())
        if self._last_values is None or self._last_values[0] != key:
            h, flags, origins = self._programs.values(x, self.params.known)
            self._last_values = (key, (np.asarray(h), [np.asarray(f) for f in flags], np.asarray(origins)))
        return self._last_values[1]

    def residual(self, x: Array, y: Array | None = None) -> np.ndarray:
        """The whitened residual r(x) (measurements, then priors)."""
        y = self.y if y is None else np.asarray(y, dtype=float)
        # NumPy arguments straight into the compiled program: ~3 µs, where jax.device_put costs ~30 µs each
        return np.asarray(self._programs.residual(np.asarray(x, dtype=float), y, self.params.known))

    def jacobian(self, x: Array, y: Array | None = None) -> np.ndarray:
        """J = ∂r/∂x (whitened; rows like :meth:`residual`), by forward-mode autodiff."""
        y = self.y if y is None else np.nan_to_num(np.asarray(y, dtype=float))
        J = self._programs.jacobian(np.asarray(x, dtype=float), y, self.params.known)
        return np.asarray(J)

    def residual_and_jacobian(self, x: Array) -> tuple[np.ndarray, np.ndarray]:
        """r(x) and J(x) at the measured values, from one compiled forward-mode pass."""
        J, r = self._programs.both(np.asarray(x, dtype=float), self.y, self.params.known)
        return np.asarray(r), np.asarray(J)

    def _visible(self, x: Array, known: Array) -> list[Array]:
        scenes = self.scenes(x, known)
        return [_visible(g, scenes) for g in self.groups]

    def first_analysis(self) -> bool:
        """Whether no calibration in this process has analysed a problem of this structure yet (its
        analysis programs are not loaded): :func:`mbcal.api.calibrate` then loads them beside the
        solve.  Later calls say False."""
        first = not self._programs.analysed
        self._programs.analysed = True
        return first

    def visible(self, x: Array | None = None) -> np.ndarray:
        """Per measurement: whether it can be made (point in front of the camera and in the image, ...)."""
        flags = self._values(self.params.x0 if x is None else x)[1]
        out = np.ones(len(self.measurements), dtype=bool)
        for g, f in zip(self.groups, flags):
            out[g.members] = np.asarray(f)
        return out

    def point_jacobian(self, x: Array, configs: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World positions (k, 3) of points in configurations, and their Jacobians (k, 3, n) ∂p/∂x."""
        key = (configs.tobytes(), points.tobytes())
        cache = self._programs.points  # one entry: the latest points asked for
        fn = cache.get(key)
        if fn is None:
            wanted = Needs(points=frozenset(int(p) for p in points))
            traced = self._programs.problem  # not self: the cached program must not keep this problem's data

            def positions(xx, known):
                return traced.scenes(xx, known, wanted).points[configs, points]

            jitted = jit(lambda xx, known: (positions(xx, known), jax.jacfwd(positions)(xx, known)))
            fn = self._programs._saveable("points " + Hasher().add(configs, points).hexdigest(), jitted)
            cache.clear()
            cache[key] = fn
        P, J = fn(np.asarray(x, dtype=float), self.params.known)
        return np.asarray(P), np.asarray(J)

    def point_jacobian_compressed(
        self, x: Array, configs: np.ndarray, points: np.ndarray, slot: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """World positions (k, 3) of points in configurations and their Jacobians (k, 3, c) with
        respect to ``dc`` in ``x + dc[slot]`` (``slot``: each unknown's column of c).  With a block
        structure's slots (:meth:`mbcal.structured.Structure.arrays`) a point's columns are its
        configuration's block and the shared unknowns: c = nb + ks tangents, not n (issue 15)."""
        key = (configs.tobytes(), points.tobytes(), slot.tobytes())
        cache = self._programs.compressed_points  # one entry: the latest points asked for
        fn = cache.get(key)
        if fn is None:
            wanted = Needs(points=frozenset(np.unique(points).tolist()))
            c = int(slot.max()) + 1 if len(slot) else 0
            traced = self._programs.problem  # not self: the cached program must not keep this problem's data

            def positions(dc, xx, known):
                return traced.scenes(xx + dc[slot], known, wanted).points[configs, points]

            def both(xx, known):
                zero = jnp.zeros(c)
                return positions(zero, xx, known), jax.jacfwd(positions)(zero, xx, known)

            name = "compressed points " + Hasher().add(configs, points, slot).hexdigest()
            fn = self._programs._saveable(name, jit(both))
            cache.clear()
            cache[key] = fn
        P, J = fn(np.asarray(x, dtype=float), self.params.known)
        return np.asarray(P), np.asarray(J)

    def whole_scenes(self, x: Array) -> Scene:
        """Every configuration's whole scene at x (arrays with a leading configuration axis), from
        a compiled program: the modeler run op by op took ~0.6 s per call (issue 16)."""
        arrays = self._programs.whole(np.asarray(x, dtype=float), self.params.known)
        return Scene(self.model, *(np.asarray(a) for a in arrays))

    def frame_origins(self, x: Array) -> np.ndarray:
        """World origin (C, F, 3) of every frame in every configuration."""
        return self._values(x)[2]

    def fingerprint(self) -> str | None:
        """A hash of everything the residual function depends on besides y and the known values:
        the model's files and meshes, the measurement structure and σ, the unknowns, mbcal's code.

        None — do not cache the compiled program across processes — while shape kinds or language
        functions registered at run time exist: their code is not part of mbcal's fingerprint, and
        a changed implementation must never reuse an old program."""
        if runtime_shapes() or runtime_functions():
            return None
        if self._fingerprint is None:  # the files are hashed once per problem
            self._fingerprint = self._hash()
        return self._fingerprint or None

    def _hash(self) -> str:
        h = Hasher().add(code_fingerprint(), self.size, self.params.names, self.params._source)
        h.add(self.model.text_digest)  # models from text: the text itself (files are hashed below)
        # The files as they were read (a file saved since is not what the model holds); one the
        # model has no digest of (a model built otherwise) as it is now.
        digests = dict(self.model.file_digests)
        for path in dict.fromkeys([*self.model.files, *self.model.data_files]):  # with meshes and point files
            h.add(str(path))
            if path in digests:
                h.add(digests[path])
            else:
                h.add_file(path)
        for g in self.groups:
            b = g.batch
            if not type(g.model).__module__.startswith("mbcal."):  # a plugin's code is not mbcal's
                plugin = source_fingerprint(g.model)
                if plugin is None:
                    return ""  # no file to hash: its programs are not kept across processes
                h.add(plugin)
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
        # the model's own values are constants of the programs: which, and their values (a model
        # changed in memory has the files of the one it came from)
        constants = self.params.model_constants
        h.add(constants, self.model.nominal[constants])
        return h.hexdigest()

    def local_residual(self, x: Array, d: Array, y: Array, known: Array) -> Array:
        """r(x ⊞ d) to first order in d: the residual with every qualifying orientation rotated by
        I + [δ]× about its current value, δ the entries of d at its angles; the other unknowns are
        x + d.

        Its value and first derivative at d = 0 are those of r(x ⊞ d) with the exact rotation
        exp([δ]×) (:meth:`OrientationSteps.plus`), and that is all the solver reads (the
        Jacobian in local coordinates about x): the exact map made the Jacobian ~2.5× slower
        (:func:`mbcal.language.soa_math.rotation_step`)."""
        additive = np.ones(self.params.size)
        for _, positions in self.orientations:
            additive[positions.ravel()] = 0.0
        x_eff = x + d * additive
        rows, configs = self.params.views(x_eff, known)
        zero_row = jnp.zeros_like(rows[0])

        def scene(row, c):
            base = self.params.view(x, row, c)
            step = self.params.view(d, zero_row, c)
            replace: dict[Any, Any] = {}
            for triple, _ in self.orientations:
                a, b, k = triple.params
                R0, _t = sm.rpy(base[a], base[b], base[k])
                rotation = (sm.matmul3(R0, sm.rotation_step((step[a], step[b], step[k]))), sm.ZERO3)
                for node in triple.nodes:
                    replace[node] = rotation
            view = self.params.view(x_eff, row, c, model_constants=True)  # as the residual: see scenes()
            return modeler(self.model, view, self.needs, replace=replace)

        scenes = jax.vmap(scene)(rows, configs)
        parts = [_predicted(g, scenes) for g in self.groups]
        r = self._whitened(jnp.concatenate(parts) if parts else jnp.zeros(0), y)
        if len(self.prior_index):
            r = jnp.concatenate([r, (x_eff[self.prior_index] - self.prior_mean) / self.prior_sigma])
        return self._unless_constants_changed(r, known)

    def _unless_constants_changed(self, r: Array, known: Array) -> Array:
        """``r``, or NaN throughout when ``known`` gives a model constant
        (:attr:`ParameterSet.model_constants`) another value than the model's: the programs hold
        those values, so a caller's other value would be ignored in silence; a solve on it stops
        as non-finite instead.  Give such a value to the :class:`Problem` (``known=``)."""
        constants = self.params.model_constants
        if not constants.any():
            return r
        nominal = self.model.nominal
        index = np.flatnonzero(constants)
        same = jnp.all(jnp.asarray(known)[:, index] == nominal[index])
        return jnp.where(same, r, jnp.nan)

    def check_ready(self) -> None:
        """Refuse problems the solver cannot start on (no unknowns, no values)."""
        if self.params.size == 0:
            raise SolverError("nothing to estimate: name the unknowns (--estimate NAME|GLOB)")
        if not len(self.measurements):
            raise SolverError("no measurements to estimate from: the measurement set is empty")
        self.measurements.require_values()


# The array fields of a Scene, in its constructor's order after the model.
_SCENE_ARRAYS = ("frame_poses", "points", "camera_intrinsics", "camera_distortion", "shape_poses", "shape_dims")


class _Programs:
    """A problem's jitted functions (built from the first problem of a structure, see
    :func:`_shared_programs`): they read the structure from that problem, and the measured
    values y and the known values as arguments."""

    def __init__(self, problem: Problem, fingerprint: str | None = None):
        fun = problem._make_residual()
        self.fun = fun
        self.problem = problem  # what later programs of this structure trace from (a stripped copy when cached)
        self.local = problem.local
        self.fingerprint = fingerprint
        self.residual = self._saveable("residual", jit(fun))
        self.jacobian = self._saveable("jacobian", jit(jax.jacfwd(fun)))
        # r and J from one pass (jacfwd computes r anyway): the post-solve analysis needs both.
        both = jit(jax.jacfwd(lambda x, y, known: (lambda r: (r, r))(fun(x, y, known)), has_aux=True))
        self.both = self._saveable("both", both)

        def values(x, known):
            # h and the visibility flags read the problem's needs; the frame origins every frame
            # (one program: XLA computes what the two scenes share once).
            origins = problem.scenes(x, known, Needs.everything()).frame_poses[..., :3, 3]
            return problem._predict(x, known), problem._visible(x, known), origins

        self.values = self._saveable("values", jit(values))

        def whole(x, known):
            scenes = problem.scenes(x, known, Needs.everything())
            return tuple(getattr(scenes, name) for name in _SCENE_ARRAYS)

        self.whole = self._saveable("whole scenes", jit(whole))
        self.points: dict[Any, Any] = {}
        self.compressed_points: dict[Any, Any] = {}
        self.analysed = False  # whether a calibration has analysed a problem of this structure

    def _saveable(self, name: str, jitted: Any) -> Any:
        """``jitted``, saved in the cache folder on its first call (:func:`mbcal.cache.exported`), so
        that the next process that analyses a problem of this structure does not trace it again."""
        if self.fingerprint is None:
            return jitted

        saved: dict[Any, Any] = {}  # by the arguments' shapes (one entry: a problem's are fixed)

        def call(*args: Any) -> Any:
            shapes = tuple((np.shape(a), str(jnp.result_type(a))) for a in args)
            program = saved.get(shapes)
            if program is None:
                key = Hasher().add(self.fingerprint, name, shapes).hexdigest()
                program = saved[shapes] = exported(key, jitted, *args, keep=False)
            return program(*args)

        return call


def _shared_programs(problem: Problem) -> _Programs:
    """The programs of ``problem``, shared through :data:`mbcal.cache.PROGRAMS` with every earlier
    problem of the same structure in this process.

    Same structure: the same fingerprint (the model's files and text, the measurement structure
    and σ, the unknowns, the priors, mbcal's code: everything but y and the known values) *and*
    the same model and measurement-model objects — a model changed in memory, or a measurement
    model registered anew under the same name, never shares.  Without a fingerprint (shapes or
    functions registered at run time) a problem has programs of its own.
    """
    fingerprint = problem.fingerprint()
    if fingerprint is None:
        return _Programs(problem)
    key = (fingerprint, id(problem.model), tuple(id(g.model) for g in problem.groups))
    # The entry keeps the first problem, so its model and measurement models stay alive: their
    # ids in the key cannot be reused by other objects while the entry exists.
    return PROGRAMS.get(key, lambda: _Programs(_kept(problem), fingerprint))


def _kept(problem: Problem) -> Problem:
    """A shallow copy of ``problem`` for the programs that :data:`PROGRAMS` keeps: what the traced
    functions read (the model, the unknowns, the groups' index arrays), without the measurement
    set, its columns and the row tables, which the entry kept alive after the problem was gone
    (issue 15: 2,000 views' 108,000 measurement objects, ~50 MB, for every structure cached)."""
    kept = copy.copy(problem)
    kept.__dict__.update(measurements=None, _columns=None, row_measurement=None, row_component=None)
    kept.__dict__.pop("measurement_rows", None)
    kept.__dict__.pop("row_blocks", None)
    kept.local = OrientationSteps(kept) if kept.orientations else None
    return kept


class OrientationSteps:
    """The solver's local parameterisation of a problem's roll-pitch-yaw orientations.

    For an orientation R(r, p, y) = Rz(y)·Ry(p)·Rx(r) whose three angles are unknown, the solver
    steps in a rotation vector δ about the current orientation: the model sees
    R(r, p, y)·exp([δ]×), whose derivative in δ is regular at every orientation, where the
    derivative in the angles loses a direction at p = ±90° (gimbal lock).  After a step the
    angles are read back from the rotation — the branch and the multiples of 2π nearest the
    previous angles, so they move continuously — and the model, the covariance and the report
    keep the user's angles.  Every other unknown is stepped additively, as without it.

    It follows :class:`mbcal.solver.LocalParameterisation`; ``SolverConfig(manifold=False)``
    turns it off.
    """

    def __init__(self, problem: Problem):
        self.problem = problem
        self.positions = np.concatenate([p for _, p in problem.orientations])  # (K, 3) positions in x
        # Where each unknown's new value comes from after a step: its place among the K rolls, the
        # K pitches and the K yaws (a gather, which XLA fuses, where a scatter into x was a loop
        # of its own and the 3 × 3 products were batched matrix products: the room's first call
        # ~0.05 s shorter, issue 16).
        K = len(self.positions)
        self._source = np.zeros(problem.params.size, dtype=np.int32)
        self._is_angle = np.zeros(problem.params.size, dtype=bool)
        for i in range(3):
            self._source[self.positions[:, i]] = i * K + np.arange(K)
            self._is_angle[self.positions[:, i]] = True

    def residual(self, x: Array, d: Array, y: Array, known: Array) -> Array:
        """r(x ⊞ d) to first order in d (see :meth:`Problem.local_residual`)."""
        return self.problem.local_residual(x, d, y, known)

    def _angles(self, v: Any) -> tuple:
        """(rolls, pitches, yaws) of ``v`` (..., n): three (..., K) arrays."""
        return tuple(v[..., self.positions[:, i]] for i in range(3))

    def _placed(self, xp: Any, base: Any, angles: tuple) -> Any:
        """``base`` with the orientations' entries replaced by ``angles`` (rolls, pitches, yaws)."""
        return xp.where(self._is_angle, xp.concatenate(angles, axis=-1)[..., self._source], base)

    def plus(self, x: Array, d: Array) -> Array:
        """x ⊞ d: additive for every unknown but the angles, which become those of R(angles)·exp([δ]×)."""
        previous = self._angles(x)
        R0, _t = sm.rpy(*previous)
        rotated = sm.matmul3(R0, sm.rotation_vector(self._angles(d)))
        return self._placed(jnp, x + d, _rpy_nearest(rotated, previous))

    def represent(self, x: Array, reference: Array) -> Array:
        """x with each orientation's angles rewritten as the equivalent ones nearest ``reference``
        (the restart's start): the other branch (r + π, π − p, y + π) or other multiples of 2π
        when they are nearer.  The orientation itself does not change."""
        return self._represented(jnp, x, reference)

    def represent_after(self, x: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """:meth:`represent` in NumPy, of every restart (rows of x and reference) at once: the
        solver calls it after the solve (in the compiled program it cost ~0.05 s of every first
        call).  Non-finite values give NaN, silently, as in the program."""
        x, reference = np.asarray(x, dtype=float), np.asarray(reference, dtype=float)
        with np.errstate(invalid="ignore", over="ignore"):
            return self._represented(np, x, reference)

    def _represented(self, xp: Any, x: Any, reference: Any) -> Any:
        return self._placed(xp, x, _equivalent_nearest(xp, self._angles(x), self._angles(reference)))


def _rpy_nearest(R: tuple, previous: tuple) -> tuple:
    """(roll, pitch, yaw) of rotations R (3 × 3 entries, each (K,)), nearest to ``previous``.

    Yaw is atan2(R10, R00) (the previous yaw at gimbal lock, where only roll ∓ yaw is defined);
    with M = Rz(−yaw)·R = Ry(pitch)·Rx(roll), pitch = atan2(−M20, M00) and roll = atan2(−M12,
    M11), exact at every pitch.  Of the two angle triples of one rotation, (r, p, y) and
    (r + π, π − p, y + π), each taken modulo 2π nearest ``previous``, the nearer is returned.
    """
    locked = jnp.hypot(R[0][0], R[1][0]) < 1e-12
    yaw = jnp.where(locked, previous[2], jnp.arctan2(R[1][0], R[0][0]))
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    m00 = c * R[0][0] + s * R[1][0]
    m11 = c * R[1][1] - s * R[0][1]
    m12 = c * R[1][2] - s * R[0][2]
    pitch = jnp.arctan2(-R[2][0], m00)
    roll = jnp.arctan2(-m12, m11)
    return _equivalent_nearest(jnp, (roll, pitch, yaw), previous)


def _equivalent_nearest(xp: Any, angles: tuple, reference: tuple) -> tuple:
    """Of the angle triples of the same rotations as ``angles`` (rolls, pitches, yaws) — (r, p, y)
    and (r + π, π − p, y + π), each angle modulo 2π — the one nearest ``reference``."""
    roll, pitch, yaw = angles
    other = (roll + np.pi, np.pi - pitch, yaw + np.pi)

    def near(a: tuple) -> tuple:
        return tuple(q + (v - q - 2.0 * np.pi * xp.round((v - q) / (2.0 * np.pi))) for v, q in zip(a, reference))

    def distance(a: tuple) -> Any:
        return sum((v - q) ** 2 for v, q in zip(a, reference))

    a, b = near(angles), near(other)
    use_other = distance(b) < distance(a)
    return tuple(xp.where(use_other, v, w) for v, w in zip(b, a))
