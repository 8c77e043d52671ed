"""Measurements as data: :class:`Measurement`, :class:`MeasurementSet`, and building them.

A measurement names its kind, what it refers to (a camera and a point, ...), its value(s) in SI
units, its covariance, and its configuration.  A set adds known parameter values, globally or
per configuration (a robot's joint readings in each attitude); a set without values is a
*plan*.  :class:`SetBuilder` turns raw records (a CSV row, a JSON object, a Python dict) into
checked measurements — :mod:`mbcal.measurements.io` reads and writes the files.
"""

from __future__ import annotations

import math
import operator
import re
import warnings
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, NoReturn, SupportsIndex, overload

import numpy as np

from mbcal.errors import MbcalError, MeasurementFileError, MeasurementFileWarning, SourceSpan, shown, suggest
from mbcal.measurements.protocol import MeasurementModel
from mbcal.measurements.registry import call_model, declared_models, registry
from mbcal.units import ANGLE, DIMENSIONLESS, LENGTH, UNITS, Dim, describe

__all__ = [
    "Columns",
    "KindColumns",
    "Measurement",
    "MeasurementSet",
    "SetBuilder",
    "merge_measurements",
    "measurements_from_records",
    "parse_quantity",
    "DEFAULT_CONFIG",
    "MAX_MEASUREMENTS",
]

DEFAULT_CONFIG = "default"
MAX_MEASUREMENTS = 2_000_000
IMAGE_MARGIN = 0.1
"""How far an image point may lie outside its camera's image, as a fraction of the width (u) and
height (v): a point beyond is *outside*.  A measurement file in which more than half of a camera's
image points lie outside is refused (docs/camera-calibration.md)."""

_DIMENSION_UNITS = {
    "length": {u for u, (_, d) in UNITS.items() if d.length == 1 and d.angle == 0},
    "angle": {u for u, (_, d) in UNITS.items() if d.angle == 1 and d.length == 0},
    "pixel": set(),
    "none": set(),
}
_PIXEL_UNITS = {"px", "pixel", "pixels"}


_NO_DATA: dict[str, float] = {}  # shared by the measurements without extra inputs (never mutated)


@dataclass(frozen=True, slots=True)
class Measurement:
    """One measurement (or, in a plan, one measurement to make).

    Attributes
    ----------
    id : str
        Unique within its set.
    kind : str
        The measurement model.
    config : str
        The configuration it was taken in.
    refs : dict
        Role → full name in the model.
    value : (size,) float or None
        Measured values in SI units (None in a plan).
    cov : (size, size) float
        Covariance of the values (SI units squared).
    data : dict
        Extra numeric inputs of the model (``ray``; the measured point of ``point_to_surface``).
    where : SourceSpan or None
        Where it is in its file.
    """

    id: str
    kind: str
    config: str
    refs: dict[str, str]
    value: np.ndarray | None
    cov: np.ndarray
    data: dict[str, float] = field(default_factory=dict)
    where: SourceSpan | None = field(default=None, compare=False)

    @property
    def sigma(self) -> np.ndarray:
        """Standard deviation of each value."""
        return np.sqrt(np.diag(self.cov))


@dataclass(frozen=True)
class KindColumns:
    """The measurements of one kind in a set, as arrays (see :meth:`MeasurementSet.columns`).

    Attributes
    ----------
    kind : str
    members : (k,) int
        Their positions in the set, in order.
    config : (k,) int
        Index into :attr:`Columns.config_names`.
    refs : dict
        Role → (distinct names in order of first appearance, (k,) index into them).
    values : (k, size) float
        Measured values (NaN in the rows of measurements without one).
    has_value : (k,) bool
    cov : (k, size, size) float
    data : (k, d) float
        The model's extra inputs (``MeasurementModel.data``), in its order.
    """

    kind: str
    members: np.ndarray
    config: np.ndarray
    refs: dict[str, tuple[list[str], np.ndarray]]
    values: np.ndarray
    has_value: np.ndarray
    cov: np.ndarray
    data: np.ndarray

    def names(self, role: str) -> list[str]:
        """The referenced name of every measurement in ``role``."""
        distinct, code = self.refs[role]
        return [distinct[i] for i in code]


@dataclass(frozen=True)
class Columns:
    """A measurement set as arrays: its configurations and one :class:`KindColumns` per kind
    (in order of first appearance)."""

    config_names: list[str]
    kinds: dict[str, KindColumns]


def _blank(value: Any) -> bool:
    """Not given: absent, None or an empty cell (an array is a value, never compared with "")."""
    return value is None or (isinstance(value, str) and not value.strip())


def _refuse(m: Measurement, what: str) -> NoReturn:
    raise MeasurementFileError(f"measurement '{m.id}': {what}", m.where)


def _wrong_size(m: Measurement, size: int) -> bool:
    return np.shape(m.cov) != (size, size) or (m.value is not None and np.shape(m.value) != (size,))


def _check_numbers(group: Sequence[Measurement], values: np.ndarray, has_value: np.ndarray, covs: np.ndarray) -> None:
    """Values finite, covariances finite and positive definite: the readers check each record, and
    this catches what was set in Python (``with_values``, ``dataclasses.replace``), where a NaN
    ended as "the residuals are not finite at any starting point" naming nothing."""
    bad = has_value & ~np.all(np.isfinite(values), axis=1)
    if bad.any():
        _refuse(group[int(np.argmax(bad))], f"its value is not finite ({values[int(np.argmax(bad))].tolist()})")
    diagonal = np.einsum("nii->ni", covs)
    bad = ~np.all(np.isfinite(covs), axis=(1, 2)) | np.any(diagonal <= 0, axis=1)
    if not bad.any() and covs.shape[1] > 1:
        off = covs - diagonal[:, :, None] * np.eye(covs.shape[1])
        dense = np.any(off != 0, axis=(1, 2))
        if dense.any():  # not positive definite: no Cholesky factor (the whitening needs one)
            eig = np.full(len(covs), np.inf)
            eig[dense] = np.linalg.eigvalsh(covs[dense]).min(axis=1)
            bad = eig <= 0
    if bad.any():
        _refuse(group[int(np.argmax(bad))], "its σ or covariance must be finite and positive (definite)")


def _build_columns(ms: Sequence[Measurement], config_names: list[str]) -> Columns:
    config_index = {c: i for i, c in enumerate(config_names)}
    by_kind: dict[str, list[int]] = {}
    for i, m in enumerate(ms):
        by_kind.setdefault(m.kind, []).append(i)
    models = registry()
    kinds = {}
    for kind, positions in by_kind.items():
        group = [ms[i] for i in positions]
        first = group[0]
        size = first.cov.shape[0]
        mm = models.get(kind)  # an unknown kind is reported by whoever needs its model
        refs = {}
        for role in [r.name for r in mm.roles] if mm is not None else list(first.refs):
            names = [m.refs[role] for m in group]
            distinct = list(dict.fromkeys(names))
            code = {n: i for i, n in enumerate(distinct)}
            refs[role] = (distinct, np.array([code[n] for n in names], dtype=np.int64))
        has_value = np.array([m.value is not None for m in group], dtype=bool)
        values = np.full((len(group), size), np.nan)
        try:
            covs = np.stack([m.cov for m in group]).astype(float)
            if has_value.all():
                values[:] = [m.value for m in group]
            elif has_value.any():
                values[has_value] = [m.value for m in group if m.value is not None]
        except ValueError:  # a value or covariance of another size (set in Python: files are checked)
            _refuse(next(m for m in group if _wrong_size(m, size)), f"its value or covariance is not of size {size}")
        _check_numbers(group, values, has_value, covs)
        data_names = list(mm.data) if mm is not None else sorted(first.data)
        data = np.array([[m.data[k] for k in data_names] for m in group], dtype=float).reshape(len(group), -1)
        kinds[kind] = KindColumns(
            kind,
            np.asarray(positions, dtype=np.int64),
            np.array([config_index[m.config] for m in group], dtype=np.int64),
            refs,
            values,
            has_value,
            covs,
            data,
        )
    return Columns(config_names, kinds)


@dataclass
class MeasurementSet:
    """Measurements, known parameter values and configurations read from files.

    Attributes
    ----------
    measurements : list of Measurement
    known : dict
        Known parameter values (SI) for every configuration.
    configurations : dict
        Configuration name → {parameter: value (SI)} known in that configuration.
    path : str or None
        The file it came from.
    """

    measurements: list[Measurement]
    known: dict[str, float] = field(default_factory=dict)
    configurations: dict[str, dict[str, float]] = field(default_factory=dict)
    path: str | None = None
    images: dict[str, str] = field(default_factory=dict)  # configuration → image file it was measured in
    _columns: tuple[Any, ...] | None = field(default=None, init=False, repr=False, compare=False)

    def columns(self) -> Columns:
        """The set as arrays, one :class:`KindColumns` per kind (issue 15: a problem, Zhang's start
        and the reports read these instead of walking thousands of objects).

        Built on first use and kept while the set holds the same measurement objects with the
        same configurations (appending, removing or replacing a measurement rebuilds it).
        Measurements are values: change one by replacing it (``dataclasses.replace``), not by
        writing into its arrays.
        """
        ms = self.measurements
        key = (tuple(map(id, ms)), tuple(self.configurations))
        cached = self._columns
        if cached is not None and cached[0] == key:
            return cached[2]
        columns = _build_columns(ms, self.config_names)
        self._columns = (key, tuple(ms), columns)  # the objects kept alive: their ids stay theirs
        return columns

    def __len__(self) -> int:
        return len(self.measurements)

    def __iter__(self):
        return iter(self.measurements)

    @overload
    def __getitem__(self, index: SupportsIndex) -> Measurement: ...

    @overload
    def __getitem__(self, index: slice) -> MeasurementSet: ...

    def __getitem__(self, index: SupportsIndex | slice) -> Measurement | MeasurementSet:
        """``ms[i]``: the i-th measurement (negative from the end, as a list); ``ms[a:b]``: a
        :class:`MeasurementSet` of those measurements with this set's known values,
        configurations, path and images, as :meth:`subset` gives (a set, so that it can be
        calibrated, simulated or written)."""
        if isinstance(index, slice):
            return self._with_measurements(self.measurements[index])
        if isinstance(index, (bool, np.bool_)) or not hasattr(index, "__index__"):
            raise TypeError(
                f"a measurement set is indexed by position (an int) or a slice, not {type(index).__name__}; "
                "subset(keep) takes a flag per measurement"
            )
        i = operator.index(index)
        n = len(self.measurements)
        if not -n <= i < n:
            raise IndexError(f"measurement index {i} is out of range: the set has {n} measurement{'s' * (n != 1)}")
        return self.measurements[i]

    @property
    def config_names(self) -> list[str]:
        """Configurations in order: those with known values first, then as measurements name them."""
        names = list(dict.fromkeys([*self.configurations, *(m.config for m in self.measurements)]))
        return names or [DEFAULT_CONFIG]

    @property
    def is_plan(self) -> bool:
        """True when no measurement has a value."""
        return all(m.value is None for m in self.measurements)

    @property
    def kinds(self) -> list[str]:
        return list(dict.fromkeys(m.kind for m in self.measurements))

    def with_values(self, values: Sequence[np.ndarray | None]) -> MeasurementSet:
        """A copy with new values (one array per measurement), as ``simulate`` makes."""
        if len(values) != len(self.measurements):
            raise ValueError("one value array per measurement is needed")
        ms = [
            replace(m, value=None if v is None else np.asarray(v, dtype=float))
            for m, v in zip(self.measurements, values)
        ]
        return MeasurementSet(ms, dict(self.known), {k: dict(v) for k, v in self.configurations.items()}, self.path)

    def subset(self, keep: Iterable[bool]) -> MeasurementSet:
        """Only the measurements where ``keep`` is true."""
        return self._with_measurements([m for m, k in zip(self.measurements, keep) if k])

    def _with_measurements(self, ms: list[Measurement]) -> MeasurementSet:
        return MeasurementSet(
            ms, dict(self.known), {k: dict(v) for k, v in self.configurations.items()}, self.path, dict(self.images)
        )

    def require_values(self) -> None:
        """Raise if any measurement lacks a value (the file is a plan)."""
        missing = [m for m in self.measurements if m.value is None]
        if missing:
            m = missing[0]
            raise MeasurementFileError(
                f"measurement '{m.id}' has no value ({len(missing)} of {len(self.measurements)} have none): "
                "is this a measurement plan? Use 'mbcal simulate' to make measurements from a plan",
                m.where,
            )


# ---- parsing helpers -------------------------------------------------------------------------------


def parse_quantity(
    text: Any,
    where: SourceSpan | None,
    what: str,
    dimension: str | Dim | None = None,
    *,
    unit: str | None = None,
    unit_where: SourceSpan | None = None,
) -> float:
    """A number, or a string ``"12.5 deg"`` / ``"3cm"``, in SI units.

    ``dimension`` (``length``, ``angle``, or a :class:`~mbcal.units.Dim`), when given, is checked
    against the unit.  ``unit``, when given, is the unit written beside the number (a CSV
    file's ``unit`` cell, at ``unit_where``): the same units and checks as one written after
    the number; the two may not disagree.
    """
    if isinstance(text, bool):
        raise MeasurementFileError(f"{what}: expected a number, got {shown(text)}", where)
    beside = str(unit).strip() if unit is not None else ""
    if isinstance(text, (int, float)):
        value = _float(text, where, what)
        written = None
    else:
        s = str(text).strip()
        m = re.fullmatch(
            r"([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?(?:nan|inf|infinity))\s*([A-Za-z]*)", s, re.I
        )
        if not m:
            raise MeasurementFileError(f"{what}: expected a number (with an optional unit), got {shown(s)}", where)
        value = float(m.group(1))
        written = m.group(2) or None
    if beside and written and beside != written:
        raise MeasurementFileError(
            f"{what}: {shown(text)} says '{written}' but the unit column says '{beside}'", unit_where or where
        )
    if beside:
        value *= _unit_to_si(beside, unit_where or where, what, dimension)
    elif written:
        value *= _unit_to_si(written, where, what, dimension)
    if not math.isfinite(value):
        raise MeasurementFileError(f"{what}: value must be finite, got {shown(text)}", where)
    return value


def _unit_to_si(unit: str, where: SourceSpan | None, what: str, dimension: str | Dim | None) -> float:
    """The factor of ``unit`` to SI, checked against ``dimension`` (see :func:`parse_quantity`)."""
    if unit not in UNITS:
        raise MeasurementFileError(
            f"{what}: unknown unit '{unit}'", where, hint=suggest(unit, UNITS) or f"units: {', '.join(UNITS)}"
        )
    factor, dim = UNITS[unit]
    if dimension in ("length", LENGTH) and dim != LENGTH:
        raise MeasurementFileError(f"{what}: '{unit}' is not a length unit", where)
    if dimension in ("angle", ANGLE) and dim != ANGLE:
        raise MeasurementFileError(f"{what}: '{unit}' is not an angle unit", where)
    if isinstance(dimension, Dim) and dim != dimension:
        raise MeasurementFileError(f"{what}: the unit '{unit}' does not fit {describe(dimension)}", where)
    return factor


# A number as a measurement file writes it: Python's float() also takes "1_000" and "infinity", which
# no reader of a CSV or JSON file would take for a number.
_PLAIN_NUMBER = re.compile(r"\s*[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?\s*|\s*[-+]?(?:nan|inf)\s*", re.I)


def _float(value: int | float, where: SourceSpan | None, what: str, field: str | None = None) -> float:
    """A JSON number as a float: an integer too large for one is an error there, not an OverflowError."""
    try:
        return float(value)
    except OverflowError:
        raise MeasurementFileError(
            f"{what}: must be finite, got an integer too large for a number", where, field=field
        ) from None


def _number(text: Any, where: SourceSpan | None, what: str, field: str | None = None) -> float:
    if isinstance(text, bool) or text is None:
        raise MeasurementFileError(f"{what}: expected a number, got {shown(text)}", where, field=field)
    if isinstance(text, str) and not _PLAIN_NUMBER.fullmatch(text):
        raise MeasurementFileError(f"{what}: expected a number, got {shown(text)}", where, field=field)
    if isinstance(text, int):
        return _float(text, where, what, field)
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise MeasurementFileError(f"{what}: expected a number, got {shown(text)}", where, field=field) from None
    if not math.isfinite(value):
        raise MeasurementFileError(f"{what}: must be finite, got {shown(text)}", where, field=field)
    return value


def _unit_factor(unit: str | None, mm: MeasurementModel, where: SourceSpan | None) -> float:
    if not unit:
        return 1.0
    dim = mm.value_dimension
    if dim == "pixel":
        if unit in _PIXEL_UNITS:
            return 1.0
        raise MeasurementFileError(
            f"'{mm.kind}' values are in pixels; unit '{unit}' does not apply", where, field="unit"
        )
    if unit not in UNITS:
        raise MeasurementFileError(f"unknown unit '{unit}'", where, hint=suggest(unit, UNITS), field="unit")
    if unit not in _DIMENSION_UNITS.get(dim, set()):
        kind = {"length": "a length", "angle": "an angle"}.get(dim, "a plain number")
        raise MeasurementFileError(f"'{mm.kind}' values are {kind}; unit '{unit}' does not fit", where, field="unit")
    return UNITS[unit][0]


class SetBuilder:
    """Turns raw records (dicts of field → text) into checked :class:`Measurement` objects."""

    def __init__(self, model, path: str):
        self.model = model
        self.path = path
        self.models = registry()
        self.measurements: list[Measurement] = []
        self.ids: dict[str, SourceSpan | None] = {}
        self.known: dict[str, float] = {}
        self.configurations: dict[str, dict[str, float]] = {}
        self.images: dict[str, str] = {}
        # the model's 'measure' kinds, each installed (else a located error at the statement)
        self.declared = set(declared_models(model)) if model is not None else set()
        # Diagonal covariances are shared between measurements with the same σ (read-only): a file
        # of a million rows holds a handful of them, not a million.
        self._covariances: dict[tuple[str, tuple[float, ...]], np.ndarray] = {}
        self._configs: dict[str, str] = {}
        # Where each configuration is first listed or used, and the parameters given for each (by
        # full name; None: for every configuration): a per-configuration value given in some
        # configurations must be given in all of them (see result()).
        self._config_where: dict[str, SourceSpan | None] = {}
        self._given: dict[str | None, dict[str, str]] = {}
        # Likewise the refs: 2,000 views of a 54-corner board name 54 (camera, point) pairs, not
        # 108,000 (a dict each was ~20 MB; nothing mutates a measurement's refs).
        self._refs: dict[tuple[tuple[str, str], ...], dict[str, str]] = {}
        self._applies: dict[str, set[str]] = {}  # per kind: the keys a record of it may fill
        # Per camera (its index): the image points with values, and those outside its image
        # (:data:`IMAGE_MARGIN`), with the first of them (id, where, u, v): see _check_image_points.
        self._image_points: dict[int, list[Any]] = {}
        # The rows of a file without an id, by a hash of what they say (kind, configuration, names,
        # values, σ, data) → the first such measurement's index; and the rows that repeat an earlier
        # one to all digits (where, where the first is): a row pasted twice (see _check_repeats).
        self._rows: dict[int, int] = {}
        self._repeats: list[tuple[SourceSpan, SourceSpan]] = []
        self.row_word = "row"  # what the file's warnings call a measurement ("row" in CSV)

    def configuration(self, config: str, where: SourceSpan | None) -> None:
        """Note a configuration the file lists (with or without known values) and where."""
        self.configurations.setdefault(config, {})
        self._config_where.setdefault(config, where)

    def known_value(
        self,
        name: str,
        value: Any,
        config: str | None,
        where: SourceSpan | None,
        unit: str | None = None,
        unit_where: SourceSpan | None = None,
    ) -> None:
        """A known parameter value, for every configuration or for ``config``.

        ``value`` is a number or a string with an optional unit (``"25 cm"``); ``unit`` is a
        unit given beside it (a CSV ``known`` row's ``unit`` cell, located at ``unit_where``),
        read by the same rules.
        """
        if not name:
            raise MeasurementFileError("a 'known' row needs a parameter name in column 'param'", where, field="param")
        dimension = None
        full = name
        if self.model is not None:
            try:
                info = self.model.param(name)
            except MbcalError as err:
                raise MeasurementFileError(err.message, where, hint=err.hint, field="param") from None
            full = info.name
            # declared without a unit: what its places require (ParamInfo.given_dim), else a plain number
            dimension = info.given_dim or DIMENSIONLESS
            if config and not info.per_configuration:
                raise MeasurementFileError(
                    f"'{name}' is given for configuration '{config}' but is not declared 'per configuration' "
                    "in the model",
                    where,
                    field="param",
                )
        v = parse_quantity(value, where, f"value of '{name}'", dimension, unit=unit, unit_where=unit_where)
        if self.model is not None:
            outside = info.outside_limits(v)  # as --set: a file's value may not leave the model either
            if outside:
                raise MeasurementFileError(f"value of '{name}': {outside}", where)
        if config:
            self.configuration(config, where)
        target = self.configurations[config] if config else self.known
        given = self._given.setdefault(config or None, {})
        if full in given or name in target:
            first = given.get(full, name)
            also = f" (as '{first}')" if first != name else ""
            raise MeasurementFileError(
                f"'{name}' is given twice{also}" + (f" for configuration '{config}'" if config else ""),
                where,
                field="param",
            )
        given[full] = name
        target[name] = v

    def add(self, record: Mapping[str, Any], where: SourceSpan | None, index: int) -> None:
        kind = str(record.get("kind") or "").strip()
        if not kind:
            raise MeasurementFileError("missing 'kind'", where, field="kind")
        if kind not in self.models:
            raise MeasurementFileError(
                f"unknown measurement kind '{kind}' (available: {', '.join(sorted(self.models))})",
                where,
                hint=suggest(kind, self.models),
                field="kind",
            )
        if self.declared and kind not in self.declared:
            raise MeasurementFileError(
                f"the model declares the measurement models {', '.join(sorted(self.declared))}; '{kind}' is not one "
                "of them",
                where,
                hint="add it to the model's 'measure' statement if it is meant",
                field="kind",
            )
        mm = self.models[kind]
        kind = mm.kind  # one string shared by every measurement of the kind
        applies = self._applies.get(kind)
        if applies is None:
            applies = self._applies[kind] = _COMMON_KEYS | kind_keys(mm)
        for key, cell in record.items():
            if key not in applies and cell is not None and not (isinstance(cell, str) and not cell.strip()):
                # a cell of another kind's column (a file of mixed kinds): given here, it would be ignored
                raise MeasurementFileError(
                    f"'{key}' does not apply to a '{kind}' measurement (it takes "
                    f"{', '.join([*(r.name for r in mm.roles), *mm.values, *mm.data])})",
                    where,
                    field=key,
                )
        mid = str(record.get("id") or "").strip() or f"{kind}{index}"
        if mid in self.ids:
            first = self.ids[mid]
            raise MeasurementFileError(
                f"duplicate id '{mid}'" + (f" (first at {first})" if first else ""), where, field="id"
            )
        self.ids[mid] = where
        config = str(record.get("config") or "").strip() or DEFAULT_CONFIG
        shared_config = self._configs.get(config)
        if shared_config is None:  # one string per configuration
            shared_config = self._configs[config] = config
            self._config_where.setdefault(config, where)
        config = shared_config
        refs: dict[str, str] = {}
        ref_index: dict[str, int] = {}
        for role in mm.roles:
            name = str(record.get(role.name) or "").strip() or role.default
            if not name:
                raise MeasurementFileError(
                    f"'{kind}' needs '{role.name}' (a {role.lookup} name)", where, field=role.name
                )
            if self.model is not None:
                table = "frame" if role.lookup == "object" else role.lookup
                try:
                    full = self.model.resolve(table, name)
                    ref_index[role.name] = (
                        self.model.frame_index(full) if table == "frame" else self.model._lookup(table, full)
                    )
                except MbcalError as err:
                    raise MeasurementFileError(
                        f"'{role.name}': {err.message}", where, hint=err.hint, field=role.name
                    ) from None
                refs[role.name] = full
            else:
                refs[role.name] = name
        data: dict[str, float] = {}
        for key in mm.data:
            raw = record.get(key)
            if raw is None or (isinstance(raw, str) and not raw.strip()):
                raise MeasurementFileError(f"'{kind}' needs '{key}'", where, field=key)
            v = _number(raw, where, f"'{key}'", key)
            if key in mm.integer_data and v != int(v):
                raise MeasurementFileError(f"'{key}' must be a whole number, got {shown(raw)}", where, field=key)
            data[key] = v
        unit = str(record.get("unit") or "").strip() or None
        factor = _unit_factor(unit, mm, where)
        if unit:  # data in the values' unit (point_to_surface's measured point); never an index (a ray)
            converted = mm.converted_data
            data = {k: v * factor if k in converted else v for k, v in data.items()}
        value = self._values(record, mm, where, factor)
        cov = self._covariance(record, mm, where, factor)
        if self.model is not None:
            message = call_model(mm, "check", self.model, ref_index, data, where=where)
            if message:
                raise MeasurementFileError(message, where)
            if kind == "image_point" and value is not None and "camera" in ref_index:
                self._image_point(ref_index["camera"], value, mid, where)
        if len(self.measurements) >= MAX_MEASUREMENTS:
            raise MeasurementFileError(f"more than {MAX_MEASUREMENTS} measurements", where)
        shared = self._refs.get(pairs := tuple(refs.items()))
        if shared is None and len(self._refs) < 100_000:
            shared = self._refs[pairs] = refs
        m = Measurement(mid, kind, config, shared or refs, value, cov, data or _NO_DATA, where)
        self.measurements.append(m)
        if where is not None and value is not None and not str(record.get("id") or "").strip():
            self._note_repeat(m, hash((kind, config, pairs, value.tobytes(), cov.tobytes(), *data.items())))

    def _note_repeat(self, m: Measurement, key: int) -> None:
        """Note a measurement of a file that repeats an earlier one without an id to all digits:
        same kind, configuration, names, values, σ and data (``key``: a hash of them; compared
        exactly when it matches)."""
        index = self._rows.setdefault(key, len(self.measurements) - 1)
        first = self.measurements[index]
        if (
            first is not m
            and first.where is not None
            and m.where is not None
            and (first.kind, first.config, first.refs, first.data) == (m.kind, m.config, m.refs, m.data)
            and np.array_equal(first.value, m.value)  # type: ignore[arg-type]  # both noted with a value
            and np.array_equal(first.cov, m.cov)
        ):
            self._repeats.append((m.where, first.where))

    def _check_repeats(self) -> None:
        """Warn (:class:`~mbcal.errors.MeasurementFileWarning`) of rows that repeat an earlier row to
        all digits: almost always a row pasted twice, which counts its measurement twice (its σ as if
        halved in variance).  Not refused: one point measured twice can give the same number."""
        if not self._repeats:
            return
        (where, first), more = self._repeats[0], self._repeats[1:]
        word = self.row_word
        text = f"{where.path}:{where.line}: {word} repeats line {first.line} (same kind, names, configuration, "
        text += "values and σ: pasted twice?); both are used"
        if more:
            lines = ", ".join(str(w.line) for w, _ in more[:5]) + (", …" if len(more) > 5 else "")
            text += f"; {len(more)} more {word}s repeat earlier ones (lines {lines})"
        warnings.warn(MeasurementFileWarning(text), stacklevel=4)

    def _image_point(self, camera: int, value: np.ndarray, mid: str, where: SourceSpan | None) -> None:
        """Count an image point, and whether it lies outside its camera's image (by more than
        :data:`IMAGE_MARGIN` of the width or height: lens distortion and corners detected at the
        border are allowed for)."""
        counts = self._image_points.get(camera)
        if counts is None:
            counts = self._image_points[camera] = [0, 0, None]
        counts[0] += 1
        info = self.model.cameras[camera]
        u, v = float(value[0]), float(value[1])
        mu, mv = IMAGE_MARGIN * info.width, IMAGE_MARGIN * info.height
        if not (-mu <= u <= info.width + mu and -mv <= v <= info.height + mv):
            counts[1] += 1
            if counts[2] is None:
                counts[2] = (mid, where, u, v)

    def _check_image_points(self) -> None:
        """Refuse a camera most of whose image points lie outside its image: they are not in its
        pixels (another camera's resolution, scaled or doubled coordinates), and a fit to them
        went far outside the search ranges and still looked 'consistent and well determined'."""
        for camera, (total, outside, first) in self._image_points.items():
            if outside * 2 <= total:  # a few stray points are the fit's outliers to report
                continue
            info = self.model.cameras[camera]
            mid, where, u, v = first
            raise MeasurementFileError(
                f"{outside} of the {total} image points of camera '{self.model.short_name('camera', info.name)}' lie "
                f"outside its {info.width}×{info.height} image (by more than {IMAGE_MARGIN:.0%} of its width or "
                f"height), the first: measurement '{mid}' at u = {u:g}, v = {v:g}",
                where,
                hint="image points are in pixels of the camera's own image, (0, 0) its top-left corner: are they of "
                "another resolution, or scaled?",
            )

    def _values(self, record, mm: MeasurementModel, where, factor: float) -> np.ndarray | None:
        if mm.implicit_value is not None:
            given = [k for k in ("value", "distance", *mm.values) if not _blank(record.get(k))]
            if given:  # it would be ignored: the value of this kind is fixed
                raise MeasurementFileError(
                    f"'{mm.kind}' takes no value (it is {mm.implicit_value:g} by definition); '{given[0]}' is given",
                    where,
                    field=given[0],
                )
            return np.full(mm.size, mm.implicit_value)
        raw: list[Any] = []
        if not _blank(record.get("value")) and "value" not in mm.values:
            named = [n for n in mm.values if not _blank(record.get(n))]
            if named:  # two ways of giving the values at once: which one was meant?
                raise MeasurementFileError(
                    f"the values are given twice: as 'value' and as {', '.join(repr(n) for n in named)}; give one",
                    where,
                    field=named[0],
                )
            listed = record["value"]
            if isinstance(listed, np.ndarray):
                listed = listed.tolist()
            if not isinstance(listed, (list, tuple)):
                listed = [listed]
            if len(listed) != mm.size:
                raise MeasurementFileError(
                    f"'{mm.kind}' has {mm.size} values ({', '.join(mm.values)}), got {len(listed)}",
                    where,
                    field="value",
                )
            raw = list(listed)
        else:
            raw = [record.get(name) for name in mm.values]
            if len(raw) == 1 and isinstance(raw[0], (list, tuple)):
                if len(raw[0]) != 1:
                    raise MeasurementFileError(f"'{mm.kind}' has one value, got {len(raw[0])}", where)
                raw = list(raw[0])
        present = [r is not None and not (isinstance(r, str) and not r.strip()) for r in raw]
        if not any(present):
            return None
        if not all(present):
            missing = [n for n, p in zip(mm.values, present) if not p]
            raise MeasurementFileError(
                f"'{mm.kind}' needs all of {', '.join(mm.values)}; missing {', '.join(missing)}",
                where,
                field=missing[0],
            )
        return np.array([_number(r, where, f"value '{n}'", n) * factor for r, n in zip(raw, mm.values)])

    def _covariance(self, record, mm: MeasurementModel, where, factor: float) -> np.ndarray:
        size = mm.size
        if not _blank(record.get("cov")):
            given = [k for k in ("sigma", *(f"sigma_{n}" for n in mm.values)) if not _blank(record.get(k))]
            if given:  # the covariance would win silently
                raise MeasurementFileError(f"both 'cov' and '{given[0]}' are given; give one", where, field=given[0])
            raw = record["cov"]
            if isinstance(raw, str):
                raw = [p for p in re.split(r"[;\s]+", raw.strip()) if p]
            flat = np.array([_number(v, where, "'cov'", "cov") for v in np.ravel(np.asarray(raw, dtype=object))])
            if flat.size != size * size:
                raise MeasurementFileError(
                    f"'cov' must have {size}×{size} = {size * size} entries, got {flat.size}", where, field="cov"
                )
            cov = flat.reshape(size, size) * factor * factor
            if not np.allclose(cov, cov.T, rtol=1e-9, atol=0):
                raise MeasurementFileError("'cov' must be symmetric", where, field="cov")
            if np.any(np.linalg.eigvalsh(cov) <= 0):
                raise MeasurementFileError("'cov' must be positive definite", where, field="cov")
            return cov
        sigmas = []
        common = record.get("sigma")
        for name in mm.values:
            raw, column = record.get(f"sigma_{name}"), f"sigma_{name}"
            if _blank(raw):
                raw, column = common, "sigma"
            if isinstance(raw, (list, tuple, np.ndarray)):
                raise MeasurementFileError("'sigma' is one number; use 'cov' for a matrix", where, field=column)
            if _blank(raw):
                sigmas.append(mm.default_sigma)
                continue
            s = _number(raw, where, "'sigma'", column) * factor
            if not s > 0:
                raise MeasurementFileError(f"sigma must be positive, got {shown(raw)}", where, field=column)
            if not 0 < s * s < math.inf:  # its variance must be a number too (1e300² overflowed, with a warning)
                raise MeasurementFileError(
                    f"sigma {shown(raw)} is out of range: its square is not a finite positive number",
                    where,
                    field=column,
                )
            sigmas.append(s)
        key = (mm.kind, tuple(sigmas))
        shared = self._covariances.get(key)
        if shared is None:
            shared = np.diag(np.square(sigmas))
            shared.flags.writeable = False
            if len(self._covariances) < 10_000:
                self._covariances[key] = shared
        return shared

    def result(self) -> MeasurementSet:
        if not self.measurements:
            raise MeasurementFileError("no measurements", SourceSpan(self.path, 1, 1))
        self._check_configurations()
        self._check_image_points()
        self._check_repeats()
        if self.model is not None and self.known:  # as --set: sizes positive, poses finite with them
            from mbcal.language.check import check_at_nominal

            X = self.model.nominal.copy()
            for name, value in self.known.items():
                X[self.model.param_index(name)] = value
            check_at_nominal(self.model, X, where=f"with the known values of {self.path}")
        return MeasurementSet(self.measurements, self.known, self.configurations, self.path, self.images)

    def _check_configurations(self) -> None:
        check_configurations(
            self._given, [*self.configurations, *self._configs], self._config_where, self.configurations
        )


def check_configurations(
    given: Mapping[str | None, Mapping[str, str]],
    configs: Sequence[str],
    where: Mapping[str, SourceSpan | None],
    listed: Collection[str] = (),
) -> None:
    """Refuse a per-configuration value given in some configurations but not in another that is
    listed or measured in: the parameter would silently keep the model's nominal value there.
    (A value given once for every configuration covers the others; a parameter never given keeps
    its nominal value everywhere.)

    ``given``: configuration (None: every configuration) → {full parameter name: the name as
    written}; ``configs``: the configurations listed or measured in, in order; ``where``: where
    each is first seen; ``listed``: those written in a list of configurations (the others are
    only measured in, and the message says so)."""
    givers: dict[str, list[str]] = {}
    for config, names in given.items():
        if config is not None:
            for full in names:
                givers.setdefault(full, []).append(config)
    if not givers:
        return
    everywhere = given.get(None, {})
    for config in dict.fromkeys(configs):
        have = given.get(config, {})
        missing = [n for n in givers if n not in have and n not in everywhere]
        if not missing:
            continue
        name = missing[0]
        others = givers[name]
        shown = ", ".join(f"'{c}'" for c in others[:3]) + (f" and {len(others) - 3} more" if len(others) > 3 else "")
        also = ""
        if len(missing) > 1:
            rest = ", ".join(f"'{n}'" for n in missing[1:4]) + (", ..." if len(missing) > 4 else "")
            also = f" (nor for {rest})"
        measured = "" if config in listed else ", which measurements are taken in,"
        raise MeasurementFileError(
            f"configuration '{config}'{measured} gives no value for '{name}'{also}, which "
            f"{'configuration' if len(others) == 1 else 'configurations'} {shown} "
            f"{'gives' if len(others) == 1 else 'give'}: a per-configuration value must be given in every "
            "configuration, or it would silently take the model's nominal value there",
            where.get(config),
            hint=f"give '{name}' in configuration '{config}' too, or once without a configuration as its "
            "value in every configuration that does not give its own",
        )


def merge_measurements(sets: Sequence[MeasurementSet], model=None) -> MeasurementSet:
    """One set from several files: measurements appended, known values and images merged.

    Configurations with the same name are the same configuration.  Raises when two files use
    the same measurement id or give different known values for the same parameter, and when the
    files together give a per-configuration value in some configurations but not in another they
    measure in (each file alone may be complete: one gives the joint readings of configurations a
    and b, the other measures in a, b and c).  ``model`` resolves the parameters' names as written
    (a short and a full name of one parameter are one parameter); without it they are compared as
    written.
    """
    if len(sets) == 1:
        return sets[0]
    out = MeasurementSet([], {}, {}, ", ".join(s.path or "<records>" for s in sets), {})
    ids: dict[str, SourceSpan | None] = {}
    for ms in sets:
        for m in ms:
            if m.id in ids:
                raise MeasurementFileError(f"duplicate id '{m.id}' (first at {ids[m.id]})", m.where)
            ids[m.id] = m.where
            out.measurements.append(m)
        for name, value in ms.known.items():
            if name in out.known and out.known[name] != value:
                raise MeasurementFileError(f"'{name}' is known as {out.known[name]} and as {value} in {ms.path}")
            out.known[name] = value
        for config, values in ms.configurations.items():
            target = out.configurations.setdefault(config, {})
            for name, value in values.items():
                if name in target and target[name] != value:
                    raise MeasurementFileError(f"'{name}@{config}' is given two different values ({ms.path})")
                target[name] = value
        out.images.update(ms.images)

    def full(name: str) -> str:
        return model.param(name).name if model is not None else name

    given: dict[str | None, dict[str, str]] = {None: {full(n): n for n in out.known}}
    for config, values in out.configurations.items():
        given[config] = {full(n): n for n in values}
    where: dict[str, SourceSpan | None] = {}
    for m in out.measurements:
        where.setdefault(m.config, m.where)
    check_configurations(given, [*out.configurations, *where], where, out.configurations)
    return out


_COMMON_KEYS = {"id", "kind", "config", "configuration", "unit", "sigma", "cov", "value", "comment"}
"""Keys of every measurement record, whatever its kind (a CSV file's ``param`` column belongs to
its ``known`` rows: empty in a measurement row)."""


def csv_columns() -> set[str]:
    """The columns a CSV measurement file may have (those of every registered measurement kind,
    plugins' included); records take the same keys (:func:`record_keys`)."""
    cols = (_COMMON_KEYS - {"comment"}) | {"param"}
    for mm in registry().values():
        cols |= kind_keys(mm)
    return cols


def kind_keys(mm: MeasurementModel) -> set[str]:
    """The columns (record keys) of one measurement kind: its roles, values, data and a σ per value."""
    return {r.name for r in mm.roles} | set(mm.values) | set(mm.data) | {f"sigma_{v}" for v in mm.values}


def record_keys() -> set[str]:
    """The keys a measurement record (a JSON file's, or :func:`measurements_from_records`') may
    have: the CSV columns, less ``param`` (known values come as ``known`` and ``configurations``),
    plus ``comment`` (JSON has no comment lines)."""
    return (csv_columns() - {"param"}) | {"comment"}


def measurements_from_records(
    records: Iterable[Mapping[str, Any]], model=None, *, known=None, configurations=None
) -> MeasurementSet:
    """Build a :class:`MeasurementSet` from Python dicts shaped like the JSON records."""
    builder = SetBuilder(model, "<records>")
    for name, value in (known or {}).items():
        builder.known_value(name, value, None, None)
    for config, values in (configurations or {}).items():
        if not isinstance(values, Mapping):
            raise MeasurementFileError(
                f"configuration '{config}': expected a mapping of parameter values, got {shown(values)}"
            )
        builder.configuration(config, None)
        for name, value in values.items():
            builder.known_value(name, value, config, None)
    allowed = record_keys()
    for i, record in enumerate(records):
        if not isinstance(record, Mapping):
            raise MeasurementFileError(
                f"record {i + 1}: expected a mapping (a dict like a JSON record), got {shown(record)}"
            )
        lowered = {str(k).lower(): v for k, v in record.items()}
        for key in lowered:
            if key not in allowed:  # a typo ("sigam") would silently be the default
                raise MeasurementFileError(f"record {i + 1}: unknown key '{key}'", None, hint=suggest(key, allowed))
        builder.add(lowered, None, i + 1)
    return builder.result()
