"""Orientations without gimbal lock (issue 14, item 3): roll-pitch-yaw triples stepped as a rotation
vector about the current orientation, their Jacobian, and the 89.9° pitch case."""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest

import mbcal
from mbcal.errors import SolverError
from mbcal.modeling import rpy_triples
from mbcal.problem import Problem
from mbcal.solver import SolverConfig, least_squares

from conftest import MEASUREMENTS, MODELS, ROOM_TRUTH

jnp = jax.numpy
D = math.radians
ANGLES = ["room.roll", "room.pitch", "room.yaw"]


def rotation(roll, pitch, yaw):
    """Rz(yaw)·Ry(pitch)·Rx(roll) with numpy."""
    cr, sr, cp, sp, cy, sy = (f(a) for a in (roll, pitch, yaw) for f in (np.cos, np.sin))
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def exp_so3(w):
    theta = np.linalg.norm(w)
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if theta < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(theta) / theta * K + (1 - np.cos(theta)) / theta**2 * K @ K


def angle_between(Ra, Rb):
    return math.degrees(math.acos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1)))


# ---- which orientations -------------------------------------------------------------------------------


def test_the_rooms_orientation_is_found(room):
    (triple,) = rpy_triples(room)
    assert [room.params[i].name for i in triple.params] == ANGLES
    assert len(triple.nodes) == 1 and triple.nodes[0].op == "rpy"


@pytest.mark.parametrize(
    "text, found",
    [
        ("frame f at rpy(a, b, c)", [("a", "b", "c")]),
        ("frame f at pose(1 m, 0, 0, a, b, c)\nframe g at rpy(a, b, c) * rot_x(d)", [("a", "b", "c")]),
        ("frame f at rpy(a, b, c)\nframe g at rot_x(a)", []),  # 'a' is used elsewhere too
        ("frame f at rpy(a, b, c)\nframe g at rpy(c, b, a)", []),  # the same angles in other roles
        ("frame f at rpy(a, b, d)\nframe g at rpy(a, b, c)", []),
        ("frame f at rpy(a, a, c)", []),
        ("frame f at rpy(-a, b, c)", []),  # an angle that is not a parameter by itself
        ("frame f at rpy(a, 10 deg, c)", []),
    ],
)
def test_only_triples_of_parameters_used_nowhere_else_qualify(text, found):
    model = mbcal.load_model_text("param a = 0 deg\nparam b = 0 deg\nparam c = 0 deg\nparam d = 0 deg\n" + text)
    assert [tuple(model.params[i].name for i in t.params) for t in rpy_triples(model)] == found


@pytest.fixture(scope="module")
def room_data(room):
    plan = mbcal.read_measurements(MEASUREMENTS / "room_plan.csv", room)
    return mbcal.simulate(room, plan, ROOM_TRUTH, noise=1.0, seed=11)


def test_all_three_angles_must_be_estimated_without_limits_or_priors(room, room_data):
    assert Problem(room, room_data, ["room.*"]).orientation_names == [tuple(ANGLES)]
    assert Problem(room, room_data, ["room.x", "room.roll", "room.pitch"]).local is None
    limited = mbcal.load_model_text(
        (MODELS / "teleexistence.mdl")
        .read_text(encoding="utf-8")
        .replace("param room.yaw   = 0 deg in [-5 deg, 5 deg]", "param room.yaw = 0 deg in [-5 deg, 5 deg] bounded"),
        str(MODELS / "teleexistence.mdl"),
    )
    assert limited.param("room.yaw").limited
    assert Problem(limited, room_data, ["room.*"]).local is None
    prior = mbcal.load_model_text(
        (MODELS / "teleexistence.mdl")
        .read_text(encoding="utf-8")
        .replace(
            "param room.yaw   = 0 deg in [-5 deg, 5 deg]", "param room.yaw = 0 deg in [-5 deg, 5 deg] sigma 1 deg"
        ),
        str(MODELS / "teleexistence.mdl"),
    )
    assert Problem(prior, room_data, ["room.*"]).local is None
    assert Problem(prior, room_data, ["room.*"], priors=False).local is not None


PER_VIEW = """
param tag.x = 0 m per configuration
param tag.roll = 0 deg per configuration
param tag.pitch = 0 deg per configuration
param tag.yaw = 0 deg per configuration
object tag at pose(tag.x, 0, 1 m, tag.roll, tag.pitch, tag.yaw) {
  point a = (10 cm, 0, 0)
  point b = (0, 20 cm, 0)
  point c = (0, 0, 30 cm)
}
"""


def per_view_records():
    return [
        {"kind": "point3d", "point": f"tag.{p}", "config": c, "sigma": 0.001} for c in ("one", "two") for p in "abc"
    ]


@pytest.fixture(scope="module")
def per_view():
    model = mbcal.load_model_text(PER_VIEW)
    plan = mbcal.measurements_from_records(per_view_records(), model)
    truth = {
        "tag.roll@one": D(20),
        "tag.pitch@one": D(89.9),
        "tag.yaw@one": D(-40),
        "tag.roll@two": D(-5),
        "tag.pitch@two": D(30),
        "tag.yaw@two": D(170),
        "tag.x@two": 0.1,
    }
    data = mbcal.simulate(model, plan, {}, noise=0)
    problem = Problem(model, data, ["tag.*"])
    x = problem.params.from_dict(truth)
    return model, plan, problem, x


def test_per_configuration_orientations_get_one_rotation_each(per_view):
    model, plan, problem, _ = per_view
    assert problem.orientation_names == [
        ("tag.roll@one", "tag.pitch@one", "tag.yaw@one"),
        ("tag.roll@two", "tag.pitch@two", "tag.yaw@two"),
    ]
    assert Problem(model, plan, ["tag.*@two"]).orientation_names == [("tag.roll@two", "tag.pitch@two", "tag.yaw@two")]
    mixed = mbcal.load_model_text(PER_VIEW.replace("param tag.yaw = 0 deg per configuration", "param tag.yaw = 0 deg"))
    mixed_plan = mbcal.measurements_from_records(per_view_records(), mixed)
    assert Problem(mixed, mixed_plan, ["tag.*"]).local is None  # one yaw in two rotations: plain steps


# ---- the step and its Jacobian -------------------------------------------------------------------------


def local_jacobian(problem, x):
    y, known = jnp.asarray(np.nan_to_num(problem.y)), jnp.asarray(problem.params.known)
    fun = jax.jit(lambda xx, d: problem.local.residual(xx, d, y, known))
    J = jax.jit(jax.jacfwd(lambda xx, d: problem.local.residual(xx, d, y, known), argnums=1))
    n = len(x)
    return np.asarray(fun(jnp.asarray(x), jnp.zeros(n))), np.asarray(J(jnp.asarray(x), jnp.zeros(n)))


def finite_differences(problem, x, h=1e-6):
    """∂r(x ⊞ d)/∂d by central differences through the step itself and the plain residual."""
    plus = jax.jit(problem.local.plus)
    n = len(x)
    columns = []
    for i in range(n):
        e = np.zeros(n)
        e[i] = h
        forward = problem.residual(np.asarray(plus(jnp.asarray(x), jnp.asarray(e))))
        backward = problem.residual(np.asarray(plus(jnp.asarray(x), jnp.asarray(-e))))
        columns.append((forward - backward) / (2 * h))
    return np.stack(columns, axis=1)


@pytest.mark.parametrize("pitch", [10.0, 89.9, 90.0, -90.0])
def test_the_jacobian_in_the_rotation_vector_matches_finite_differences(room, room_data, pitch):
    problem = Problem(room, room_data, ["room.*", "lever.angle"])
    x = problem.params.x0.copy()
    names = problem.params.names
    for name, value in zip(ANGLES, (D(20), D(pitch), D(-30))):
        x[names.index(name)] = value
    r, J = local_jacobian(problem, x)
    np.testing.assert_allclose(r, problem.residual(x), rtol=1e-9, atol=1e-6)
    Jfd = finite_differences(problem, x)
    assert np.all(np.isfinite(J))
    assert np.max(np.abs(J - Jfd)) <= 1e-6 * np.max(np.abs(J))
    # Regular at the lock: the three rotation columns stay independent (the angles' would not).
    rotation_columns = J[:, [names.index(a) for a in ANGLES]]
    assert np.linalg.matrix_rank(rotation_columns, tol=1e-6 * np.abs(rotation_columns).max()) == 3


def test_the_jacobian_per_configuration_matches_finite_differences(per_view):
    _, _, problem, x = per_view
    r, J = local_jacobian(problem, x)
    np.testing.assert_allclose(r, problem.residual(x), atol=1e-9)
    assert np.max(np.abs(J - finite_differences(problem, x))) <= 1e-6 * np.max(np.abs(J))


@pytest.mark.parametrize("angles", [(20.0, 89.9, -40.0), (0.0, 90.0, 0.0), (170.0, -30.0, -175.0), (5.0, -90.0, 60.0)])
def test_the_step_rotates_about_the_current_orientation(room, room_data, angles):
    problem = Problem(room, room_data, ["room.*"])
    names = problem.params.names
    idx = [names.index(a) for a in ANGLES]
    x = problem.params.x0.copy()
    x[idx] = np.radians(angles)
    plus = jax.jit(problem.local.plus)
    assert np.max(np.abs(np.asarray(plus(jnp.asarray(x), jnp.zeros(len(x)))) - x)) < 1e-12  # x ⊞ 0 = x
    rng = np.random.default_rng(1)
    for _ in range(5):
        d = rng.normal(scale=0.3, size=len(x))
        moved = np.asarray(plus(jnp.asarray(x), jnp.asarray(d)))
        expected = rotation(*x[idx]) @ exp_so3(d[idx])
        np.testing.assert_allclose(rotation(*moved[idx]), expected, atol=1e-12)
        others = [i for i in range(len(x)) if i not in idx]
        np.testing.assert_array_equal(moved[others], x[others] + d[others])
        assert np.all(np.abs(moved[idx] - x[idx]) < math.pi + 0.5)  # angles move continuously (mod 2π)


@pytest.mark.parametrize("which", ["room", "per_view"])
def test_results_are_written_in_the_angles_nearest_their_starts(room, room_data, per_view, which):
    """represent_after (NumPy, all restarts after the solve) and represent (traced, one restart):
    the other branch (r + π, π − p, y + π) and other multiples of 2π are rewritten as the
    equivalent angles nearest each restart's start; nothing else moves.  Two orientations
    (per_view) place each rotation's angles at its own positions."""
    problem = Problem(room, room_data, ["room.*"]) if which == "room" else per_view[2]
    names = problem.params.names
    triples = [[names.index(a) for a in triple] for triple in problem.orientation_names]
    idx = [i for triple in triples for i in triple]
    rng = np.random.default_rng(4)
    starts = np.tile(problem.params.x0, (5, 1)) + rng.normal(scale=0.01, size=(5, len(names)))
    starts[:, idx] = rng.uniform(-3.0, 3.0, size=(5, len(idx)))
    moved = starts.copy()
    for t in triples:
        k = rng.choice([-2, -1, 1, 2], size=(5, 3)) * 2.0 * np.pi  # whole turns, none zero
        r, p, y = starts[:, t].T
        moved[:, t] = np.stack([r + np.pi, np.pi - p, y + np.pi], axis=1) + k  # the same rotations
        moved[0, t] = starts[0, t] + k[0]  # the same branch, other turns
    out = problem.local.represent_after(moved, starts)
    assert out.shape == moved.shape and np.all(out[:, idx] != moved[:, idx])
    np.testing.assert_allclose(out[:, idx], starts[:, idx], atol=1e-12)
    others = [i for i in range(len(names)) if i not in idx]
    np.testing.assert_array_equal(out[:, others], moved[:, others])
    for row, before in zip(out, moved):
        for t in triples:
            np.testing.assert_allclose(rotation(*row[t]), rotation(*before[t]), atol=1e-12)
    traced = jax.jit(jax.vmap(problem.local.represent))(jnp.asarray(moved), jnp.asarray(starts))
    np.testing.assert_allclose(np.asarray(traced), out, rtol=0, atol=1e-15)
    with np.errstate(all="raise"):  # a non-finite result gives NaN, without a warning
        bad = moved.copy()
        bad[1, idx[0]] = np.inf
        assert np.isnan(problem.local.represent_after(bad, starts)[1, idx[0]])


class Wrapped:
    """A user's local parameterisation of an angle, without represent_after: its represent is
    traced into the solver's program, one restart at a time (the protocol's first form)."""

    def residual(self, x, d, *args):
        return circle(x + d)

    def plus(self, x, d):
        return x + d

    def represent(self, x, reference):
        turns = jnp.round((x[0] - reference[0]) / (2.0 * np.pi))
        return x.at[0].set(x[0] - 2.0 * np.pi * turns)


def circle(x):
    return jnp.stack([jnp.cos(x[0]) - np.cos(0.7), jnp.sin(x[0]) - np.sin(0.7), x[1] - 7.0])


def test_a_local_parameterisation_without_represent_after_is_represented_in_the_program():
    starts = np.array([[0.5 + 4.0 * np.pi, 0.0], [1.0, 1.0]])
    solved = least_squares(circle, starts, local=Wrapped())
    assert isinstance(solved.x, np.ndarray) and solved.x.shape == (2, 2)
    np.testing.assert_allclose(solved.x[:, 0], [0.7 + 4.0 * np.pi, 0.7], atol=1e-9)  # each nearest its start
    np.testing.assert_allclose(solved.x[:, 1], [7.0, 7.0], atol=1e-9)  # the other unknown untouched


class WrappedAfter(Wrapped):
    """The same, written for all restarts at once in NumPy: the solver calls it after the solve."""

    def represent_after(self, x, reference):
        x = np.array(x)
        x[:, 0] -= 2.0 * np.pi * np.round((x[:, 0] - reference[:, 0]) / (2.0 * np.pi))
        return x


def beyond(x):
    return jnp.stack([x[0] - (np.pi + 0.5), x[1] - 7.0])


class Beyond(Wrapped):
    def residual(self, x, d, *args):
        return beyond(x + d)


class BeyondAfter(WrappedAfter):
    def residual(self, x, d, *args):
        return beyond(x + d)


@pytest.mark.parametrize("local", [Beyond(), BeyondAfter()], ids=["represent", "represent_after"])
def test_the_active_bounds_are_of_the_solvers_own_x_whichever_represent(local):
    """The unknown ends on its upper bound π; represented nearest the start (-3) it reads -π.  The
    active bound is the one it ended on (+1), in the program or after it, densely or by blocks (the
    dense program had taken the represented x: none active)."""
    from mbcal.structured import Structure, least_squares_structured

    bounds = (np.array([-np.pi, -np.inf]), np.array([np.pi, np.inf]))
    start = np.array([[-3.0, 0.0]])
    dense = least_squares(beyond, start, bounds=bounds, local=local)
    structure = Structure(
        blocks=np.array([[0]]), shared=np.array([[1]]), row_block=np.zeros(2, int), row_group=np.zeros(2, int)
    )
    by_blocks = least_squares_structured(beyond, start, structure, bounds=bounds, local=local)
    for solved in (dense, by_blocks):
        np.testing.assert_allclose(solved.x[0], [-np.pi, 7.0], atol=1e-9)
        np.testing.assert_array_equal(solved.active[0], [1, 0])


class TurnUp(Wrapped):
    """Represents every result one turn up (the same angle, other coordinates): seen whenever it runs."""

    def represent(self, x, reference):
        return x.at[0].add(2.0 * np.pi)


def test_an_object_that_gains_or_loses_represent_after_is_represented_either_way():
    """The compiled programs are kept per object: one made while it had represent_after (no
    represent inside) must not serve it once it has none (its results came back unrepresented),
    nor the other way round (represented twice)."""
    local = TurnUp()
    starts = np.array([[0.5, 0.0], [1.0, 1.0]])
    turned = [0.7 + 2.0 * np.pi, 0.7 + 2.0 * np.pi]

    def after(x, reference):
        x = np.array(x)
        x[:, 0] += 2.0 * np.pi
        return x

    local.represent_after = after
    np.testing.assert_allclose(least_squares(circle, starts, local=local).x[:, 0], turned, atol=1e-9)
    del local.represent_after
    np.testing.assert_allclose(least_squares(circle, starts, local=local).x[:, 0], turned, atol=1e-9)
    local.represent_after = after
    np.testing.assert_allclose(least_squares(circle, starts, local=local).x[:, 0], turned, atol=1e-9)


def test_represent_after_must_give_every_restart_back():
    class Flat(Wrapped):
        def represent_after(self, x, reference):
            return x[0]  # one row, not every restart's

    with pytest.raises(SolverError, match=r"represent_after returned shape \(2,\) for results of shape \(2, 2\)"):
        least_squares(circle, np.array([[0.5, 0.0], [1.0, 1.0]]), local=Flat())


# ---- the 89.9° case ------------------------------------------------------------------------------------

TILTED = {
    "room.x": 0.02,
    "room.y": 0.05,
    "room.z": 0.015,
    "room.roll": D(25),
    "room.pitch": D(89.9),
    "room.yaw": D(-40),
}


@pytest.fixture(scope="module")
def survey(room):
    """3-D positions of ten points of the room (a laser tracker's survey), exact, at 89.9° pitch."""
    points = [p.name for p in room.points if p.name.startswith("room.")][:10]
    plan = mbcal.measurements_from_records([{"kind": "point3d", "point": p, "sigma": 0.001} for p in points], room)
    return mbcal.simulate(room, plan, TILTED, noise=0)


def test_at_89_9_degrees_pitch_the_rotation_step_converges_where_angle_steps_crawl(room, survey):
    problem = Problem(room, survey, ["room.*"])
    names = problem.params.names
    idx = [names.index(a) for a in ANGLES]
    truth = rotation(*(TILTED[a] for a in ANGLES))
    # Sixteen starts 5° to 60° away from the true orientation (whose angles may be far from the truth's).
    rng = np.random.default_rng(0)
    starts = np.tile(problem.params.x0, (16, 1))
    for k in range(16):
        axis = rng.normal(size=3)
        start = truth @ exp_so3(D(rng.uniform(5, 60)) * axis / np.linalg.norm(axis))
        yaw, pitch = math.atan2(start[1, 0], start[0, 0]), math.asin(-start[2, 0])
        roll = math.atan2(start[2, 1], start[2, 2])
        starts[k, idx] = roll, pitch, yaw
    args = (problem.y, problem.params.known)

    def solve(manifold, budget):
        config = SolverConfig(manifold=manifold, max_iterations=budget)
        return least_squares(problem.residual_function, starts, args=args, config=config, local=problem.local)

    def errors(fit):
        return np.array([angle_between(rotation(*x[idx]), truth) for x in fit.x])

    steps = solve(True, 12)
    assert all(s.converged for s in steps.statuses())
    # degrees: 1.2e-6° where the step is solved by LAPACK's Cholesky (stopped by the cost test)
    assert np.all(errors(steps) < 1e-5)
    assert np.all(steps.cost < 1e-12)
    plain = solve(False, 12)  # the same budget: the angles crawl
    assert not any(s.converged for s in plain.statuses())
    assert np.median(errors(plain)) > 1e-3 and np.median(plain.cost) > 1e-6
    patient = solve(False, 100)  # they get there, in about twice the iterations or more
    assert np.median(patient.iterations) >= 2 * np.median(steps.iterations)


@pytest.mark.slow
def test_calibrate_keeps_the_users_angles_at_89_9_degrees(room, survey):
    steps = mbcal.calibrate(room, survey, ["room.*"], restarts=1, suggest=False)  # from the nominal pose
    assert steps.converged and steps.problem.orientation_names == [tuple(ANGLES)]
    for name, true in TILTED.items():
        assert steps.values[name] == pytest.approx(true, abs=1e-7), name  # the angles themselves, not 180° off
    plain = mbcal.calibrate(room, survey, ["room.*"], restarts=1, suggest=False, config=SolverConfig(manifold=False))
    assert steps.solver.iterations[0] < plain.solver.iterations[0]
    budget = SolverConfig(max_iterations=int(steps.solver.iterations[0]))
    assert mbcal.calibrate(room, survey, ["room.*"], restarts=1, suggest=False, config=budget).converged
    crawl = SolverConfig(manifold=False, max_iterations=int(steps.solver.iterations[0]))
    assert not mbcal.calibrate(room, survey, ["room.*"], restarts=1, suggest=False, config=crawl).converged


def test_problems_without_such_orientations_are_solved_bit_for_bit_as_before(room, room_data):
    for estimate in (["room.x", "room.y", "room.yaw"], ["room.*"]):
        problem = Problem(room, room_data, estimate)
        starts = np.tile(problem.params.x0, (4, 1)) + np.linspace(0, 0.01, 4)[:, None]
        args = (problem.y, problem.params.known)
        plain = least_squares(problem.residual_function, starts, args=args)
        offered = least_squares(
            problem.residual_function, starts, args=args, local=problem.local, config=SolverConfig(manifold=False)
        )
        for field in ("x", "cost", "iterations", "status"):
            np.testing.assert_array_equal(getattr(plain, field), getattr(offered, field))
        if problem.local is None:  # nothing to offer: the manifold setting changes nothing
            same = least_squares(problem.residual_function, starts, args=args, local=problem.local)
            np.testing.assert_array_equal(same.x, plain.x)


def test_the_rotation_step_reaches_the_same_estimate_as_angle_steps_away_from_the_lock(room, room_data):
    steps = mbcal.calibrate(room, room_data, ["room.*"], restarts=4, seed=0, suggest=False)
    plain = mbcal.calibrate(
        room, room_data, ["room.*"], restarts=4, seed=0, suggest=False, config=SolverConfig(manifold=False)
    )
    for name, value in plain.values.items():
        assert steps.values[name] == pytest.approx(value, abs=1e-7)
        assert steps.std[name] == pytest.approx(plain.std[name], rel=1e-6)
