"""The studio: the seed's human interface and superimposer as a local web page (``mbcal studio``).

The operator sees each camera's photo with the model drawn over it, picks a model point and
its position in the photo, chooses the unknowns, checks observability, solves and saves
(seed §2.6, §3.3 module 1, §3.5, Figures 10-11).  See docs/studio.md.

- :mod:`mbcal.studio.session`: the operator's clicks, unknowns and values, saved at every edit;
- :mod:`mbcal.studio.engine`: the model, projections of points and wireframes, observe, solve,
  save, all through mbcal's library;
- :mod:`mbcal.studio.server`: the web server (FastAPI on uvicorn, the optional ``studio`` extra)
  with its security rules, and the page it serves (``static/``).
"""

from __future__ import annotations

from typing import Any

from mbcal import _submodule

__all__ = ["MISSING_EXTRA"]

MISSING_EXTRA = "the studio needs its optional dependencies: pip install 'mbcal[studio]'"


def __getattr__(name: str) -> Any:  # the modules on first use: a dotted name works after 'import mbcal'
    return _submodule(__name__, name)
