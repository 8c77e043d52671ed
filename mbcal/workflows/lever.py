"""The seed's lever task (section 4.3) in simulation: pulling the smoke shut-off lever through the
virtual room.

The operator works in the *virtual* room — the factory corner's model with the room's pose as the
model says (uncalibrated) or as the room calibration of section 4.2 found it (calibrated) — and
plans the hand's path there: reach in front of the lever's knob, approach it, close the hand,
pull the lever down to its stop, hold.  The master arm's joints follow that path; the slave arm
executes it in the *real* room (the true pose, :data:`mbcal.workflows.demo.DEMO_TRUTH`) under
impedance control with the seed's M = 6I kg, B = 100I N s/m, K = 50I N/m, or under position
control.  The real lever is caught only if the hand is within 6 cm of its knob in every direction
when it closes (the seed: "about 6.0 cm in both vertical and horizontal directions").

The robot is the seed's anthropomorphic arm (``models/arm7.mdl``, right arm, 7 joints), standing
on its mobile base in front of the valve.  Numbers the paper does not give — the lever's spring,
friction and inertia, the stiffness of the closed hand and of hard contact — are set once in
:class:`LeverTask` from plausible hardware and reported with the results.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from mbcal.api import calibrate, simulate
from mbcal.control import (
    Contact,
    ControlRun,
    Environment,
    Grasp,
    Impedance,
    Lever,
    follow_path,
    lever_from_model,
    min_jerk,
    surfaces_from_model,
)
from mbcal.control import simulate as run_control
from mbcal.geometry import transforms as geo
from mbcal.kinematics import Kinematics
from mbcal.language import load_model
from mbcal.language.model import Model
from mbcal.measurements.io import read_measurements
from mbcal.resources import bundled
from mbcal.text import table
from mbcal.workflows.demo import DEMO_TRUTH

__all__ = [
    "LeverTask",
    "LeverCase",
    "calibrated_room",
    "run_lever_task",
    "seed_cases",
    "plan",
    "displaced",
    "lever_table",
    "case_cells",
    "with_task",
]

ROOM_PARAMS = ("room.x", "room.y", "room.z", "room.roll", "room.pitch", "room.yaw")


@dataclass(frozen=True)
class LeverTask:
    """The task's setting; every number here is reported beside the results.

    Attributes
    ----------
    base : (x, y, yaw)
        The robot's mobile base in the room's world (m, m, rad): 30 cm left of the cameras'
        origin, 40 cm towards the wall, facing it (the arm model's x axis along the room's y).
    ready : (7,)
        The arm's joints at the start (rad): upper arm hanging, forearm raised forwards (elbow 110°).
    grip : (3,)
        The hand's grip point in the hand's frame (m): between the knuckles.
    knob : float
        The lever's grip point along the lever from its hub (m): the knob's centre.
    standoff : float
        How far in front of the knob (towards the robot) the reach ends (m).
    reach, approach, close, dwell, pull, hold : float
        Durations of the plan's phases (s); the hand closes ``close`` s into the dwell.
    pull_to : float
        The angle the operator pulls the virtual lever to (rad): its stop, horizontal.
    pulled : float
        The real lever counts as pulled at this angle or beyond (rad).
    dt : float
        Integration step (s).
    impedance : Impedance
        The seed's M, B, K.
    grasp_capture, grasp_stiffness, grasp_damping, grasp_closing : float
        The closed hand: capture tolerance per axis (m), the spring (N/m) and damper (N s/m)
        between the grip point and the knob, and how long the fingers take to close (s).
    contact : Contact
        Hard surfaces: hand radius, stiffness, damping.
    lever : dict
        The lever's hinge: return spring (N m/rad, relaxed at its starting angle), friction
        (N m s/rad), inertia (kg m²), stops (rad) and their stiffness (N m/rad).
    """

    base: tuple[float, float, float] = (-0.30, 0.40, math.pi / 2)
    ready: tuple[float, ...] = tuple(math.radians(a) for a in (0.0, 0.0, 0.0, -110.0, 0.0, 0.0, 0.0))
    grip: tuple[float, float, float] = (0.015, 0.0, -0.55 * 0.108 * 1.75)
    knob: float = 0.25
    standoff: float = 0.10
    reach: float = 2.0
    approach: float = 1.0
    close: float = 0.2
    dwell: float = 0.5
    pull: float = 3.0
    hold: float = 1.0
    pull_to: float = math.radians(90.0)
    pulled: float = math.radians(80.0)
    dt: float = 1e-3
    impedance: Impedance = field(default_factory=Impedance)
    grasp_capture: float = 0.06
    grasp_stiffness: float = 5e3
    grasp_damping: float = 50.0
    grasp_closing: float = 0.3
    contact: Contact = field(default_factory=Contact)
    lever: Mapping[str, float] = field(
        default_factory=lambda: {
            "stiffness": 0.2,
            "damping": 0.02,
            "inertia": 0.01,
            "lower": -math.pi / 2,
            "upper": math.pi / 2,
            "stop_stiffness": 100.0,
        }
    )

    @property
    def base_pose(self) -> np.ndarray:
        x, y, yaw = self.base
        return np.asarray(geo.compose(geo.translation(np, [x, y, 0.0]), geo.rot_z(np, yaw)), dtype=float)

    @property
    def grasp_time(self) -> float:
        return self.reach + self.approach + self.close


@dataclass(frozen=True)
class LeverCase:
    """One run of the task and what it showed.

    Attributes
    ----------
    name : str
    virtual : dict
        The virtual room's parameter values the operator planned in.
    impedance : bool
        Impedance control (else position control).
    run : ControlRun
        The simulation, step by step.
    virtual_lever, real_lever : Lever
    grasp_error : (3,)
        Hand minus the real knob when the hand closed (m, room world axes: x across, y depth, z up).
    held : bool
        The hand caught the knob.
    final_angle : float
        The real lever's angle at the end (rad).
    pulled : bool
        ``final_angle`` reached the task's ``pulled``.
    peak_force, peak_pull_force : float
        The largest |F| on the hand over the run, and after the hand closed (N).
    peak_contact : float
        The largest force from hard surfaces (N).
    """

    name: str
    virtual: dict[str, float]
    impedance: bool
    run: ControlRun
    virtual_lever: Lever
    real_lever: Lever
    grasp_error: np.ndarray
    held: bool
    final_angle: float
    pulled: bool
    peak_force: float
    peak_pull_force: float
    peak_contact: float

    @property
    def success(self) -> bool:
        """The lever was caught and pulled down."""
        return self.held and self.pulled

    @property
    def grasp_distance(self) -> float:
        return float(np.linalg.norm(self.grasp_error))


def calibrated_room(*, restarts: int = 32, seed: int = 0, noise: float = 1.0) -> dict[str, float]:
    """The room's pose as the seed's room calibration finds it: the demo's 24 stereo points,
    clicked with ``noise`` px of noise in images of the true room, estimated by :func:`mbcal.calibrate`.

    Returns
    -------
    dict
        ``room.x`` … ``room.yaw`` (SI).
    """
    model = load_model(bundled("models/teleexistence.mdl"))
    plan = read_measurements(bundled("measurements/room_plan.csv"), model)
    data = simulate(model, plan, DEMO_TRUTH, noise=noise, seed=seed)
    result = calibrate(model, data, ["room.*"], restarts=restarts, seed=seed)
    return {name: float(result.values[name]) for name in ROOM_PARAMS}


def seed_cases(calibrated: Mapping[str, float]) -> list[tuple[str, dict[str, float], bool]]:
    """The issue's three runs: (name, virtual room values, impedance control?)."""
    return [
        ("uncalibrated model, impedance control", {}, True),
        ("calibrated model, impedance control", dict(calibrated), True),
        ("calibrated model, position control", dict(calibrated), False),
    ]


def _room() -> Model:
    return load_model(bundled("models/teleexistence.mdl"))


def _arm(task: LeverTask) -> Kinematics:
    arm = load_model(bundled("models/arm7.mdl"))
    # The grip point, given in the hand's frame, as an offset from its wrist point (at the hand's origin).
    return Kinematics(arm, "hand.wrist", chain="arm.q*", tool=task.grip, base=task.base_pose)


def _lever(room: Model, values: Mapping[str, float], task: LeverTask) -> Lever:
    return lever_from_model(
        room, "room.valve.lever", "lever.angle", dict(values), grip=(0.0, 0.0, task.knob), physics=task.lever
    )


def plan(task: LeverTask, arm: Kinematics, lever: Lever) -> tuple[np.ndarray, np.ndarray, int]:
    """The operator's hand path in the virtual room and the master arm's joints along it.

    Returns
    -------
    path : (T, 3)
    theta : (T, 7)
    grasp_step : int
    """
    dt = task.dt
    start = np.asarray(arm.position(np.asarray(task.ready)))
    knob = np.asarray(lever.grip(lever.angle))
    toward_robot = np.array([0.0, -1.0, 0.0])
    pre = knob + task.standoff * toward_robot

    def phase(duration: float) -> np.ndarray:
        n = max(1, int(round(duration / dt)))
        return np.arange(1, n + 1) / n

    pieces = [start[None], min_jerk(start, pre, phase(task.reach)), min_jerk(pre, knob, phase(task.approach))]
    pieces.append(np.repeat(knob[None], int(round(task.dwell / dt)), axis=0))
    angles = min_jerk(np.array([lever.angle]), np.array([task.pull_to]), phase(task.pull))[:, 0]
    pieces.append(np.asarray(lever.grip(angles)))
    end = np.asarray(lever.grip(task.pull_to))
    pieces.append(np.repeat(end[None], int(round(task.hold / dt)), axis=0))
    path = np.concatenate(pieces)
    theta = follow_path(arm, path, np.asarray(task.ready))
    grasp_step = int(round(task.grasp_time / dt))
    return path, theta, grasp_step


def run_lever_task(
    cases: Sequence[tuple[str, Mapping[str, float], bool]],
    *,
    truth: Mapping[str, float] = DEMO_TRUTH,
    task: LeverTask | None = None,
) -> list[LeverCase]:
    """Run the lever task for each (name, virtual room values, impedance control?) case.

    Parameters
    ----------
    cases : sequence
        The virtual rooms the operator plans in; ``{}`` is the uncalibrated model.
    truth : mapping
        The real room's values (default: the demo's true room pose).
    task : LeverTask, optional

    Returns
    -------
    list of LeverCase
    """
    task = task or LeverTask()
    room = _room()
    arm = _arm(task)
    real_lever = _lever(room, truth, task)
    free = task.base_pose[:3, 3] + np.array([0.0, 0.0, 1.0])
    surfaces = surfaces_from_model(room, dict(truth), exclude=["room.valve.lever"], free_point=free)
    environment = Environment(surfaces=surfaces, lever=real_lever, contact=task.contact)
    out = []
    for name, virtual, impedance in cases:
        virtual_lever = _lever(room, virtual, task)
        _, theta, grasp_step = plan(task, arm, virtual_lever)
        grasp = Grasp(
            step=grasp_step,
            capture=task.grasp_capture,
            stiffness=task.grasp_stiffness,
            damping=task.grasp_damping,
            closing=task.grasp_closing,
        )
        run = run_control(
            arm, theta, environment, dt=task.dt, impedance=task.impedance if impedance else None, grasp=grasp
        )
        force = np.linalg.norm(run.force, axis=1)
        final = float(run.lever_angle[-1])
        held = run.held
        out.append(
            LeverCase(
                name=name,
                virtual=dict(virtual),
                impedance=impedance,
                run=run,
                virtual_lever=virtual_lever,
                real_lever=real_lever,
                grasp_error=run.grasp_error,
                held=held,
                final_angle=final,
                pulled=final >= task.pulled,
                peak_force=float(force.max()),
                peak_pull_force=float(force[grasp_step:].max()),
                peak_contact=float(np.linalg.norm(run.contact_force, axis=1).max()),
            )
        )
    return out


def displaced(truth: Mapping[str, float], depth: float) -> dict[str, float]:
    """The true room moved ``depth`` m towards the robot: a virtual room with that residual error
    along the cameras' line of sight."""
    values = {name: float(truth.get(name, 0.0)) for name in ROOM_PARAMS}
    values["room.y"] -= depth
    return values


def case_cells(case: LeverCase, flag: Callable[[bool], str] = lambda b: "yes" if b else "no") -> list[str]:
    """A case's outcome as table cells: name, hand − knob (cm, x / y / z), its length, caught,
    the lever's final angle (deg) and the peak pulling force (N); ``flag`` writes the yes/no."""
    err = 100 * case.grasp_error
    return [
        case.name,
        f"{err[0]:+.1f} / {err[1]:+.1f} / {err[2]:+.1f}",
        f"{100 * case.grasp_distance:.1f}",
        flag(case.held),
        f"{math.degrees(case.final_angle):.1f}",
        f"{case.peak_pull_force:.1f}",
    ]


def lever_table(cases: Sequence[LeverCase]) -> str:
    """The outcome of each case as a text table."""
    rows = [[*case_cells(c), "yes" if c.success else "no"] for c in cases]
    return table(
        ["case", "hand − knob x/y/z (cm)", "|error| (cm)", "caught", "lever (deg)", "peak ‖F‖ (N)", "success"],
        rows,
        align="lrrlrrl",
    )


def with_task(task: LeverTask, **changes: object) -> LeverTask:
    """A copy of ``task`` with some fields changed (``with_task(task, grasp_stiffness=2e4)``)."""
    return replace(task, **changes)  # type: ignore[arg-type]
