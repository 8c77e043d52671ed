"""Sizes: a million measurements stream with bounded memory; absurd sizes are refused up front."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import tracemalloc

import numpy as np
import pytest

import mbcal
from mbcal.api import MAX_DENSE_UNKNOWNS, MAX_RESTARTS, MAX_SOLVER_BYTES, check_size
from mbcal.cli import main
from mbcal.errors import SolverError
from mbcal.solver import solver_byte_limit

from conftest import MEASUREMENTS, MODELS, ROOT

ONE_UNKNOWN_PER_CONFIGURATION = """
param q = 0 m per configuration
frame f at (q, 0, 0) { point p = (0, 0, 0) }
"""


def test_a_billion_restarts_are_refused_before_anything_is_allocated(room):
    data = mbcal.read_measurements(MEASUREMENTS / "room_plan.csv", room)
    tracemalloc.start()
    with pytest.raises(SolverError) as info:
        mbcal.calibrate(room, data, ["room.*"], restarts=10**9)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert f"more than mbcal runs ({MAX_RESTARTS})" in str(info.value) and info.value.hint
    assert peak < 16 * 2**20, peak  # 10⁹ starting points of 6 unknowns would be 48 GB


def test_the_command_line_refuses_them_before_reading_the_files(capsys):
    status = main(["solve", str(MODELS / "teleexistence.mdl"), "no-such-file.csv", "--restarts", "1000000000"])
    err = capsys.readouterr().err
    assert status == 2 and "1000000000 restarts is more than mbcal runs" in err and "hint:" in err
    assert main(["solve", str(MODELS / "teleexistence.mdl"), "no-such-file.csv", "--restarts", "0"]) == 2


@pytest.mark.slow
def test_a_100000_dimensional_unknown_vector_is_refused_on_the_dense_path():
    model = mbcal.load_model_text(ONE_UNKNOWN_PER_CONFIGURATION)
    records = [{"kind": "point3d", "point": "f.p", "config": f"c{k}", "x": 0, "y": 0, "z": 0} for k in range(100_000)]
    data = mbcal.measurements_from_records(records, model)
    limit = f"100000 unknowns is more than the dense solver handles \\({MAX_DENSE_UNKNOWNS}\\)"
    with pytest.raises(SolverError, match=limit):
        mbcal.calibrate(model, data, ["q"], restarts=1)
    with pytest.raises(SolverError, match="100000 unknowns"):
        mbcal.observe(model, data, ["q"])


def test_the_limits():
    check_size(32, 6, 96)  # the room
    check_size(MAX_RESTARTS, 15, 1_000)  # (within half the memory of a 4 GiB machine)
    with pytest.raises(SolverError, match="at least 1"):
        check_size(0)
    with pytest.raises(SolverError, match="unknowns is more"):
        check_size(1, MAX_DENSE_UNKNOWNS + 1, MAX_DENSE_UNKNOWNS + 1)
    with pytest.raises(SolverError, match="GiB of dense Jacobians") as info:
        check_size(1000, 1000, 10**6)  # 8 TB of Jacobians
    assert "--restarts" in info.value.hint
    check_size(32, 6, 2 * 10**6)  # a million image points (two residuals each), 32 restarts: accepted
    # ... and the limit is where the dense Jacobians (8 bytes × restarts × rows × unknowns) pass it
    rows = solver_byte_limit() // (8 * 32 * 6)
    assert solver_byte_limit() <= MAX_SOLVER_BYTES
    check_size(32, 6, rows - 20)
    with pytest.raises(SolverError, match="GiB of dense Jacobians"):
        check_size(32, 6, rows + 1)


@pytest.mark.slow
def test_a_million_rows_stream_with_bounded_memory(tmp_path):
    """The reader holds one row at a time: the peak is the measurements themselves (docs/reliability.md)."""
    room = mbcal.load_model(MODELS / "teleexistence.mdl")
    points = [p.name for p in room.points]
    rng = np.random.default_rng(0)
    n = 1_000_000
    u, v = rng.uniform(0, 669, n), rng.uniform(0, 453, n)
    path = tmp_path / "million.csv"
    with open(path, "w") as f:
        f.write("id,kind,camera,point,u,v,sigma\n")
        f.writelines(
            f"m{k},image_point,eyes.{'left' if k % 2 else 'right'},{points[k % len(points)]},{u[k]:.3f},{v[k]:.3f},1\n"
            for k in range(n)
        )
    probe = textwrap.dedent(
        f"""
        import resource, time
        import mbcal
        room = mbcal.load_model({str(MODELS / "teleexistence.mdl")!r})
        mbcal.read_measurements({str(MEASUREMENTS / "room_plan.csv")!r}, room)  # everything imported
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        start = time.perf_counter()
        data = mbcal.read_measurements({str(path)!r}, room)
        elapsed = time.perf_counter() - start
        after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        print(len(data), elapsed, (after - before) * 1024)
        """
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    count, elapsed, growth = out.stdout.split()
    assert int(count) == n
    # Measured: about 700 bytes a measurement (0.7 GB) in about 13 s; the file's 70 MB text is never held.
    assert int(growth) < n * 1024, int(growth) / n


def test_a_batch_that_does_not_fit_in_memory_is_an_error_of_the_input():
    """10,000 restarts of a scan fit: XLA's RESOURCE_EXHAUSTED came out as a traceback, exit 1."""
    from mbcal.solver import _out_of_memory

    err = _out_of_memory(
        RuntimeError("RESOURCE_EXHAUSTED: Out of memory allocating 100570886920 bytes."), np.zeros((10_000, 6)), 24588
    )
    assert isinstance(err, SolverError) and "--restarts" in err.hint
    assert str(err).startswith("10000 restarts of 6 unknowns over 24588 residual rows did not fit in memory")
    other = RuntimeError("INTERNAL: something else")
    assert _out_of_memory(other, np.zeros((1, 6)), None) is other  # any other failure as it was


@pytest.mark.parametrize(
    "command",
    [
        ["fit", "models/room_depth.mdl", "scan.png", "--estimate", "room.*"],
        ["watch", "models/room_depth.mdl", "--scans", "scans", "--out", "out", "--estimate", "room.*", "--once"],
        ["kinematics", "models/arm7.mdl", "--point", "hand.tip", "--chain", "arm.q*", "--ik", "0.3,-0.35,0.95"],
    ],
)
def test_every_command_refuses_more_restarts_than_mbcal_runs_before_the_work(command, tmp_path, monkeypatch, capsys):
    """solve and calibrate-camera refused more than 10,000 restarts; fit, watch and kinematics ran
    into JAX's out-of-memory traceback (and watch left its --out folder behind)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "scans").mkdir()
    command = [str(ROOT / c) if c.startswith("models/") else c for c in command]
    command[1] = "missing.mdl"  # checked before any file is read
    assert main([*command, "--restarts", "10000000"]) == 2
    assert "10000000 restarts is more than mbcal runs (10000)" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
