"""The part of a residual that depends on its known inputs only, computed before its program.

A residual ``fun(x, *args)`` of a model whose known values come per configuration (joint
readings, a robot's pose in each attitude) computes much from ``args`` alone: the frames those
readings move and the cameras they carry.  Traced into the solver's program, that part was traced
under ``vmap`` and ``jacfwd`` and compiled with the loop, where XLA:CPU fused it into kernels that
each recomputed it (the seed's arm: 170 of the residual's 462 operations, the torso's and neck's
joints, in ten kernels of ~50 operations, one per entry of a camera pose; issue 16).

:func:`split` traces ``fun`` once and divides its operations: those computed from ``args`` (and
constants) alone by an operation NumPy can compute here (:data:`NUMPY`), and the rest.  The first
become a :class:`Recipe`, evaluated in NumPy from the arguments' values before each call; the rest
a function of ``x`` and the recipe's outputs (:attr:`Split.program`), the program the solver
traces.  The residual is the same to rounding (NumPy's sine may differ from XLA's in the last bit);
the first process and later ones compute the inputs by the same recipe, which the persistent cache
keeps beside the exported program (:meth:`Recipe.to_json`), so a later process neither traces
``fun`` nor splits it.

What depends on constants only stays in the program (XLA folds it), as does every operation
without a NumPy counterpart here (a dot product, a gather, integer division, custom derivatives).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import threading
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from jax.extend import core as jcore

from mbcal._jax import jax
from mbcal.cache import recipe_path, source_edited
from mbcal.outputs import atomic_write

__all__ = ["NUMPY", "Prepared", "Recipe", "Split", "StaleRecipeError", "forget", "prepare", "split"]

RECIPE_FORMAT = 1
# A constant read by the recipe is written into the cache's JSON: larger ones stay in the program.
_LARGEST_CONSTANT = 4096


def _broadcast_in_dim(a, *, shape, broadcast_dimensions, **_):
    full = [1] * len(shape)
    for i, d in enumerate(broadcast_dimensions):
        full[d] = a.shape[i]
    return np.broadcast_to(np.reshape(a, full), shape)


def _slice(a, *, start_indices, limit_indices, strides=None):
    steps = strides or (1,) * len(start_indices)
    return a[tuple(slice(s, e, k) for s, e, k in zip(start_indices, limit_indices, steps))]


def _iota(*, dtype, shape, dimension, **_):
    along = [1] * len(shape)
    along[dimension] = shape[dimension]
    return np.broadcast_to(np.arange(shape[dimension], dtype=dtype).reshape(along), shape)


def _select_n(which, *cases):
    if len(cases) == 1:
        return cases[0]
    if which.dtype == np.bool_:
        return np.where(which, cases[1], cases[0])
    return np.choose(which.astype(np.intp), np.broadcast_arrays(*cases))


def _flushed(v: np.ndarray) -> np.ndarray:
    """Subnormal floats as zeros of their sign, as XLA:CPU reads and writes them."""
    if v.dtype.kind != "f" or v.size == 0:
        return v
    small = (np.abs(v) < np.finfo(v.dtype).tiny) & (v != 0)
    return np.where(small, np.copysign(np.zeros((), v.dtype), v), v) if small.any() else v


def _elementwise(f: Callable) -> Callable:
    return lambda *a, **_: f(*a)


# The operations computed in NumPy: name → function(*inputs, **params).  Not here: sign, max and
# min (NumPy's sign(−0) is +0, XLA's −0; max(0, −0) differs likewise), and everything else that
# NumPy and XLA:CPU compute differently.  XLA:CPU flushes subnormal numbers to zero: the recipe
# does too (_flushed).  _FLOAT_ONLY: moved for floating-point values only (integer division and
# powers round differently in NumPy and XLA).
NUMPY: dict[str, Callable[..., Any]] = {
    "add": _elementwise(np.add),
    "sub": _elementwise(np.subtract),
    "mul": _elementwise(np.multiply),
    "neg": _elementwise(np.negative),
    "abs": _elementwise(np.abs),
    "eq": _elementwise(np.equal),
    "ne": _elementwise(np.not_equal),
    "lt": _elementwise(np.less),
    "le": _elementwise(np.less_equal),
    "gt": _elementwise(np.greater),
    "ge": _elementwise(np.greater_equal),
    "not": _elementwise(np.invert),
    "and": _elementwise(np.bitwise_and),
    "or": _elementwise(np.bitwise_or),
    "is_finite": _elementwise(np.isfinite),
    "square": _elementwise(np.square),
    "div": _elementwise(np.divide),
    "sin": _elementwise(np.sin),
    "cos": _elementwise(np.cos),
    "tan": _elementwise(np.tan),
    "asin": _elementwise(np.arcsin),
    "acos": _elementwise(np.arccos),
    "atan": _elementwise(np.arctan),
    "atan2": _elementwise(np.arctan2),
    "sinh": _elementwise(np.sinh),
    "cosh": _elementwise(np.cosh),
    "tanh": _elementwise(np.tanh),
    "exp": _elementwise(np.exp),
    "log": _elementwise(np.log),
    "log1p": _elementwise(np.log1p),
    "expm1": _elementwise(np.expm1),
    "sqrt": _elementwise(np.sqrt),
    "pow": _elementwise(np.power),
    "broadcast_in_dim": _broadcast_in_dim,
    "slice": _slice,
    "squeeze": lambda a, *, dimensions: np.squeeze(a, axis=tuple(dimensions)),
    "reshape": lambda a, *, new_sizes, **_: np.reshape(a, new_sizes),
    "transpose": lambda a, *, permutation: np.transpose(a, permutation),
    "concatenate": lambda *a, dimension: np.concatenate(a, axis=dimension),
    "stack": lambda *a, axis: np.stack(a, axis=axis),
    "iota": _iota,
    "select_n": _select_n,
    "convert_element_type": lambda a, *, new_dtype, **_: a.astype(new_dtype),
    "copy": _elementwise(np.array),
    "reduce_sum": lambda a, *, axes, **_: np.sum(a, axis=tuple(axes)),
}
_FLOAT_ONLY = {"div", "pow", "sin", "cos", "tan", "asin", "acos", "atan", "atan2", "sinh", "cosh", "tanh"}
_FLOAT_ONLY |= {"exp", "log", "log1p", "expm1", "sqrt"}


def _plain(value: Any) -> bool:
    """Whether a parameter value can be written to JSON and read back as it was."""
    if value is None or isinstance(value, (bool, int, float, str, np.dtype)):
        return True
    if isinstance(value, tuple):
        return all(_plain(v) for v in value)
    return False


def _movable(eqn: Any) -> bool:
    """Whether NumPy computes this operation here as XLA would (a nested jitted function: all of
    its own operations)."""
    name = eqn.primitive.name
    if name in ("jit", "pjit"):
        inner = eqn.params["jaxpr"]
        small = all(np.size(c) <= _LARGEST_CONSTANT for c in inner.consts)
        return small and not eqn.effects and all(_movable(e) for e in inner.jaxpr.eqns)
    if name not in NUMPY or eqn.effects:
        return False
    params = dict(eqn.params)
    if params.pop("accuracy", None) is not None:  # a transcendental asked for another accuracy
        return False
    if name == "reshape" and params.get("dimensions") is not None:
        return False
    if params.get("sharding") is not None or params.get("out_sharding") is not None:
        return False
    if not all(_plain(v) for v in params.values()):
        return False
    avals = [v.aval for v in (*eqn.invars, *eqn.outvars)]
    if not all(getattr(a, "shape", None) is not None and hasattr(a, "dtype") for a in avals):
        return False
    kinds = {np.dtype(a.dtype).kind for a in avals}
    if "c" in kinds or not kinds <= set("biuf"):  # complex numbers (JSON has none), and other kinds
        return False
    if name in _FLOAT_ONLY and kinds != {"f"}:
        return False
    # float → integer: XLA saturates (NaN → 0), NumPy wraps or gives INT_MIN
    return not (name == "convert_element_type" and np.dtype(params["new_dtype"]).kind in "iu" and "f" in kinds)


# ---- the recipe: the moved operations, flat, as data ---------------------------------------------

# A reference to a value: ("a", i) the i-th argument, ("c", i) the i-th constant, ("v", i) the
# output of an operation, ("l", value, dtype) a literal number.
Ref = tuple


# The recipe's JSON: Python's json module writes and reads NaN and ±Infinity as they are (mbcal
# alone reads these files); dtypes and tuples are marked.


def _encode(value: Any) -> Any:
    if isinstance(value, np.dtype):
        return {"dtype": value.name}
    if isinstance(value, tuple):
        return {"tuple": [_encode(v) for v in value]}
    return value


def _decode(value: Any) -> Any:
    if isinstance(value, dict):
        if "dtype" in value:
            return np.dtype(value["dtype"])
        if "tuple" in value:
            return tuple(_decode(v) for v in value["tuple"])
    if isinstance(value, list):
        return tuple(_decode(v) for v in value)
    return value


@dataclass(frozen=True)
class Recipe:
    """The operations moved out of a program, flat (nested jitted functions inlined), with the
    constants they read: evaluated by :meth:`inputs` in NumPy, written to the cache as JSON."""

    n_args: int
    constants: tuple[np.ndarray, ...]
    steps: tuple[tuple[str, dict, tuple[Ref, ...], tuple[tuple[int, str, tuple[int, ...]], ...]], ...]
    outputs: tuple[Ref, ...]
    # The last arguments (their bytes) and the inputs made from them: a warm solve called again
    # with the same data does not evaluate the recipe again (the arm's: ~0.5 ms of ~19 ms).
    _last: list = field(default_factory=list, compare=False, repr=False)

    def inputs(self, args: Sequence[Any]) -> tuple[np.ndarray, ...]:
        """The program's inputs besides the unknowns, from the residual's ``args``."""
        if len(args) != self.n_args:
            raise ValueError(f"the recipe takes {self.n_args} arguments, got {len(args)}")
        given = [np.asarray(a) for a in args]
        key = tuple((a.shape, a.dtype.str, a.tobytes()) for a in given)
        last = self._last[0] if self._last else None
        if last is not None and last[0] == key:
            return last[1]
        made = self._evaluate(given)
        self._last[:] = [(key, made)]
        return made

    def _evaluate(self, given: list[np.ndarray]) -> tuple[np.ndarray, ...]:
        values: dict[int, np.ndarray] = {}
        given = [_flushed(a) for a in given]

        def read(ref: Ref) -> np.ndarray:
            kind = ref[0]
            if kind == "a":
                return given[ref[1]]
            if kind == "c":
                return _flushed(self.constants[ref[1]])
            if kind == "l":
                return _flushed(np.asarray(ref[1], dtype=ref[2]))
            return values[ref[1]]

        with np.errstate(all="ignore"):  # NaN and inf as the program gives them, without warnings
            for name, params, ins, outs in self.steps:
                result = NUMPY[name](*(read(r) for r in ins), **params)
                (index, dtype, shape) = outs[0]
                result = _flushed(np.asarray(result, dtype=dtype))
                if result.shape != shape:
                    raise ValueError(f"{name} gave shape {result.shape}, not {shape}")
                values[index] = result
            # copies (C order, 0-d kept): an input kept by the memo never aliases a caller's array
            return tuple(np.array(read(r), order="C") for r in self.outputs)

    @functools.cached_property
    def digest(self) -> str:
        """SHA-256 of :meth:`to_json`: the exported program made for this recipe is keyed by it."""
        return hashlib.sha256(self.to_json().encode("utf-8")).hexdigest()

    def to_json(self) -> str:
        constants = [
            {"dtype": c.dtype.name, "shape": list(c.shape), "data": c.ravel().tolist()} for c in self.constants
        ]
        steps = [
            [
                name,
                {k: _encode(v) for k, v in params.items()},
                [list(r) for r in ins],
                [[i, d, list(s)] for i, d, s in outs],
            ]
            for name, params, ins, outs in self.steps
        ]
        outputs = [list(r) for r in self.outputs]
        return json.dumps(
            {"format": RECIPE_FORMAT, "n_args": self.n_args, "constants": constants, "steps": steps, "outputs": outputs}
        )

    @staticmethod
    def from_json(text: str) -> Recipe:
        doc = json.loads(text)
        if not isinstance(doc, dict) or doc.get("format") != RECIPE_FORMAT:
            raise ValueError("another recipe format")
        constants = tuple(np.asarray(c["data"], dtype=c["dtype"]).reshape(c["shape"]) for c in doc["constants"])
        steps = []
        for name, params, ins, outs in doc["steps"]:
            if name not in NUMPY:
                raise ValueError(f"unknown operation {name!r}")
            steps.append(
                (
                    name,
                    {k: _decode(v) for k, v in params.items()},
                    tuple(_ref_from_json(r) for r in ins),
                    tuple((int(i), str(d), tuple(int(n) for n in s)) for i, d, s in outs),
                )
            )
        return Recipe(int(doc["n_args"]), constants, tuple(steps), tuple(_ref_from_json(r) for r in doc["outputs"]))


def _ref_from_json(ref: list) -> Ref:
    if ref[0] == "l":
        return ("l", ref[1], str(ref[2]))
    if ref[0] not in ("a", "c", "v"):
        raise ValueError(f"unknown reference {ref!r}")
    return (str(ref[0]), int(ref[1]))


# ---- the split ---------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Split:
    """``fun(*unknowns, *args)`` in two parts: ``program(*unknowns, *recipe.inputs(args))`` is the
    residual; ``moved`` operations were taken out of the program, ``kept`` stay."""

    program: Callable[..., Any]
    recipe: Recipe
    moved: int
    kept: int


def _literal(v: Any) -> Ref:
    value = v.val
    dtype = np.dtype(v.aval.dtype)
    item = np.asarray(value, dtype=dtype).item()
    return ("l", item, dtype.name)


def split(fun: Callable[..., Any], unknowns: Sequence[Any], args: Sequence[Any]) -> Split:
    """Trace ``fun(*unknowns, *args)`` (shapes and dtypes are all it reads of the values) and split
    it (module documentation)."""
    n_unknown = len(unknowns)
    closed = jax.make_jaxpr(fun)(*unknowns, *args)
    jaxpr = closed.jaxpr
    arg_vars = jaxpr.invars[n_unknown:]
    # Values computed from the arguments (at least one) and small constants, by movable operations.
    from_args: dict[Any, Ref] = {v: ("a", i) for i, v in enumerate(arg_vars)}
    constants: list[np.ndarray] = []
    small: dict[Any, Any] = {}
    for v, value in zip(jaxpr.constvars, closed.consts):
        if np.size(value) <= _LARGEST_CONSTANT:
            small[v] = value
    steps: list = []
    moved, kept = [], []
    counter = [0]

    const_refs: dict = {}

    def ref_of(v: Any) -> Ref:
        if isinstance(v, jcore.Literal):
            return _literal(v)
        if v in from_args:
            return from_args[v]
        if v not in const_refs:
            const_refs[v] = ("c", len(constants))
            constants.append(np.asarray(small[v]))
        return const_refs[v]

    def emit(eqn: Any, ins: list[Ref]) -> list[Ref]:
        """Append eqn's steps (a nested jitted function inlined) and return its outputs' refs."""
        if eqn.primitive.name in ("jit", "pjit"):
            inner = eqn.params["jaxpr"]
            local: dict[Any, Ref] = dict(zip(inner.jaxpr.invars, ins))
            inner_consts = dict(zip(inner.jaxpr.constvars, inner.consts))
            for v, value in inner_consts.items():
                local[v] = ("c", len(constants))
                constants.append(np.asarray(value))
            for e in inner.jaxpr.eqns:
                e_ins = [_literal(v) if isinstance(v, jcore.Literal) else local[v] for v in e.invars]
                for v, r in zip(e.outvars, emit(e, e_ins)):
                    local[v] = r
            return [_literal(v) if isinstance(v, jcore.Literal) else local[v] for v in inner.jaxpr.outvars]
        index = counter[0]
        counter[0] += 1
        out = eqn.outvars[0]
        params = {k: v for k, v in eqn.params.items() if k not in ("accuracy", "sharding", "out_sharding")}
        steps.append(
            (eqn.primitive.name, params, tuple(ins), ((index, np.dtype(out.aval.dtype).name, tuple(out.aval.shape)),))
        )
        return [("v", index)]

    for eqn in jaxpr.eqns:
        vars_in = [v for v in eqn.invars if not isinstance(v, jcore.Literal)]
        available = all(v in from_args or v in small for v in vars_in)
        if vars_in and available and any(v in from_args for v in vars_in) and _movable(eqn):
            ins = [ref_of(v) for v in eqn.invars]  # every NUMPY operation has one output
            for v, r in zip(eqn.outvars, emit(eqn, ins)):
                from_args[v] = r
            moved.append(eqn)
        else:
            kept.append(eqn)
    # The moved values the program reads (arguments it reads directly included): its new inputs.
    needed: list = []
    seen: set = set()
    for atom in [*(v for e in kept for v in e.invars), *jaxpr.outvars]:
        if not isinstance(atom, jcore.Literal) and atom in from_args and atom not in seen:
            seen.add(atom)
            needed.append(atom)
    recipe = Recipe(len(arg_vars), tuple(constants), tuple(steps), tuple(from_args[v] for v in needed))
    invars = [*jaxpr.invars[:n_unknown], *needed]
    names = tuple(jaxpr.debug_info.arg_names or ())[:n_unknown]
    names += tuple(f"input{i}" for i in range(len(invars) - len(names)))
    program_jaxpr = jcore.Jaxpr(
        constvars=jaxpr.constvars,
        invars=invars,
        outvars=jaxpr.outvars,
        eqns=kept,
        effects=jaxpr.effects,
        debug_info=jaxpr.debug_info._replace(arg_names=names),
    )
    consts = list(closed.consts)
    single = len(jaxpr.outvars) == 1

    def program(*values: Any) -> Any:
        out = jax.core.eval_jaxpr(program_jaxpr, consts, *values)
        return out[0] if single else out

    return Split(program, recipe, len(moved), len(kept))


# ---- one split per function and shapes; the recipe kept in the persistent cache -------------------


def signature(values: Sequence[Any]) -> tuple:
    """Shapes, dtypes and weak types (a JAX array's: it changes type promotion): what a split
    depends on besides the function."""
    return tuple(
        (
            tuple(np.shape(v)),
            np.dtype(getattr(v, "dtype", None) or np.asarray(v).dtype).name,
            bool(getattr(v, "weak_type", False)),
        )
        for v in values
    )


def _abstract(sig: tuple) -> list[Any]:
    return [jax.ShapeDtypeStruct(shape, np.dtype(dtype), weak_type=weak) for shape, dtype, weak in sig]


# A few functions only (as mbcal.solver._compiled): a split holds its function's trace.
@functools.lru_cache(maxsize=8)
def _split_for(fun: Callable[..., Any], unknowns: tuple, args: tuple) -> Split:
    return split(fun, _abstract(unknowns), _abstract(args))


class StaleRecipeError(Exception):
    """Raised while a program is traced for a recipe read from the cache that this process's split
    of the function does not give (made by another version or other settings of JAX): the caller
    solves without the cached recipe (:func:`forget`)."""


@functools.lru_cache(maxsize=8)
def _program_for(fun: Callable[..., Any], unknowns: tuple, args: tuple, digest: str) -> Callable[..., Any]:
    """The program of ``fun``'s split for the recipe ``digest``, one object per function, shapes and
    recipe (programs compiled from it are found again), splitting ``fun`` only when it is traced:
    a process that loads the exported program and the recipe never does."""

    def program(*values: Any) -> Any:
        made = _split_for(fun, unknowns, args)
        if made.recipe.digest != digest:
            raise StaleRecipeError(digest)
        return made.program(*values)

    return program


def forget(key: str) -> None:
    """Drop the recipe kept for ``key``, in this process and in the cache folder."""
    with _RECIPES_LOCK:
        for entry in [k for k in _RECIPES if k[1] == key]:
            del _RECIPES[entry]
    path = recipe_path(key)
    if path is not None:
        with contextlib.suppress(OSError):
            path.unlink()


class Prepared(NamedTuple):
    """What :func:`prepare` gives: call ``program(*unknowns, *inputs)``; ``digest`` identifies the
    recipe (an exported program of ``program`` is keyed by it, so the two never mismatch)."""

    program: Callable[..., Any]
    inputs: tuple[np.ndarray, ...]
    digest: str


# Recipes read or made in this process, by function, cache key and shapes (a few: as the solver's
# programs): a warm solve neither reads nor parses its recipe again.
_RECIPES: OrderedDict[tuple, Recipe] = OrderedDict()
_RECIPES_LOCK = threading.Lock()


def _remember(key: tuple, recipe: Recipe) -> None:
    with _RECIPES_LOCK:
        _RECIPES[key] = recipe
        _RECIPES.move_to_end(key)
        while len(_RECIPES) > 8:
            _RECIPES.popitem(last=False)


def prepare(
    fun: Callable[..., Any], unknowns: Sequence[Any], args: Sequence[Any], key: str | None = None
) -> Prepared | None:
    """The residual split (:func:`split`) with its inputs for ``args``: ``program(*unknowns,
    *inputs) == fun(*unknowns, *args)``; None when ``fun`` is not split (it cannot be a cache key,
    or tracing it fails: the solver traces it whole and meets the error there).  ``key``: where the
    persistent cache keeps the recipe, read from there or written there."""
    try:
        hash(fun)
    except TypeError:  # the splits are kept per function: one that cannot be a key is not split
        return None
    sig_u, sig_a = signature(unknowns), signature(args)
    path = None if key is None else recipe_path(key)
    recipe = None
    from_disk = False
    memory = (fun, key, sig_u, sig_a)
    if key is not None:
        with _RECIPES_LOCK:
            recipe = _RECIPES.get(memory)
    if recipe is None and path is not None and path.is_file():
        try:
            recipe = Recipe.from_json(path.read_text(encoding="utf-8"))
            from_disk = True
        except Exception:  # noqa: BLE001 — truncated, foreign or of another version: split again, write anew
            recipe = None
    if recipe is None:
        try:
            made = _split_for(fun, sig_u, sig_a)
        except Exception:  # noqa: BLE001 — whatever fails here fails again, with its own message, where the solver traces fun
            return None
        recipe = made.recipe
        if path is not None and not source_edited(exact=True):
            with contextlib.suppress(Exception):  # a read-only cache: still correct, only slower next time
                path.parent.mkdir(parents=True, exist_ok=True)
                atomic_write(path, recipe.to_json().encode("utf-8"), at_once=True)
    try:
        inputs = recipe.inputs(args)
        digest = recipe.digest
    except Exception:  # noqa: BLE001 — a recipe that does not fit these arguments: the program computes it all
        if from_disk and key is not None:
            forget(key)  # and the next call splits again and writes its own
        return None
    if key is not None:
        _remember(memory, recipe)
    return Prepared(_program_for(fun, sig_u, sig_a, digest), inputs, digest)
