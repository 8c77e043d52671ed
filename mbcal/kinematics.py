"""Kinematics from the model: f(θ), J(θ), J*(θ) and inverse kinematics (seed, eqs. 5–7).

The seed drives its slave arm through the kinematics model: the endpoint x = f(θ) of the joint
angles θ, its Jacobian J(θ) = ∂f/∂θ and J*(θ) = Jᵀ(JJᵀ)⁻¹ (eq. 7).  Here these come from any
model (.mdl or URDF) at given parameter values — nominal or calibrated — for a *chain*: the
parameters that act as joint variables, every other parameter held at its value.

>>> import mbcal
>>> from mbcal.kinematics import Kinematics
>>> arm = Kinematics(mbcal.load_model("models/arm7.mdl"), "hand.tip", chain="arm.q*")  # doctest: +SKIP
>>> arm.position([0.0, -0.5, 0.0, -1.2, 0.0, 0.3, 0.0])                                # doctest: +SKIP

Two evaluators compute the same numbers.  When every chain variable is the reading of one joint
on the path from the world to the target and enters nowhere else (the usual serial arm), the
constant parts of the chain are folded with numpy once and J comes from the joint axes
(column k = [aₖ × (p − oₖ); aₖ] for a revolute joint, [aₖ; 0] for a prismatic one), computed as
arrays with the batch along the last axis — a few fused kernels for any number of
configurations.  Otherwise (a parameter that drives two joints, a URDF ``<mimic>``, a variable
inside an ``at`` expression) the frames are evaluated as the modeler does and J comes from
``jax.jacfwd``.  Both are checked against the modeler, yourdfpy and finite differences.

Everything runs in float64 whatever the caller did before: inputs are converted to float64 and
every computation runs inside ``jax.enable_x64(True)`` (a float32 array made before mbcal was
imported, or a later ``jax_enable_x64 = False``, does not make J float32).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, NamedTuple

import numpy as np

from mbcal._jax import float64, jax, jnp
from mbcal.errors import KinematicsError, ParameterError, UnknownNameError, UnreachableError, suggest
from mbcal.geometry.transforms import rpy_from_matrix
from mbcal.language import ir, soa
from mbcal.language import soa_math as sm
from mbcal.language.graph import TRANSFORM, ParamRef, depends_on
from mbcal.language.model import Model
from mbcal.modeling import parameter_vector
from mbcal.solver import SolverConfig, Status, check_size, least_squares
from mbcal.text import fmt, table
from mbcal.units import ANGLE, LENGTH, within

Array = Any

__all__ = [
    "Kinematics",
    "Forward",
    "IKResult",
    "pseudo_inverse",
    "manipulability",
    "select_part",
    "to_local",
    "ROW_NAMES",
]

Part = Literal["full", "position", "orientation"]
FrameName = Literal["world", "local"]

ROW_NAMES = ("vx", "vy", "vz", "wx", "wy", "wz")
"""The rows of a full Jacobian: linear velocity of the target (m per unit of θ), then angular."""

_PARTS = {"full": slice(0, 6), "position": slice(0, 3), "orientation": slice(3, 6)}

SINGULAR = 1e-13
"""JJᵀ + λ²I counts as singular when its eigenvalues' ratio falls below this (cond(J) > ~3e6)."""


class Forward(NamedTuple):
    """f(θ) and J(θ) of one or many configurations (leading axes ``...`` as the input's).

    Attributes
    ----------
    position : (..., 3) array
        World position of the target (m).
    rotation : (..., 3, 3) array
        World orientation of the target's frame (its columns are the frame's axes).
    jacobian : (..., 6, n) array
        ∂(position, orientation)/∂θ in world axes: rows vx, vy, vz (linear velocity of the target
        point) then wx, wy, wz (angular velocity), one column per chain variable.
    """

    position: Array
    rotation: Array
    jacobian: Array


# ---- pure functions of J (usable inside jit, vmap, scan) -------------------------------------------


def select_part(J: Array, part: Part = "full") -> Array:
    """Rows of a full (..., 6, n) Jacobian: ``full`` (6), ``position`` (3) or ``orientation`` (3)."""
    if part not in _PARTS:
        raise KinematicsError(f"unknown Jacobian part '{part}' (full, position or orientation)")
    return J[..., _PARTS[part], :]


def to_local(J: Array, rotation: Array) -> Array:
    """A full (..., 6, n) world Jacobian expressed in the target's own axes: blockdiag(Rᵀ, Rᵀ) J."""
    Rt = jnp.swapaxes(rotation, -1, -2)
    return jnp.concatenate([Rt @ J[..., :3, :], Rt @ J[..., 3:, :]], axis=-2)


def pseudo_inverse(J: Array, damping: float | Array = 0.0) -> Array:
    """J* = Jᵀ(JJᵀ + λ²I)⁻¹ (seed, eq. 7; λ = ``damping``, 0 gives the seed's J*), or
    (JᵀJ + λ²I)⁻¹Jᵀ for a chain with fewer joints than rows.

    Parameters
    ----------
    J : (..., m, n) array
        Jacobians.  m ≤ n: the right inverse, J J* = I where JJᵀ is invertible.  m > n (fewer
        joints than rows: JJᵀ has rank n < m and is never invertible): the left inverse, the
        least-squares joint step, J* J = I where JᵀJ is invertible.  Both are the Moore–Penrose
        inverse of a J of full rank, and the same matrix for λ > 0.
    damping : float
        λ of the damped least-squares inverse (Wampler, Nakamura): finite at singular
        configurations, at the price of ‖J J* − I‖ ≈ λ²/σ² along directions of small σ.

    Returns
    -------
    (..., n, m) array
        NaN where JJᵀ + λ²I (JᵀJ + λ²I for m > n) is singular to working precision (eigenvalue
        ratio below :data:`SINGULAR`; only possible for λ = 0 or a tiny λ).
    """
    m, n = J.shape[-2], J.shape[-1]
    Jt = jnp.swapaxes(J, -1, -2)
    if m > n:
        A = Jt @ J + (damping * damping) * jnp.eye(n, dtype=J.dtype)
        out = jnp.linalg.solve(A, Jt)
    else:
        A = J @ Jt + (damping * damping) * jnp.eye(m, dtype=J.dtype)
        # (A⁻¹ J)ᵀ = Jᵀ A⁻¹ since A is symmetric.
        out = jnp.swapaxes(jnp.linalg.solve(A, J), -1, -2)
    # Singular to working precision (σ_min/σ_max of J below ~3e-7): NaN, not a huge finite number
    # that round-off happened to leave invertible.
    w = jnp.linalg.eigvalsh(A)
    singular = w[..., 0] <= SINGULAR * jnp.maximum(w[..., -1], jnp.finfo(J.dtype).tiny)
    return jnp.where(singular[..., None, None], jnp.nan, out)


def manipulability(J: Array) -> Array:
    """Yoshikawa's manipulability √det(JJᵀ) of (..., m, n) Jacobians, √det(JᵀJ) when m > n (fewer
    joints than rows, where det(JJᵀ) is always 0): the product of J's singular values, 0 at a
    singularity."""
    Jt = jnp.swapaxes(J, -1, -2)
    A = Jt @ J if J.shape[-2] > J.shape[-1] else J @ Jt
    sign, logdet = jnp.linalg.slogdet(A)
    return jnp.where(sign > 0, jnp.exp(0.5 * logdet), 0.0)


# ---- the chain --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Segment:
    """One chain joint of the fast evaluator: constant pose before it, its axis, offset and column."""

    before: np.ndarray  # (4, 4) from the previous chain joint's frame (after its motion) to this joint's frame
    axis: np.ndarray  # (3,) unit axis in the joint's frame
    offset: float  # added to the variable (the encoder's zero point)
    prismatic: bool
    column: int  # position of the variable in the chain


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def _motion(kind: str, axis: np.ndarray, value: float) -> np.ndarray:
    """The 4×4 motion of a joint at a known value (numpy), as the modeler computes it."""
    T = np.eye(4)
    if kind == "prismatic":
        T[:3, 3] = axis * value
    else:
        T[:3, :3] = np.array(sm.rodrigues(tuple(float(a) for a in axis), float(value)), dtype=float)
    return T


def _rotation_batch(axis: np.ndarray, s: Array, c: Array) -> Array:
    """(3, 3, ...) rotations about a constant unit ``axis`` by angles of sine ``s``, cosine ``c``."""
    zero, one = jnp.zeros_like(s), jnp.ones_like(s)
    principal = np.flatnonzero(axis)
    if len(principal) == 1 and abs(abs(axis[principal[0]]) - 1.0) < 1e-15:
        i = int(principal[0])
        s = s if axis[i] > 0 else -s
        rows = {
            0: ((one, zero, zero), (zero, c, -s), (zero, s, c)),
            1: ((c, zero, s), (zero, one, zero), (-s, zero, c)),
            2: ((c, -s, zero), (s, c, zero), (zero, zero, one)),
        }[i]
        return jnp.stack([jnp.stack(r) for r in rows])
    K = _skew(axis)
    K2 = K @ K
    shape = (3, 3) + (1,) * jnp.ndim(s)
    return np.eye(3).reshape(shape) + K.reshape(shape) * s + K2.reshape(shape) * (1.0 - c)


def _mm(A: Array, B: Array) -> Array:
    """Products of 3×3 matrices with the batch on the last axes (either side may have none)."""
    return jnp.einsum("ij...,jk...->ik...", A, B)


def _mv(A: Array, v: Array) -> Array:
    return jnp.einsum("ij...,j...->i...", A, v)


class Kinematics:
    """f(θ), J(θ), J*(θ) and inverse kinematics of one point or frame of a model.

    Parameters
    ----------
    model : Model
        Any checked model (.mdl or URDF).
    target : str
        A point (``hand.tip``) or a frame (``link7``); full names or unique dotted suffixes.
    chain : str or sequence of str, optional
        The joint variables θ, in order: parameter names, globs (``arm.q*``, expanded in the
        model's order), names of frames with a joint (their reading) or of joints ``J`` whose
        reading is ``J.q`` (a URDF's joint names).  A string may list several, separated by
        commas.  Default: the readings of every joint between the world
        and the target, from the root outwards.
    values : mapping or (n_params,) array, optional
        The values of all other parameters (SI units, by name; the rest nominal) — for example a
        calibration's ``result.values``.  Default: the nominal values.
    what : {"point", "frame"}, optional
        Say which kind ``target`` is when a point and a frame share a name (default: a point
        first, then a frame).
    tool : (3,) sequence, optional
        A tool point fixed in the target's frame (m), added to the target's position (the
        target's frame origin, or the point).
    base : (4, 4) array, optional
        The pose of the model's world in the caller's world (a robot's mobile base); default
        the identity.

    Notes
    -----
    The other parameters are folded in as constants when the programs are compiled, so a
    ``Kinematics`` is made for one set of values: build a new one for other values.  Joint
    limits (``lower``/``upper`` of the model's joints, the readings they apply to) bound the
    inverse kinematics: those of the chain's variables, and those of the joints the chain
    drives through an expression (:attr:`driven`: a URDF ``<mimic>``, ``0.5 * q``).
    """

    def __init__(
        self,
        model: Model,
        target: str,
        chain: str | Sequence[str] | None = None,
        values: Mapping[str, float] | Array | None = None,
        *,
        what: Literal["point", "frame"] | None = None,
        tool: Sequence[float] | None = None,
        base: Array | None = None,
    ) -> None:
        self.model = model
        self.what, index = _resolve_target(model, target, what)
        self.point = index if self.what == "point" else None
        self.frame = model.points[index].frame if self.what == "point" else index
        self.target = model.points[index].name if self.what == "point" else model.frames[index].name
        self.label = model.short_name(self.what, self.target)  # for reports: 'hand.tip'
        if values is None:
            X = model.nominal
        elif isinstance(values, Mapping):
            X = parameter_vector(model, values)
        else:
            X = np.asarray(values, dtype=float)
            if X.shape != (len(model.params),):
                raise ParameterError(f"values must have one entry per parameter ({len(model.params)}), got {X.shape}")
            if not np.all(np.isfinite(X)):
                bad = model.params[int(np.argmin(np.isfinite(X)))].name
                raise ParameterError(f"values: {bad} is not a finite number ({X[model.param_index(bad)]})")
        self.values = np.array(X, dtype=float)
        self.tool = np.zeros(3) if tool is None else np.asarray(tool, dtype=float).reshape(3)
        self.base = np.eye(4) if base is None else np.asarray(base, dtype=float).reshape(4, 4)
        self.path = _ancestry(model, self.frame)
        self.joints = _resolve_chain(model, chain, self.path, self.point, self.label)
        self.indices = np.array([model.param_index(n) for n in self.joints], dtype=int)
        self.n = len(self.joints)
        self.lower, self.upper, self.kinds = _limits(model, self.joints, self.path)
        self._driven = _driven_joints(model, self.indices)
        self.driven = [d.name for d in self._driven]
        # the variables the target's pose has period 2π in (IK brings them into (−π, π]): not one
        # that a limited driven joint follows either, whose limits hold for θ, not for θ − 2π
        bounded = {i for d in self._driven if d.limited for i in depends_on(d.q)}
        self.periodic = (
            _periodic(model, self.indices, self.path, self.point)
            & ~(np.isfinite(self.lower) | np.isfinite(self.upper))
            & np.array([int(i) not in bounded for i in self.indices], dtype=bool)
        )
        self._segments: list[_Segment] | None = None
        self._tail: np.ndarray | None = None
        self._local: np.ndarray | None = None
        if self._is_serial():
            self._segments, self._tail, self._local = self._fold()
        self._jit: dict[str, Callable] = {}
        self._ik_funs: dict[tuple[bool, float], Callable] = {}

    # ---- description ---------------------------------------------------------------------------

    @property
    def fast(self) -> bool:
        """Whether J comes from the joint axes (a serial chain) rather than from ``jax.jacfwd``."""
        return self._segments is not None

    @property
    def theta0(self) -> np.ndarray:
        """(n,) the chain variables' values in ``values`` (nominal unless given)."""
        return self.values[self.indices].copy()

    def driven_values(self, theta: Array) -> np.ndarray:
        """(..., d) the readings of the joints the chain drives through an expression (a URDF
        ``<mimic>``, ``joint revolute(z, 0.5 * q)``), in the order of :attr:`driven` (SI units)."""
        if not self._driven:
            return np.zeros(np.shape(theta)[:-1] + (0,))
        return np.asarray(self._call("driven", lambda th: jax.vmap(self._driven_single)(th), theta))

    def _driven_single(self, theta: Array) -> Array:
        X: list[Any] = [float(v) for v in self.values]
        for k, i in enumerate(self.indices):
            X[int(i)] = theta[k]
        memo: dict[int, Any] = {}
        return jnp.stack([jnp.asarray(soa.evaluate(d.q, X, memo), dtype=jnp.float64) for d in self._driven])

    def _outside_driven(self, values: np.ndarray, slack: Callable[[str], float] | None = None) -> list[str]:
        """Names of the driven joints outside their limits (``slack(kind)`` allowed;
        default a few ulps, :func:`mbcal.units.within`)."""
        out = []
        for d, v in zip(self._driven, values):
            extra = 0.0 if slack is None else slack(d.kind)
            if not (within(float(v), d.lower, d.upper) or d.lower - extra <= v <= d.upper + extra):
                out.append(d.name)
        return out

    def __repr__(self) -> str:
        joints = ", ".join(self.joints)
        return f"Kinematics({self.model.path!r}, {self.label!r}, chain=[{joints}])"

    # ---- the evaluators --------------------------------------------------------------------------

    def _is_serial(self) -> bool:
        """Every chain variable is exactly one joint's reading on the path and appears nowhere else."""
        uses: dict[int, int] = {}
        direct: set[int] = set()
        for node in self._nodes():
            for i in depends_on(node):
                uses[i] = uses.get(i, 0) + 1
        for f in self.path:
            joint = self.model.frames[f].joint
            if joint is not None and isinstance(joint.q, ParamRef):
                direct.add(joint.q.index)
        return all(i in direct and uses.get(i, 0) == 1 for i in self.indices)

    def _nodes(self) -> list[ir.Node]:
        return _path_nodes(self.model, self.path, self.point)

    def _const(self, node: ir.Node) -> np.ndarray:
        return np.asarray(ir.evaluate(node, self.values, {}, np), dtype=float)

    def _fold(self) -> tuple[list[_Segment], np.ndarray, np.ndarray]:
        """The serial chain as constant poses between the chain's joints (numpy, once)."""
        column = {int(i): k for k, i in enumerate(self.indices)}
        segments: list[_Segment] = []
        C = self.base.copy()
        for f in self.path:
            frame = self.model.frames[f]
            if frame.pose is not None:
                C = C @ self._const(frame.pose)
            joint = frame.joint
            if joint is None:
                continue
            axis = self._const(joint.axis)
            offset = float(self._const(joint.offset)) if joint.offset is not None else 0.0
            if isinstance(joint.q, ParamRef) and joint.q.index in column:
                segments.append(_Segment(C, axis, offset, joint.kind == "prismatic", column[joint.q.index]))
                C = np.eye(4)
            else:
                C = C @ _motion(joint.kind, axis, float(self._const(joint.q)) + offset)
        local = self.tool.copy()
        if self.point is not None:
            local = local + self._const(self.model.points[self.point].position)
        return segments, C, local

    def _serial(self, theta: Array, with_jacobian: bool = True) -> tuple[Array, Array, Array | None]:
        """The fast evaluator: θ (n, ...) with the batch on the last axes → p (3, ...),
        R (3, 3, ...), J (6, n, ...)."""
        assert self._segments is not None and self._tail is not None and self._local is not None
        R: Array = None
        t: Array = None
        columns: list[Array] = [None] * self.n
        origins = []
        for seg in self._segments:
            if R is None:
                extra = (1,) * (jnp.ndim(theta) - 1)  # the batch axes, broadcast
                R = jnp.reshape(jnp.asarray(seg.before[:3, :3]), (3, 3) + extra)
                t = jnp.reshape(jnp.asarray(seg.before[:3, 3]), (3,) + extra)
            else:
                t = t + _mv(R, seg.before[:3, 3])
                R = _mm(R, seg.before[:3, :3])
            q = theta[seg.column] + seg.offset
            a = _mv(R, seg.axis)  # the joint's axis in the world (unchanged by its own rotation)
            origins.append((seg, a, t))
            if seg.prismatic:
                t = t + a * q
            else:
                R = _mm(R, _rotation_batch(seg.axis, jnp.sin(q), jnp.cos(q)))
        t = t + _mv(R, self._tail[:3, 3])
        R = _mm(R, self._tail[:3, :3])
        p = t + _mv(R, self._local)
        if not with_jacobian:
            return p, R, None
        for seg, a, o in origins:
            a = jnp.broadcast_to(a, p.shape)
            if seg.prismatic:
                columns[seg.column] = jnp.concatenate([a, jnp.zeros_like(a)])
            else:
                d = p - o
                v = jnp.stack([a[1] * d[2] - a[2] * d[1], a[2] * d[0] - a[0] * d[2], a[0] * d[1] - a[1] * d[0]])
                columns[seg.column] = jnp.concatenate([v, a])
        return p, R, jnp.stack(columns, axis=1)

    def _pose_general(self, theta: Array) -> tuple[Array, Array]:
        """p (3,), R (3, 3) of one configuration, frames evaluated as the modeler does."""
        X: list[Any] = [float(v) for v in self.values]
        for k, i in enumerate(self.indices):
            X[int(i)] = theta[k]
        memo: dict[int, Any] = {}

        def ev(node: ir.Node) -> Any:
            return soa.evaluate(node, X, memo)

        T = sm.from_constant(self.base, TRANSFORM)
        for f in self.path:
            frame = self.model.frames[f]
            if frame.pose is not None:
                T = sm.compose(T, ev(frame.pose))
            joint = frame.joint
            if joint is not None:
                q = ev(joint.q)
                if joint.offset is not None:
                    q = sm.add(q, ev(joint.offset))
                axis = ev(joint.axis)
                if joint.kind == "prismatic":
                    T = sm.compose(T, (sm.I3, tuple(sm.mul(a, q) for a in axis)))
                else:
                    T = sm.compose(T, (sm.rodrigues(axis, q), sm.ZERO3))
        local: Any = tuple(float(v) for v in self.tool)
        if self.point is not None:
            local = tuple(sm.add(a, b) for a, b in zip(ev(self.model.points[self.point].position), local))
        p = sm.stack_scalars(sm.apply_point(T, local))
        R = jnp.reshape(sm.stack_scalars([T[0][i][j] for i in range(3) for j in range(3)]), (3, 3))
        return p, R

    def _general(self, theta: Array) -> tuple[Array, Array, Array]:
        p, R = self._pose_general(theta)
        dp, dR = jax.jacfwd(self._pose_general)(theta)  # (3, n), (3, 3, n)
        W = jnp.einsum("ijk,lj->ilk", dR, R)  # dR Rᵀ: skew-symmetric, one per variable
        omega = jnp.stack([W[2, 1], W[0, 2], W[1, 0]])
        return p, R, jnp.concatenate([dp, omega])

    def forward_single(self, theta: Array) -> Forward:
        """f and J of one configuration θ (n,): a pure JAX function to use inside ``jit``,
        ``vmap``, ``grad`` or ``lax.scan`` (no conversion, no float64 switch: the caller's
        program decides).

        Returns
        -------
        Forward
            position (3,), rotation (3, 3), jacobian (6, n), world axes.
        """
        if jnp.shape(theta) != (self.n,):  # known while tracing too
            raise KinematicsError(f"θ must hold one value per chain variable ({self.n}), got shape {jnp.shape(theta)}")
        if self.fast:
            p, R, J = self._serial(theta)
            assert J is not None
            return Forward(p, R, J)
        return Forward(*self._general(theta))

    def _forward_batch(self, theta: Array) -> Forward:
        """(B, n) → Forward with a leading batch axis."""
        if self.fast:
            p, R, J = self._serial(theta.T)
            assert J is not None
            return Forward(p.T, jnp.moveaxis(R, -1, 0), jnp.moveaxis(J, -1, 0))
        return Forward(*jax.vmap(self._general)(theta))

    def _pose_single(self, theta: Array) -> tuple[Array, Array]:
        """p (3,), R (3, 3) without J (what inverse kinematics differentiates)."""
        if self.fast:
            p, R, _ = self._serial(theta, with_jacobian=False)
            return p, R
        return self._pose_general(theta)

    # ---- the public, compiled entry points -------------------------------------------------------------

    def _theta(self, theta: Array) -> Array:
        """θ as float64 of shape (..., n), checked (inside :func:`float64`)."""
        arr: Any
        if isinstance(theta, jax.Array):
            arr = theta if theta.dtype == jnp.float64 else theta.astype(jnp.float64)
        else:
            try:
                arr = np.asarray(theta, dtype=np.float64)
            except (TypeError, ValueError) as err:
                raise KinematicsError(f"joint values must be numbers: {err}") from None
        if arr.ndim == 0 or arr.shape[-1] != self.n:
            raise KinematicsError(
                f"the joint values have shape {tuple(arr.shape)}, but the chain has {self.n} variables "
                f"({', '.join(self.joints)}): give (..., {self.n})"
            )
        return arr

    def _call(self, name: str, batch: Callable, theta: Array, static: tuple = (), dynamic: tuple = ()) -> Any:
        """``batch((B, n), *static, *dynamic)`` compiled, on θ of any leading shape (the reshapes
        are part of the program: one dispatch per call)."""
        if name not in self._jit:
            n = self.n

            def run(th: Array, *args: Any) -> Any:
                lead = th.shape[:-1]
                out = batch(th.reshape((-1, n)), *args)
                return jax.tree_util.tree_map(lambda v: v.reshape(lead + v.shape[1:]), out)

            self._jit[name] = jax.jit(run, static_argnums=tuple(range(1, 1 + len(static))))
        with float64():
            return self._jit[name](self._theta(theta), *static, *dynamic)

    def forward(self, theta: Array) -> Forward:
        """f(θ) and J(θ) (world axes, full 6 × n) of one or many configurations.

        Parameters
        ----------
        theta : (..., n) array_like
            Joint values in SI units (rad, m), in the order of ``joints``.

        Returns
        -------
        Forward
            position (..., 3), rotation (..., 3, 3), jacobian (..., 6, n), float64.
        """
        return Forward(*self._call("forward", self._forward_batch, theta))

    def _poses_batch(self, theta: Array) -> Array:
        p, R = jax.vmap(self._pose_single)(theta)
        top = jnp.concatenate([R, p[:, :, None]], axis=2)
        bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0]), (theta.shape[0], 1, 4))
        return jnp.concatenate([top, bottom], axis=1)

    def pose(self, theta: Array) -> Array:
        """(..., 4, 4) world pose of the target: its frame's axes and the target's position."""
        return self._call("pose", self._poses_batch, theta)

    def position(self, theta: Array) -> Array:
        """(..., 3) world position of the target: x = f(θ) (seed, eq. 5)."""
        return self._call("position", lambda th: jax.vmap(lambda q: self._pose_single(q)[0])(th), theta)

    def jacobian(self, theta: Array, *, frame: FrameName = "world", part: Part = "full") -> Array:
        """J(θ) = ∂f/∂θ (seed, eq. 7).

        Parameters
        ----------
        theta : (..., n) array_like
        frame : {"world", "local"}
            Axes of the rows: the world's, or the target frame's own.
        part : {"full", "position", "orientation"}
            All six rows (vx, vy, vz, wx, wy, wz), or three of them.

        Returns
        -------
        (..., m, n) array
            m = 6 or 3.
        """
        _check_options(frame, part)
        return self._call("jacobian", self._jacobian_batch, theta, static=(frame, part))

    def _jacobian_batch(self, theta: Array, frame: str, part: Part) -> Array:
        out = self._forward_batch(theta)
        J = to_local(out.jacobian, out.rotation) if frame == "local" else out.jacobian
        return select_part(J, part)

    def pseudo_inverse(
        self, theta: Array, *, frame: FrameName = "world", part: Part = "full", damping: float = 0.0
    ) -> Array:
        """J*(θ) = Jᵀ(JJᵀ + λ²I)⁻¹ (seed, eq. 7 with λ = ``damping`` = 0); (JᵀJ + λ²I)⁻¹Jᵀ when the
        chain has fewer joints than the part has rows (see :func:`pseudo_inverse`).

        Returns
        -------
        (..., n, m) array
            J J* = I (J* J = I for fewer joints than rows) away from singularities; not finite
            at one when λ = 0 (see :meth:`damped_pseudo_inverse`).
        """
        _check_options(frame, part)
        if not damping >= 0:
            raise KinematicsError(f"damping must be ≥ 0, got {damping}")

        def batch(th: Array, f: str, p: Part, lam: Array) -> Array:
            return pseudo_inverse(self._jacobian_batch(th, f, p), lam)

        return self._call("pinv", batch, theta, static=(frame, part), dynamic=(np.float64(damping),))

    def damped_pseudo_inverse(
        self, theta: Array, damping: float = 1e-2, *, frame: FrameName = "world", part: Part = "full"
    ) -> Array:
        """The damped least-squares J* (λ = ``damping``, in the units of J: m for a position row,
        1 for an angular one): finite everywhere, also at a singular configuration."""
        return self.pseudo_inverse(theta, frame=frame, part=part, damping=damping)

    def manipulability(self, theta: Array, *, part: Part = "full") -> Array:
        """(...,) Yoshikawa's √det(JJᵀ) (√det(JᵀJ) for fewer joints than rows): how far from a
        singularity (0 at one; frame-independent)."""
        _check_options("world", part)

        def batch(th: Array, p: Part) -> Array:
            return manipulability(self._jacobian_batch(th, "world", p))

        return self._call("manip", batch, theta, static=(part,))

    # ---- inverse kinematics ----------------------------------------------------------------------------

    def ik(
        self,
        target: Array,
        *,
        orientation: Array | None = None,
        initial: Array | None = None,
        restarts: int = 8,
        seed: int | None = 0,
        tolerance: float = 1e-6,
        angle_tolerance: float = 1e-6,
        orientation_weight: float = 1.0,
        config: SolverConfig | None = None,
    ) -> IKResult:
        """Joint values that put the target at ``target`` (and, if given, in ``orientation``).

        Marquardt's method (:func:`mbcal.solver.least_squares`) from ``restarts`` starts per
        target — the initial values, then uniform draws within the joint limits (or the
        parameter's search range, or ±180° for an angle, ±1 m for a length) — all targets and
        restarts in one compiled, vmapped call.  A chain variable's joint limits hold exactly: a
        limited variable is θ = c + h·sin(u) with c ± h its limits.  The joints the chain drives
        through an expression (:attr:`driven`, a ``<mimic>``) are kept within theirs by residual
        rows that are 0 inside them: a target is reached only with each of them within its
        limits (to ``angle_tolerance`` rad or ``tolerance`` m).

        Parameters
        ----------
        target : (3,) or (B, 3) array_like
            Target positions in the world (m).
        orientation : (3, 3) or (B, 3, 3) array_like, optional
            Target rotations; residual rows w/√2·(R − R_target), w = ``orientation_weight``
            (m per rad), so that an angle φ counts as ≈ w·φ metres.
        initial : (n,) or (B, n) array_like, optional
            The first start; default: the chain's values in ``values``, brought within limits.
        restarts : int
            Starts per target (≥ 1).
        seed : int, optional
            Seed of the random starts.
        tolerance, angle_tolerance : float
            A target counts as reached when the position error is ≤ ``tolerance`` (m) and the
            orientation error ≤ ``angle_tolerance`` (rad); converged solutions of reachable
            targets are typically within 1e-12 m.
        config : SolverConfig, optional
            Default: 200 iterations, ftol = xtol = gtol = 1e-15 (iterate to round-off).

        Returns
        -------
        IKResult
            The best restart of every target; ``result.unreachable`` lists the targets not
            reached, with the closest pose found and its distance (``result.report()``,
            ``result.check()``).
        """
        if restarts < 1:
            raise KinematicsError(f"restarts must be ≥ 1, got {restarts}")
        check_size(restarts)  # 10,000,000 was JAX's out-of-memory traceback
        for name, value in (("tolerance", tolerance), ("angle_tolerance", angle_tolerance)):
            if not (np.isfinite(value) and value > 0):  # a negative one called every reached target unreached
                raise KinematicsError(f"{name} must be a positive number, got {value}")
        config = config or SolverConfig(max_iterations=200, ftol=1e-15, xtol=1e-15, gtol=1e-15)
        with float64():
            targets = np.asarray(target, dtype=float)
            single = targets.ndim == 1
            targets = np.atleast_2d(targets)
            if targets.ndim != 2 or targets.shape[1] != 3:
                raise KinematicsError(f"IK targets must be (3,) or (B, 3) positions, got shape {np.shape(target)}")
            B = targets.shape[0]
            rotations = None
            if orientation is not None:
                given = np.asarray(orientation, dtype=float)
                if given.shape[-2:] != (3, 3) or given.ndim not in (2, 3):
                    raise KinematicsError(
                        f"IK orientations must be (3, 3) or (B, 3, 3) rotations, got shape {given.shape}"
                    )
                rotations = given.reshape(-1, 3, 3)
                if rotations.shape[0] == 1 and B > 1:
                    rotations = np.repeat(rotations, B, axis=0)
                if rotations.shape[0] != B:
                    raise KinematicsError(f"{rotations.shape[0]} orientations for {B} targets")
            if not np.all(np.isfinite(targets)):
                raise KinematicsError("IK targets must be finite")
            starts = self._starts(B, restarts, initial, seed)  # (B, R, n)
            u0 = _to_free(starts, self.lower, self.upper)
            data = targets[:, None, :].repeat(restarts, axis=1)
            if rotations is not None:
                rv = np.array([_rotvec(R) for R in rotations])
                data = np.concatenate([data, rv[:, None, :].repeat(restarts, axis=1)], axis=2)
            x0 = np.concatenate([u0, data], axis=2).reshape(B * restarts, -1)
            fun = self._ik_fun(rotations is not None, orientation_weight)
            solved = least_squares(fun, x0, config=config)
            u = solved.x[:, : self.n].reshape(B, restarts, self.n)
            cost = np.where(np.isfinite(solved.cost), solved.cost, np.inf).reshape(B, restarts)
            every = _wrap(_from_free(u, self.lower, self.upper), self.periodic)
            best = self._choose(every, cost, starts[:, 0], tolerance)
            theta = every[np.arange(B), best]
            status = solved.status.reshape(B, restarts)[np.arange(B), best]
            iterations = solved.iterations.reshape(B, restarts)[np.arange(B), best]
            poses = np.asarray(self.pose(theta))
            driven = self.driven_values(theta)  # (B, d)
        position, rotation = poses[:, :3, 3], poses[:, :3, :3]
        distance = np.linalg.norm(position - targets, axis=1)
        angle = None
        reached = distance <= tolerance
        if rotations is not None:
            angle = np.array([_angle_between(R, Rt) for R, Rt in zip(rotation, rotations)])
            reached &= angle <= angle_tolerance
        reached &= np.all(np.isfinite(theta), axis=1)
        # a driven joint (a <mimic>) outside its limits: the robot cannot take θ, the target is not reached
        slack = {"revolute": angle_tolerance, "prismatic": tolerance}
        outside = tuple(tuple(self._outside_driven(row, slack.__getitem__)) for row in driven)
        reached &= np.array([not names for names in outside], dtype=bool)
        return IKResult(
            joints=tuple(self.joints),
            target=self.label,
            theta=theta,
            position=position,
            rotation=rotation,
            target_position=targets,
            target_rotation=rotations,
            distance=distance,
            angle=angle,
            reached=reached,
            status=status.astype(int),
            iterations=iterations.astype(int),
            restarts=restarts,
            tolerance=tolerance,
            angle_tolerance=angle_tolerance,
            single=single,
            units=tuple(self._unit(k) for k in range(self.n)),
            outside_limits=outside,
        )

    def _choose(self, theta: np.ndarray, cost: np.ndarray, initial: np.ndarray, tolerance: float) -> np.ndarray:
        """Per target, the restart that reached it with the least joint motion from the initial
        values; the smallest cost when none reached it.  θ (B, R, n), cost (B, R) → (B,)."""
        step = theta - initial[:, None, :]
        step = np.where(self.periodic, np.pi - np.mod(np.pi - step, 2.0 * np.pi), step)  # the shorter way round
        motion = np.linalg.norm(step, axis=2)
        reached = cost <= tolerance * tolerance
        return np.where(reached.any(axis=1), np.argmin(np.where(reached, motion, np.inf), axis=1), np.argmin(cost, 1))

    def _ik_fun(self, with_orientation: bool, weight: float) -> Callable:
        """The residual of inverse kinematics; one function object per kind, so the solver's
        compiled program is reused.  Each row of x is (u, target): the target rides along with
        a zero derivative (``stop_gradient``), so one vmapped call serves many targets."""
        key = (with_orientation, float(weight))
        if key in self._ik_funs:
            return self._ik_funs[key]
        n, lower, upper = self.n, self.lower, self.upper
        # joints driven through an expression (a <mimic>) are held within their limits by rows
        # that are 0 inside them and the excess outside (rad or m, weighed as metres)
        limited = [d for d in self._driven if d.limited]
        low, high = np.array([d.lower for d in limited]), np.array([d.upper for d in limited])

        def excess(theta: Array) -> Array:
            v = self._driven_single(theta)[np.array([d.limited for d in self._driven])]
            above = jnp.where(np.isfinite(high), jnp.maximum(v - np.where(np.isfinite(high), high, 0.0), 0.0), 0.0)
            below = jnp.where(np.isfinite(low), jnp.minimum(v - np.where(np.isfinite(low), low, 0.0), 0.0), 0.0)
            return above + below

        def fun(x: Array) -> Array:
            theta = _from_free_jax(x[:n], lower, upper)
            data = jax.lax.stop_gradient(x[n:])
            p, R = self._pose_single(theta)
            r = p - data[:3]
            if with_orientation:
                Rt = jnp.stack([jnp.stack(row) for row in sm.rotation_vector((data[3], data[4], data[5]))])
                r = jnp.concatenate([r, (weight / math.sqrt(2.0)) * (R - Rt).reshape(9)])
            if limited:
                r = jnp.concatenate([r, excess(theta)])
            return r

        self._ik_funs[key] = fun
        return fun

    def _starts(self, B: int, restarts: int, initial: Array | None, seed: int | None) -> np.ndarray:
        """(B, R, n) starting values: the initial guess, then random draws."""
        if initial is None:
            first = np.tile(self.theta0, (B, 1))
        else:
            first = np.asarray(initial, dtype=float)
            if first.shape[-1] != self.n:
                raise KinematicsError(f"the initial joint values need {self.n} entries, got shape {first.shape}")
            first = np.broadcast_to(first.reshape(-1, self.n), (B, self.n)).copy()
        lo_ok, hi_ok = np.isfinite(self.lower), np.isfinite(self.upper)
        first = np.clip(first, np.where(lo_ok, self.lower, -np.inf), np.where(hi_ok, self.upper, np.inf))
        lo, hi = self._sampling_range()
        rng = np.random.default_rng(seed)
        draws = lo + (hi - lo) * rng.uniform(size=(B, restarts, self.n))
        draws[:, 0, :] = first
        return draws

    def _sampling_range(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = np.empty(self.n), np.empty(self.n)
        for k, name in enumerate(self.joints):
            info = self.model.param(name)
            if np.isfinite(self.lower[k]) and np.isfinite(self.upper[k]):
                lo[k], hi[k] = self.lower[k], self.upper[k]
            elif info.lower is not None and info.upper is not None and not info.per_configuration:
                lo[k], hi[k] = info.lower, info.upper
            elif info.dim == ANGLE or self.kinds[k] == "revolute":
                lo[k], hi[k] = -math.pi, math.pi
            else:
                lo[k], hi[k] = -1.0, 1.0
            if np.isfinite(self.lower[k]):
                lo[k] = max(lo[k], self.lower[k])
            if np.isfinite(self.upper[k]):
                hi[k] = min(hi[k], self.upper[k])
        return lo, hi

    # ---- reports -----------------------------------------------------------------------------------------

    def report(
        self,
        theta: Array,
        *,
        frame: FrameName = "world",
        part: Part = "position",
        damping: float = 0.0,
        ik: IKResult | None = None,
    ) -> tuple[str, dict[str, Any]]:
        """The text and JSON report of one configuration: f, J (full), J* of ``part``, and an IK
        solution if given (what ``mbcal kinematics`` prints)."""
        theta = np.asarray(theta, dtype=float).reshape(self.n)
        out = self.forward(theta)
        p, R = np.asarray(out.position), np.asarray(out.rotation)
        J = np.asarray(self.jacobian(theta, frame=frame))
        Jp = np.asarray(self.pseudo_inverse(theta, frame=frame, part=part, damping=damping))
        w = float(self.manipulability(theta, part=part))
        rows = ROW_NAMES[_PARTS[part]]
        # fewer joints than rows: JJᵀ is never invertible, J* is the left inverse (least squares)
        left = self.n < len(rows)
        units = [self._unit(k) for k in range(self.n)]
        lines = [f"{self.label} of {self.model.path}: chain of {self.n} ({'joint axes' if self.fast else 'jacfwd'})"]
        lines.append(
            table(
                ["joint", "value", "unit", "lower", "upper"],
                [
                    [
                        name,
                        self._show(k, theta[k]),
                        units[k],
                        self._show(k, self.lower[k]),
                        self._show(k, self.upper[k]),
                    ]
                    for k, name in enumerate(self.joints)
                ],
                title="\nθ",
            )
        )
        driven = self.driven_values(theta)
        if self._driven:
            lines.append(
                table(
                    ["joint", "value", "unit", "lower", "upper"],
                    [
                        [
                            d.name,
                            _display(d.kind, value),
                            _kind_unit(d.kind),
                            _display(d.kind, d.lower),
                            _display(d.kind, d.upper),
                        ]
                        for d, value in zip(self._driven, driven)
                    ],
                    title="\njoints the chain drives",
                )
            )
        # a configuration the joints cannot take (IK holds these limits): said, not silent
        outside = [name for k, name in enumerate(self.joints) if not self.lower[k] <= theta[k] <= self.upper[k]]
        outside += self._outside_driven(driven)
        if outside:
            lines.append(f"outside the joint limits: {', '.join(outside)} (the robot cannot take this configuration)")
        rpy = np.degrees(rpy_from_matrix(R))
        lines.append(
            f"\nf(θ): position ({', '.join(fmt(v, 6) for v in p)}) m, "
            f"roll/pitch/yaw ({', '.join(fmt(v, 5) for v in rpy)}) deg"
        )
        lines.append(
            table(
                ["J"] + list(self.joints),
                [[r] + _shown(J[i], J) for i, r in enumerate(ROW_NAMES)],
                title=f"\nJ ({frame} axes; v per unit of θ: m/rad or m/m)",
            )
        )
        lines.append(
            table(
                ["J*"] + list(rows),
                [[name] + _shown(Jp[k], Jp) for k, name in enumerate(self.joints)],
                title=f"\nJ* = {_formula(left, damping)} of the {part} rows"
                + (f", λ = {fmt(damping)}" if damping else "")
                + (
                    f" — the chain has fewer joints ({self.n}) than rows ({len(rows)}): J* is the least-squares "
                    "joint step, J* J = I (J J* = I cannot hold)"
                    if left
                    else ""
                ),
            )
        )
        singular = not np.all(np.isfinite(Jp))
        gram = "JᵀJ" if left else "JJᵀ"
        lines.append(
            f"\nmanipulability √det({gram}) ({part}): {fmt(w)}"
            + (f"  — singular: {gram} cannot be inverted (give a damping)" if singular else "")
        )
        data: dict[str, Any] = {
            "model": self.model.path,
            "target": self.target,
            "kind": self.what,
            "evaluator": "joint axes" if self.fast else "jacfwd",
            "chain": [
                {
                    "name": name,
                    "value": float(theta[k]),
                    "unit": "rad" if units[k] == "deg" else units[k],
                    "lower": _finite(self.lower[k]),
                    "upper": _finite(self.upper[k]),
                }
                for k, name in enumerate(self.joints)
            ],
            "driven": [
                {
                    "name": d.name,
                    "value": float(value),
                    "unit": "m" if d.kind == "prismatic" else "rad",
                    "lower": _finite(d.lower),
                    "upper": _finite(d.upper),
                }
                for d, value in zip(self._driven, driven)
            ],
            "position": p.tolist(),
            "rotation": R.tolist(),
            "jacobian": {"frame": frame, "rows": list(ROW_NAMES), "matrix": _json_matrix(J)},
            "pseudo_inverse": {
                "part": part,
                "damping": damping,
                "inverse": "left" if left else "right",
                "rows": list(self.joints),
                "columns": list(rows),
                "matrix": _json_matrix(Jp),
            },
            "manipulability": w,
            "singular": singular,
            "outside_limits": outside,
        }
        if ik is not None:
            lines.append("\n" + ik.report(units=units))
            data["ik"] = ik.to_json()
        return "\n".join(lines), data

    def _unit(self, k: int) -> str:
        info = self.model.param(self.joints[k])
        if info.dim == ANGLE or (info.dim is None and self.kinds[k] == "revolute"):
            return "deg"
        if info.dim == LENGTH or self.kinds[k] == "prismatic":
            return "m"
        return ""

    def _show(self, k: int, value: float) -> float:
        return math.degrees(value) if self._unit(k) == "deg" else float(value)


# ---- inverse kinematics results -------------------------------------------------------------------------


@dataclass(frozen=True)
class IKResult:
    """Inverse kinematics of one or many targets: the best restart of each.

    Arrays have a leading batch axis (B) unless a single target was given (``single``).

    Attributes
    ----------
    joints : tuple of str
        The chain's variables.
    theta : (B, n) array
        Joint values found (the closest found for a target out of reach).
    position : (B, 3) array
        Where they put the target point; ``rotation`` (B, 3, 3) its frame's orientation.
    target_position : (B, 3) array
        The targets; ``target_rotation`` (B, 3, 3) or None.
    distance : (B,) array
        Position error (m).
    angle : (B,) array or None
        Orientation error (rad) when orientations were given.
    reached : (B,) bool
        Within ``tolerance`` (and ``angle_tolerance``).
    status, iterations : (B,) int
        The solver's :class:`~mbcal.solver.Status` code and iterations of the best restart.
    outside_limits : (B,) tuple of tuples of str
        The joints the chain drives through an expression (a ``<mimic>``) that θ puts outside
        their limits, named as in :attr:`Kinematics.driven`; such a target is not reached.
    """

    joints: tuple[str, ...]
    target: str
    theta: np.ndarray
    position: np.ndarray
    rotation: np.ndarray
    target_position: np.ndarray
    target_rotation: np.ndarray | None
    distance: np.ndarray
    angle: np.ndarray | None
    reached: np.ndarray
    status: np.ndarray
    iterations: np.ndarray
    restarts: int
    tolerance: float
    angle_tolerance: float
    single: bool = field(default=False)
    units: tuple[str, ...] = ()
    outside_limits: tuple[Any, ...] = ()

    def __post_init__(self) -> None:
        if self.single:
            if self.outside_limits:
                object.__setattr__(self, "outside_limits", tuple(self.outside_limits[0]))
            for name in ("theta", "position", "rotation", "target_position", "distance", "reached", "status",
                         "iterations"):  # fmt: skip
                object.__setattr__(self, name, np.asarray(getattr(self, name))[0])
            for name in ("target_rotation", "angle"):
                value = getattr(self, name)
                if value is not None:
                    object.__setattr__(self, name, np.asarray(value)[0])

    def _rows(self, name: str) -> np.ndarray:
        value = np.asarray(getattr(self, name))
        return value[None] if self.single else value

    def _outside_rows(self) -> list[tuple[str, ...]]:
        count = len(self._rows("distance"))
        if not self.outside_limits:
            return [()] * count
        return [tuple(self.outside_limits)] if self.single else [tuple(names) for names in self.outside_limits]

    @property
    def unreachable(self) -> list[int]:
        """Indices of the targets not reached within the tolerances."""
        return [int(i) for i in np.flatnonzero(~self._rows("reached"))]

    @property
    def all_reached(self) -> bool:
        return not self.unreachable

    def report(self, units: Sequence[str] | None = None) -> str:
        """Text: the joint values for each target, and each target out of reach by name, with the
        closest pose found and its distance."""
        theta, pos, tgt = self._rows("theta"), self._rows("position"), self._rows("target_position")
        dist, reached, status = self._rows("distance"), self._rows("reached"), self._rows("status")
        angle = None if self.angle is None else self._rows("angle")
        outside = self._outside_rows()
        deg = [u == "deg" for u in (units or self.units or [""] * len(self.joints))]

        def show(t: np.ndarray) -> str:
            text = ", ".join(fmt(math.degrees(v) if d else v, 6) for v, d in zip(t, deg))
            return f"({text})" + (" deg" if deg and all(deg) else "")

        lines = []
        for b in range(len(dist)):
            where = f"({', '.join(fmt(v, 6) for v in tgt[b])}) m"
            label = "IK" if self.single else f"IK target {b}"
            err = f"{fmt(dist[b], 3)} m" + ("" if angle is None else f", {fmt(angle[b], 3)} rad")
            if reached[b]:
                lines.append(f"{label}: {self.target} at {where} reached (error {err}): θ = {show(theta[b])}")
            else:
                beyond = f"; it leaves the joint limits of {', '.join(outside[b])}" if outside[b] else ""
                lines.append(
                    f"{label}: {where} is out of reach for {self.target} (tolerance {fmt(self.tolerance, 3)} m): "
                    f"the closest pose found puts it at ({', '.join(fmt(v, 6) for v in pos[b])}) m, "
                    f"{err} away, with θ = {show(theta[b])} [{Status(int(status[b])).label}, "
                    f"best of {self.restarts} starts]{beyond}"
                )
        return "\n".join(lines)

    def check(self) -> IKResult:
        """Raise :class:`~mbcal.errors.UnreachableError` naming every target not reached."""
        if self.unreachable:
            lines = [line for line in self.report().splitlines() if "out of reach" in line]
            raise UnreachableError(
                f"{len(lines)} IK target(s) out of reach:\n" + "\n".join(lines),
                hint="move the target closer, free more joints, or loosen the tolerance",
            )
        return self

    def to_json(self) -> dict[str, Any]:
        rows = []
        theta, pos, tgt = self._rows("theta"), self._rows("position"), self._rows("target_position")
        dist, reached, status = self._rows("distance"), self._rows("reached"), self._rows("status")
        angle = None if self.angle is None else self._rows("angle")
        outside = self._outside_rows()
        for b in range(len(dist)):
            rows.append(
                {
                    "target": tgt[b].tolist(),
                    "reached": bool(reached[b]),
                    "theta": dict(zip(self.joints, (float(v) for v in theta[b]))),
                    "position": pos[b].tolist(),
                    "distance": float(dist[b]),
                    "angle": None if angle is None else float(angle[b]),
                    "status": Status(int(status[b])).label,
                    "outside_limits": list(outside[b]),
                }
            )
        return {"tolerance": self.tolerance, "restarts": self.restarts, "targets": rows}


# ---- helpers -------------------------------------------------------------------------------------------------


def _check_options(frame: str, part: str) -> None:
    if frame not in ("world", "local"):
        raise KinematicsError(f"unknown frame '{frame}' for the Jacobian (world or local)")
    if part not in _PARTS:
        raise KinematicsError(f"unknown Jacobian part '{part}' (full, position or orientation)")


def _resolve_target(model: Model, name: str, what: str | None) -> tuple[str, int]:
    if what not in (None, "point", "frame"):
        raise KinematicsError(f"what must be 'point' or 'frame', got '{what}'")
    kinds = ("point", "frame") if what is None else (what,)
    for kind in kinds:
        if kind == "frame" and name == "world":
            raise KinematicsError("'world' does not move: name a point or a frame of the model")
        try:
            return kind, (model.point_index(name) if kind == "point" else model.frame_index(name))
        except UnknownNameError as err:
            if "ambiguous" in err.message:
                raise
    pool = [model.short_name(kind, n) for kind in kinds for n in model.names(kind)]
    hint = suggest(name, pool) or f"the model has {len(model.points)} points and {len(model.frames)} frames"
    raise UnknownNameError(f"the model has no {' or '.join(kinds)} named '{name}'", hint=hint)


def _ancestry(model: Model, frame: int) -> list[int]:
    path = []
    while frame >= 0:
        path.append(frame)
        frame = model.frames[frame].parent
    return path[::-1]


def _path_nodes(model: Model, path: Sequence[int], point: int | None) -> list[ir.Node]:
    """Every expression on the path from the world to the target (poses, joints, the point)."""
    nodes: list[ir.Node] = []
    for f in path:
        frame = model.frames[f]
        if frame.pose is not None:
            nodes.append(frame.pose)
        if frame.joint is not None:
            nodes += [frame.joint.axis, frame.joint.q]
            if frame.joint.offset is not None:
                nodes.append(frame.joint.offset)
    if point is not None:
        nodes.append(model.points[point].position)
    return nodes


def _joint_variables(model: Model, path: Sequence[int]) -> list[str]:
    """The parameters that the readings of the joints on ``path`` depend on, root first."""
    out: list[str] = []
    for f in path:
        joint = model.frames[f].joint
        if joint is None:
            continue
        for i in sorted(depends_on(joint.q)):
            name = model.params[i].name
            if name not in out:
                out.append(name)
    return out


def _resolve_chain(
    model: Model, chain: str | Sequence[str] | None, path: Sequence[int], point: int | None, target: str
) -> list[str]:
    along = _joint_variables(model, path)
    if chain is None:
        if not along:
            raise KinematicsError(
                f"no joint moves '{target}': name the chain's variables (--chain GLOB, or chain=... in Python)"
            )
        return along
    items = [s.strip() for s in chain.split(",")] if isinstance(chain, str) else [str(s).strip() for s in chain]
    items = [s for s in items if s]
    if not items:
        raise KinematicsError("the chain is empty: name its joint variables")
    names: list[str] = []
    joint_frames = {
        f.name: f.joint.q.name
        for f in model.frames
        if f.joint is not None and isinstance(f.joint.q, ParamRef)  # a frame with a joint stands for its reading
    }
    # the readings 'J.q' of joints: 'J' names its joint's reading (a URDF's own joint names)
    readings = {f.joint.q.name for f in model.frames if f.joint is not None and isinstance(f.joint.q, ParamRef)}
    for item in items:
        if model.has("param", item):
            names.append(item)
            continue
        if any(ch in item for ch in "*?["):
            matched = model.match_params(item)
            if not matched:
                raise UnknownNameError(f"the chain pattern '{item}' matches no parameter", hint=suggest(item, along))
            names.extend(matched)
            continue
        try:
            f = model.frame_index(item)
        except UnknownNameError as err:
            if "ambiguous" in err.message:
                raise
            f = -1
        by_frame = joint_frames.get(model.frames[f].name) if f >= 0 else None
        by_joint = f"{item}.q" if f"{item}.q" in readings else None
        if by_frame is not None and by_joint is not None and by_frame != by_joint:
            raise UnknownNameError(
                f"the chain name '{item}' is ambiguous: the reading of frame {model.frames[f].name}'s joint "
                f"({by_frame}) or the joint reading {by_joint}",
                hint=f"name the parameter: {by_frame} or {by_joint}",
            )
        if by_frame is not None or by_joint is not None:
            names.append(by_frame or by_joint or "")
            continue
        follows = _follows(model, item, f)
        if follows is not None:
            raise UnknownNameError(
                f"the chain names '{item}', a joint without a reading of its own",
                hint=f"it follows {follows}: name that" if follows else "it is held at a constant value",
            )
        hint = suggest(item, sorted(readings) + list(joint_frames)) or suggest(item, model.names("param"))
        raise UnknownNameError(
            f"the chain names '{item}', which is neither a parameter, a joint's frame nor a joint (J for J.q)",
            hint=hint,
        )
    seen: set[str] = set()
    for name in names:
        if name in seen:
            raise KinematicsError(f"the chain names '{name}' twice")
        seen.add(name)
    moving: set[int] = set()
    for node in _path_nodes(model, path, point):
        moving |= depends_on(node)
    for name in names:
        if model.param_index(name) not in moving:
            between = ", ".join(along) if along else "none"
            raise KinematicsError(
                f"'{name}' does not move '{target}'",
                hint=f"the joint variables between the world and '{target}': {between}",
            )
    return names


def _follows(model: Model, item: str, frame: int) -> str | None:
    """For a chain item that names a joint without a reading of its own (a URDF ``<mimic>``, by its
    name or its frame's): the parameters it follows."""
    for f, info in enumerate(model.frames):
        joint = info.joint
        if joint is None or isinstance(joint.q, ParamRef):
            continue
        own = isinstance(joint.offset, ParamRef) and joint.offset.name == f"{item}.offset"
        if f == frame or own:
            return ", ".join(model.params[i].name for i in sorted(depends_on(joint.q)))
    return None


def _limits(model: Model, joints: Sequence[str], path: Sequence[int]) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Joint limits of each chain variable (±inf where none: those of every joint it is the
    reading of, on the path or not) and its kind (revolute, prismatic, parameter; from the path
    first)."""
    lower = np.full(len(joints), -np.inf)
    upper = np.full(len(joints), np.inf)
    kinds = ["parameter"] * len(joints)
    position = {name: k for k, name in enumerate(joints)}
    on_path = set(path)
    for f in [*path, *(f for f in range(len(model.frames)) if f not in on_path)]:
        joint = model.frames[f].joint
        if joint is None or not isinstance(joint.q, ParamRef) or joint.q.name not in position:
            continue
        k = position[joint.q.name]
        if kinds[k] == "parameter":
            kinds[k] = joint.kind
        if joint.lower is not None:
            lower[k] = max(lower[k], joint.lower)
        if joint.upper is not None:
            upper[k] = min(upper[k], joint.upper)
    return lower, upper, kinds


@dataclass(frozen=True)
class _Driven:
    """A joint the chain drives through an expression (a URDF ``<mimic>``, ``0.5 * q``), named by
    :func:`_joint_name`."""

    name: str
    kind: str  # revolute | prismatic
    q: ir.Node
    lower: float  # −inf: none
    upper: float  # inf: none

    @property
    def limited(self) -> bool:
        return math.isfinite(self.lower) or math.isfinite(self.upper)


def _driven_joints(model: Model, indices: np.ndarray) -> list[_Driven]:
    """Every joint of the model (on the path to the target or not) whose reading depends on the
    chain without being one of its variables; their limits bound the chain too."""
    chain = {int(i) for i in indices}
    out = []
    for frame in model.frames:
        joint = frame.joint
        if joint is None or (isinstance(joint.q, ParamRef) and joint.q.index in chain):
            continue
        if chain & depends_on(joint.q):
            name = _joint_name(model, frame)
            low = -math.inf if joint.lower is None else float(joint.lower)
            high = math.inf if joint.upper is None else float(joint.upper)
            out.append(_Driven(name, joint.kind, joint.q, low, high))
    return out


def _joint_name(model: Model, frame: Any) -> str:
    """A joint's name in reports: a URDF joint's own (its mdl name, the prefix of its ``J.offset``),
    else its frame's (which stands for it in a chain)."""
    joint = frame.joint
    offset = joint.offset if joint is not None else None
    if str(model.path).lower().endswith(".urdf") and isinstance(offset, ParamRef) and offset.name.endswith(".offset"):
        return offset.name[: -len(".offset")]
    return model.short_name("frame", frame.name)


def _kind_unit(kind: str) -> str:
    return "m" if kind == "prismatic" else "deg"


def _display(kind: str, value: float) -> float:
    """A joint reading (SI) as shown: degrees for a revolute joint."""
    return float(value) if kind == "prismatic" else math.degrees(value)


def _to_free(theta: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """θ → u of the bounded parametrisation (inverse of :func:`_from_free`)."""
    lo, hi = np.isfinite(lower), np.isfinite(upper)
    both = lo & hi
    c, h = _centre_half(lower, upper)
    u = np.where(both, np.arcsin(np.clip((theta - c) / h, -1.0, 1.0)), theta)
    below = np.where(lo & ~hi, np.maximum(theta - np.where(lo, lower, 0.0), 0.0) + 1.0, 1.0)
    u = np.where(lo & ~hi, np.sqrt(below * below - 1.0), u)
    above = np.where(hi & ~lo, np.maximum(np.where(hi, upper, 0.0) - theta, 0.0) + 1.0, 1.0)
    return np.where(hi & ~lo, np.sqrt(above * above - 1.0), u)


def _from_free(u: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    return np.asarray(_from_free_jax(jnp.asarray(u), lower, upper))


def _from_free_jax(u: Array, lower: np.ndarray, upper: np.ndarray) -> Array:
    """u → θ: c + h·sin(u) between two limits, lower − 1 + √(u² + 1) above one (MINUIT), u without."""
    lo, hi = np.isfinite(lower), np.isfinite(upper)
    both = lo & hi
    if not lo.any() and not hi.any():
        return u
    c, h = _centre_half(lower, upper)
    root = jnp.sqrt(u * u + 1.0)
    out = jnp.where(both, c + h * jnp.sin(u), u)
    out = jnp.where(lo & ~hi, np.where(lo, lower, 0.0) - 1.0 + root, out)
    return jnp.where(hi & ~lo, np.where(hi, upper, 0.0) + 1.0 - root, out)


def _centre_half(lower: np.ndarray, upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre and half-width of two-sided limits (0 and 1 elsewhere)."""
    both = np.isfinite(lower) & np.isfinite(upper)
    lo, hi = np.where(both, lower, 0.0), np.where(both, upper, 0.0)
    half = 0.5 * (hi - lo)
    return np.where(both, 0.5 * (lo + hi), 0.0), np.where(both & (half > 0), half, 1.0)


def _periodic(model: Model, indices: np.ndarray, path: Sequence[int], point: int | None) -> np.ndarray:
    """Which chain variables the target's pose has period 2π in, by the model's structure: every
    use on the path is the angle of a revolute joint itself (``joint revolute(AXIS, q)``, any
    offset).  A variable scaled or shifted on its way to a joint (``0.5 * q``, a URDF ``<mimic>``)
    or used in a pose is not: θ and θ − 2π put the target in different places."""
    angles: set[int] = set()
    elsewhere: set[int] = set()
    nodes: list[ir.Node] = []
    for f in path:
        frame = model.frames[f]
        if frame.pose is not None:
            nodes.append(frame.pose)
        joint = frame.joint
        if joint is None:
            continue
        nodes += [joint.axis] + ([joint.offset] if joint.offset is not None else [])
        if joint.kind == "revolute" and isinstance(joint.q, ParamRef):
            angles.add(joint.q.index)
        else:
            nodes.append(joint.q)
    if point is not None:
        nodes.append(model.points[point].position)
    for node in nodes:
        elsewhere |= depends_on(node)
    return np.array([int(i) in angles and int(i) not in elsewhere for i in indices], dtype=bool)


def _wrap(theta: np.ndarray, periodic: np.ndarray) -> np.ndarray:
    """The variables the pose has period 2π in (:func:`_periodic`, no limits) brought into (−π, π]."""
    wrapped = np.pi - np.mod(np.pi - theta, 2.0 * np.pi)
    return np.where(periodic, wrapped, theta)


def _formula(left: bool, damping: float) -> str:
    """J*'s formula as the report writes it: the right inverse, or the left one (fewer joints than rows)."""
    plus = " + λ²I" if damping else ""
    return f"(JᵀJ{plus})⁻¹Jᵀ" if left else f"Jᵀ(JJᵀ{plus})⁻¹"


def _rotvec(R: np.ndarray) -> np.ndarray:
    """The rotation vector of a rotation matrix (log map), accurate near 0 and π."""
    R = np.asarray(R, dtype=float)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise KinematicsError("an IK orientation must be a rotation matrix (orthonormal, det +1)")
    cos = np.clip(0.5 * (np.trace(R) - 1.0), -1.0, 1.0)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    sin = 0.5 * np.linalg.norm(w)
    angle = math.atan2(sin, cos)
    if angle < 1e-8:
        return 0.5 * w
    if math.pi - angle < 1e-4:
        # Near π: the axis from the symmetric part (R + I)/2 = a aᵀ.
        S = 0.5 * (R + np.eye(3))
        k = int(np.argmax(np.diag(S)))
        axis = S[:, k] / math.sqrt(max(S[k, k], 1e-300))
        if w @ axis < 0:
            axis = -axis
        return angle * axis / np.linalg.norm(axis)
    return angle * w / (2.0 * sin)


def _angle_between(R: np.ndarray, Rt: np.ndarray) -> float:
    return float(np.linalg.norm(_rotvec(np.asarray(Rt).T @ np.asarray(R))))


def _shown(row: np.ndarray, whole: np.ndarray) -> list[float]:
    """Entries for a table: round-off below 1e-12 of the matrix's largest entry shows as 0."""
    finite = np.abs(whole[np.isfinite(whole)])
    floor = 1e-12 * (float(finite.max()) if finite.size else 0.0)
    return [0.0 if abs(v) < floor else float(v) for v in row]


def _finite(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def _json_matrix(M: np.ndarray) -> list[list[float | None]]:
    return [[float(v) if np.isfinite(v) else None for v in row] for row in np.asarray(M)]
