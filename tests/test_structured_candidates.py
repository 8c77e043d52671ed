"""Candidate measurements ranked from the blocks (issue 15): the report of a structured problem
analysed without the full matrix suggests the same measurements, with the same scores, as the
dense analysis."""

from __future__ import annotations

import sys

import numpy as np
import pytest

import mbcal
from mbcal.api import _candidate_rows, _candidate_rows_by_blocks, _measured_keys
from mbcal.observability import rank_candidates
from mbcal.problem import Problem
from mbcal.structured import compressed_jacobian, rank_candidates_structured, structure_of
from mbcal.workflows.cameras import default_unknowns, initial_values

from conftest import MODELS, ROOT

sys.path.insert(0, str(ROOT / "bench"))

from scale import synthetic_views  # noqa: E402


@pytest.mark.slow
def test_a_board_seen_edge_on_gets_the_same_suggestions_from_the_blocks_as_densely():
    """View 3 sees one row of the board only: its roll about that row is unobservable; view 7
    misses two corners.  Both analyses suggest view 3's other corners (each raises the rank by 1)
    in the same order with the same σ reductions; scored all, view 7's corners (no rank gained,
    σ reduced) come after them, the same both ways."""
    model = mbcal.load_model(MODELS / "camera_calibration.mdl")
    data = synthetic_views(model, 10, seed=2)
    missing = {("view03", f"board.r{r}c{c}") for r in range(1, 6) for c in range(9)}
    missing |= {("view07", "board.r5c8"), ("view07", "board.r5c7")}
    estimate = default_unknowns(model, data)
    start = initial_values(model, data, Problem(model, data, estimate).params.names)
    data = data.subset(np.array([(m.config, m.refs["point"]) not in missing for m in data]))
    dense, blocks = (
        mbcal.calibrate(model, data, estimate, restarts=1, initial=start, points=[], analysis=how)
        for how in ("dense", "structured")
    )
    a, b = dense.observability, blocks.observability
    assert type(b.covariance).__name__ == "BlockCovariance" and not a.observable and not b.observable
    assert len(a.suggestions) == len(b.suggestions) == 10
    for u, v in zip(a.suggestions, b.suggestions):
        assert u.record == v.record and u.rank_gain == v.rank_gain == 1
        # 1 − σ/σ₀ of σ's that agree to ~1e-12: the reductions (1e-5 … 1e-3) to 1e-10 absolute
        assert v.sigma_reduction == pytest.approx(u.sigma_reduction, rel=0, abs=1e-10)
        assert v.text == u.text
    assert all(s.record["config"] == "view03" for s in b.suggestions)
    reductions = [s.sigma_reduction for s in b.suggestions]
    assert reductions == sorted(reductions, reverse=True) and reductions[0] > reductions[-1] > 0
    # Every candidate scored (top 60 of 47): the same order and scores, the rank-neutral ones last.
    problem = Problem(model, data, estimate)
    structure = structure_of(problem)
    x = blocks.x
    _, Jc = compressed_jacobian(problem.residual_function, x, structure, (problem.y, problem.params.known))
    J = problem.jacobian(x)
    keys = _measured_keys(data)
    ours = rank_candidates_structured(b, structure, Jc, _candidate_rows_by_blocks(problem, structure, x, keys), top=60)
    theirs = rank_candidates(a, J[: problem.size], None, _candidate_rows(problem, x, keys), top=60)
    assert len(ours) == len(theirs) == 47
    assert [s.record for s in ours] == [s.record for s in theirs]
    assert [s.rank_gain for s in ours] == [1] * 45 + [0] * 2
    assert [s.record["config"] for s in ours[45:]] == ["view07", "view07"] and ours[-1].sigma_reduction > 0
    np.testing.assert_allclose([s.sigma_reduction for s in ours], [s.sigma_reduction for s in theirs], atol=1e-10)
