"""param(p, x): which parameters are unknown, what the known ones are, per configuration.

A :class:`ParameterSet` splits a model's parameters into unknowns x (to estimate) and known
values p, and maps x back to the full parameter matrix X — one row per configuration — that
:func:`mbcal.modeling.modeler` takes (seed eq. 12).

Configurations are the attitudes of a robot, the views of a camera, ...: a parameter declared
``per configuration`` has one copy per configuration, known (a joint reading) or unknown (the
pose of a target in each view).  Unknown copies are named ``name@configuration``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mbcal._jax import jnp
from mbcal.errors import ParameterError, shown, suggest
from mbcal.language.model import Model, ParamInfo

Array = Any

__all__ = ["ParameterSet", "ParamView", "Unknown", "DEFAULT_CONFIGURATION"]

DEFAULT_CONFIGURATION = "default"


@dataclass(frozen=True)
class Unknown:
    """One entry of x.

    Attributes
    ----------
    name : str
        ``param`` or ``param@configuration`` for a per-configuration copy.
    param : ParamInfo
        The model parameter it sets.
    configuration : str or None
        The configuration of a per-configuration copy (None: the same in all).
    """

    name: str
    param: ParamInfo
    configuration: str | None

    @property
    def lower(self) -> float | None:
        return self.param.lower

    @property
    def upper(self) -> float | None:
        return self.param.upper

    @property
    def sigma(self) -> float | None:
        return self.param.sigma

    @property
    def limits(self) -> tuple[float, float]:
        """The hard limits (−inf, inf where the model gives none); a per-configuration copy has its parameter's."""
        lo, hi = self.param.limit_lower, self.param.limit_upper
        return (-np.inf if lo is None else lo, np.inf if hi is None else hi)


class ParameterSet:
    """The split of a model's parameters into unknown x and known p.

    Parameters
    ----------
    model : Model
        The model description.
    unknown : sequence of str
        Names or glob patterns (``room.*``, ``arm.offset?``) of the parameters to estimate.
        ``pattern@config`` selects the copy of a per-configuration parameter in one
        configuration only.
    known : mapping, optional
        Values (SI units) that replace the model's nominal values: ``{"lever.angle": 0.5}``;
        ``"name@config"`` sets one configuration's copy.
    configurations : sequence of str, optional
        Names of the configurations (default: one, called ``default``).
    per_configuration : mapping, optional
        ``{config: {name: value}}``: known per-configuration values (joint readings).
    overrides : mapping, optional
        Like ``known``, but applied last, over ``per_configuration`` too: the values a user gives
        beside a measurement file (the command line's ``--set``, ``name@config`` included).

    Raises
    ------
    ParameterError
        An unknown name or pattern matches nothing (the message lists close matches), a value
        is not finite, or a per-configuration value is given for a parameter that is not
        declared ``per configuration``.
    """

    def __init__(
        self,
        model: Model,
        unknown: Sequence[str] = (),
        *,
        known: Mapping[str, float] | None = None,
        configurations: Sequence[str] | None = None,
        per_configuration: Mapping[str, Mapping[str, float]] | None = None,
        overrides: Mapping[str, float] | None = None,
    ):
        self.model = model
        configs = list(configurations) if configurations else [DEFAULT_CONFIGURATION]
        if len(set(configs)) != len(configs):
            raise ParameterError("configuration names must be unique")
        self.configurations: tuple[str, ...] = tuple(configs)
        self._config_index = {c: i for i, c in enumerate(configs)}
        n = len(model.params)
        base = np.tile(model.nominal, (len(configs), 1))
        given_values: set[int] = set()  # the parameters a caller or a file gives a value of
        self._set(base, known, given_values)
        for given, values in (per_configuration or {}).items():
            row = self._config(given, given)
            for name, value in values.items():
                i = model.param_index(name)
                if not model.params[i].per_configuration:
                    raise ParameterError(
                        f"configuration '{given}' gives a value for '{name}', which is not declared "
                        "'per configuration' in the model",
                        hint=f"declare it as 'param {name} = ... per configuration'",
                    )
                base[row, i] = _finite(value, f"{name}@{given}")
                given_values.add(i)
        self._set(base, overrides, given_values)
        self.known = base  # (C, n): the known values, and initial values of the unknowns

        unknowns: list[Unknown] = []
        seen: set[str] = set()
        for pattern in unknown:
            name_pattern, config = _split(pattern)
            if config is not None:
                self._config(config, pattern)
            matches = model.match_params(name_pattern)
            if not matches:
                hint = suggest(name_pattern, model.names("param"))
                raise ParameterError(f"no parameter matches '{pattern}'", hint=hint or _listing(model))
            for name in matches:
                info = model.param(name)
                if info.per_configuration:
                    selected = [config] if config is not None else configs
                    entries = [Unknown(f"{name}@{c}", info, c) for c in selected]
                else:
                    if config is not None:
                        raise ParameterError(f"'{name}' is not declared 'per configuration'; drop '@{config}'")
                    entries = [Unknown(name, info, None)]
                for e in entries:
                    if e.name not in seen:
                        seen.add(e.name)
                        unknowns.append(e)
        # Global unknowns first (model order), then per-configuration copies by configuration.
        unknowns.sort(
            key=lambda u: (u.configuration is not None, self._config_index.get(u.configuration or "", 0), u.param.index)
        )
        self.unknowns: tuple[Unknown, ...] = tuple(unknowns)
        # read per call by the solver's set-up (issue 16): once here, copies handed out
        self._names = [u.name for u in unknowns]
        self._index = {name: j for j, name in enumerate(self._names)}
        self._x0_at = (self._slot_rows(), np.array([u.param.index for u in unknowns], dtype=np.int64))
        self._lower = np.array([np.nan if u.lower is None else u.lower for u in unknowns], dtype=float)
        self._upper = np.array([np.nan if u.upper is None else u.upper for u in unknowns], dtype=float)
        self._limits = np.array([u.limits for u in unknowns], dtype=float).reshape(-1, 2)
        self._bounded = any(u.param.limited for u in unknowns)

        rows, cols, src = [], [], []
        for j, u in enumerate(self.unknowns):
            targets = [self._config_index[u.configuration]] if u.configuration is not None else range(len(configs))
            for r in targets:
                rows.append(r)
                cols.append(u.param.index)
                src.append(j)
        self._rows = np.asarray(rows, dtype=np.int64)
        self._cols = np.asarray(cols, dtype=np.int64)
        self._src = np.asarray(src, dtype=np.int64)
        self._n_params = n
        # For each parameter and configuration: the position in x of its unknown, or -1 when known.
        source = np.full((len(configs), n), -1, dtype=np.int64)
        source[self._rows, self._cols] = self._src
        self._source = source
        # The model's own values: known in every configuration and given by nobody but the model
        # (its design data), so every problem of this model and structure has them.  Views for a
        # compiled program (``view(..., model_constants=True)``) hand them out as numbers, and the
        # frames, points and cameras built from them fold while tracing: the room's residual 410 →
        # 132 operations (issue 16).  Values given by a file, ``known`` or ``overrides`` stay inputs
        # of the program: new values do not compile it again.
        fixed = np.all(source < 0, axis=0)
        fixed[list(given_values)] = False
        self.model_constants: np.ndarray = fixed  # (n_params,) bool

    # ---- basic properties ----------------------------------------------------------------------

    def _config(self, name: str, context: str) -> int:
        if name not in self._config_index:
            raise ParameterError(
                f"'{context}': no configuration named '{name}'",
                hint=suggest(name, self._config_index) or f"configurations: {', '.join(self.configurations)}",
            )
        return self._config_index[name]

    def _set(self, base: np.ndarray, values: Mapping[str, float] | None, given: set[int]) -> None:
        """Write ``{name or name@config: value}`` into the (C, n) table of values; add the
        parameters written to ``given``."""
        for key, value in (values or {}).items():
            name, config = _split(key)
            i = self.model.param_index(name)
            given.add(i)
            rows = [self._config(config, key)] if config is not None else list(range(len(self.configurations)))
            if config is not None and not self.model.params[i].per_configuration:
                raise ParameterError(f"'{name}' is not declared 'per configuration'; set it without '@{config}'")
            base[rows, i] = _finite(value, key)
            outside = self.model.params[i].outside_limits(float(base[rows[0], i])) if rows else None
            if outside:
                raise ParameterError(f"the given value of '{key}': {outside}")

    @property
    def names(self) -> list[str]:
        """Names of the unknowns, in the order of x."""
        return list(self._names)

    @property
    def size(self) -> int:
        """Number of unknowns."""
        return len(self.unknowns)

    def __len__(self) -> int:
        return len(self.unknowns)

    @property
    def x0(self) -> np.ndarray:
        """The unknowns' initial values: nominal (or given) values."""
        return self.known[self._x0_at].astype(float)

    def _slot_rows(self) -> list[int]:
        return [self._config_index[u.configuration] if u.configuration is not None else 0 for u in self.unknowns]

    @property
    def lower(self) -> np.ndarray:
        """Lower ends of the search ranges (nan where none is declared); the hard limits are
        :attr:`limit_lower` and :attr:`limit_upper`."""
        return self._lower.copy()

    @property
    def upper(self) -> np.ndarray:
        """Upper ends of the search ranges (nan where none is declared)."""
        return self._upper.copy()

    @property
    def limit_lower(self) -> np.ndarray:
        """Hard lower limits of the unknowns (−inf where none): the solver never goes below them."""
        return self._limits[:, 0].copy()

    @property
    def limit_upper(self) -> np.ndarray:
        """Hard upper limits of the unknowns (inf where none)."""
        return self._limits[:, 1].copy()

    @property
    def bounded(self) -> bool:
        """Whether any unknown has a hard limit."""
        return self._bounded

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(limit_lower, limit_upper)`` for :func:`mbcal.solver.least_squares`, or None when no
        unknown has a limit (the solver then runs exactly as without bounds)."""
        return (self.limit_lower, self.limit_upper) if self.bounded else None

    @property
    def prior_sigma(self) -> np.ndarray:
        """Prior standard deviations (nan where none is declared)."""
        return np.array([np.nan if u.sigma is None else u.sigma for u in self.unknowns], dtype=float)

    @property
    def prior_mean(self) -> np.ndarray:
        """The values the priors pull towards: the model's nominal values."""
        return np.array([u.param.nominal for u in self.unknowns], dtype=float)

    # ---- the mapping -----------------------------------------------------------------------------

    def param(self, x: Array, known: Array | None = None) -> Array:
        """X = param(p, x): the (C, n_params) matrix of all parameter values, one row per configuration.

        Differentiable with respect to ``x`` (JAX).  ``known`` replaces :attr:`known` (same shape)
        without recompiling a jitted caller.
        """
        base = jnp.asarray(self.known if known is None else known)
        if self.size == 0:
            return base
        x = jnp.asarray(x)
        if jnp.shape(x) != (self.size,):  # known while tracing too: a gather would clamp, not fail
            raise ParameterError(f"x must hold one value per unknown ({self.size}), got shape {jnp.shape(x)}")
        return base.at[self._rows, self._cols].set(x[self._src])

    def views(self, x: Array, known: Array | None = None) -> tuple[Array, Array]:
        """What :class:`ParamView` needs, per configuration: the known rows and the configuration numbers."""
        base = jnp.asarray(self.known if known is None else known)
        return base, jnp.arange(base.shape[0])

    def view(self, x: Array, known_row: Array, config: Array, *, model_constants: bool = False) -> ParamView:
        """One configuration's parameter values, reading unknowns from x and the rest from ``known_row``.

        Unlike a row of :meth:`param`, the known values carry no derivative: forward-mode
        differentiation then skips everything that depends on known values only (a camera on a
        robot's neck, when only the arm is calibrated).  With ``model_constants`` the parameters
        of :attr:`model_constants` are the model's nominal values as numbers, not read from
        ``known_row``: a program traced so depends on them, and must be keyed by the model (as
        :meth:`mbcal.problem.Problem.fingerprint` is).
        """
        constants = self.model.nominal if model_constants else None
        return ParamView(self._source, x, known_row, config, constants, self.model_constants)

    def slots(self, configuration: int = 0) -> np.ndarray:
        """(n_params,) for each parameter of the model, the position in x of the unknown that gives
        its value in configuration number ``configuration``, or −1 where it is known (a copy)."""
        return self._source[configuration].copy()

    def X(self, x: Array | None = None) -> np.ndarray:
        """Like :meth:`param`, eagerly with numpy (default x: :attr:`x0`)."""
        X = self.known.copy()
        if self.size:
            x = self.x0 if x is None else np.asarray(x, dtype=float)
            if x.shape != (self.size,):
                raise ParameterError(f"x must hold one value per unknown ({self.size}), got shape {x.shape}")
            X[self._rows, self._cols] = x[self._src]
        return X

    def to_dict(self, x: Array) -> dict[str, float]:
        """x as ``{unknown name: value}`` (SI units)."""
        x = np.asarray(x, dtype=float)
        return {u.name: float(v) for u, v in zip(self.unknowns, x)}

    def from_dict(self, values: Mapping[str, float], default: Array | None = None) -> np.ndarray:
        """x from ``{unknown name: value}``; missing entries come from ``default`` (or :attr:`x0`)."""
        x = np.array(self.x0 if default is None else default, dtype=float)
        index = self._index
        for name, value in values.items():
            if name not in index:
                raise ParameterError(f"'{name}' is not an unknown", hint=suggest(name, index))
            x[index[name]] = _finite(value, name)
        return x

    def values(self, x: Array | None = None, configuration: str | None = None) -> dict[str, float]:
        """All parameter values by name for one configuration (default: the first)."""
        X = self.X(x)
        row = 0 if configuration is None else self._config(configuration, configuration)
        return {p.name: float(X[row, p.index]) for p in self.model.params}

    def info(self, name: str) -> ParamInfo:
        """The model parameter behind an unknown name (``arm.q1@pose3`` → ``arm.q1``)."""
        return self.model.param(_split(name)[0])


def _split(key: str) -> tuple[str, str | None]:
    if "@" in key:
        name, config = key.split("@", 1)
        return name, config
    return key, None


def _finite(value: Any, what: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"'{what}': not a number: {shown(value)}") from None
    if not np.isfinite(v):
        raise ParameterError(f"'{what}': value must be finite, got {v}")
    return v


def _listing(model: Model) -> str:
    names = model.names("param")
    if not names:
        return "the model declares no parameters"
    shown = ", ".join(names[:12]) + (", ..." if len(names) > 12 else "")
    return f"parameters: {shown}"


class ParamView:
    """Parameter values of one configuration, indexable like a row of X (see ParameterSet.view)."""

    def __init__(
        self,
        source: np.ndarray,
        x: Array,
        known_row: Array,
        config: Array,
        constants: np.ndarray | None = None,
        fixed: np.ndarray | None = None,
    ):
        self._source = source
        self._x = x
        self._known = known_row
        self._config = config
        self._constants = constants  # (n_params,) values of the parameters marked in ``fixed``
        self._fixed = fixed

    def __len__(self) -> int:
        return int(self._source.shape[1])

    @property
    def shape(self) -> tuple[int]:
        return (len(self),)

    @property
    def ndim(self) -> int:
        return 1

    def __getitem__(self, i: int) -> Array:
        if self._constants is not None and self._fixed is not None and self._fixed[i]:
            return float(self._constants[i])  # the model's own value: a number, folded while tracing
        column = self._source[:, i]
        if np.all(column < 0):
            return self._known[i]  # known in every configuration: no derivative
        if np.all(column == column[0]):
            return self._x[int(column[0])]  # the same unknown in every configuration
        where = jnp.asarray(column)[self._config]
        value = self._x[jnp.maximum(where, 0)]
        if np.any(column < 0):
            return jnp.where(where >= 0, value, self._known[i])
        return value
