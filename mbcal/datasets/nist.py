"""The NIST StRD nonlinear least-squares problems (Statistical Reference Datasets).

Each ``.dat`` file holds a problem's data, two starting points, the certified parameter
values and standard deviations, and the certified residual sum of squares.  The model
formulas are stated in the files' headers; they are written out here in JAX (one line each)
so the solver can differentiate them.  Reference: https://www.itl.nist.gov/div898/strd/nls/.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mbcal._jax import jnp

__all__ = ["NistProblem", "read_problem", "MODELS", "DIFFICULTY"]

Array = Any


def _gauss(b, x):
    return (
        b[0] * jnp.exp(-b[1] * x)
        + b[2] * jnp.exp(-((x - b[3]) ** 2) / b[4] ** 2)
        + b[5] * jnp.exp(-((x - b[6]) ** 2) / b[7] ** 2)
    )


def _lanczos(b, x):
    return b[0] * jnp.exp(-b[1] * x) + b[2] * jnp.exp(-b[3] * x) + b[4] * jnp.exp(-b[5] * x)


def _chwirut(b, x):
    return jnp.exp(-b[0] * x) / (b[1] + b[2] * x)


def _rational_3_3(b, x):
    return (b[0] + b[1] * x + b[2] * x**2 + b[3] * x**3) / (1 + b[4] * x + b[5] * x**2 + b[6] * x**3)


def _enso(b, x):
    w = 2 * jnp.pi * x
    return (
        b[0]
        + b[1] * jnp.cos(w / 12)
        + b[2] * jnp.sin(w / 12)
        + b[4] * jnp.cos(w / b[3])
        + b[5] * jnp.sin(w / b[3])
        + b[7] * jnp.cos(w / b[6])
        + b[8] * jnp.sin(w / b[6])
    )


# Model name → f(b, x) with x of shape (n,) or (n, k) for several predictors.
MODELS: dict[str, Callable[[Array, Array], Array]] = {
    "Misra1a": lambda b, x: b[0] * (1 - jnp.exp(-b[1] * x)),
    "Chwirut2": _chwirut,
    "Chwirut1": _chwirut,
    "Lanczos3": _lanczos,
    "Gauss1": _gauss,
    "Gauss2": _gauss,
    "DanWood": lambda b, x: b[0] * x ** b[1],
    "Misra1b": lambda b, x: b[0] * (1 - (1 + b[1] * x / 2) ** (-2)),
    "Kirby2": lambda b, x: (b[0] + b[1] * x + b[2] * x**2) / (1 + b[3] * x + b[4] * x**2),
    "Hahn1": _rational_3_3,
    "Nelson": lambda b, x: b[0] - b[1] * x[:, 0] * jnp.exp(-b[2] * x[:, 1]),
    "MGH17": lambda b, x: b[0] + b[1] * jnp.exp(-x * b[3]) + b[2] * jnp.exp(-x * b[4]),
    "Lanczos1": _lanczos,
    "Lanczos2": _lanczos,
    "Gauss3": _gauss,
    "Misra1c": lambda b, x: b[0] * (1 - (1 + 2 * b[1] * x) ** (-0.5)),
    "Misra1d": lambda b, x: b[0] * b[1] * x * ((1 + b[1] * x) ** (-1)),
    # The certified values take arctan[b3/(x-b4)] in [0, π) (atan2 with b3 > 0): with the principal
    # branch the same certified RSS is reached with b1 lower by exactly 1.
    "Roszman1": lambda b, x: b[0] - b[1] * x - jnp.arctan2(b[2], x - b[3]) / jnp.pi,
    "ENSO": _enso,
    "MGH09": lambda b, x: b[0] * (x**2 + x * b[1]) / (x**2 + x * b[2] + b[3]),
    "Thurber": _rational_3_3,
    "BoxBOD": lambda b, x: b[0] * (1 - jnp.exp(-b[1] * x)),
    "Rat42": lambda b, x: b[0] / (1 + jnp.exp(b[1] - b[2] * x)),
    "MGH10": lambda b, x: b[0] * jnp.exp(b[1] / (x + b[2])),
    "Eckerle4": lambda b, x: (b[0] / b[1]) * jnp.exp(-0.5 * ((x - b[2]) / b[1]) ** 2),
    "Rat43": lambda b, x: b[0] / ((1 + jnp.exp(b[1] - b[2] * x)) ** (1 / b[3])),
    "Bennett5": lambda b, x: b[0] * (b[1] + x) ** (-1 / b[2]),
}

# As stated in each file ("Lower/Average/Higher Level of Difficulty").
DIFFICULTY = {
    **dict.fromkeys(["Misra1a", "Chwirut2", "Chwirut1", "Lanczos3", "Gauss1", "Gauss2", "DanWood", "Misra1b"], "lower"),
    **dict.fromkeys(
        [
            "Kirby2",
            "Hahn1",
            "Nelson",
            "MGH17",
            "Lanczos1",
            "Lanczos2",
            "Gauss3",
            "Misra1c",
            "Misra1d",
            "Roszman1",
            "ENSO",
        ],
        "average",
    ),
    **dict.fromkeys(["MGH09", "Thurber", "BoxBOD", "Rat42", "MGH10", "Eckerle4", "Rat43", "Bennett5"], "higher"),
}


@dataclass(frozen=True)
class NistProblem:
    """One StRD problem: data, starting points and certified results."""

    name: str
    difficulty: str
    x: np.ndarray  # (n,) or (n, k)
    y: np.ndarray  # (n,) — for Nelson, log(y) as the model states
    starts: tuple[np.ndarray, np.ndarray]
    certified: np.ndarray
    certified_std: np.ndarray
    certified_rss: float

    @property
    def model(self) -> Callable[[Array, Array], Array]:
        return MODELS[self.name]

    def residual(self, b: Array, x: Array, y: Array) -> Array:
        """r(b) = f(b, x) − y; pass x and y as solver args."""
        return self.model(b, x) - y


_PARAM = re.compile(r"^\s*b(\d+)\s*=\s*(\S+)\s+(\S+)\s+(\S+)\s+(\S+)")


def read_problem(path: str | Path) -> NistProblem:
    """Parse a NIST StRD ``.dat`` file."""
    path = Path(path)
    name = path.stem
    if name not in MODELS:
        raise ValueError(f"unknown NIST problem {name}")
    lines = path.read_text(encoding="latin-1").splitlines()
    rows = []
    for line in lines:
        m = _PARAM.match(line)
        if m:
            rows.append([float(v) for v in m.groups()[1:]])
    params = np.array(rows)
    rss = next(float(line.split(":")[1]) for line in lines if line.startswith("Residual Sum of Squares"))
    start = max(i for i, line in enumerate(lines) if line.startswith("Data:")) + 1
    data = np.array([[float(v) for v in line.split()] for line in lines[start:] if line.strip()])
    y = data[:, 0]
    x = data[:, 1] if data.shape[1] == 2 else data[:, 1:]
    if name == "Nelson":  # the model is stated for log[y]
        y = np.log(y)
    level = next(line for line in lines if "Level of Difficulty" in line).split()[0].lower()
    return NistProblem(
        name=name,
        difficulty=level,
        x=x,
        y=y,
        starts=(params[:, 0], params[:, 1]),
        certified=params[:, 2],
        certified_std=params[:, 3],
        certified_rss=rss,
    )
