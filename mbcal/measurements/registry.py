"""The registry of measurement models: mbcal's built-ins and plugins, found the same way.

Models are found through the ``mbcal.measurements`` entry-point group.  A plugin package
declares, in its ``pyproject.toml``::

    [project.entry-points."mbcal.measurements"]
    my_kind = "my_package.module:MyModel"

where ``MyModel`` follows :class:`~mbcal.measurements.protocol.MeasurementModel`.  The
built-ins are registered that way in mbcal's own ``pyproject.toml``, and are added directly
when mbcal runs from a source tree without installed metadata.  :func:`register` adds a model
from Python (a notebook).  See docs/plugins.md.
"""

from __future__ import annotations

import warnings
from importlib import metadata
from typing import Any

from mbcal.cache import source_fingerprint
from mbcal.errors import MbcalError, MdlError, MeasurementFileError, MeasurementModelError, SourceSpan, suggest
from mbcal.language.model import Model
from mbcal.measurements.builtin import BUILTINS
from mbcal.measurements.protocol import MeasurementModel

__all__ = [
    "registry",
    "get_model",
    "declared_models",
    "register",
    "register_measurement_model",
    "describe",
    "call_model",
    "ENTRY_POINT_GROUP",
]

ENTRY_POINT_GROUP = "mbcal.measurements"

_REGISTRY: dict[str, MeasurementModel] | None = None
_EXTRA: dict[str, MeasurementModel] = {}
# The package (distribution) of each model an entry point provided, by id; the model is kept with
# it, so that the id is never another object's.
_PACKAGES: dict[int, tuple[MeasurementModel, str]] = {}


def _load() -> dict[str, MeasurementModel]:
    found: dict[str, MeasurementModel] = {}
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        try:
            obj = ep.load()
            instance = obj() if isinstance(obj, type) else obj
            if not getattr(instance, "kind", "") or not callable(getattr(instance, "predict", None)):
                raise TypeError("it has no 'kind' or no 'predict'")
        except Exception as err:  # a broken plugin must not break mbcal
            dist = getattr(ep, "dist", None)
            origin = f" (package {dist.name})" if dist is not None else ""
            warnings.warn(
                f"measurement model plugin '{ep.name}'{origin} failed to load: {type(err).__name__}: {err}",
                RuntimeWarning,
                stacklevel=3,
            )
            continue
        if instance.kind != ep.name:
            warnings.warn(
                f"measurement plugin entry point '{ep.name}' provides kind '{instance.kind}'; using '{instance.kind}'",
                RuntimeWarning,
                stacklevel=3,
            )
        found.setdefault(instance.kind, instance)
        _take_digest(instance)
        dist = getattr(ep, "dist", None)
        if dist is not None and dist.name:
            _PACKAGES[id(instance)] = (instance, dist.name)
    # Running from a source tree without installed metadata: the built-ins are still there.
    for cls in BUILTINS:
        found.setdefault(cls.kind, cls())
    return found


def registry(*, reload: bool = False) -> dict[str, MeasurementModel]:
    """Every available measurement model, by kind (entry points, then programmatic ones)."""
    global _REGISTRY
    if _REGISTRY is None or reload:
        _REGISTRY = _load()
    return {**_REGISTRY, **_EXTRA}


def register(model: MeasurementModel | type[MeasurementModel], *, replace: bool = False) -> MeasurementModel:
    """Register a measurement model from Python (without an entry point), e.g. in a notebook.

    A kind registered earlier with :func:`register` is replaced by the new model (a notebook's
    cell run again, a test's plugin).  A kind that mbcal itself or an installed plugin package
    provides (``image_point``, ``point3d``, ...) is refused with a :class:`ValueError` unless
    ``replace=True``: replacing it would silently change what every model measuring that kind
    computes.  ``replace=True`` replaces it for this process.
    """
    instance = model() if isinstance(model, type) else model
    if not instance.kind:
        raise ValueError("a measurement model needs a 'kind'")
    installed = registry()
    if not replace and instance.kind not in _EXTRA and instance.kind in installed:
        current = installed[instance.kind]
        source = (
            "one of mbcal's built-in measurement models" if _builtin(current) else f"provided by {describe(current)}"
        )
        raise ValueError(
            f"register({type(instance).__name__}): kind '{instance.kind}' is {source}; registering "
            "another model of that kind would replace it for every model that measures it. Give the "
            f"model another kind, or call register(..., replace=True) to replace '{instance.kind}' on purpose"
        )
    _EXTRA[instance.kind] = instance
    _take_digest(instance)
    return instance


def _builtin(model: MeasurementModel) -> bool:
    """Whether mbcal itself defines the model (its failures are mbcal's bugs, not a plugin's)."""
    return type(model).__module__.startswith("mbcal.")


def _take_digest(instance: MeasurementModel) -> None:
    """A plugin's source digested as it is loaded (mbcal.cache.source_fingerprint): a file edited
    later is not the code that runs."""
    if not _builtin(instance):
        source_fingerprint(instance)


register_measurement_model = register


def describe(model: MeasurementModel) -> str:
    """``measurement model 'kind'`` for messages, with the package of a plugin that an entry point
    provided (``measurement model 'height' (package mbcal-example-plugin)``)."""
    text = f"measurement model '{getattr(model, 'kind', '') or type(model).__name__}'"
    known = _PACKAGES.get(id(model))
    if known is not None and known[0] is model and not _builtin(model):
        text += f" (package {known[1]})"
    return text


def call_model(model: MeasurementModel, method: str, *args: Any, where: SourceSpan | None = None) -> Any:
    """``model.method(*args)``; a plugin's failure there as a :class:`MeasurementModelError`
    (``measurement model 'boom' failed in predict: ValueError: plugin bug``, the original error
    its ``__cause__``), which the command line reports with exit status 2 like other bad input —
    not as a traceback with status 1 ("solved, not trustworthy").

    A built-in model's failure is mbcal's own bug and propagates unchanged, as does an
    :class:`~mbcal.errors.MbcalError` a plugin raises itself.  ``predict`` and ``visible`` are
    called through here while they are traced, never in the compiled programs: no cost on a warm
    solve.  ``where``: the place the error is about (the measurement being checked).
    """
    bound = getattr(model, method)
    if _builtin(model):
        return bound(*args)
    try:
        return bound(*args)
    except MbcalError:
        raise
    except Exception as err:
        raise MeasurementModelError(
            f"{describe(model)} failed in {method}: {type(err).__name__}: {err}",
            where,
            hint="an error in the plugin's code, not in the model or the measurements",
        ) from err


def get_model(kind: str) -> MeasurementModel:
    """The measurement model of a kind; a clear error listing the available ones otherwise."""
    models = registry()
    if kind in models:
        return models[kind]
    available = ", ".join(sorted(models))
    raise MeasurementFileError(
        f"unknown measurement kind '{kind}' (available: {available})",
        hint=suggest(kind, models) or "plugins register kinds through the 'mbcal.measurements' entry point group",
    )


def declared_models(model: Model) -> dict[str, MeasurementModel]:
    """The measurement models a model's ``measure`` statements name, by kind.

    ``mbcal check`` loads no measurement model (nor JAX): a kind no installed model provides is
    reported here, when the model is used with measurements (a measurement set built for it, a
    problem).

    Raises
    ------
    MdlError
        A kind that no installed model provides, located at its ``measure`` statement, with the
        installed kinds and close matches.
    """
    models = registry()
    spans = model.measure_spans
    for i, kind in enumerate(model.measures):
        if kind not in models:
            raise MdlError(
                f"no installed measurement model provides '{kind}' (installed: {', '.join(sorted(models))})",
                spans[i] if i < len(spans) else None,
                hint=suggest(kind, models)
                or "a plugin registers its kinds through the 'mbcal.measurements' entry point group (docs/plugins.md)",
            )
    return {kind: models[kind] for kind in model.measures}
