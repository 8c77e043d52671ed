"""NIST StRD nonlinear regression: the lower- and average-difficulty problems reach the certified
values to at least 6 significant digits from both starting points, through the low-level API."""

from __future__ import annotations

import numpy as np
import pytest

from mbcal.datasets.nist import DIFFICULTY, read_problem
from mbcal.solver import SolverConfig, least_squares

from conftest import shared_data

PROBLEMS = sorted(name for name, level in DIFFICULTY.items() if level in ("lower", "average"))
# Reference-grade precision: tolerances near float64 round-off (the defaults stop at 1e-10).
CONFIG = SolverConfig(max_iterations=1000, ftol=1e-15, xtol=1e-15, gtol=1e-15)


def log_relative_error(estimate, certified):
    """NIST's LRE: the number of correct significant digits of each parameter."""
    with np.errstate(divide="ignore"):
        return -np.log10(np.abs(estimate - certified) / np.abs(certified))


@pytest.mark.parametrize("name", PROBLEMS)
def test_certified_values_from_both_starts(name):
    problem = read_problem(shared_data("nist", f"{name}.dat"))
    assert problem.difficulty == DIFFICULTY[name]
    starts = np.stack(problem.starts)
    result = least_squares(problem.residual, starts, args=(problem.x, problem.y), config=CONFIG)
    for k in range(2):
        lre = log_relative_error(result.x[k], problem.certified)
        assert np.all(lre >= 6.0), f"start {k + 1}: digits {np.round(lre, 1)}, status {result.statuses()[k]}"
        assert result.statuses()[k].converged
        # Lanczos1's certified RSS (1.4e-25) is itself round-off: compare it in absolute terms.
        assert abs(result.cost[k] - problem.certified_rss) <= 1e-6 * problem.certified_rss + 1e-26


def test_reader_parses_data_starts_and_certified_values():
    problem = read_problem(shared_data("nist", "Misra1a.dat"))
    assert problem.x.shape == (14,) and problem.y.shape == (14,)
    np.testing.assert_array_equal(problem.starts[0], [500, 1e-4])
    np.testing.assert_array_equal(problem.starts[1], [250, 5e-4])
    np.testing.assert_allclose(problem.certified, [2.3894212918e02, 5.5015643181e-04])
    assert problem.certified_rss == pytest.approx(1.2455138894e-01)
