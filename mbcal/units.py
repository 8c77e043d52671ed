"""Units and dimensions of model quantities.

mbcal stores every value in SI: metres and radians.  A literal without a unit is taken as SI
and is *free*: it takes on whatever dimension the expression around it needs, so ``0.2`` is
0.2 m where a length is expected and 0.2 rad where an angle is.  A literal with a unit has a
fixed dimension, and mixing dimensions (adding an angle to a length, giving an angle where a
length is expected) is a :class:`~mbcal.errors.UnitError`.

Angles are treated as a dimension of their own (not as dimensionless, as SI would), because
the mistake users most often make is an angle where a length belongs, or the reverse.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from fractions import Fraction

__all__ = [
    "Dim",
    "LENGTH",
    "ANGLE",
    "DIMENSIONLESS",
    "UNITS",
    "describe",
    "unify",
    "fits",
    "to_display",
    "real",
    "at_least",
    "whole",
    "within",
]


@dataclass(frozen=True)
class Dim:
    """A physical dimension: powers of length and angle."""

    length: Fraction = Fraction(0)
    angle: Fraction = Fraction(0)

    def __mul__(self, other: Dim) -> Dim:
        return Dim(self.length + other.length, self.angle + other.angle)

    def __truediv__(self, other: Dim) -> Dim:
        return Dim(self.length - other.length, self.angle - other.angle)

    def __pow__(self, k: Fraction | int | float) -> Dim:
        k = Fraction(k).limit_denominator(1000)
        return Dim(self.length * k, self.angle * k)

    @property
    def is_dimensionless(self) -> bool:
        return self.length == 0 and self.angle == 0


LENGTH = Dim(Fraction(1), Fraction(0))
ANGLE = Dim(Fraction(0), Fraction(1))
DIMENSIONLESS = Dim()

# unit name → (factor to SI, dimension)
UNITS: dict[str, tuple[float, Dim]] = {
    "m": (1.0, LENGTH),
    "cm": (0.01, LENGTH),
    "mm": (0.001, LENGTH),
    "um": (1e-6, LENGTH),
    "km": (1000.0, LENGTH),
    "inch": (0.0254, LENGTH),
    "ft": (0.3048, LENGTH),
    "rad": (1.0, ANGLE),
    "mrad": (0.001, ANGLE),
    "deg": (math.pi / 180.0, ANGLE),
}


def _power(name: str, p: Fraction) -> str:
    if p == 1:
        return name
    return f"{name}^{p}"


def describe(dim: Dim | None) -> str:
    """Human words for a dimension: 'a length (m)', 'an angle (rad)', 'a plain number'."""
    if dim is None:
        return "a number without unit"
    if dim == LENGTH:
        return "a length (m)"
    if dim == ANGLE:
        return "an angle (rad)"
    if dim.is_dimensionless:
        return "a plain number"
    parts = []
    if dim.length:
        parts.append(_power("m", dim.length))
    if dim.angle:
        parts.append(_power("rad", dim.angle))
    return "a quantity in " + "·".join(parts)


def unify(a: Dim | None, b: Dim | None) -> tuple[bool, Dim | None]:
    """The common dimension of two summands; (False, None) when they cannot be added."""
    if a is None:
        return True, b
    if b is None or a == b:
        return True, a
    return False, None


def to_display(unit: str, value: float) -> float:
    """A value in SI units in its display unit: degrees for angles (``unit == "deg"``)."""
    return float(math.degrees(value)) if unit == "deg" else float(value)


def within(value: float, low: float, high: float) -> bool:
    """``low ≤ value ≤ high`` with a few units in the last place of slack at each end: a value and a
    limit written in different units differ by the rounding of their conversion (35 cm is
    0.35000000000000003 m, and a limit of 0.35 m refused it, showing both as 0.35)."""
    return low - 4 * math.ulp(low) <= value <= high + 4 * math.ulp(high)


def fits(dim: Dim | None, expected: Dim) -> bool:
    """Whether a value of dimension ``dim`` may stand where ``expected`` is required."""
    return dim is None or dim == expected


def real(value: object) -> float | None:
    """``value`` as a float when it is one real number — a Python, NumPy or JAX scalar, or a 0-d
    array — and None otherwise (text, a flag, None, an array of several); NaN and ±inf are
    returned as they are, for the caller to judge."""
    if isinstance(value, (str, bytes, bool)) or value is None:
        return None
    try:
        shape = getattr(value, "shape", ())
        if len(shape) != 0:
            return None
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None


def at_least(value: object, low: float, *, strict: bool = False) -> bool:
    """Whether ``value`` is one finite real number (:func:`real`) ≥ ``low`` (> ``low`` with ``strict``):
    the check of a setting that must be a count of σ, a length, a tolerance."""
    number = real(value)
    return number is not None and math.isfinite(number) and (number > low if strict else number >= low)


def whole(value: object, low: int | None = None) -> bool:
    """Whether ``value`` is a whole number (a Python or NumPy integer, not a flag), ≥ ``low`` when given."""
    if not isinstance(value, numbers.Integral) or isinstance(value, bool):
        return False
    return low is None or int(value) >= low
