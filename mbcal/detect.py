"""Deprecated alias of mbcal.workflows.detect (mbcal 0.1's path), kept for one release: docs/architecture.md."""

import warnings

from mbcal.workflows import detect as _new

globals().update({name: getattr(_new, name) for name in dir(_new) if not name.startswith("_")})
warnings.warn("mbcal.detect is deprecated; import from mbcal.workflows.detect", DeprecationWarning, stacklevel=2)
