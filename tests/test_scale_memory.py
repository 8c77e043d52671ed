"""Memory at scale (issue 15): the JSON report of a problem analysed from its blocks writes the
covariance by blocks, never the n × n matrix (2,000 views of a board: 12,009 unknowns, 144 million
entries); the cache of compiled programs does not keep a problem's measurements alive."""

from __future__ import annotations

import gc
import json
import sys
import weakref

import numpy as np
import pytest

import mbcal
from mbcal.problem import Problem
from mbcal.solver import SolverConfig
from mbcal.workflows.cameras import default_unknowns, initial_values

from conftest import MODELS, ROOT

sys.path.insert(0, str(ROOT / "bench"))

from scale import synthetic_views  # noqa: E402


@pytest.mark.slow
def test_a_report_analysed_from_the_blocks_writes_the_covariance_by_blocks():
    model = mbcal.load_model(MODELS / "camera_calibration.mdl")
    data = synthetic_views(model, 6, seed=3)
    estimate = default_unknowns(model, data)
    start = initial_values(model, data, Problem(model, data, estimate).params.names)
    forced = SolverConfig(structure="structured")  # 6 views: the dense solver would be chosen
    dense, ours = (
        mbcal.calibrate(model, data, estimate, restarts=1, initial=start, analysis=how, suggest=False, config=forced)
        for how in ("dense", "structured")
    )
    assert type(ours.covariance).__name__ == "BlockCovariance"
    a = dense.to_json()["covariance"]
    b = json.loads(json.dumps(ours.to_json()))["covariance"]  # plain JSON, as written to a file
    names = a["names"]
    n = len(names)
    assert "form" not in a and np.shape(a["covariance"]) == (n, n)
    assert b["form"] == "blocks" and b["names"] == names and "covariance" not in b and "correlation" not in b
    [shared] = b["shared"]
    assert shared["names"][:4] == ["cam.fx", "cam.fy", "cam.cx", "cam.cy"] and len(shared["names"]) == 9
    assert len(b["blocks"]) == 6 and all(len(block["names"]) == 6 for block in b["blocks"])
    assert b["blocks"][2]["names"][0].endswith("@view03")
    # every unknown exactly once, and each part's entries are the dense report's (to round-off)
    parts = [shared, *b["blocks"]]
    assert sorted(name for part in parts for name in part["names"]) == sorted(names)
    C, R = np.array(a["covariance"], dtype=float), np.array(a["correlation"], dtype=float)
    std = np.sqrt(np.diag(C))
    for part in parts:
        i = [names.index(name) for name in part["names"]]
        ours_c = np.array(part["covariance"], dtype=float)
        assert np.max(np.abs(ours_c - C[np.ix_(i, i)]) / np.outer(std[i], std[i])) < 1e-9
        np.testing.assert_allclose(np.array(part["correlation"], dtype=float), R[np.ix_(i, i)], atol=1e-9)
        np.testing.assert_allclose(np.sqrt(np.diag(ours_c)), [ours.std[name] for name in part["names"]], rtol=1e-12)


@pytest.mark.slow
def test_the_program_cache_keeps_no_measurements_alive():
    """A problem's programs stay cached for the next problem of its structure, but not its
    measurement set: 2,000 views' 108,000 measurement objects once stayed in memory with them."""
    model = mbcal.load_model(MODELS / "camera_calibration.mdl")
    data = synthetic_views(model, 2, seed=5)
    problem = Problem(model, data, ["cam.cx", "cam.cy", "board.*"])  # a structure of its own: a new entry
    r = problem.residual(problem.params.x0)
    again = Problem(model, synthetic_views(model, 2, seed=5), ["cam.cx", "cam.cy", "board.*"])
    assert again.residual_function is problem.residual_function  # shared through the cache
    np.testing.assert_array_equal(again.residual(again.params.x0), r)
    gone = weakref.ref(data)
    del problem, data
    gc.collect()
    assert gone() is None
