"""Deprecated alias (mbcal 0.1's path), kept for one release: docs/architecture.md.  URDF reading
is now in :mod:`mbcal.language.urdf` (``mbcal.language.load_urdf``), writing in :mod:`mbcal.export.urdf`."""

import warnings

from mbcal.errors import UrdfError
from mbcal.export.urdf import write_urdf
from mbcal.language import load_urdf
from mbcal.language.urdf import resolve_mesh, urdf_names, urdf_to_mdl

__all__ = ["UrdfError", "load_urdf", "resolve_mesh", "urdf_names", "urdf_to_mdl", "write_urdf"]
warnings.warn(
    "mbcal.urdf is deprecated; import from mbcal.language.urdf and mbcal.export.urdf", DeprecationWarning, stacklevel=2
)
