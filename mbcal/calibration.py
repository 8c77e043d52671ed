"""Deprecated alias of mbcal.workflows.cameras (mbcal 0.1's path), kept for one release: docs/architecture.md."""

import warnings

from mbcal.workflows import cameras as _new

globals().update({name: getattr(_new, name) for name in dir(_new) if not name.startswith("_")})
warnings.warn("mbcal.calibration is deprecated; import from mbcal.workflows.cameras", DeprecationWarning, stacklevel=2)
