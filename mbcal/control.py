"""Impedance control of a master–slave arm in contact with its environment (seed, eqs. 1–4 and 7).

The seed's slave arm follows its master arm under impedance control: with the slave's endpoint
x = x_s and the master's x_r = x_m (eqs. 3–4), the deviation e = x − x_r obeys

    M ë + B ė + K e = F                                   (eq. 2)

for the external force F measured at the wrist, and the slave's joints are commanded to
θ_s = θ_m + J*(θ) e with J* = Jᵀ(JJᵀ)⁻¹ (eq. 7).  Under *position control* e = 0: the slave copies
the master whatever it touches.

This module simulates that loop at a fixed step (semi-implicit Euler, one ``lax.scan``): the
master's joint trajectory is given, the servo reaches each commanded θ_s (as the seed assumes),
and the environment pushes back through

* hard surfaces — half-spaces, boxes, cylinders and spheres taken from a model's shapes — as stiff
  penalty springs with damping on the hand, a sphere of radius ``Contact.hand_radius``;
* a lever — a body hinged about a fixed axis, with a return spring, damping, inertia and end
  stops — that the hand can grasp: when the operator closes the hand and the hand is within the
  capture tolerance of the lever's grip in every axis (the seed's "about 6.0 cm in both vertical
  and horizontal directions"), a grasp spring ties the hand to the grip.

Kinematics come from :class:`mbcal.kinematics.Kinematics`, so the same code runs any model.
The seed's lever task (section 4.3) is built from these parts in :mod:`mbcal.workflows.lever`.
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mbcal._jax import jax, jnp
from mbcal.errors import KinematicsError
from mbcal.kinematics import Kinematics, float64, pseudo_inverse
from mbcal.language.model import Model
from mbcal.modeling import modeler, parameter_vector
from mbcal.text import fmt

Array = Any

__all__ = [
    "Impedance",
    "HalfSpace",
    "Sphere",
    "Cylinder",
    "Box",
    "Surface",
    "Contact",
    "Lever",
    "Grasp",
    "Environment",
    "ControlRun",
    "surfaces_from_model",
    "lever_from_model",
    "min_jerk",
    "follow_path",
    "simulate",
]


Vec3 = tuple[float, float, float]


def _v3(a: Array) -> Vec3:
    x, y, z = (float(v) for v in np.asarray(a, dtype=float).reshape(3))
    return (x, y, z)


def _matrix(value: float | Sequence[float] | np.ndarray, name: str) -> np.ndarray:
    """A scalar (times I), a diagonal (3,) or a full (3, 3) matrix."""
    a = np.asarray(value, dtype=float)
    if a.ndim == 0:
        return float(a) * np.eye(3)
    if a.shape == (3,):
        return np.diag(a)
    if a.shape == (3, 3):
        return a
    raise KinematicsError(f"{name} must be a number, 3 diagonal entries or a 3×3 matrix, got shape {a.shape}")


@dataclass(frozen=True)
class Impedance:
    """The target impedance M ë + B ė + K e = F (seed, eq. 2); the seed's values by default (eqs. 19–21).

    Attributes
    ----------
    M : float, (3,) or (3, 3)
        Inertia (kg): a number means M·I.  Default 6 kg.
    B : float, (3,) or (3, 3)
        Viscosity (N s/m).  Default 100 N s/m.
    K : float, (3,) or (3, 3)
        Elasticity (N/m).  Default 50 N/m.
    """

    M: float | Sequence[float] | np.ndarray = 6.0
    B: float | Sequence[float] | np.ndarray = 100.0
    K: float | Sequence[float] | np.ndarray = 50.0

    def matrices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(M, B, K) as 3×3 matrices; M must be symmetric positive definite, B and K ≥ 0."""
        M, B, K = _matrix(self.M, "M"), _matrix(self.B, "B"), _matrix(self.K, "K")
        for name, A, strict in (("M", M, True), ("B", B, False), ("K", K, False)):
            if not np.allclose(A, A.T):
                raise KinematicsError(f"the impedance's {name} must be symmetric")
            low = float(np.min(np.linalg.eigvalsh(A)))
            if low <= 0 if strict else low < 0:
                raise KinematicsError(
                    f"the impedance's {name} must be positive {'definite' if strict else 'semi-definite'}"
                )
        return M, B, K


# ---- hard surfaces: signed distances (negative inside) -----------------------------------------------------


@dataclass(frozen=True)
class HalfSpace:
    """The solid behind a plane: free where normal·(x − point) > 0."""

    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    name: str = ""

    def distance(self, x: Array) -> Array:
        n = np.asarray(self.normal, dtype=float)
        n = n / np.linalg.norm(n)
        return (x - np.asarray(self.point)) @ n


@dataclass(frozen=True)
class Sphere:
    centre: tuple[float, float, float]
    radius: float
    name: str = ""

    def distance(self, x: Array) -> Array:
        d = x - np.asarray(self.centre)
        return jnp.sqrt(jnp.sum(d * d) + 1e-300) - self.radius


@dataclass(frozen=True)
class Cylinder:
    """A closed cylinder: ``centre``, unit ``axis``, ``radius``, ``length`` (pipes count as solid)."""

    centre: tuple[float, float, float]
    axis: tuple[float, float, float]
    radius: float
    length: float
    name: str = ""

    def distance(self, x: Array) -> Array:
        a = np.asarray(self.axis, dtype=float)
        a = a / np.linalg.norm(a)
        d = x - np.asarray(self.centre)
        along = d @ a
        radial = jnp.sqrt(jnp.sum((d - along * a) ** 2) + 1e-300)
        q = jnp.stack([radial - self.radius, jnp.abs(along) - 0.5 * self.length])
        outside = jnp.sqrt(jnp.sum(jnp.maximum(q, 0.0) ** 2) + 1e-300)
        return jnp.where(jnp.all(q <= 0), jnp.max(q), outside)


@dataclass(frozen=True)
class Box:
    """An oriented box: ``centre``, ``rotation`` (its axes as columns), full ``size``."""

    centre: tuple[float, float, float]
    rotation: tuple[tuple[float, float, float], ...]
    size: tuple[float, float, float]
    name: str = ""

    def distance(self, x: Array) -> Array:
        local = (x - np.asarray(self.centre)) @ np.asarray(self.rotation)
        q = jnp.abs(local) - 0.5 * np.asarray(self.size)
        outside = jnp.sqrt(jnp.sum(jnp.maximum(q, 0.0) ** 2) + 1e-300)
        return jnp.where(jnp.all(q <= 0), jnp.max(q), outside)


Surface = HalfSpace | Sphere | Cylinder | Box


@dataclass(frozen=True)
class Contact:
    """Penalty contact between the hand and hard surfaces.

    Attributes
    ----------
    hand_radius : float
        The hand as a sphere around its endpoint (m).
    stiffness : float
        N/m per metre of penetration (a padded hand on steel: stiff, but finite).
    damping : float
        N s/m, against the approach speed only (no sticking).
    """

    hand_radius: float = 0.04
    stiffness: float = 2e4
    damping: float = 200.0


@dataclass(frozen=True)
class Lever:
    """A lever turning about a fixed axis: its grip point moves on the circle
    centre + r0·cos φ + (axis × r0)·sin φ.

    Attributes
    ----------
    centre : (3,)
        The circle's centre on the hinge axis (m).
    axis : (3,)
        Unit hinge axis; φ turns right-handed about it.
    r0 : (3,)
        Grip point minus centre at φ = 0 (perpendicular to the axis; its length is the lever arm).
    angle : float
        φ at the start (rad).
    rest : float
        Angle where the return spring is relaxed (rad).
    stiffness, damping : float
        Return spring (N m/rad) and viscous friction (N m s/rad) of the hinge.
    inertia : float
        About the hinge (kg m²).
    lower, upper : float
        End stops (rad), springs of ``stop_stiffness`` (N m/rad) beyond them.
    """

    centre: tuple[float, float, float]
    axis: tuple[float, float, float]
    r0: tuple[float, float, float]
    angle: float
    rest: float
    stiffness: float = 0.2
    damping: float = 0.02
    inertia: float = 0.01
    lower: float = -math.pi / 2
    upper: float = math.pi / 2
    stop_stiffness: float = 100.0

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.r0))

    def grip(self, angle: Array) -> Array:
        """(..., 3) world position of the grip at angles (...)."""
        a, r0 = np.asarray(self.axis), np.asarray(self.r0)
        angle = jnp.asarray(angle)[..., None]
        return np.asarray(self.centre) + r0 * jnp.cos(angle) + np.cross(a, r0) * jnp.sin(angle)

    def grip_velocity(self, angle: Array) -> Array:
        """∂grip/∂φ (..., 3): the lever's Jacobian, also the map from a force at the grip to torque."""
        a, r0 = np.asarray(self.axis), np.asarray(self.r0)
        angle = jnp.asarray(angle)[..., None]
        return -r0 * jnp.sin(angle) + np.cross(a, r0) * jnp.cos(angle)


@dataclass(frozen=True)
class Grasp:
    """The hand closing on the lever's grip.

    Attributes
    ----------
    step : int
        The time step at which the operator closes the hand (−1: never).
    capture : float
        The grasp holds only if the hand is within this distance of the grip along each world
        axis (m); the seed's task needed "about 6.0 cm".
    stiffness, damping : float
        The closed hand as a spring (N/m) and damper (N s/m) between its endpoint and the grip.
    closing : float
        The fingers take this long to close (s): the grip's spring and damper grow linearly from
        zero to full over it.
    """

    step: int
    capture: float = 0.06
    stiffness: float = 5e3
    damping: float = 50.0
    closing: float = 0.3


@dataclass(frozen=True)
class Environment:
    """What the slave's hand can touch: hard surfaces and, optionally, a lever to grasp."""

    surfaces: tuple[Surface, ...] = ()
    lever: Lever | None = None
    contact: Contact = field(default_factory=Contact)


# ---- from a model ---------------------------------------------------------------------------------------


def surfaces_from_model(
    model: Model,
    values: dict[str, float] | None = None,
    *,
    shapes: Sequence[str] | None = None,
    exclude: Sequence[str] = (),
    free_point: Sequence[float] = (0.0, 0.0, 1.0),
) -> tuple[Surface, ...]:
    """Hard surfaces from a model's shapes at given parameter values.

    Parameters
    ----------
    model : Model
    values : mapping, optional
        Parameter values (SI, by name); the rest nominal.
    shapes : sequence of str, optional
        Shape names (unique suffixes allowed); default: every shape.
    exclude : sequence of str
        Frames whose shapes (and their descendants') are left out — a lever that moves, say.
    free_point : (3,)
        A point in free space: flat shapes (``rectangle``, ``plane``) become half-spaces solid on
        the side away from it.

    Returns
    -------
    tuple
        :class:`Box`, :class:`Cylinder` (cylinders and tubes, solid), :class:`Sphere`,
        :class:`HalfSpace`; other kinds (cones, meshes) are left out.
    """
    scene = modeler(model, parameter_vector(model, values or {}))
    poses, dims = np.asarray(scene.shape_poses), np.asarray(scene.shape_dims)
    if shapes is None:
        chosen = list(range(len(model.shapes)))
    else:
        chosen = [model.shape_index(s) for s in shapes]
    skipped = {i for frame in exclude for i in model.shapes_of(frame)}
    free = np.asarray(free_point, dtype=float)
    out: list[Surface] = []
    for i in chosen:
        if i in skipped:
            continue
        shape = model.shapes[i]
        T, d = poses[i], dims[i]
        c, z = _v3(T[:3, 3]), _v3(T[:3, 2])
        name = model.short_name("shape", shape.name)
        if shape.kind == "box":
            rot = tuple(_v3(row) for row in T[:3, :3])
            out.append(Box(c, rot, _v3(d), name))
        elif shape.kind == "cylinder":
            out.append(Cylinder(c, z, float(d[0]), float(d[1]), name))
        elif shape.kind == "tube":
            out.append(Cylinder(c, z, float(d[0]), float(d[2]), name))
        elif shape.kind == "sphere":
            out.append(Sphere(c, float(d[0]), name))
        elif shape.kind in ("rectangle", "plane"):
            n = T[:3, 2] if float(T[:3, 2] @ (free - T[:3, 3])) >= 0 else -T[:3, 2]
            out.append(HalfSpace(c, _v3(n), name))
    return tuple(out)


def lever_from_model(
    model: Model,
    frame: str,
    angle: str,
    values: dict[str, float] | None = None,
    *,
    grip: Sequence[float] = (0.0, 0.0, 0.0),
    base: np.ndarray | None = None,
    physics: Mapping[str, float] | None = None,
) -> Lever:
    """A :class:`Lever` from a model's frame turned by a revolute joint.

    Parameters
    ----------
    model : Model
    frame : str
        The lever's frame (its joint turns it).
    angle : str
        The parameter of the joint's angle (``lever.angle``); its value in ``values`` is the
        lever's starting angle, and its φ is the same angle.
    values : mapping, optional
        Parameter values (the room's pose, the lever's angle), SI by name.
    grip : (3,)
        The grip point in the lever's frame (m), e.g. the knob's centre.
    base : (4, 4), optional
        The model's world in the caller's world.
    physics : mapping, optional
        :class:`Lever` fields: rest, stiffness, damping, inertia, lower, upper, stop_stiffness
        (rest defaults to the starting angle).
    """
    kin = Kinematics(model, frame, chain=[angle], values=values, what="frame", tool=grip, base=base)
    phi0 = float(kin.theta0[0])
    out = kin.forward(np.zeros(1))
    p0 = np.asarray(out.position)
    axis = np.asarray(out.jacobian)[3:, 0]
    if not np.isclose(np.linalg.norm(axis), 1.0, atol=1e-9):
        raise KinematicsError(f"'{angle}' does not turn '{frame}' by a revolute joint")
    hinge = np.asarray(Kinematics(model, frame, chain=[angle], values=values, what="frame", base=base).position([0.0]))
    centre = hinge + ((p0 - hinge) @ axis) * axis
    r0 = p0 - centre
    settings: dict[str, float] = {"rest": phi0, **(physics or {})}
    return Lever(
        centre=_v3(centre),
        axis=_v3(axis),
        r0=_v3(r0),
        angle=phi0,
        **settings,  # type: ignore[arg-type]
    )


# ---- the master's motion -----------------------------------------------------------------------------------


def min_jerk(start: Array, end: Array, s: Array) -> Array:
    """The minimum-jerk blend from ``start`` to ``end`` for s ∈ [0, 1] (Flash & Hogan): (..., d)."""
    s = np.clip(np.asarray(s, dtype=float), 0.0, 1.0)[..., None]
    blend = 10 * s**3 - 15 * s**4 + 6 * s**5
    return np.asarray(start, dtype=float) + (np.asarray(end, dtype=float) - np.asarray(start, dtype=float)) * blend


def follow_path(kin: Kinematics, path: Array, theta0: Array, *, damping: float = 1e-3) -> np.ndarray:
    """Joint values that make the target follow ``path``: resolved-rate control with J* (seed, eq. 7).

    θ_{k+1} = θ_k + J*(θ_k) (x_{k+1} − f(θ_k)): the error of each step is corrected in the next,
    so the path is followed to second order in its step length.

    Parameters
    ----------
    kin : Kinematics
        The arm.
    path : (T, 3)
        Positions of the target, one per time step (m).
    theta0 : (n,)
        Joint values at the first point (e.g. from :meth:`Kinematics.ik`).
    damping : float
        λ of the damped J* (keeps the motion finite near singularities).

    Returns
    -------
    (T, n) array
    """
    with float64():
        path = jnp.asarray(path, dtype=jnp.float64)
        theta0 = jnp.asarray(theta0, dtype=jnp.float64)
        if path.ndim != 2 or path.shape[1] != 3:
            raise KinematicsError(f"the path must be (T, 3) positions, got {tuple(path.shape)}")

        program = _cached(kin, "follow_path", lambda: _follower(kin))
        thetas = program(theta0, path[1:], jnp.float64(damping))
        return np.concatenate([np.asarray(theta0)[None], np.asarray(thetas)], axis=0)


def _follower(kin: Kinematics) -> Callable:
    def run(theta0: Array, xs: Array, damping: Array) -> Array:
        def step(theta: Array, x_next: Array) -> tuple[Array, Array]:
            out = kin.forward_single(theta)
            new = theta + pseudo_inverse(out.jacobian[:3], damping) @ (x_next - out.position)
            return new, new

        return jax.lax.scan(step, theta0, xs)[1]

    return jax.jit(run)


# ---- the simulation ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ControlRun:
    """One simulated run, every array with one row per time step.

    Attributes
    ----------
    t : (T,) s
    theta_master, theta_slave : (T, n)
        The master's joints and the slave's commanded joints θ_s = θ_m + J* e.
    x_master, x_slave : (T, 3)
        Endpoints f(θ_m) and f(θ_s) (m).
    e : (T, 3)
        x_s − x_m (m); zero under position control.
    force : (T, 3)
        External force on the hand (N): what the wrist's force sensor reads.
    contact_force : (T, 3)
        Its part from hard surfaces (the rest is the grasp).
    lever_angle : (T,)
        The lever's angle (rad); NaN without a lever.
    grip : (T, 3)
        The lever's grip point (m).
    grasped : (T,) bool
        Whether the hand holds the lever.
    impedance : bool
        Impedance control (else position control).
    grasp_step : int
        The step at which the hand closed (−1: never).
    """

    t: np.ndarray
    theta_master: np.ndarray
    theta_slave: np.ndarray
    x_master: np.ndarray
    x_slave: np.ndarray
    e: np.ndarray
    force: np.ndarray
    contact_force: np.ndarray
    lever_angle: np.ndarray
    grip: np.ndarray
    grasped: np.ndarray
    impedance: bool
    grasp_step: int

    @property
    def peak_force(self) -> float:
        """The largest |F| of the run (N)."""
        return float(np.max(np.linalg.norm(self.force, axis=1)))

    @property
    def held(self) -> bool:
        """Whether the grasp caught the lever."""
        return bool(self.grasped[-1])

    @property
    def grasp_error(self) -> np.ndarray:
        """(3,) hand minus grip at the moment the hand closed (m); NaN if it never closed."""
        if self.grasp_step < 0:
            return np.full(3, np.nan)
        return self.x_slave[self.grasp_step] - self.grip[self.grasp_step]


def simulate(
    kin: Kinematics,
    theta_master: Array,
    environment: Environment,
    *,
    dt: float = 1e-3,
    impedance: Impedance | None = None,
    grasp: Grasp | None = None,
    damping: float = 0.0,
) -> ControlRun:
    """Run the master–slave loop through a trajectory of the master's joints.

    Each step: the master's endpoint x_m = f(θ_m); the slave's command θ_s = θ_m + J*(θ_m) e
    (impedance control; θ_s = θ_m under position control); the slave's endpoint x_s = f(θ_s);
    the external force F on it (grasp spring and hard surfaces); then e and the lever advance
    by semi-implicit Euler: M ë + B ė + K e = F for the hand, I φ̈ = gᵀ(−F_grasp) − k(φ − φ_rest)
    − b φ̇ + (stops) for the lever (g = ∂grip/∂φ).

    Parameters
    ----------
    kin : Kinematics
        The slave arm (the real one: its true parameters).
    theta_master : (T, n)
        The master arm's joints at each step (from the operator, e.g. :func:`follow_path`).
    environment : Environment
        The real environment.
    dt : float
        Fixed time step (s).
    impedance : Impedance, optional
        The target impedance; None means position control (e = 0).
    grasp : Grasp, optional
        When the hand closes and how it holds; None: it never closes.
    damping : float
        λ of J* = Jᵀ(JJᵀ + λ²I)⁻¹ (0: the seed's Jᵀ(JJᵀ)⁻¹, which is not finite at a singular
        configuration of the master — give λ > 0, e.g. 1e-2, for a trajectory through or near one).

    Returns
    -------
    ControlRun

    Raises
    ------
    KinematicsError
        The master's trajectory is not finite; or, at some step, J* is not finite (the master's
        configuration is singular and ``damping`` is 0 or too small) or the simulated state is
        not finite (diverged): the message names the first such step, its time and the master's
        joints there.  A run never comes back with NaN joints and a force that reads 0 N.
    """
    theta_master = np.asarray(theta_master, dtype=float)
    if theta_master.ndim != 2 or theta_master.shape[1] != kin.n:
        raise KinematicsError(f"the master trajectory must be (T, {kin.n}), got {theta_master.shape}")
    if not dt > 0:
        raise KinematicsError(f"the time step must be positive, got {dt}")
    if not (math.isfinite(damping) and damping >= 0):
        raise KinematicsError(f"the damping λ of J* must be finite and ≥ 0, got {damping}")
    unfinite = ~np.all(np.isfinite(theta_master), axis=1)
    if unfinite.any():
        k = int(np.argmax(unfinite))
        raise KinematicsError(
            f"the master trajectory is not finite at step {k} (t = {fmt(k * dt)} s): "
            + _joints_text(kin, theta_master[k])
        )
    T = theta_master.shape[0]
    grasp = grasp or Grasp(step=-1)
    lever = environment.lever
    use_impedance = impedance is not None
    M, B, K = (impedance or Impedance()).matrices()
    grasp_step = int(grasp.step) if lever is not None else -1
    settings = {
        "Minv": np.linalg.inv(M),
        "B": B,
        "K": K,
        "dt": float(dt),
        "damping": float(damping),
        "grasp_step": grasp_step,
        "capture": float(grasp.capture),
        "grip_k": float(grasp.stiffness),
        "grip_c": float(grasp.damping),
        "closing": float(grasp.closing),
    }
    program = _cached(
        kin, ("simulate", environment, use_impedance), lambda: _simulation(kin, environment, use_impedance)
    )
    with float64():
        phi0 = lever.angle if lever is not None else 0.0
        x0 = kin.forward_single(jnp.asarray(theta_master[0])).position
        state0 = (jnp.zeros(3), jnp.zeros(3), jnp.float64(phi0), jnp.float64(0.0), jnp.float64(-1.0), x0)
        rec = program(state0, jnp.asarray(theta_master), jax.tree_util.tree_map(jnp.asarray, settings))
        theta_s, x_m, x_s, e, F, f_contact, g, held, phi, j_finite = (np.asarray(r) for r in rec)
    state = (theta_s, x_s, e, F, phi if lever is not None else None)
    _check_finite(kin, theta_master, dt, float(damping), j_finite, state)
    # The lever's angle recorded is the one after the step; shift so row k is the angle at step k.
    angle = np.concatenate([[phi0], phi[:-1]]) if lever is not None else np.full(T, np.nan)
    return ControlRun(
        t=np.arange(T) * dt,
        theta_master=theta_master,
        theta_slave=theta_s,
        x_master=x_m,
        x_slave=x_s,
        e=e if use_impedance else np.zeros_like(x_s),
        force=F,
        contact_force=f_contact,
        lever_angle=angle,
        grip=g,
        grasped=held.astype(bool),
        impedance=use_impedance,
        grasp_step=grasp_step,
    )


def _joints_text(kin: Kinematics, theta: np.ndarray) -> str:
    """The master's joints as 'name value unit, ...' (angles in degrees)."""
    parts = []
    for k, name in enumerate(kin.joints):
        unit = kin._unit(k)
        value = float(theta[k])
        if not math.isfinite(value):
            parts.append(f"{name} {value}")
            continue
        parts.append(f"{name} {fmt(kin._show(k, value), 6)}{(' ' + unit) if unit else ''}")
    return "θ_m = " + ", ".join(parts)


def _check_finite(
    kin: Kinematics,
    theta_master: np.ndarray,
    dt: float,
    damping: float,
    j_finite: np.ndarray,
    records: tuple[np.ndarray | None, ...],
) -> None:
    """Refuse a run whose J* or state is not finite at some step, naming the first such step.

    A NaN hand touches nothing, so the force would read 0 N although the master pushes into a
    wall: a wrong run that looks right.  Checked on the recorded arrays after the compiled loop."""
    state_finite = np.ones(len(j_finite), dtype=bool)
    for r in records:
        if r is not None:
            state_finite &= np.all(np.isfinite(r.reshape(len(r), -1)), axis=1)
    bad = ~(j_finite.astype(bool) & state_finite)
    if not bad.any():
        return
    k = int(np.argmax(bad))
    where = f"step {k} (t = {fmt(k * dt)} s), {_joints_text(kin, theta_master[k])}"
    if not j_finite[k]:
        gram = "JᵀJ" if kin.n < 3 else "JJᵀ"
        formula = "(JᵀJ)⁻¹Jᵀ" if kin.n < 3 else "Jᵀ(JJᵀ)⁻¹"
        if damping > 0:
            formula = ("(JᵀJ + λ²I)⁻¹Jᵀ" if kin.n < 3 else "Jᵀ(JJᵀ + λ²I)⁻¹") + f" with λ = {fmt(damping)}"
        raise KinematicsError(
            f"impedance control: J* = {formula} is not finite at {where}: the master's configuration is "
            f"singular ({gram} cannot be inverted), so θ_s = θ_m + J* e, the slave's hand and the force on "
            "it are undefined from there on",
            hint=(
                "give simulate a damping λ > 0 such as damping=1e-2, which keeps J* = Jᵀ(JJᵀ + λ²I)⁻¹ finite"
                if damping == 0
                else f"give a larger damping than λ = {fmt(damping)}, such as damping=1e-2"
            )
            + ", or start the master away from the singularity",
        )
    raise KinematicsError(
        f"the simulation is not finite from {where}: the slave's joints, hand, e, force or the lever's angle "
        "overflowed",
        hint="a time step too large for the stiffnesses makes the explicit integration diverge: try a smaller dt",
    )


_PROGRAMS: weakref.WeakKeyDictionary[Kinematics, dict[Any, Callable]] = weakref.WeakKeyDictionary()


def _cached(kin: Kinematics, key: Any, build: Callable[[], Callable]) -> Callable:
    """A compiled program per arm and key (environment, control mode); rebuilt when the key
    cannot be hashed (an environment given with lists)."""
    try:
        hash(key)
    except TypeError:
        return build()
    table = _PROGRAMS.setdefault(kin, {})
    if key not in table:
        table[key] = build()
    return table[key]


def _simulation(kin: Kinematics, environment: Environment, use_impedance: bool) -> Callable:
    """The compiled loop: (state0, θ_m (T, n), settings) → records, one row per step."""
    lever = environment.lever
    contact = environment.contact
    surfaces = environment.surfaces

    def surface_force(x: Array, v: Array) -> Array:
        total = jnp.zeros(3)
        for surface in surfaces:
            d, n = jax.value_and_grad(surface.distance)(x)
            n = n / jnp.sqrt(jnp.sum(n * n) + 1e-300)
            depth = contact.hand_radius - d
            push = contact.stiffness * depth - contact.damping * (v @ n)
            total = total + jnp.where(depth > 0, jnp.maximum(push, 0.0), 0.0) * n
        return total

    def run(state0: tuple, theta_master: Array, c: dict[str, Array]) -> tuple:
        dt = c["dt"]

        def step(state: tuple, inputs: tuple) -> tuple[tuple, tuple]:
            e, de, phi, dphi, closed_at, x_prev = state
            theta_m, k = inputs
            out_m = kin.forward_single(theta_m)
            if use_impedance:
                J_star = pseudo_inverse(out_m.jacobian[:3], c["damping"])
                j_finite = jnp.all(jnp.isfinite(J_star))
                theta_s = theta_m + J_star @ e
            else:
                j_finite = jnp.asarray(True)
                theta_s = theta_m
            x_s = kin.forward_single(theta_s).position
            v_s = jnp.where(k > 0, (x_s - x_prev) / dt, 0.0)
            if lever is not None:
                g, dg = lever.grip(phi), lever.grip_velocity(phi)
                caught = (k == c["grasp_step"]) & jnp.all(jnp.abs(x_s - g) <= c["capture"])
                closed_at = jnp.where((closed_at < 0) & caught, k * dt, closed_at)
                held = closed_at >= 0
                # The hand closes over `closing` seconds: its grip stiffens from 0 to full.
                ramp = jnp.clip((k * dt - closed_at) / jnp.maximum(c["closing"], dt), 0.0, 1.0)
                pull = -ramp * (c["grip_k"] * (x_s - g) + c["grip_c"] * (v_s - dg * dphi))
                f_grasp = jnp.where(held, pull, 0.0)
            else:
                g, dg, held = jnp.full(3, jnp.nan), jnp.zeros(3), jnp.asarray(False)
                f_grasp = jnp.zeros(3)
            f_contact = surface_force(x_s, v_s)
            F = f_grasp + f_contact
            e_now = e
            if use_impedance:
                dde = c["Minv"] @ (F - c["B"] @ de - c["K"] @ e)
                de = de + dt * dde
                e = e + dt * de
            if lever is not None:
                torque = dg @ (-f_grasp) - lever.stiffness * (phi - lever.rest) - lever.damping * dphi
                torque = torque - lever.stop_stiffness * (
                    jnp.maximum(phi - lever.upper, 0.0) + jnp.minimum(phi - lever.lower, 0.0)
                )
                dphi = dphi + dt * torque / lever.inertia
                phi = phi + dt * dphi
            record = (theta_s, out_m.position, x_s, e_now, F, f_contact, g, held, phi, j_finite)
            return (e, de, phi, dphi, closed_at, x_s), record

        steps = jnp.arange(theta_master.shape[0])
        return jax.lax.scan(step, state0, (theta_master, steps))[1]

    return jax.jit(run)
