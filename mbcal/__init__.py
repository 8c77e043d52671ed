"""mbcal — model-based measurement and calibration.

Describe an environment in mbcal's model language (.mdl), predict what sensors measure in
it, and estimate any parameter the measurements can observe.  The public API:

>>> import mbcal
>>> model = mbcal.load_model("models/teleexistence.mdl")          # doctest: +SKIP
>>> scene = mbcal.modeler(model, {"lever.angle": 0.5})             # doctest: +SKIP
>>> scene.point("room.valve.lever.tip")                             # doctest: +SKIP
"""

from __future__ import annotations

from importlib import import_module
from importlib.util import find_spec
from typing import Any

from mbcal import _sources  # noqa: F401  (the source files as imported: mbcal.cache's key trusts only them)

__version__ = "0.1.0"

# Public names → the module that defines them.  Loaded on first use so that `mbcal check`
# does not pay for importing JAX.
_EXPORTS = {
    "load_model": "mbcal.language",
    "load_model_text": "mbcal.language",
    "Model": "mbcal.language.model",
    "modeler": "mbcal.modeling",
    "parameter_vector": "mbcal.modeling",
    "Scene": "mbcal.scene",
    "ParameterSet": "mbcal.params",
    "Problem": "mbcal.problem",
    "calibrate": "mbcal.api",
    "simulate": "mbcal.api",
    "observe": "mbcal.api",
    "CalibrationResult": "mbcal.api",
    "CalibrateOptions": "mbcal.api",
    "FitConfig": "mbcal.fit",
    "FitVerdict": "mbcal.fit",
    "read_measurements": "mbcal.measurements.io",
    "write_measurements": "mbcal.measurements.io",
    "measurements_from_records": "mbcal.measurements.io",
    "merge_measurements": "mbcal.measurements.sets",
    "MeasurementSet": "mbcal.measurements.io",
    "Measurement": "mbcal.measurements.io",
    "MeasurementModel": "mbcal.measurements",
    "Role": "mbcal.measurements",
    "Batch": "mbcal.measurements",
    "register_measurement_model": "mbcal.measurements",
    "least_squares": "mbcal.solver",
    "SolverConfig": "mbcal.solver",
    "Status": "mbcal.solver",
    "Kinematics": "mbcal.kinematics",
    "MbcalError": "mbcal.errors",
    "MdlError": "mbcal.errors",
    "ParameterError": "mbcal.errors",
}

__all__ = [*_EXPORTS, "__version__"]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        return _submodule(__name__, name)  # mbcal.measurements.registry() after a plain 'import mbcal'
    value = getattr(import_module(module), name)
    globals()[name] = value
    return value


def _submodule(package: str, name: str) -> Any:
    """The module ``package.name``, imported on first use: a package's ``__getattr__`` (PEP 562)
    for its modules, so that a dotted name (``mbcal.workflows.cameras.plan_views``) works after a
    plain ``import mbcal`` without importing them all at start-up.  An error inside the module (a
    missing optional dependency) is its own, not an AttributeError."""
    if name.startswith("__") or find_spec(f"{package}.{name}") is None:
        raise AttributeError(f"module '{package}' has no attribute '{name}'")
    return import_module(f"{package}.{name}")


def __dir__() -> list[str]:
    return sorted(__all__)
