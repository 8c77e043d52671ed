"""The seed's section 4.2 in simulation: the room's pose and the arm's joint offsets.

Run from the repository root::

    python bench/experiments.py            # 200 Monte Carlo trials per case, writes docs/experiments.md
    python bench/experiments.py --trials 20 --out /tmp/exp.md   # a quick look

For each experiment and each click noise (1 px, as with a mouse, and 0.5 px) the script

1. simulates exact measurements of the bundled plan from a known "true" world that differs from
   the model (the seed's "before"),
2. adds Gaussian noise to the image points, ``--trials`` times, and estimates the unknowns from
   the model's nominal values and random restarts in their search ranges — the problem is traced
   and compiled once, only the measured values change between trials,
3. measures the error of the lever's (room) or the hand's (arm) points across (⟂) and along (∥)
   the left camera's line of sight, before and after, and compares the σ that mbcal predicts
   from its covariance with the spread of the Monte Carlo estimates,
4. writes the tables, the seed's numbers beside ours, and before/after overlay images.

The simulation has no structural model error: the true world differs from the model only in the
unknowns.  The seed's real experiments also carry errors of the model itself (link lengths,
camera calibration, a slightly wrong room), which no number of clicks averages away.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from plans import HAND_POINTS, ROOM_POINTS  # noqa: E402

import mbcal  # noqa: E402
from mbcal.measurements.sets import MeasurementSet  # noqa: E402
from mbcal.outputs import atomic_write  # noqa: E402
from mbcal.problem import Problem  # noqa: E402
from mbcal.solver import SolverConfig, least_squares, random_starts  # noqa: E402
from mbcal.text import table  # noqa: E402
from mbcal.workflows.demo import DEMO_TRUTH  # noqa: E402

CAMERA = "eyes.left"

# The arm's true encoder offsets (degrees): one draw in the ±8° range, fixed here so that the
# experiment is the same every run.  With the cameras aimed at the hand, offset errors move the
# hand mostly across the line of sight: these give 6.9 cm ⟂ at the hand before calibration, the
# seed's 6.5 cm ⟂; our ∥ error before is smaller than the seed's 13.2 cm (see the notes).
ARM_TRUTH_DEG = (4.9, 4.9, 0.2, -3.4, -7.1, -1.9, -1.5)
ARM_TRUTH = {f"arm.offset{i + 1}": math.radians(d) for i, d in enumerate(ARM_TRUTH_DEG)}

# The seed's numbers (section 4.2), cm: (⟂, ∥).
SEED = {
    "room": {"before": (4.2, 16.5), "after": (1.5, 2.9)},
    "arm": {"before": (6.5, 13.2), "after": (2.5, 4.2), "unseen": (6.9, None)},
}


@dataclasses.dataclass
class Case:
    name: str
    title: str
    model: str
    plan: str
    unknowns: list[str]
    truth: dict[str, float]
    points: tuple[str, ...]
    unseen_plan: str | None = None


CASES = {
    "room": Case(
        "room",
        "room pose: 6 unknowns from 24 points in both stereo images",
        "models/teleexistence.mdl",
        "measurements/room_plan.csv",
        ["room.*"],
        dict(DEMO_TRUTH),
        tuple(p for p in ROOM_POINTS if p.startswith("lever")),
    ),
    "arm": Case(
        "arm",
        "arm joint offsets: 7 unknowns from 84 image points of the hand in 10 attitudes",
        "models/arm7.mdl",
        "measurements/arm_plan.json",
        ["arm.offset*"],
        ARM_TRUTH,
        HAND_POINTS[:4],
        unseen_plan="measurements/arm_unseen_plan.json",
    ),
}


def with_sigma(plan: MeasurementSet, sigma: float) -> MeasurementSet:
    """The plan with every measurement's σ set to ``sigma`` (in the measurement's SI unit)."""
    out = [dataclasses.replace(m, cov=np.eye(len(m.cov)) * sigma**2) for m in plan.measurements]
    return dataclasses.replace(plan, measurements=out)


class PointSet:
    """The watched points (every attitude) of a problem, and their split along the line of sight."""

    def __init__(self, problem: Problem, names: tuple[str, ...], x_true: np.ndarray):
        model = problem.model
        configs = problem.params.configurations
        self.problem = problem
        self.points = np.array([model.point_index(model.resolve("point", p)) for p in names] * len(configs))
        self.configs = np.repeat(np.arange(len(configs)), len(names))
        camera_frame = model.cameras[model.camera_index(model.resolve("camera", CAMERA))].frame
        self.eyes = problem.frame_origins(x_true)[self.configs, camera_frame]
        self.truth, self.J = problem.point_jacobian(x_true, self.configs, self.points)
        u = self.truth - self.eyes
        self.u = u / np.linalg.norm(u, axis=1)[:, None]

    def positions(self, x: np.ndarray) -> np.ndarray:
        return self.problem.point_jacobian(x, self.configs, self.points)[0]

    def split(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(⟂, ∥) error of every point for estimated positions P (k, 3)."""
        e = P - self.truth
        along = np.sum(e * self.u, axis=1)
        across = np.linalg.norm(e - along[:, None] * self.u, axis=1)
        return across, np.abs(along)

    def sigmas(self, cov3: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(σ⟂ largest, σ∥) of point covariances (k, 3, 3) relative to each line of sight."""
        par = np.sqrt(np.einsum("ki,kij,kj->k", self.u, cov3, self.u))
        P = np.eye(3)[None] - self.u[:, :, None] * self.u[:, None, :]
        perp = np.sqrt(np.maximum(np.linalg.eigvalsh(P @ cov3 @ P)[:, -1], 0.0))
        return perp, par


def run_case(case: Case, sigma: float, trials: int, restarts: int, seed: int, say) -> dict:
    model = mbcal.load_model(ROOT / case.model)
    plan = with_sigma(mbcal.read_measurements(ROOT / case.plan, model), sigma)
    exact = mbcal.simulate(model, plan, case.truth, noise=0.0)
    problem = Problem(model, exact, case.unknowns)
    params = problem.params
    x_true = params.from_dict({k: v for k, v in case.truth.items() if k in params.names})
    y_true, known = problem.y, np.asarray(params.known)
    sigmas = np.empty(problem.size)  # σ of every row of h
    for m, rows in zip(exact.measurements, problem.measurement_rows):
        sigmas[rows] = m.sigma

    # The covariance mbcal predicts (at the truth: the Monte Carlo's own linearisation point).
    J = problem.jacobian(x_true)
    cov = np.linalg.inv(J.T @ J)
    watched = PointSet(problem, case.points, x_true)
    pred_perp, pred_par = watched.sigmas(np.einsum("kin,nm,kjm->kij", watched.J, cov, watched.J))
    before = watched.split(watched.positions(params.x0))

    unseen = None
    if case.unseen_plan:
        uplan = with_sigma(mbcal.read_measurements(ROOT / case.unseen_plan, model), sigma)
        uproblem = Problem(model, mbcal.simulate(model, uplan, case.truth, noise=0.0), case.unknowns)
        order = [uproblem.params.names.index(n) for n in params.names]
        ux = uproblem.params.from_dict({k: v for k, v in case.truth.items() if k in params.names})
        unseen = PointSet(uproblem, case.points, ux)
        unseen_before = unseen.split(unseen.positions(uproblem.params.x0))

    def to_unseen(x):
        out = np.array(unseen.problem.params.x0, dtype=float)
        out[order] = x
        return out

    rng = np.random.default_rng(seed)
    starts = random_starts(params.x0, params.lower, params.upper, restarts, seed)
    config = SolverConfig()
    errors, unseen_errors, estimates, statuses, iterations, times = [], [], [], [], [], []
    for t in range(trials):
        y = y_true + rng.normal(size=y_true.shape) * sigmas
        t0 = time.perf_counter()
        solved = least_squares(
            problem.residual_function, starts, args=(y, known), config=config, size=problem.n_residuals
        )
        times.append(time.perf_counter() - t0)
        x = solved.x_best
        estimates.append(x)
        statuses.append(solved.status_best.converged)
        iterations.append(int(solved.iterations[solved.best]))
        errors.append(watched.positions(x))
        if unseen is not None:
            unseen_errors.append(unseen.positions(to_unseen(x)))
        if (t + 1) % max(1, trials // 10) == 0:
            say(f"  {case.name} σ={sigma} px: {t + 1}/{trials} trials")
    P = np.stack(errors)  # (T, k, 3)
    perp, par = zip(*(watched.split(p) for p in P))
    perp, par = np.array(perp), np.array(par)  # (T, k)
    mc_perp, mc_par = watched.sigmas(np.stack([np.cov(P[:, k, :].T) for k in range(P.shape[1])]))
    out = {
        "case": case,
        "sigma": sigma,
        "trials": trials,
        "restarts": restarts,
        "m": problem.size,
        "n": params.size,
        "converged": float(np.mean(statuses)),
        "iterations": float(np.median(iterations)),
        "time_ms": 1e3 * float(np.median(times[1:] if len(times) > 1 else times)),
        "before": (before[0].max(), before[1].max()),
        "after_median": (np.median(perp.max(axis=1)), np.median(par.max(axis=1))),
        "after_p95": (np.percentile(perp.max(axis=1), 95), np.percentile(par.max(axis=1), 95)),
        "pred": (pred_perp, pred_par),
        "mc": (mc_perp, mc_par),
        "x_rms": np.sqrt(np.mean((np.stack(estimates) - x_true) ** 2, axis=0)),
        "x_std_pred": np.sqrt(np.diag(cov)),
        "names": params.names,
    }
    if unseen is not None:
        U = np.stack(unseen_errors)
        uperp, upar = (np.array(v) for v in zip(*(unseen.split(p) for p in U)))
        out["unseen_before"] = (unseen_before[0].max(), unseen_before[1].max())
        out["unseen_median"] = (np.median(uperp.max(axis=1)), np.median(upar.max(axis=1)))
        out["unseen_p95"] = (np.percentile(uperp.max(axis=1), 95), np.percentile(upar.max(axis=1), 95))
    return out


def overlays(case: Case, images: Path, doc_dir: Path, say) -> list[str]:
    """One calibration at 1 px, drawn over the (rendered) true camera image before and after."""
    from mbcal.modeling import modeler
    from mbcal.render.overlays import calibration_overlays
    from mbcal.render.views import render_view

    model = mbcal.load_model(ROOT / case.model)
    plan = mbcal.read_measurements(ROOT / case.plan, model)
    data = mbcal.simulate(model, plan, case.truth, noise=1.0, seed=0)
    result = mbcal.calibrate(model, data, case.unknowns, restarts=16, seed=0)
    config = result.problem.params.configurations[0]
    X_true = np.atleast_2d(result.problem.params.X(result.problem.params.from_dict(case.truth)))
    scene = modeler(model, X_true[0])
    background = render_view(scene, CAMERA).color
    folder = images / case.name
    written = calibration_overlays(
        result, folder, backgrounds={CAMERA: background}, cameras=[CAMERA], configurations=[config]
    )
    say(f"  wrote {', '.join(p.name for p in written)}")
    return [Path(os.path.relpath(p, doc_dir)).as_posix() for p in written]


def cm(v) -> str:
    return "—" if v is None else f"{100 * v:.2f}"


def agreement(pred: np.ndarray, mc: np.ndarray) -> str:
    r = mc / pred
    return f"{r.min():.2f} … {r.max():.2f}"


def write_doc(results: list[dict], pictures: dict[str, list[str]], path: Path, elapsed: float) -> str:
    import jax

    lines = [
        "# The seed's experiments, reproduced in simulation",
        "",
        "Written by `python bench/experiments.py` (do not edit by hand; run it again). "
        f"{results[0]['trials']} Monte Carlo trials per row, {results[0]['restarts']} restarts per trial; "
        f"took {elapsed / 60:.1f} min on {platform.machine()} with {jax.device_count()} JAX "
        f"{jax.default_backend().upper()} device(s), Python {platform.python_version()}, JAX {jax.__version__}.",
        "",
        "The seed (section 4.2) calibrates a teleexistence robot's model of a factory corner: the",
        "room's pose from 24 points clicked in the robot's stereo images, and the unknown zero",
        "offsets of its 7-joint arm from 84 image points of the hand in 10 attitudes.  Here the",
        "same models (`models/teleexistence.mdl`, `models/arm7.mdl`) and plans (`measurements/`)",
        "are simulated: a known true world, Gaussian click noise, the estimate from the nominal",
        "model, and the error of the watched points across (⟂) and along (∥) the left camera's",
        "line of sight.  The seed reports the largest error of the lever's (room) or the hand's",
        "(arm) points; so does the table, as the median and the 95th percentile over the trials.",
        "",
        "**The simulation has no structural model error.**  Its true world differs from the model",
        "only in the unknowns, so the error after calibration is click noise alone, propagated",
        "through the geometry.  The seed's real robot also had model errors (link lengths, camera",
        "calibration, the room's own shape) that more clicks do not average away: its numbers are",
        "an upper bound that ours should beat, and a beaten number here does not promise the same",
        "margin on a real robot.",
        "",
    ]
    for case_name in ("room", "arm"):
        rows = [r for r in results if r["case"].name == case_name]
        if not rows:
            continue
        case = rows[0]["case"]
        seed = SEED[case_name]
        what = "lever" if case_name == "room" else "hand (every attitude)"
        lines += [f"## {case.title}", ""]
        head = ["", "⟂ (cm)", "∥ (cm)", "seed ⟂ (cm)", "seed ∥ (cm)"]
        body = [
            [
                "before (largest, " + what + ")",
                cm(rows[0]["before"][0]),
                cm(rows[0]["before"][1]),
                f"{seed['before'][0]}",
                f"{seed['before'][1]}",
            ]
        ]
        for r in rows:
            s = r["sigma"]
            body.append(
                [
                    f"after, σ = {s} px: median of largest",
                    cm(r["after_median"][0]),
                    cm(r["after_median"][1]),
                    f"{seed['after'][0]}",
                    f"{seed['after'][1]}",
                ]
            )
            body.append([f"after, σ = {s} px: 95th percentile", cm(r["after_p95"][0]), cm(r["after_p95"][1]), "", ""])
            if "unseen_median" in r:
                body.append(
                    [
                        f"unseen attitudes, σ = {s} px: median of largest",
                        cm(r["unseen_median"][0]),
                        cm(r["unseen_median"][1]),
                        f"{seed['unseen'][0]}",
                        "—",
                    ]
                )
        if "unseen_before" in rows[0]:
            body.insert(
                1,
                [
                    "unseen attitudes, before",
                    cm(rows[0]["unseen_before"][0]),
                    cm(rows[0]["unseen_before"][1]),
                    "—",
                    "—",
                ],
            )
        lines += [_markdown(head, body), ""]
        lines += [
            "Predicted σ (from the covariance at the solution's linearisation) against the Monte Carlo",
            "spread of the same points; the ratio column is MC / predicted over every watched point",
            "(the issue asks for agreement within ±25 %, i.e. 0.75 … 1.25):",
            "",
        ]
        head = [
            "σ clicks",
            "largest σ⟂ pred. (cm)",
            "σ⟂ MC (cm)",
            "ratio ⟂",
            "largest σ∥ pred. (cm)",
            "σ∥ MC (cm)",
            "ratio ∥",
            "converged",
            "iterations",
            "ms / solve",
        ]
        body = []
        for r in rows:
            (pp, pa), (mp, ma) = r["pred"], r["mc"]
            kp, ka = int(np.argmax(pp)), int(np.argmax(pa))
            body.append(
                [
                    f"{r['sigma']} px",
                    cm(pp[kp]),
                    cm(mp[kp]),
                    agreement(pp, mp),
                    cm(pa[ka]),
                    cm(ma[ka]),
                    agreement(pa, ma),
                    f"{100 * r['converged']:.0f} %",
                    f"{r['iterations']:.0f}",
                    f"{r['time_ms']:.1f}",
                ]
            )
        lines += [_markdown(head, body), ""]
        for pic in pictures.get(case_name, []):
            lines += [f"![{Path(pic).stem}]({pic})", ""]
    lines += [
        "## How ours compares with the seed, and why",
        "",
        *_verdict(results),
        "",
        "Regenerate: `python bench/experiments.py`;",
        "`--trials` and `--restarts` change the effort, `--out` the file.",
        "",
    ]
    text = "\n".join(lines)
    atomic_write(path, text)
    return text


def _verdict(results: list[dict]) -> list[str]:
    out = []
    for r in results:
        name, s = r["case"].name, r["sigma"]
        seed = SEED[name]["after"]
        ours = r["after_p95"]
        better = all(o * 100 < t for o, t in zip(ours, seed))
        out.append(
            f"- {name}, σ = {s} px: the 95th percentile of our largest error after calibration "
            f"({cm(ours[0])} ⟂ / {cm(ours[1])} ∥ cm) is {'below' if better else 'NOT below'} the seed's "
            f"{seed[0]} / {seed[1]} cm."
        )
        if "unseen_p95" in r:
            u = r["unseen_p95"][0]
            ok = 100 * u < SEED["arm"]["unseen"][0]
            out.append(
                f"- arm at unseen attitudes, σ = {s} px: 95th percentile {cm(u)} cm ⟂, "
                f"{'below' if ok else 'NOT below'} the seed's {SEED['arm']['unseen'][0]} cm."
            )
    out.append(
        "- Both 'after' columns are click noise only (no structural error, see above); the seed's "
        "residual errors after calibration are dominated by its model's own errors."
    )
    arm = [r for r in results if r["case"].name == "arm"]
    if arm:
        out.append(
            f"- Our arm's 'before' (∥ {cm(arm[0]['before'][1])} cm) is smaller along the line of sight than "
            "the seed's 13.2 cm: with the cameras aimed at the hand, wrong joint offsets swing the hand "
            "mostly across the line of sight; the seed's larger ∥ error before also includes its model's "
            "other errors.  The offsets are chosen to match the seed's ⟂ error before."
        )
    return out


def _markdown(head: list[str], rows: list[list[str]]) -> str:
    out = ["| " + " | ".join(head) + " |", "|" + "|".join(["---"] + ["--:"] * (len(head) - 1)) + "|"]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(out)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=200, help="Monte Carlo trials per case and noise (200)")
    parser.add_argument("--restarts", type=int, default=16, help="random restarts per solve (16)")
    parser.add_argument("--noise", type=float, nargs="+", default=[1.0, 0.5], help="click noise σ in px (1 0.5)")
    parser.add_argument("--cases", nargs="+", choices=sorted(CASES), default=["room", "arm"])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "experiments.md", help="the report to write")
    parser.add_argument("--no-images", action="store_true", help="skip the overlay images")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    def say(msg):
        print(msg, file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    results = []
    for name in args.cases:
        for k, sigma in enumerate(args.noise):
            say(f"{name}: σ = {sigma} px, {args.trials} trials")
            # An independent noise draw per noise level (the same seed would only rescale the trials).
            results.append(run_case(CASES[name], sigma, args.trials, args.restarts, args.seed + 1000 * k, say))
    pictures = {}
    if not args.no_images:
        images = args.out.parent / "images" / "experiments"
        for name in args.cases:
            say(f"{name}: overlays")
            pictures[name] = overlays(CASES[name], images, args.out.parent, say)
    text = write_doc(results, pictures, args.out, time.perf_counter() - t0)
    for r in results:
        (pp, pa), (mp, ma) = r["pred"], r["mc"]
        print(
            table(
                ["", "⟂ (cm)", "∥ (cm)"],
                [
                    ["before", cm(r["before"][0]), cm(r["before"][1])],
                    ["after, median of largest", cm(r["after_median"][0]), cm(r["after_median"][1])],
                    ["after, 95th percentile", cm(r["after_p95"][0]), cm(r["after_p95"][1])],
                    ["MC / predicted σ", agreement(pp, mp), agreement(pa, ma)],
                ],
                align="lrr",
                title=f"{r['case'].name}, σ = {r['sigma']} px, {r['trials']} trials:",
            )
        )
    print(f"\nwrote {args.out} ({len(text.splitlines())} lines)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
