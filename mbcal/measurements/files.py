"""Deprecated alias of mbcal.measurements.io (mbcal 0.1's path), kept for one release: docs/architecture.md."""

import warnings

from mbcal.measurements import io as _new

globals().update({name: getattr(_new, name) for name in dir(_new) if not name.startswith("_")})
warnings.warn(
    "mbcal.measurements.files is deprecated; import from mbcal.measurements.io", DeprecationWarning, stacklevel=2
)
