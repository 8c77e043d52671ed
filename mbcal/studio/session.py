"""The studio's session: what the operator did, saved to ``--out`` after every edit.

A session holds the clicked correspondences (camera, configuration, model point, pixel, σ — or
σ of u and of v), the
chosen unknowns and the coarse-alignment values.  It is written atomically to
``<out>/studio-session.json`` after every change, so a closed tab, a browser crash or a
restarted studio loses nothing; :func:`load_session` reads it back.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from mbcal.errors import MbcalError
from mbcal.outputs import atomic_write

__all__ = ["Click", "Session", "SESSION_FILE", "SESSION_FORMAT", "load_session", "save_session"]

SESSION_FILE = "studio-session.json"
SESSION_FORMAT = "mbcal-studio-session-1"


@dataclass
class Click:
    """One correspondence: a model point and where the operator saw it in a photo."""

    id: str
    camera: str  # full camera name
    config: str
    point: str  # full point name
    u: float
    v: float
    sigma: float = 1.0  # px: of u and v, or of u alone when sigma_v is given
    sigma_v: float | None = None  # px: of v when it differs from u's (from a measurement file's sigma_u, sigma_v)


@dataclass
class Session:
    """Everything the operator has done so far."""

    clicks: list[Click] = field(default_factory=list)
    estimate: list[str] = field(default_factory=list)
    values: dict[str, float] = field(default_factory=dict)  # SI, by parameter name (coarse alignment)
    hidden: list[str] = field(default_factory=list)  # objects switched off in the overlay
    model: str = ""  # the model file the clicks were made on (absolute path; "" in older sessions)

    def to_json(self) -> dict[str, Any]:
        return {
            "format": SESSION_FORMAT,
            "model": self.model,
            "clicks": [_click_json(c) for c in self.clicks],
            "estimate": list(self.estimate),
            "values": dict(self.values),
            "hidden": list(self.hidden),
        }


def _click_json(click: Click) -> dict[str, Any]:
    out = asdict(click)
    if click.sigma_v is None:  # one σ of both: as sessions always held it
        del out["sigma_v"]
    return out


def _finite(value: Any, what: str, path: Path) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise MbcalError(f"{path}: {what} is not a number: {value!r}") from None
    if not math.isfinite(v):
        raise MbcalError(f"{path}: {what} is not finite")
    return v


def load_session(path: Path) -> Session | None:
    """The session saved at ``path``, or None when there is none yet."""
    if not path.exists():
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise MbcalError(f"{path}: cannot read the studio session: {err}") from None
    if not isinstance(doc, dict) or doc.get("format") != SESSION_FORMAT:
        raise MbcalError(f"{path}: not a studio session (format '{SESSION_FORMAT}' expected)")
    clicks = []
    for i, c in enumerate(doc.get("clicks", [])):
        if not isinstance(c, dict):
            raise MbcalError(f"{path}: click {i + 1} is not an object")
        try:
            clicks.append(
                Click(
                    id=str(c["id"]),
                    camera=str(c["camera"]),
                    config=str(c["config"]),
                    point=str(c["point"]),
                    u=_finite(c["u"], f"click {i + 1} u", path),
                    v=_finite(c["v"], f"click {i + 1} v", path),
                    sigma=_finite(c.get("sigma", 1.0), f"click {i + 1} sigma", path),
                    sigma_v=None if c.get("sigma_v") is None else _finite(c["sigma_v"], f"click {i + 1} sigma_v", path),
                )
            )
        except KeyError as err:
            raise MbcalError(f"{path}: click {i + 1} lacks {err}") from None
    values = {str(k): _finite(v, f"value of {k}", path) for k, v in dict(doc.get("values", {})).items()}
    return Session(
        clicks=clicks,
        estimate=[str(e) for e in doc.get("estimate", [])],
        values=values,
        hidden=[str(h) for h in doc.get("hidden", [])],
        model=str(doc.get("model", "")),
    )


def save_session(session: Session, path: Path) -> None:
    """Write the session atomically."""
    atomic_write(path, json.dumps(session.to_json(), indent=1) + "\n")
