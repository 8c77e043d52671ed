"""The seed's calibration experiments (section 4.2): measurement plans for the bundled models.

``python bench/plans.py plans`` writes the plans in ``measurements/`` (they ship with mbcal; run
this only to make them anew):

* ``room_plan.csv`` — 24 named points of the factory corner, each clicked in both images of the
  robot's stereo camera (48 image points, 96 values), σ = 1 px (mouse clicking).
* ``arm_plan.json`` — the arm in 10 attitudes, the neck turned to look at the hand, with the
  encoder readings of every joint per attitude; 4 hand points in both images per attitude,
  5 in two of them: 84 image points, σ = 1 px.
* ``arm_unseen_plan.json`` — 4 further attitudes, not used for the estimate, where the error of
  the calibrated arm is checked (the seed's "other attitudes").

The attitudes are drawn at random (seeded) from joint ranges that put the hand in front of the
robot, and kept only when every hand point is in both images with a margin — also when every
encoder offset is off by up to 10° (the search range), so the plan works before calibration.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from mbcal._jax import jax, jnp
from mbcal.language import load_model
from mbcal.language.model import Model
from mbcal.measurements.io import write_measurements
from mbcal.measurements.sets import MeasurementSet, measurements_from_records
from mbcal.modeling import modeler, parameter_vector

__all__ = [
    "room_plan",
    "arm_attitudes",
    "arm_plan",
    "ROOM_POINTS",
    "HAND_POINTS",
    "write_plans",
]

ROOT = Path(__file__).resolve().parents[1]

# The 24 points clicked in the room experiment: on the lever, the valve, the pipes, the gauge,
# the box and the fan — spread over the image so the pose is well determined.
ROOM_POINTS = (
    "lever.hub", "lever.middle", "lever.knob_front", "lever.tip", "valve.front",
    "upper_pipe.end_a", "upper_pipe.end_b", "lower_pipe.end_a", "lower_pipe.end_b", "riser.end_a", "riser.end_b",
    "gauge.center", "gauge.top",
    "box.front_bottom_left", "box.front_bottom_right", "box.front_top_left", "box.front_top_right",
    "box.back_top_left", "box.back_top_right",
    "fan.hub", "blade_1.tip", "blade_2.tip", "blade_3.tip", "blade_4.tip",
)  # fmt: skip
STEREO = ("eyes.left", "eyes.right")
HAND_POINTS = ("hand.tip", "hand.knuckle_a", "hand.knuckle_b", "hand.thumb", "hand.wrist")

# Joint ranges (degrees) that put the hand in front of the robot's face.
ARM_RANGES = {
    "torso.q": (-15, 15),
    "arm.q1": (-100, -40),
    "arm.q2": (-25, 5),
    "arm.q3": (-30, 30),
    "arm.q4": (-100, -30),
    "arm.q5": (-60, 60),
    "arm.q6": (-30, 30),
    "arm.q7": (-15, 15),
}


def room_plan(model: Model, sigma: float = 1.0) -> MeasurementSet:
    """The room experiment: the 24 points in both cameras."""
    records = [
        {"id": f"{cam.split('.')[-1]}:{pt}", "kind": "image_point", "camera": cam, "point": pt, "sigma": sigma}
        for pt in ROOM_POINTS
        for cam in STEREO
    ]
    return measurements_from_records(records, model)


def _look_at_hand(model: Model, readings: dict[str, float]) -> dict[str, float]:
    """Neck pan and tilt that point the cameras at the hand."""
    scene = modeler(model, parameter_vector(model, readings))
    hand = np.asarray(scene.point("hand.knuckle_a"))
    neck = np.asarray(scene.frame("neck_pan"))[:3, 3]
    eyes = np.asarray(scene.frame("head.eyes"))[:3, 3]
    torso = math.radians(0) + readings.get("torso.q", 0.0)
    d = hand - neck
    pan = math.atan2(d[1], d[0]) - torso
    height = eyes[2] - neck[2]
    horizontal = math.hypot(d[0], d[1])
    tilt = math.atan2(neck[2] + height - hand[2], horizontal)
    return {"neck.q1": pan, "neck.q2": tilt, "neck.q3": 0.0}


def _projector(model: Model):
    """A jitted X (k, n) → (depth, pixels) of the hand points in both cameras."""

    def one(X):
        scene = modeler(model, X)
        depth, pixels = [], []
        for cam in STEREO:
            view = scene.camera(cam)
            p = jnp.stack([scene.point(pt) for pt in HAND_POINTS])
            depth.append(view.to_camera(p)[:, 2])
            pixels.append(view.project(p))
        return jnp.stack(depth), jnp.stack(pixels)

    return jax.jit(jax.vmap(one))


def _hand_visible(model: Model, project, readings: dict[str, float], margin: float = 30.0) -> bool:
    base = parameter_vector(model, readings)
    offsets = [np.zeros(7)] + [s * math.radians(10.0) * np.eye(7)[j] for j in range(7) for s in (-1, 1)]
    X = np.tile(base, (len(offsets), 1))
    for k, off in enumerate(offsets):
        for j in range(7):
            X[k, model.param_index(f"arm.offset{j + 1}")] = off[j]
    depth, uv = (np.asarray(a) for a in project(X))
    width, height = model.cameras[0].width, model.cameras[0].height
    inside = (
        (uv[..., 0] >= margin)
        & (uv[..., 0] <= width - margin)
        & (uv[..., 1] >= margin)
        & (uv[..., 1] <= height - margin)
    )
    return bool(np.all(inside & (depth > 0.2)))


def arm_attitudes(model: Model, n: int, seed: int) -> list[dict[str, float]]:
    """n attitudes (joint readings in radians, neck aimed at the hand) with the hand in both images."""
    rng = np.random.default_rng(seed)
    project = _projector(model)
    out: list[dict[str, float]] = []
    tries = 0
    while len(out) < n:
        tries += 1
        if tries > 20000:
            raise RuntimeError("could not find attitudes with the hand in view")
        readings = {k: math.radians(rng.uniform(lo, hi)) for k, (lo, hi) in ARM_RANGES.items()}
        readings.update(_look_at_hand(model, readings))
        if _hand_visible(model, project, readings):
            out.append(readings)
    return out


def arm_plan(
    model: Model, attitudes: list[dict[str, float]], *, extra_points: int = 2, prefix: str = "pose", sigma: float = 1.0
) -> MeasurementSet:
    """Hand points in both cameras in every attitude: 4 points, 5 in the first ``extra_points`` attitudes."""
    records = []
    configurations = {}
    for i, readings in enumerate(attitudes):
        config = f"{prefix}{i + 1:02d}"
        configurations[config] = {k: f"{math.degrees(v):.6f} deg" for k, v in readings.items()}
        points = HAND_POINTS if i < extra_points else HAND_POINTS[:4]
        for pt in points:
            for cam in STEREO:
                records.append(
                    {
                        "id": f"{config}:{cam.split('.')[-1]}:{pt.split('.')[-1]}",
                        "kind": "image_point",
                        "config": config,
                        "camera": cam,
                        "point": pt,
                        "sigma": sigma,
                    }
                )
    return measurements_from_records(records, model, configurations=configurations)


def write_plans(folder: Path | None = None) -> list[Path]:
    """Write the seed's plans into ``folder`` (default: the repository's measurements/)."""
    folder = Path(folder or ROOT / "measurements")
    room = load_model(ROOT / "models" / "teleexistence.mdl")
    arm = load_model(ROOT / "models" / "arm7.mdl")
    written = []
    plan = room_plan(room)
    write_measurements(plan, folder / "room_plan.csv")
    written.append(folder / "room_plan.csv")
    attitudes = arm_attitudes(arm, 14, seed=4)
    write_measurements(arm_plan(arm, attitudes[:10]), folder / "arm_plan.json")
    write_measurements(arm_plan(arm, attitudes[10:], extra_points=0, prefix="unseen"), folder / "arm_unseen_plan.json")
    written += [folder / "arm_plan.json", folder / "arm_unseen_plan.json"]
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python bench/plans.py", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("plans", help="write the seed's measurement plans")
    p.add_argument("--folder", type=Path, default=None, help="where to write (default: measurements/)")
    args = parser.parse_args(argv)
    if args.command == "plans":
        for path in write_plans(args.folder):
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
