"""Forward kinematics and the full Jacobian of a 7-DOF arm for 10,000 configurations, warm.

mbcal's ``Kinematics.forward`` (one compiled call for the whole batch) beside Pinocchio (the ``pin``
package, looping in Python) when it is installed, on the same robot: the bundled URDF arm
(tests/data/arm7.urdf: seven revolute joints about skewed axes, a fixed tool frame) and, for
mbcal alone, the seed's arm (models/arm7.mdl).  Both programs' results are compared entry by
entry.  The section it writes goes into docs/performance.md between its markers (the rest of the
page is bench/run.py's); ``--out -`` prints it instead.

    python bench/kinematics.py                 # 10,000 configurations, best of 20
    python bench/kinematics.py --configs 1000 --repeats 3 --out -
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common import best_of, cores_and_system, cpu_name, publish  # noqa: E402

import mbcal  # noqa: E402
from mbcal._jax import jax  # noqa: E402
from mbcal.kinematics import Kinematics  # noqa: E402

URDF = ROOT / "tests" / "data" / "arm7.urdf"
BEGIN = "<!-- bench/kinematics.py: begin -->"
END = "<!-- bench/kinematics.py: end -->"
GOAL_MS = 13.0  # the reference: Pinocchio looping in Python, 1.3 µs per configuration


def configurations(kin: Kinematics, count: int, seed: int = 0) -> np.ndarray:
    lo = np.where(np.isfinite(kin.lower), kin.lower, -np.pi)
    hi = np.where(np.isfinite(kin.upper), kin.upper, np.pi)
    return np.random.default_rng(seed).uniform(lo, hi, size=(count, kin.n))


def ours(kin: Kinematics, Q: np.ndarray, repeats: int) -> dict:
    out = kin.forward(Q)  # compile
    jax.block_until_ready(out)
    batch = best_of(lambda: jax.block_until_ready(kin.forward(Q)), repeats)
    single = Q[:200]
    kin.forward(single[0])
    one = best_of(lambda: [jax.block_until_ready(kin.forward(q)) for q in single], max(1, repeats // 4)) / len(single)
    return {"batch_s": batch, "one_s": one, "out": out}


def pinocchio(Q: np.ndarray, frame: str, repeats: int) -> dict | None:
    try:
        import pinocchio as pin  # optional: pip install pin
    except ImportError:
        return None
    model = pin.buildModelFromUrdf(str(URDF))
    data = model.createData()
    fid = model.getFrameId(frame)
    world = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED

    def separate():
        for q in Q:
            pin.computeJointJacobians(model, data, q)  # forward kinematics and every joint's Jacobian
            pin.updateFramePlacement(model, data, fid)
            pin.getFrameJacobian(model, data, fid, world)

    def combined():
        for q in Q:
            pin.computeFrameJacobian(model, data, q, fid, world)  # forward kinematics and this frame's J
            pin.updateFramePlacement(model, data, fid)

    separate()
    times = {"computeJointJacobians + getFrameJacobian": best_of(separate, repeats)}
    times["computeFrameJacobian + updateFramePlacement"] = best_of(combined, repeats)
    positions, jacobians = [], []
    for q in Q:
        J = pin.computeFrameJacobian(model, data, q, fid, world)
        positions.append(np.array(pin.updateFramePlacement(model, data, fid).translation))
        jacobians.append(np.array(J))
    return {
        "version": pin.__version__,
        "times": times,
        "position": np.array(positions),
        "jacobian": np.array(jacobians),
    }


def section(results: dict, count: int) -> str:
    import jaxlib

    pin = results.get("pinocchio")
    lines = [
        BEGIN,
        "## Kinematics: f(θ) and the full Jacobian of a 7-DOF arm",
        "",
        "Written by `python bench/kinematics.py` (do not edit by hand; run it again).  Forward",
        f"kinematics (position and orientation) and the full 6 × 7 Jacobian for {count:,} random",
        "configurations within the joint limits, warm (compiled before timing), best of several runs.",
        "mbcal evaluates the whole batch in one compiled call (`Kinematics.forward`); Pinocchio is",
        "called once per configuration from a Python loop, as a user of its Python bindings would.",
        "",
        f"- machine: {cpu_name()}, {cores_and_system()}",
        f"- Python {platform.python_version()}, JAX {jax.__version__} (jaxlib {jaxlib.__version__}, "
        f"backend {jax.default_backend()}), NumPy {np.__version__}"
        + (f", Pinocchio {pin['version']}" if pin else ", Pinocchio not installed (`pip install pin`)"),
        f"- run on {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}",
        "",
        f"| robot | program | {count:,} configurations (ms) | per configuration (µs) | goal ≤ {GOAL_MS:g} ms |",
        "|---|---|--:|--:|--:|",
    ]
    for name, r in results["ours"].items():
        ms = 1e3 * r["batch_s"]
        verdict = "met" if ms * 10_000 / count <= GOAL_MS else "**missed**"
        lines.append(f"| {name} | mbcal, one batch | {ms:.2f} | {1e6 * r['batch_s'] / count:.3f} | {verdict} |")
        per_call = r["one_s"]
        lines.append(
            f"| {name} | mbcal, one configuration per call | {1e3 * per_call * count:.0f} | {1e6 * per_call:.1f} | — |"
        )
    if pin:
        for variant, seconds in pin["times"].items():
            lines.append(
                f"| arm7.urdf | Pinocchio, Python loop: `{variant}` | {1e3 * seconds:.2f} | "
                f"{1e6 * seconds / count:.2f} | — |"
            )
    lines.append("")
    if pin:
        lines += [
            f"Agreement with Pinocchio over the {count:,} configurations (tool frame of arm7.urdf, world-aligned "
            f"Jacobian): position {results['agree_p']:.1e} m, Jacobian {results['agree_J']:.1e} (largest "
            "absolute difference).",
            "",
        ]
    batch = results["ours"]["arm7.urdf"]["batch_s"]
    notes = [
        "- The batch is where mbcal is fast: the constant parts of the chain are folded once, and the",
        "  whole batch runs as a few fused array kernels with the configurations along the last axis;",
        "  J comes from the joint axes (column k = [aₖ × (p − oₖ); aₖ]), not from automatic differentiation.",
    ]
    if pin:
        fastest = min(pin["times"].values())
        notes.append(
            f"- Per configuration in a Python loop Pinocchio is the faster ({1e6 * fastest / count:.1f} µs against "
            f"mbcal's {1e6 * results['ours']['arm7.urdf']['one_s']:.0f} µs, which is the cost of dispatching a "
            "compiled JAX call): for one configuration at a time (a control loop in Python) call "
            "`Kinematics.forward_single` inside your own jitted loop, as `mbcal.control` does."
        )
        notes.append(
            f"- For the batch mbcal takes {1e3 * batch:.1f} ms against Pinocchio's {1e3 * fastest:.1f} ms "
            f"({fastest / batch:.1f}×)."
        )
    lines += [*notes, "", END]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--configs", type=int, default=10_000, help="configurations (default 10,000)")
    parser.add_argument("--repeats", type=int, default=20, help="timed repeats (best of)")
    parser.add_argument("--out", default=str(ROOT / "docs" / "performance.md"), help="page to write ('-': print)")
    args = parser.parse_args(argv)

    urdf = Kinematics(mbcal.load_model(URDF), "tool_center")
    seed_arm = Kinematics(mbcal.load_model(ROOT / "models" / "arm7.mdl"), "hand.tip", chain="arm.q*")
    Q = configurations(urdf, args.configs)
    results: dict = {"ours": {}}
    results["ours"]["arm7.urdf"] = ours(urdf, Q, args.repeats)
    results["ours"]["models/arm7.mdl"] = ours(seed_arm, configurations(seed_arm, args.configs), args.repeats)
    pin = pinocchio(Q, "tool-center", max(1, args.repeats // 5))
    if pin is not None:
        results["pinocchio"] = pin
        out = results["ours"]["arm7.urdf"]["out"]
        results["agree_p"] = float(np.abs(np.asarray(out.position) - pin["position"]).max())
        results["agree_J"] = float(np.abs(np.asarray(out.jacobian) - pin["jacobian"]).max())
    text = section(results, args.configs)
    publish(text, args.out, BEGIN, END)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
