"""The room pose with 20 % of the clicked points replaced by gross mis-clicks (20-80 px).

Prints, for a plain least-squares solve and for the Huber and Cauchy losses, how far each
estimate lies from the outlier-free estimate, in units of that estimate's σ, and how many of
the mis-clicks the report lists as outliers.  Run: python bench/outliers.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_reliability import misclicked  # noqa: E402

import mbcal  # noqa: E402
from mbcal.solver import SolverConfig  # noqa: E402
from mbcal.text import table  # noqa: E402

from conftest import ROOM_TRUTH  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main(trials: int = 5) -> None:
    room = mbcal.load_model(ROOT / "models" / "teleexistence.mdl")
    plan = mbcal.read_measurements(ROOT / "measurements" / "room_plan.csv", room)
    rows = {"least squares": [], "huber (1.345σ)": [], "cauchy (2.385σ)": []}
    recall = {k: [] for k in rows}
    for trial in range(trials):
        clean = mbcal.simulate(room, plan, ROOM_TRUTH, seed=100 + trial)
        dirty, bad = misclicked(clean, 0.2, seed=200 + trial)
        reference = mbcal.calibrate(room, clean, ["room.*"], restarts=8, points=[])
        for label, config in (
            ("least squares", None),
            ("huber (1.345σ)", SolverConfig(loss="huber", loss_scale=1.345)),
            ("cauchy (2.385σ)", SolverConfig(loss="cauchy", loss_scale=2.385)),
        ):
            result = mbcal.calibrate(room, dirty, ["room.*"], restarts=8, points=[], config=config)
            worst = max(abs(result.values[n] - reference.values[n]) / reference.std[n] for n in reference.names)
            rows[label].append(worst)
            recall[label].append(len({r.id for r in result.outliers} & bad) / len(bad))
    print(
        table(
            ["solve", "largest deviation (σ), median", "max over trials", "mis-clicks listed"],
            [[k, f"{np.median(v):.2f}", f"{max(v):.2f}", f"{100 * np.mean(recall[k]):.0f} %"] for k, v in rows.items()],
            title=f"room pose, 48 image points, 20 % mis-clicked, {trials} trials:",
        )
    )


if __name__ == "__main__":
    main()
