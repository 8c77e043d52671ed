"""Marquardt's method for many configurations: the Schur complement (issue 15).

Many calibration problems are *block-arrow* shaped: configurations (board poses, 3-D points of a
bundle adjustment) each own a small block of unknowns that no other configuration touches, and
all share a few unknowns (intrinsics, cameras).  Every residual row depends on one block and on
one *group* of the shared unknowns.  The normal matrix is then

    A = [ U  W ]      U = diag(U_1 … U_B), U_b = J_bᵀ J_b (small: nb × nb)
        [ Wᵀ V ]      V = diag(V_1 … V_G), V_g = J_gᵀ J_g (ks × ks), W the coupling.

Each Marquardt step solves (A + λ·diag(D)) δ = −g by eliminating the blocks: with
Ũ_b = U_b + λ D_b (inverted block by block, vmapped), the reduced system over the shared unknowns
is S δ_s = −g_s + Wᵀ Ũ⁻¹ g_b with S = Ṽ − Wᵀ Ũ⁻¹ W (dense, ns × ns), and δ_b = −Ũ_b⁻¹ (g_b + W_b δ_s)
(Triggs et al., *Bundle adjustment — a modern synthesis*, 2000, section 6.1).  D is Marquardt's
scaling exactly as in :mod:`mbcal.solver` (the running maximum of diag(JᵀJ), floored at 1e-12 of
its largest entry), λ follows the same gain-ratio rule, the same tests stop it: on a small
problem the iterates agree with the dense solver to round-off.

The Jacobian is never formed column by column: because row i depends only on its own block and
group, one forward-mode pass with nb + ks tangents — each block's k-th unknown moved together,
each group's k-th unknown moved together — gives every row's derivatives (a *compressed*
Jacobian, m × (nb + ks), as in Curtis, Powell & Reid's column grouping).  Cost per iteration is
linear in the number of blocks; the largest matrix is ns × ns.

The low-level entry point :func:`least_squares_structured` takes any residual function with the
structure stated explicitly (:class:`Structure`), so problems written outside the model language
— bundle adjustment — use it too (``bench/scale.py`` solves BAL files with it);
:func:`structure_of` finds the structure of a :class:`mbcal.problem.Problem` built from a model
(each configuration's own unknowns, e.g. ``board.roll@view17``, form its block).

Hard bounds take the dense solver's projected steps (its active-set rule, :func:`mbcal.solver.active_set`)
by blocks: a held unknown's rows and columns of the damped blocks become the identity's.

After the solve, :func:`analyze_structured` gives the covariance of the shared unknowns from the
reduced system, the marginal covariance of any block on request, and the unobservable directions
by name — within a block from that block alone, across the shared unknowns from the reduced
system — without ever forming the full n × n matrix; :func:`observability_structured` is the
report's analysis, and :func:`rank_candidates_structured` ranks candidate measurements, by blocks.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from mbcal._jax import as_argument, in_float64, jax, jit, jnp, release_memory
from mbcal.cache import Hasher, exported
from mbcal.datasets.bal import BalProblem
from mbcal.errors import SolverError
from mbcal.observability import (
    Observability,
    ObservabilityConfig,
    PointUncertainty,
    Suggestion,
    _combination,
    _sparse_basis,
    active_sides,
    best_suggestions,
    null_seen,
    point_uncertainties,
)
from mbcal.problem import Problem, RowBlocks, blocks_by_size
from mbcal.solver import (
    LeastSquaresResult,
    LocalParameterisation,
    SolverConfig,
    Status,
    _Identity,
    _solve_spd,
    _solve_step,
    active_at_end,
    active_set,
    hard_limits,
    marquardt_trial,
    projected,
    represented_after,
    represented_in_program,
    restart_loop,
    robust_system,
    step_status,
)

Array = Any

__all__ = [
    "Structure",
    "StructuredAnalysis",
    "least_squares_structured",
    "structure_of",
    "analyze_structured",
    "pays",
    "bal_structure",
    "STRUCTURED_MIN_BLOCKS",
    "DENSE_ANALYSIS_ENTRIES",
    "dense_jacobian",
    "expand_jacobian",
    "square_root_information",
    "compressed_jacobian",
    "check_structure",
    "BlockCovariance",
    "block_point_uncertainties",
    "joint_from_dense",
    "StructuredLinear",
    "observability_structured",
    "held_columns",
    "rank_candidates_structured",
]

STRUCTURED_MIN_BLOCKS = 8
"""``structure="auto"`` uses the Schur complement when a problem has a block structure with at
least this many blocks and its blocks hold most of the unknowns (see :func:`pays`)."""


@dataclass(frozen=True, eq=False)
class Structure:
    """Which unknowns each residual row depends on.

    Attributes
    ----------
    blocks : (B, nb) int
        Positions in x of each block's unknowns (a configuration's own unknowns).
    shared : (G, ks) int
        Positions in x of each group of shared unknowns (G = 1 when every row may depend on all
        of them; a bundle adjustment has one group per camera).
    row_block : (m,) int
        The block each residual row depends on (any block for a row that depends on no block's
        unknowns, such as a prior on a shared unknown: its derivatives there are zero).
    row_group : (m,) int
        The group of shared unknowns each row depends on.
    names : sequence of str, optional
        Names of the unknowns (n), for the analysis.

    Every unknown must be in exactly one block or group.  Compared by identity (the compiled
    program is cached per structure object: keep it between calls).
    """

    blocks: np.ndarray
    shared: np.ndarray
    row_block: np.ndarray
    row_group: np.ndarray
    names: Sequence[str] | None = None
    _derived: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        blocks = np.asarray(self.blocks, dtype=np.int64)
        shared = np.asarray(self.shared, dtype=np.int64)
        row_block = np.asarray(self.row_block, dtype=np.int64).ravel()
        row_group = np.asarray(self.row_group, dtype=np.int64).ravel()
        if blocks.ndim != 2 or shared.ndim != 2 or blocks.shape[1] < 1 or shared.shape[1] < 1:
            raise SolverError("a structure needs blocks (B, nb) and shared groups (G, ks), each with nb, ks ≥ 1")
        if row_block.shape != row_group.shape:
            raise SolverError("row_block and row_group must give one block and one group per residual row")
        n = blocks.size + shared.size
        every = np.concatenate([blocks.ravel(), shared.ravel()])
        if np.any(np.sort(every) != np.arange(n)):
            raise SolverError(f"every unknown 0 … {n - 1} must be in exactly one block or shared group")
        if row_block.size and (row_block.min() < 0 or row_block.max() >= len(blocks)):
            raise SolverError(f"row_block must name blocks 0 … {len(blocks) - 1}")
        if row_group.size and (row_group.min() < 0 or row_group.max() >= len(shared)):
            raise SolverError(f"row_group must name shared groups 0 … {len(shared) - 1}")
        for name, value in (("blocks", blocks), ("shared", shared), ("row_block", row_block), ("row_group", row_group)):
            object.__setattr__(self, name, value)

    # ---- sizes ------------------------------------------------------------------------------------

    @property
    def n(self) -> int:
        return int(self.blocks.size + self.shared.size)

    @property
    def m(self) -> int:
        return int(self.row_block.size)

    @property
    def nb(self) -> int:
        return int(self.blocks.shape[1])

    @property
    def ks(self) -> int:
        return int(self.shared.shape[1])

    @property
    def n_blocks(self) -> int:
        return int(self.blocks.shape[0])

    @property
    def n_groups(self) -> int:
        return int(self.shared.shape[0])

    # ---- index arrays the compiled program uses ---------------------------------------------------

    def arrays(self) -> dict[str, np.ndarray]:
        """Host-side index arrays (computed once): the compressed column of each unknown, the
        (block, group) pairs that rows couple, and the pairs of pairs within one block."""
        if self._derived:
            return self._derived
        nb, ks, B, G = self.nb, self.ks, self.n_blocks, self.n_groups
        slot = np.zeros(self.n, dtype=np.int64)
        slot[self.blocks] = np.arange(nb)[None, :]
        slot[self.shared] = nb + np.arange(ks)[None, :]
        key = self.row_block * G + self.row_group
        pairs, row_pair = np.unique(key, return_inverse=True)
        pair_block, pair_group = pairs // G, pairs % G
        # Pairs of pairs (p, q), p < q, within one block: S gets W_pᵀ Ũ_b⁻¹ W_q at groups (g_p, g_q)
        # and its transpose at (g_q, g_p); the pairs p = q are S's diagonal terms (symmetry halves
        # the work).
        order = np.argsort(pair_block, kind="stable")
        counts = np.bincount(pair_block, minlength=B)
        starts = np.concatenate([[0], np.cumsum(counts)])
        pa, pb = [], []
        for b in np.nonzero(counts > 1)[0]:
            members = order[starts[b] : starts[b + 1]]
            i, j = np.triu_indices(len(members), k=1)
            pa.append(members[i])
            pb.append(members[j])
        pp_a = np.concatenate(pa) if pa else np.zeros(0, dtype=np.int64)
        pp_b = np.concatenate(pb) if pb else np.zeros(0, dtype=np.int64)
        # Each pair's rows in a padded table (P, L) (index m: a zero row), so that the normal
        # equations are batched products, not scatters of every row; when padding would more than
        # double the rows, the rows are scattered instead.
        P, m = len(pairs), self.m
        per_pair = np.bincount(row_pair, minlength=P)
        L = int(per_pair.max()) if m else 1
        padded = P * L <= 2 * m + 64
        pair_rows = np.full((P, L if padded else 1), m, dtype=np.int64)
        if padded:
            by_pair = np.argsort(row_pair, kind="stable")
            first = np.concatenate([[0], np.cumsum(per_pair)])[:-1]
            pair_rows[row_pair[by_pair], np.arange(m) - first[row_pair[by_pair]]] = by_pair
        self._derived.update(
            padded=padded,
            pair_rows=pair_rows,
            slot=slot,
            row_block=self.row_block,
            row_group=self.row_group,
            row_pair=row_pair.astype(np.int64),
            pair_block=pair_block.astype(np.int64),
            pair_group=pair_group.astype(np.int64),
            pp_a=pp_a.astype(np.int64),
            pp_b=pp_b.astype(np.int64),
            pp_target=(pair_group[pp_a] * G + pair_group[pp_b]).astype(np.int64),
            blocks=self.blocks,
            shared=self.shared,
        )
        return self._derived

    def block_of_unknown(self) -> tuple[np.ndarray, np.ndarray]:
        """(n,) the block of each unknown (−1: shared) and (n,) its group (−1: in a block)."""
        block = np.full(self.n, -1, dtype=np.int64)
        group = np.full(self.n, -1, dtype=np.int64)
        block[self.blocks] = np.arange(self.n_blocks)[:, None]
        group[self.shared] = np.arange(self.n_groups)[:, None]
        return block, group


class _Arrays(NamedTuple):
    slot: Array
    row_block: Array
    row_group: Array
    row_pair: Array
    pair_block: Array
    pair_group: Array
    pp_a: Array
    pp_b: Array
    pp_target: Array
    blocks: Array
    shared: Array
    pair_rows: Array


# Up to this many blocks, Ũ_b's inverses come from LAPACK's Cholesky (one batched call), beyond it
# from the unrolled factorisation, vmapped (issue 16).  The unrolled one is a few hundred fused
# scalar operations that XLA compiles and, from the compilation cache, rebuilds at every load:
# for 13 views of a 9 × 6 board (6 × 6 blocks) LAPACK's made the first `calibrate_cameras` of a
# process with an empty cache 2.6–2.9 → 2.1–2.2 s (XLA's compile 2.0–2.3 → 1.6–1.7 s), the second
# process's 0.22 → 0.17–0.19 s and a warm `mbcal calibrate-camera` 0.97–1.00 → 0.91–0.94 s
# (alternating runs), the warm call unchanged.  LAPACK works block by block: on their own, the
# inverses of 8–40 blocks took the same time either way, of 64 blocks 60–124 µs against 60–63,
# of 1,000 blocks 760 µs against 510 and a warm calibration of 1,000 views ~10 % longer (2 cores).
LAPACK_BLOCKS = 32


def _inverse_spd(M: Array) -> Array:
    """Inverse of a small symmetric positive definite matrix (NaN when it is not)."""
    n = M.shape[0]
    return jax.vmap(lambda e: _solve_spd(M, e))(jnp.eye(n))


def _inverse_blocks(M: Array) -> Array:
    """The inverses of a stack (B, k, k) of symmetric positive definite blocks (NaN where a block
    is not): by LAPACK up to :data:`LAPACK_BLOCKS` blocks, else unrolled."""
    B, k = M.shape[0], M.shape[1]
    if B > LAPACK_BLOCKS:
        return jax.vmap(_inverse_spd)(M)
    chol = jnp.linalg.cholesky(M)  # NaN where a block is not positive definite
    half = jax.scipy.linalg.solve_triangular(chol, jnp.broadcast_to(jnp.eye(k), M.shape), lower=True)
    return jax.scipy.linalg.solve_triangular(jnp.swapaxes(chol, 1, 2), half, lower=False)


class _Normal(NamedTuple):
    """The pieces of the normal equations at a point (weighted by the robust loss)."""

    U: Array  # (B, nb, nb)
    V: Array  # (G, ks, ks)
    W: Array  # (P, nb, ks)
    gb: Array  # (B, nb)
    gs: Array  # (G, ks)


def _normal(Jw: Array, rw: Array, ix: _Arrays, B: int, G: int, P: int, nb: int, padded: bool) -> _Normal:
    seg = jax.ops.segment_sum
    if padded:  # each pair's rows gathered: U_p, W_p, V_p and g_p as batched products
        c = Jw.shape[1]
        Jp = jnp.concatenate([Jw, jnp.zeros((1, c))])[ix.pair_rows]  # (P, L, c)
        rp = jnp.concatenate([rw, jnp.zeros(1)])[ix.pair_rows]
        A = jnp.einsum("pli,plj->pij", Jp, Jp)
        g = jnp.einsum("pli,pl->pi", Jp, rp)
        U = seg(A[:, :nb, :nb], ix.pair_block, B)
        gb = seg(g[:, :nb], ix.pair_block, B)
        if G == 1:
            return _Normal(
                U, jnp.sum(A[:, nb:, nb:], axis=0)[None], A[:, :nb, nb:], gb, jnp.sum(g[:, nb:], axis=0)[None]
            )
        V = seg(A[:, nb:, nb:], ix.pair_group, G)
        return _Normal(U, V, A[:, :nb, nb:], gb, seg(g[:, nb:], ix.pair_group, G))
    Jb, Js = Jw[:, :nb], Jw[:, nb:]
    U = seg(Jb[:, :, None] * Jb[:, None, :], ix.row_block, B)
    W = seg(Jb[:, :, None] * Js[:, None, :], ix.row_pair, P)
    gb = seg(Jb * rw[:, None], ix.row_block, B)
    if G == 1:  # one group (a camera's intrinsics): products, not a scatter into one segment
        return _Normal(U, (Js.T @ Js)[None], W, gb, (Js.T @ rw)[None])
    V = seg(Js[:, :, None] * Js[:, None, :], ix.row_group, G)
    gs = seg(Js * rw[:, None], ix.row_group, G)
    return _Normal(U, V, W, gb, gs)


def _segment_sum(xp: Any, data: Any, ids: Any, n: int) -> Any:
    if xp is np:
        out = np.zeros((n, *data.shape[1:]))
        np.add.at(out, ids, data)
        return out
    return jax.ops.segment_sum(data, ids, n)


def _reduced(Ui: Array, Vd: Array, W: Array, ix: _Arrays, G: int, xp: Any = jnp) -> Array:
    """S = Ṽ − Wᵀ Ũ⁻¹ W as a dense (G·ks, G·ks) matrix, from the block inverses Ũ⁻¹ (B, nb, nb).
    ``xp``: jax.numpy inside the solver, numpy for the analysis after it (nothing to dispatch)."""
    ks = Vd.shape[-1]
    Y = xp.einsum("pij,pjk->pik", Ui[ix.pair_block], W)  # Ũ_b⁻¹ W_p
    diagonal = _segment_sum(xp, xp.einsum("pij,pik->pjk", W, Y), ix.pair_group, G)  # W_pᵀ Ũ_b⁻¹ W_p
    contrib = xp.einsum("qij,qik->qjk", W[ix.pp_a], Y[ix.pp_b])  # W_pᵀ Ũ_b⁻¹ W_q, p < q
    off = _segment_sum(xp, contrib, ix.pp_target, G * G).reshape(G, G, ks, ks)
    off = off + off.transpose(1, 0, 3, 2)
    if xp is np:
        off[np.arange(G), np.arange(G)] += diagonal - Vd
        full = off
    else:
        full = off.at[jnp.arange(G), jnp.arange(G)].add(diagonal - Vd)
    return -full.transpose(0, 2, 1, 3).reshape(G * ks, G * ks)


class _State(NamedTuple):
    x: Array
    r: Array
    rw: Array
    Jw: Array  # the normal equations' blocks (_Normal) at x, packed: not the (m, nb + ks) Jacobian
    cost: Array
    x_try: Array
    predicted: Array
    lam: Array
    nu: Array
    Db: Array  # (B, nb)
    Ds: Array  # (G, ks)
    it: Array
    status: Array


def _lm_structured(
    fun: Callable,
    config: SolverConfig,
    x0s: Array,
    args: tuple,
    ix: _Arrays,
    sizes: tuple[int, int, int, int, int, bool],
    local: LocalParameterisation | None,
    bounds: tuple[Array, Array] | None = None,
    represent: bool = True,
) -> tuple:
    """The Schur-complement Marquardt loop from each start (rows of ``x0s``): (x, cost, status,
    iterations) per start (the restarts run in :func:`mbcal.solver.restart_loop`), and with
    ``bounds`` the active bounds at the end (−1, 0, +1 per unknown).

    With bounds, the projected steps of :func:`mbcal.solver.least_squares` by blocks: an active
    unknown's rows and columns of U_b + λD_b (or of V_g + λD_g) become the identity's, its rows or
    columns of W and its entry of g zero, so the Schur complement gives it δ = 0 and the others the
    dense solver's step; the trial point is clipped.  Without bounds the traced program is the
    unbounded one."""
    m, B, G, P, nb, padded = sizes
    loss, scale = config.loss, config.loss_scale
    assert scale is not None
    n = x0s.shape[1]
    ks = ix.shared.shape[1]
    c = nb + ks

    def expand(dc):
        return dc[ix.slot]

    if local is None:

        def evaluate(x):
            return jax.jacfwd(lambda dc: (lambda r: (r, r))(fun(x + expand(dc), *args)), has_aux=True)(jnp.zeros(c))

    else:

        def evaluate(x):
            return jax.jacfwd(lambda dc: (lambda r: (r, r))(local.residual(x, expand(dc), *args)), has_aux=True)(
                jnp.zeros(c)
            )

    shapes = ((B, nb, nb), (G, ks, ks), (P, nb, ks), (B, nb), (G, ks))
    ends = np.cumsum([int(np.prod(shape)) for shape in shapes])

    def weighted(r, J):
        # The loop keeps the normal equations' blocks, not the compressed Jacobian: at 2,000 views
        # (m = 215,764 rows × 15) its carried and selected copies were ~50 MB (issue 15).
        cost, rw, Jw = robust_system(loss, scale, r, J)
        return cost, rw, jnp.concatenate([jnp.ravel(a) for a in _normal(Jw, rw, ix, B, G, P, nb, padded)])

    def unpack(packed):
        return _Normal(*(packed[a:b].reshape(shape) for a, b, shape in zip([0, *ends[:-1]], ends, shapes)))

    def free_of(x, N):
        """(B, nb), (G, ks): the unknowns not held at an active bound (the dense solver's rule)."""
        assert bounds is not None
        lo, up = bounds
        fb = ~active_set(x[ix.blocks], N.gb, lo[ix.blocks], up[ix.blocks])
        fs = ~active_set(x[ix.shared], N.gs, lo[ix.shared], up[ix.shared])
        return fb, fs

    def gradient_small(rw, N, x):
        # ‖J_j‖² is the diagonal of JᵀJ: of U for block unknowns, of V for shared ones.
        colb = jnp.sqrt(jnp.diagonal(N.U, axis1=1, axis2=2))
        cols = jnp.sqrt(jnp.diagonal(N.V, axis1=1, axis2=2))
        gb, gs = N.gb, N.gs
        if bounds is not None:  # the projected gradient
            fb, fs = free_of(x, N)
            gb, gs = jnp.where(fb, gb, 0.0), jnp.where(fs, gs, 0.0)
        rn = jnp.sqrt(jnp.sum(rw * rw))

        def cosine(g, col):
            denom = col * rn
            return jnp.max(jnp.where(denom > 0, jnp.abs(g) / jnp.where(denom > 0, denom, 1.0), 0.0), initial=0.0)

        return jnp.maximum(cosine(gb, colb), cosine(gs, cols)) <= config.gtol

    def start(x0):
        return _State(
            x=x0,
            r=jnp.zeros(m),
            rw=jnp.zeros(m),
            Jw=jnp.zeros(int(ends[-1])),
            cost=jnp.asarray(jnp.inf),
            x_try=x0,
            predicted=jnp.asarray(0.0),
            lam=jnp.asarray(config.lambda_init),
            nu=jnp.asarray(2.0),
            Db=jnp.zeros((B, nb)),
            Ds=jnp.zeros((G, ks)),
            it=jnp.int32(0),
            status=jnp.int32(0),
        )

    def body(state: _State) -> _State:
        x, r, rw, Jw, cost, x_try, predicted, lam, nu, Db, Ds, it, status = state
        trial = marquardt_trial(evaluate, weighted, loss, scale, state)
        first, ok, accept, actual = trial.first, trial.ok, trial.accept, trial.actual
        x, r, rw, Jw, cost, lam, nu = trial.x, trial.r, trial.rw, trial.Jw, trial.cost, trial.lam, trial.nu
        it = it + 1
        N = unpack(Jw)
        status = jnp.where(first & ~ok, Status.NON_FINITE, 0)
        tiny = trial.resolved | ((actual <= config.ftol * cost) & (predicted <= config.ftol * cost))
        status = jnp.where((status == 0) & accept & ~first & tiny, Status.CONVERGED_COST, status)
        status = jnp.where((status == 0) & accept & (cost == 0), Status.CONVERGED_COST, status)
        status = jnp.where((status == 0) & accept & gradient_small(rw, N, x), Status.CONVERGED_GRADIENT, status)
        # Marquardt's scaling, as the dense solver: running maximum of diag(JᵀJ), floored.
        Db = jnp.maximum(Db, jnp.diagonal(N.U, axis1=1, axis2=2))
        Ds = jnp.maximum(Ds, jnp.diagonal(N.V, axis1=1, axis2=2))
        floor = 1e-12 * jnp.maximum(jnp.maximum(jnp.max(Db), jnp.max(Ds)), 1e-300)
        Dcb, Dcs = jnp.maximum(Db, floor), jnp.maximum(Ds, floor)
        Ud = N.U + lam * jax.vmap(jnp.diag)(Dcb)
        Vd = N.V + lam * jax.vmap(jnp.diag)(Dcs)
        W, gb, gs = N.W, N.gb, N.gs
        if bounds is not None:
            # Active unknowns are held: their rows and columns become the identity's, as densely.
            fb, fs = free_of(x, N)
            Ud = jnp.where(fb[:, :, None] & fb[:, None, :], Ud, 0.0) + jax.vmap(jnp.diag)(jnp.where(fb, 0.0, 1.0))
            Vd = jnp.where(fs[:, :, None] & fs[:, None, :], Vd, 0.0) + jax.vmap(jnp.diag)(jnp.where(fs, 0.0, 1.0))
            W = jnp.where(fb[ix.pair_block][:, :, None] & fs[ix.pair_group][:, None, :], W, 0.0)
            gb, gs = jnp.where(fb, gb, 0.0), jnp.where(fs, gs, 0.0)
        Ui = _inverse_blocks(Ud)  # (B, nb, nb)
        S = _reduced(Ui, Vd, W, ix, G)
        ub = jnp.einsum("bij,bj->bi", Ui, gb)  # Ũ⁻¹ g_b
        rhs = -gs + jax.ops.segment_sum(jnp.einsum("pij,pi->pj", W, ub[ix.pair_block]), ix.pair_group, G)
        # LAPACK's Cholesky: one small system per restart; unrolled (as the blocks' inverses, which
        # it vectorises across blocks) its 9 × 9 took 0.3 s of a cold first call's compile (issue 16).
        ds = _solve_step(S, rhs.reshape(-1)).reshape(G, ks)
        Wds = jax.ops.segment_sum(jnp.einsum("pij,pj->pi", W, ds[ix.pair_group]), ix.pair_block, B)
        db = -jnp.einsum("bij,bj->bi", Ui, gb + Wds)
        finite_step = jnp.all(jnp.isfinite(db)) & jnp.all(jnp.isfinite(ds))
        db = jnp.where(finite_step, db, 0.0)
        ds = jnp.where(finite_step, ds, 0.0)
        delta = jnp.zeros(n).at[ix.blocks].set(db).at[ix.shared].set(ds)
        tb, ts = db, ds  # the step taken: δ, or with bounds its projection
        if bounds is not None:
            taken = projected(x, delta, bounds[0], bounds[1])
            tb, ts = taken[ix.blocks], taken[ix.shared]
        # The linear model's decrease: −(2 gᵀδ + ‖J δ‖²), ‖J δ‖² = δᵀ JᵀJ δ from the blocks.
        JdJd = (
            jnp.einsum("bi,bij,bj->", tb, N.U, tb)
            + 2.0 * jnp.einsum("pi,pij,pj->", tb[ix.pair_block], N.W, ts[ix.pair_group])
            + jnp.einsum("gi,gij,gj->", ts, N.V, ts)
        )
        gd = jnp.sum(N.gb * tb) + jnp.sum(N.gs * ts)
        predicted = jnp.where(finite_step, -(2.0 * gd + JdJd), -1.0)
        status = step_status(config, status, finite_step, delta, x, lam, it)
        x_next = x + delta if local is None else local.plus(x, delta)
        if bounds is not None:
            x_next = jnp.clip(x_next, bounds[0], bounds[1])
        x_try = jnp.where(finite_step, x_next, x)
        return _State(x, r, rw, Jw, cost, x_try, predicted, lam, nu, Db, Ds, it, status.astype(jnp.int32))

    def finish(final: _State, x0: Array) -> tuple:
        total = robust_system(loss, scale, final.r, jnp.zeros((m, 1)))[0]
        cost = jnp.where(final.status == Status.NON_FINITE, jnp.inf, total)
        x = local.represent(final.x, x0) if local is not None and represent else final.x  # (or represent_after)
        if bounds is None:
            return x, cost, final.status, final.it
        N = unpack(final.Jw)
        col = jnp.zeros(n).at[ix.blocks].set(jnp.diagonal(N.U, axis1=1, axis2=2))
        col = jnp.sqrt(col.at[ix.shared].set(jnp.diagonal(N.V, axis1=1, axis2=2)))
        g = jnp.zeros(n).at[ix.blocks].set(N.gb).at[ix.shared].set(N.gs)
        rn = jnp.sqrt(jnp.sum(final.rw * final.rw))
        active = active_at_end(final.x, g, col, rn, bounds[0], bounds[1], config.gtol)
        return x, cost, final.status, final.it, active

    final = restart_loop(lambda s: s.status == 0, body, jax.vmap(start)(x0s))
    return jax.vmap(finish)(final, x0s)


# Few programs, as in mbcal.solver: each compiled program holds hundreds of XLA's memory maps, and a
# long process that kept dozens alive came near the kernel's limit, where XLA:CPU crashes (issue 16).
@functools.lru_cache(maxsize=8)
def _compiled(
    fun: Callable,
    config: SolverConfig,
    sizes: tuple[int, ...],
    wrapped: _Identity | None,
    bounded: bool = False,
    represent: bool = True,
) -> Callable:
    local = None if wrapped is None else wrapped.obj
    if not bounded:  # the unbounded program, as it always was

        def batch(x0s, args, ix):
            return _lm_structured(fun, config, x0s, args, _Arrays(*ix), sizes, local, None, represent)  # type: ignore[arg-type]

        return jit(batch)

    def batch_bounded(x0s, args, ix, lower, upper):
        return _lm_structured(fun, config, x0s, args, _Arrays(*ix), sizes, local, (lower, upper), represent)  # type: ignore[arg-type]

    return jit(batch_bounded)


@in_float64
def least_squares_structured(
    fun: Callable[..., Array],
    x0: Array,
    structure: Structure,
    *,
    args: tuple = (),
    config: SolverConfig | None = None,
    local: LocalParameterisation | None = None,
    cache_key: str | None = None,
    bounds: tuple[Array, Array] | None = None,
) -> LeastSquaresResult:
    """Minimise ``Σ ρ(r_i²)`` for ``r = fun(x, *args)`` by Schur-complement Marquardt steps.

    The same contract as :func:`mbcal.solver.least_squares` (one start or a batch of restarts,
    the same :class:`~mbcal.solver.SolverConfig`, statuses and result), plus the ``structure``:
    row i of ``fun`` must depend only on the unknowns of block ``structure.row_block[i]`` and of
    shared group ``structure.row_group[i]`` (a row that broke the promise would get a wrong
    Jacobian: :func:`check_structure` tests it on a small problem).  ``bounds``: hard bounds
    (lower, upper), as for the dense solver — the same projected steps, taken by blocks, the same
    validation, starts moved inside, and the result's ``active``; None or all infinite: the
    unbounded program.  ``cache_key``: as for the dense solver, a fingerprint of everything
    ``fun`` (and ``local``) depends on besides ``args``: the traced program is saved and a later
    process reuses it without tracing (issue 16).
    """
    config = config or SolverConfig()
    x0 = np.atleast_2d(np.asarray(x0, dtype=float))
    if x0.shape[1] != structure.n:
        raise SolverError(f"x0 has {x0.shape[1]} unknowns; the structure names {structure.n}")
    limits, x0 = hard_limits(bounds, x0)
    # NumPy arguments go straight into the compiled program (~3 µs; jax.device_put costs ~30 µs
    # each, jnp.asarray compiles a program per shape: issue 16)
    args = tuple(as_argument(a) for a in args)
    local = local if config.manifold else None
    in_program = represented_in_program(local)  # decided once: the program and what follows it agree
    ix = structure.arrays()
    sizes = (structure.m, structure.n_blocks, structure.n_groups, len(ix["pair_block"]), structure.nb, ix["padded"])
    program = _compiled(fun, config, sizes, None if local is None else _Identity(local), limits is not None, in_program)
    arrays = tuple(ix[name] for name in _Arrays._fields)
    example: tuple[Any, ...] = (x0, args, arrays)
    if limits is not None:
        example += limits
    if cache_key is not None:  # the structure's index arrays are arguments: only their shapes enter
        key = Hasher().add("structured", cache_key, repr(config), sizes, x0.shape)
        key.add([(a.shape, str(a.dtype)) for a in args], [(a.shape, str(a.dtype)) for a in arrays])
        if limits is not None:
            key.add("bounded")
        if local is not None:
            key.add("local", type(local).__module__, type(local).__qualname__, in_program)
        program = exported(key.hexdigest(), program, *example)
    out = program(*example)
    x, cost, status, it = (np.asarray(v) for v in out[:4])
    active = np.asarray(out[4]) if limits is not None else None
    del out
    if local is not None and not in_program:  # each result in the coordinates nearest its start
        x = represented_after(local, x, x0)
    release_memory(8 * structure.m * (structure.nb + structure.ks) * len(x0))  # the program's m × c buffers
    finite = np.isfinite(cost)
    best = int(np.argmin(np.where(finite, cost, np.inf))) if finite.any() else -1
    return LeastSquaresResult(
        x=x, x0=x0, cost=cost, status=status, iterations=it, best=best, config=config, active=active
    )


@functools.lru_cache(maxsize=8)
def _compressed_program(fun: Callable, c: int, wrapped: _Identity | None) -> Callable:
    local = None if wrapped is None else wrapped.obj

    def jac(x, slot, args):
        def f(dc):
            r = fun(x + dc[slot], *args) if local is None else local.residual(x, dc[slot], *args)
            return r, r

        return jax.jacfwd(f, has_aux=True)(jnp.zeros(c))

    return jit(jac)


def compressed_jacobian(
    fun: Callable[..., Array],
    x: Array,
    structure: Structure,
    args: tuple = (),
    local: LocalParameterisation | None = None,
    cache_key: str | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(r, Jc): the residual at x and its compressed Jacobian (m, nb + ks): row i's derivatives
    with respect to its own block's unknowns (first nb columns) and its group's (last ks).
    ``cache_key``: as for :func:`least_squares_structured` (a second process loads the program
    instead of tracing it: ~0.15 s of a command-line calibration, issue 16)."""
    c = structure.nb + structure.ks
    program = _compressed_program(fun, c, None if local is None else _Identity(local))
    args = tuple(as_argument(a) for a in args)
    example = (np.asarray(x, dtype=float), structure.arrays()["slot"], args)
    if cache_key is not None:
        key = Hasher().add("compressed", cache_key, c, example[0].shape, example[1].shape)
        key.add([(a.shape, str(a.dtype)) for a in args])
        if local is not None:
            key.add("local", type(local).__module__, type(local).__qualname__)
        program = exported(key.hexdigest(), program, *example)
    J, r = program(*example)
    release_memory(8 * structure.m * c)  # the program's temporaries
    return np.asarray(r), np.asarray(J)


def check_structure(fun: Callable[..., Array], x: Array, structure: Structure, args: tuple = ()) -> None:
    """Raise a :class:`SolverError` naming a row that depends on an unknown outside its block and
    group (compares the full Jacobian's pattern: for small problems and tests only)."""
    J = np.asarray(jax.jacfwd(lambda z: fun(z, *args))(jnp.asarray(x, dtype=float)))
    block, group = structure.block_of_unknown()
    allowed = (block[None, :] == structure.row_block[:, None]) | (group[None, :] == structure.row_group[:, None])
    bad = np.argwhere((J != 0) & ~allowed)
    if len(bad):
        i, j = bad[0]
        raise SolverError(
            f"residual row {i} depends on unknown {j}, which is neither in its block "
            f"{structure.row_block[i]} nor in its shared group {structure.row_group[i]}"
        )


# ---- structure of a model-built problem ----------------------------------------------------------


def block_point_uncertainties(
    problem: Problem,
    structure: Structure,
    joint: np.ndarray,
    x: np.ndarray,
    cfg_idx: np.ndarray,
    idx: np.ndarray,
    items: Sequence[tuple[str, str, str | None]],
    eyes: Sequence[np.ndarray | None] | np.ndarray,
) -> Sequence[PointUncertainty]:
    """Point uncertainties of a problem with a block per configuration (:func:`structure_of`)
    from each point's compressed Jacobian and its block's joint covariance with the shared
    unknowns ``joint`` (B, nb + ks, nb + ks): k × 3 × (nb + ks) numbers, where the dense way
    formed k × 3 × n (100 views of a board: 5,398 points × 3 × 609, 79 MB and 70 ms)."""
    if not len(items):
        return []
    P, Jp = problem.point_jacobian_compressed(x, cfg_idx, idx, structure.arrays()["slot"])
    used = np.any(Jp != 0, axis=1)  # (k, c)
    bad = ~np.isfinite(np.diagonal(joint, axis1=1, axis2=2))  # (B, c): the unobservable unknowns
    finite = np.where(np.isfinite(joint), joint, 0.0)
    covs = np.empty((len(items), 3, 3))
    for a in range(0, len(items), 8192):  # in chunks: the gathered (k, c, c) would be large
        k = slice(a, a + 8192)
        covs[k] = Jp[k] @ finite[cfg_idx[k]] @ np.swapaxes(Jp[k], 1, 2)  # batched products (einsum: 3× slower)
    covs[np.any(used & bad[cfg_idx], axis=1)] = np.inf
    return point_uncertainties(items, P, None, None, eyes, covariances=covs)


def joint_from_dense(structure: Structure, covariance: np.ndarray) -> np.ndarray:
    """Each block's joint covariance with the shared unknowns (B, nb + ks, nb + ks), read from a
    dense covariance (what :meth:`BlockCovariance.joint` computes from the factors)."""
    s = structure
    idx = np.concatenate([s.blocks, np.broadcast_to(s.shared[0], (s.n_blocks, s.ks))], axis=1)
    return np.asarray(covariance, dtype=float)[idx[:, :, None], idx[:, None, :]]


def structure_of(problem: Problem) -> Structure | None:
    """The block structure of a calibration problem, or None when it has none worth using.

    Each configuration's own unknowns (per-configuration parameters such as ``board.x@view3``)
    form its block; every other unknown is shared (one group).  Needs the same number of own
    unknowns in every configuration and at least one shared unknown; a row belongs to the
    configuration of its measurement (a prior row to the configuration of its unknown).
    """
    params = problem.params
    source = params._source  # (C, n_params): position in x, −1 when known
    C = source.shape[0]
    if C < 2:
        return None
    own_columns = []
    shared_positions: list[int] = []
    for k in range(source.shape[1]):
        column = source[:, k]
        if np.all(column < 0):
            continue
        if np.all(column == column[0]):
            shared_positions.append(int(column[0]))
        elif np.all(column >= 0) and len(np.unique(column)) == C:
            own_columns.append(column)
        else:
            return None  # unknown in some configurations only, or shared by a few
    if not own_columns or not shared_positions:
        return None
    blocks = np.stack(own_columns, axis=1)  # (C, nb)
    shared = np.array(sorted(set(shared_positions)), dtype=np.int64)[None, :]
    if blocks.size + shared.size != params.size:
        return None
    row_block = np.zeros(problem.n_residuals, dtype=np.int64)
    for g in problem.groups:  # a row's block: its measurement's configuration
        row_block[g.start : g.start + g.rows] = np.repeat(g.batch.config, g.model.size)
    block_of = np.full(params.size, -1, dtype=np.int64)
    block_of[blocks] = np.arange(len(blocks))[:, None]
    for k, j in enumerate(problem.prior_index):
        row_block[problem.size + k] = max(block_of[j], 0)
    names = params.names
    return Structure(blocks, shared, row_block, np.zeros(problem.n_residuals, dtype=np.int64), names=names)


def bal_structure(bal: BalProblem) -> Structure:
    """The structure of a bundle adjustment (:func:`mbcal.datasets.bal.read_bal`): each point is a
    block of 3 unknowns, each camera a group of 9 shared ones; observation i gives rows 2i, 2i+1."""
    C, N = bal.n_cameras, bal.n_points
    shared = np.arange(9 * C).reshape(C, 9)
    blocks = 9 * C + np.arange(3 * N).reshape(N, 3)
    names = [f"camera{c}.{k}" for c in range(C) for k in ("rx", "ry", "rz", "tx", "ty", "tz", "f", "k1", "k2")]
    names += [f"point{p}.{k}" for p in range(N) for k in "xyz"]
    return Structure(blocks, shared, np.repeat(bal.point_index, 2), np.repeat(bal.camera_index, 2), names=names)


def pays(structure: Structure | None) -> bool:
    """The rule of ``structure="auto"``: the Schur complement is used when the problem has a
    block structure with at least :data:`STRUCTURED_MIN_BLOCKS` blocks whose unknowns outnumber
    the shared ones (then the dense normal matrix, (B·nb + ns)², dwarfs the reduced one, ns²)."""
    return (
        structure is not None
        and structure.n_blocks >= STRUCTURED_MIN_BLOCKS
        and structure.blocks.size > structure.shared.size
    )


# ---- uncertainty and observability at scale ------------------------------------------------------


@dataclass
class StructuredAnalysis:
    """Covariance and observability of a block-structured problem at a solution.

    Attributes
    ----------
    shared_covariance : (ns, ns)
        Covariance of the shared unknowns (in the order of ``structure.shared.ravel()``): the
        inverse of the reduced system S = V − Wᵀ U⁻¹ W (pseudo-inverse where rank deficient).
    shared_std : (ns,)
    block_std : (B, nb)
        σ of every block unknown (the diagonal of each block's marginal covariance).
    rank : int
        Rank of the whole Jacobian: each block's own rank plus the reduced system's.
    unobservable : list of dict
        One per null direction: ``{"where": "shared" | "block <b>", "combination": {name: weight}}``.
    """

    structure: Structure
    shared_covariance: np.ndarray
    shared_std: np.ndarray
    block_std: np.ndarray
    rank: int
    unobservable: list[dict[str, Any]]
    _U_pinv: np.ndarray = field(repr=False)
    _W: np.ndarray = field(repr=False)
    _scale: float = 1.0

    def block_covariance(self, b: int) -> np.ndarray:
        """The marginal covariance (nb, nb) of block b's unknowns:
        U_b⁻¹ + U_b⁻¹ W_b S⁻¹ W_bᵀ U_b⁻¹, with W_b the block's coupling to all shared unknowns."""
        Ui = self._U_pinv[b]  # both scaled by the same χ² factor c: c·U⁻¹ + (cU⁻¹) W (cS⁻¹) Wᵀ (cU⁻¹) / c²
        Wb = self._block_coupling(b)
        c = self._scale
        return Ui + Ui @ Wb @ self.shared_covariance @ Wb.T @ Ui / (c * c)

    def _block_coupling(self, b: int) -> np.ndarray:
        ix = self.structure.arrays()
        G, ks = self.structure.n_groups, self.structure.ks
        Wb = np.zeros((self.structure.nb, G * ks))
        for p in np.nonzero(ix["pair_block"] == b)[0]:
            g = ix["pair_group"][p]
            Wb[:, g * ks : (g + 1) * ks] += self._W[p]
        return Wb

    @property
    def observable(self) -> bool:
        return not self.unobservable


def _pinv_sym(M: np.ndarray, rtol: float) -> tuple[np.ndarray, int, np.ndarray]:
    """Pseudo-inverse of a symmetric PSD matrix, with its rank and null vectors, judged on the
    matrix scaled to unit diagonal (so units do not decide the rank)."""
    inv, rank, null = _pinv_sym_stack(M[None], rtol)
    return inv[0], int(rank[0]), null[0]


def _pinv_sym_stack(M: np.ndarray, rtol: float) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """:func:`_pinv_sym` of a stack (B, k, k) in one batched eigendecomposition: the inverses
    (B, k, k), the ranks (B,) and each matrix's null vectors (k, k − rank)."""
    d = np.sqrt(np.clip(np.einsum("bii->bi", M), 0, None))
    dn = np.where(d > 0, d, 1.0)
    Ms = M / dn[:, :, None] / dn[:, None, :]
    w, v = np.linalg.eigh(Ms)
    top = np.maximum(w.max(axis=1, initial=0.0), 1e-300)
    keep = w > rtol * top[:, None]
    inv_w = np.where(keep, 1.0 / np.where(keep, w, 1.0), 0.0)
    inv_s = np.einsum("bik,bk,bjk->bij", v, inv_w, v)
    k = M.shape[1]
    nulls = [np.zeros((k, 0))] * len(M)
    for b in np.flatnonzero(~keep.all(axis=1)):
        null = v[b][:, ~keep[b]] / dn[b][:, None]
        nulls[b] = null / np.maximum(np.linalg.norm(null, axis=0), 1e-300)
    return inv_s / dn[:, :, None] / dn[:, None, :], keep.sum(axis=1), nulls


def _segment_products(A: np.ndarray, C: np.ndarray, segment: np.ndarray, count: int) -> np.ndarray:
    """(count, a, c): Σ over the rows of each segment of A_iᵀ C_i — rows sorted by segment once,
    then summed in chunks of about 2 M products (never the whole (m, a, c) array)."""
    a, c = A.shape[1], C.shape[1]
    out = np.zeros((count, a, c))
    order = np.argsort(segment, kind="stable")
    seg = segment[order]
    step = max(1, 2_000_000 // max(a * c, 1))
    for s in range(0, len(order), step):
        rows, sg = order[s : s + step], seg[s : s + step]
        products = (A[rows][:, :, None] * C[rows][:, None, :]).reshape(len(rows), a * c)
        starts = np.flatnonzero(np.r_[True, sg[1:] != sg[:-1]])
        out[sg[starts]] += np.add.reduceat(products, starts, axis=0).reshape(-1, a, c)
    return out


def _blocks_of_normal(Jc: np.ndarray, structure: Structure, ix: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """U (B, nb, nb), V (G, ks, ks), W (P, nb, ks) of JᵀJ from the compressed Jacobian, in NumPy:
    when the structure is padded (every pair's rows gathered, few rows each) by one batched
    product per pair, else by segment sums."""
    nb, B, G = structure.nb, structure.n_blocks, structure.n_groups
    P = len(ix["pair_block"])
    if ix["padded"]:
        # (P, L, c) gathered straight from Jc, the padding (index m) zeroed after, a few hundred
        # pairs at a time: no padded copy of the whole Jc (2,000 views: 26 MB less at the peak)
        rows = ix["pair_rows"]
        c = Jc.shape[1]
        A = np.empty((len(rows), c, c))
        step = max(1, (1 << 19) // max(1, rows.shape[1] * c))  # ~4 MB of float64 per chunk
        for a in range(0, len(rows), step):
            r = rows[a : a + step]
            Jp = np.take(Jc, np.minimum(r, len(Jc) - 1), axis=0, out=np.empty((*r.shape, c)))
            Jp[r == len(Jc)] = 0.0
            np.matmul(Jp.transpose(0, 2, 1), Jp, out=A[a : a + step])
        U = _segment_sum(np, A[:, :nb, :nb], ix["pair_block"], B)
        V = _segment_sum(np, A[:, nb:, nb:], ix["pair_group"], G)
        return U, V, A[:, :nb, nb:].copy()
    Jb, Js = Jc[:, :nb], Jc[:, nb:]
    U = _segment_products(Jb, Jb, structure.row_block, B)
    V = _segment_products(Js, Js, structure.row_group, G)
    W = _segment_products(Jb, Js, ix["row_pair"], P)
    return U, V, W


def analyze_structured(
    fun: Callable[..., Array],
    x: Array,
    structure: Structure,
    *,
    args: tuple = (),
    local: LocalParameterisation | None = None,
    rtol: float = 1e-10,
    chi2_scale: float = 1.0,
) -> StructuredAnalysis:
    """Covariance and unobservable directions at x without the full n × n matrix.

    A block whose own columns are dependent (a board seen edge-on, a point seen once) is named
    with its null combination; the shared unknowns' null directions come from the reduced system
    (built with each block's pseudo-inverse).  ``chi2_scale`` multiplies the covariance.
    """
    _, Jc = compressed_jacobian(fun, x, structure, args, local)
    nb, G, ks = structure.nb, structure.n_groups, structure.ks
    ix = structure.arrays()
    U, V, W = _blocks_of_normal(Jc, structure, ix)
    names = list(structure.names) if structure.names is not None else [f"x[{j}]" for j in range(structure.n)]
    unobservable: list[dict[str, Any]] = []
    U_pinv, ranks, nulls = _pinv_sym_stack(U, rtol)
    rank = int(ranks.sum())
    for b, null in enumerate(nulls):
        for k in range(null.shape[1]):
            combo = {names[structure.blocks[b, i]]: float(null[i, k]) for i in range(nb) if abs(null[i, k]) > 1e-6}
            unobservable.append({"where": f"block {b}", "combination": combo})
    arrays = _Arrays(*(np.asarray(ix[k]) for k in _Arrays._fields))
    S = _reduced(U_pinv, V, W, arrays, G, xp=np)
    S = 0.5 * (S + S.T)
    S_inv, rk_s, null_s = _pinv_sym(S, rtol)
    rank += rk_s
    shared_names = [names[j] for j in structure.shared.ravel()]
    for k in range(null_s.shape[1]):
        combo = {shared_names[i]: float(null_s[i, k]) for i in range(len(shared_names)) if abs(null_s[i, k]) > 1e-6}
        unobservable.append({"where": "shared", "combination": combo})
    # σ of every block unknown: diag(U⁻¹) + diag(U⁻¹ W_b S⁻¹ W_bᵀ U⁻¹), summed over pairs of pairs.
    Y = np.einsum("pij,pjk->pik", U_pinv[ix["pair_block"]], W)  # (P, nb, ks): U_b⁻¹ W_p
    S_blocks = S_inv.reshape(G, ks, G, ks).transpose(0, 2, 1, 3)  # (G, G, ks, ks)
    gp, gq = ix["pair_group"][ix["pp_a"]], ix["pair_group"][ix["pp_b"]]
    inner = np.einsum("qik,qkl,qil->qi", Y[ix["pp_a"]], S_blocks[gp, gq], Y[ix["pp_b"]])  # p < q: twice
    g = ix["pair_group"]
    own = np.einsum("pik,pkl,pil->pi", Y, S_blocks[g, g], Y)  # p = q
    block_var = np.einsum("bii->bi", U_pinv).copy()  # einsum gives a view of the diagonal
    np.add.at(block_var, ix["pair_block"][ix["pp_a"]], 2.0 * inner)
    np.add.at(block_var, ix["pair_block"], own)
    temporaries = Jc.nbytes
    del Jc, Y
    release_memory(temporaries)
    return StructuredAnalysis(
        structure=structure,
        shared_covariance=S_inv * chi2_scale,
        shared_std=np.sqrt(np.clip(np.diag(S_inv) * chi2_scale, 0, None)),
        block_std=np.sqrt(np.clip(block_var * chi2_scale, 0, None)),
        rank=rank,
        unobservable=unobservable,
        _U_pinv=U_pinv * chi2_scale,
        _W=W,
        _scale=chi2_scale,
    )


def dense_jacobian(
    fun: Callable[..., Array],
    x: Array,
    structure: Structure,
    args: tuple = (),
    local: LocalParameterisation | None = None,
    cache_key: str | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(r, J, Jc): the residual, the full m × n Jacobian scattered from the compressed one Jc (one
    forward pass with nb + ks tangents instead of n), and Jc itself.  For the dense analysis of
    problems of moderate size (see :data:`DENSE_ANALYSIS_ENTRIES`)."""
    r, Jc = compressed_jacobian(fun, x, structure, args, local, cache_key)
    return r, expand_jacobian(Jc, structure), Jc


def expand_jacobian(Jc: np.ndarray, structure: Structure, start: int = 0) -> np.ndarray:
    """The m × n Jacobian rows ``start … start + len(Jc)`` scattered from their compressed rows."""
    nb = structure.nb
    where = slice(start, start + len(Jc))
    J = np.zeros((len(Jc), structure.n))
    rows = np.arange(len(Jc))[:, None]
    J[rows, structure.blocks[structure.row_block[where]]] = Jc[:, :nb]
    J[rows, structure.shared[structure.row_group[where]]] = Jc[:, nb:]
    return J


def square_root_information(Jc: np.ndarray, row_block: np.ndarray, structure: Structure) -> np.ndarray:
    """An n × n matrix R with RᵀR = JᵀJ for the rows of compressed Jacobian ``Jc`` (their blocks in
    ``row_block``), by orthogonal transformations only (so R has J's singular values and right
    singular vectors to round-off): a QR factorisation of each block's rows [J_b | J_s], then one
    of the stacked shared remainders.  One group of shared unknowns only (the structure of a
    model-built problem).  The observability analysis of a structured problem works on R, an
    n × n matrix, instead of the m × n Jacobian."""
    if structure.n_groups != 1:
        raise SolverError("square_root_information needs one group of shared unknowns")
    nb, ks, B, n = structure.nb, structure.ks, structure.n_blocks, structure.n
    c = nb + ks
    table = _block_table(Jc, row_block, B, c)
    R: Any = np.linalg.qr(table, mode="r")  # (B, c, c): only R (numpy's stubs type the result loosely)
    Rs: Any = np.linalg.qr(np.ascontiguousarray(R[:, nb:, nb:]).reshape(B * ks, ks), mode="r")
    out = np.zeros((n, n))
    blocks, shared = structure.blocks, structure.shared[0]
    out[blocks[:, :, None], blocks[:, None, :]] = R[:, :nb, :nb]
    out[blocks[:, :, None], shared[None, None, :]] = R[:, :nb, nb:]
    out[shared[:, None], shared[None, :]] = Rs
    return out


def _block_table(Jc: np.ndarray, row_block: np.ndarray, B: int, at_least: int = 1) -> np.ndarray:
    """(B, L, c): each block's rows of a compressed Jacobian, padded with zero rows (they change
    neither JᵀJ nor a QR or SVD factor), L ≥ ``at_least``."""
    m, c = Jc.shape
    counts = np.bincount(row_block, minlength=B)
    L = max(int(counts.max()) if m else 0, at_least)
    order = np.argsort(row_block, kind="stable")
    first = np.concatenate([[0], np.cumsum(counts)])[:-1]
    within = np.empty(m, dtype=np.int64)  # each row's place among its block's rows
    within[order] = np.arange(m) - first[row_block[order]]
    table = np.zeros((B, L, c))
    table[row_block, within] = Jc  # (not Jc[order]: a copy of the m × c rows)
    return table


DENSE_ANALYSIS_ENTRIES = 40_000_000
"""The largest m × n Jacobian (320 MB) that :func:`mbcal.calibrate` analyses densely after a
structured solve (``CalibrateOptions.analysis="auto"``); beyond it the report (rank, covariance,
fit verdict, point uncertainties) is computed from the blocks (:func:`observability_structured`,
:class:`StructuredLinear`), without any n × n or m × n matrix."""


# ---- the report's analysis without the full matrix (calibrate at scale) ------------------------------
#
# Beyond DENSE_ANALYSIS_ENTRIES, `calibrate` analyses a structured problem (one group of shared
# unknowns) from its compressed Jacobian: (JᵀJ)⁺ by blocks, the covariance as a lazy
# `BlockCovariance`, extreme eigenvalues by Lanczos iterations, and the fit verdict's linear algebra
# (refit residuals, leverages, deletion statistics) from the same pieces.

_LANCZOS_DENSE = 64  # below this many unknowns an operator is formed and decomposed exactly


class _BlockFactor:
    """(JᵀJ)⁺ of the rows of a compressed Jacobian with one shared group, by blocks (without
    forming JᵀJ, so that rank decisions see J's singular values, not their squares):

    - each block's rows J_b = P Σ Qᵀ (a batched SVD of the rows padded per block): U_b⁺ = Q Σ⁻² Qᵀ
      over the singular values above ``rtol · smax``, the block's own null directions Q₀;
    - the shared remainder Z = (I − P Pᵀ) J_s stacked over the blocks, whose SVD gives
      S = ZᵀZ = V − Σ W_bᵀ U_b⁺ W_b (the reduced system) and S⁺, and Y_b = U_b⁺ W_b.

    ``solve`` applies the generalised inverse C = [[U⁺ + Y S⁺ Yᵀ, −Y S⁺], [−S⁺ Yᵀ, S⁺]] (the
    inverse when J has full rank; with the null space projected out, the pseudo-inverse)."""

    def __init__(
        self,
        Jc: np.ndarray,
        row_block: np.ndarray,
        B: int,
        nb: int,
        rtol: float,
        exact: bool = False,
        scales: tuple[np.ndarray, np.ndarray] | None = None,
    ):
        """``exact``: judge the rank relative to J's largest singular value (Lanczos iterations on
        JᵀJ), as the dense analysis does; otherwise relative to the largest of the blocks' and the
        reduced system's.  ``scales``: the factor is of J with each column times its unknown's
        scale, (B, nb) for the blocks' and (ks,) for the shared ones (applied to the padded rows:
        no scaled copy of J, 26 MB at 2,000 views)."""
        c = Jc.shape[1]
        ks = c - nb
        self.B, self.nb, self.ks = B, nb, ks
        table = _block_table(Jc, row_block, B, nb)  # the thin SVD needs at least nb rows
        if scales is not None:
            table[:, :, :nb] *= scales[0][:, None, :]
            table[:, :, nb:] *= scales[1]
        self.table = table
        P, sb, Qt = np.linalg.svd(table[:, :, :nb], full_matrices=False)  # (B, L, nb), (B, nb), (B, nb, nb)
        Zs = table[:, :, nb:]
        top = float(sb.max()) if sb.size else 0.0
        smax = top
        if exact:
            w, _ = _largest_eigenvalues(self._information, B * nb + ks)
            smax = float(np.sqrt(max(w[-1], 0.0)))
        self.smax = smax
        keep = sb > rtol * max(smax, 1e-300)
        inv = np.where(keep, 1.0 / np.where(keep, sb, 1.0), 0.0)
        Pk = np.multiply(P, keep[:, None, :], out=P)  # (in place: P is not needed beyond)
        PtJs = np.einsum("bli,blk->bik", Pk, Zs)  # (B, nb, ks): P_kᵀ J_s
        Z = np.einsum("bli,bik->blk", Pk, PtJs)
        Z = np.subtract(Zs, Z, out=Z)  # the shared remainder per block
        Q = np.swapaxes(Qt, 1, 2)
        self.Uinv = np.einsum("bij,bj,bkj->bik", Q, inv * inv, Q)
        self.Y = np.einsum("bij,bj,bjk->bik", Q, inv, PtJs)  # U_b⁺ W_b
        _, ss, Vt_s = (
            np.linalg.svd(Z.reshape(-1, ks), full_matrices=False) if ks else (None, np.zeros(0), np.zeros((0, 0)))
        )
        keep_s = ss > rtol * max(smax, 1e-300)
        Vs = Vt_s.T
        self.Sinv = (Vs[:, keep_s] / ss[keep_s] ** 2) @ Vs[:, keep_s].T
        self.shared_null = Vs[:, ~keep_s]  # (ks, k0)
        self.block_null = [(b, Q[b][:, ~keep[b]]) for b in np.nonzero(~keep.all(axis=1))[0]]
        self.rank = int(keep.sum() + keep_s.sum())
        del self.table  # (B, L, c) rows, read by _information above only: a result keeps the factor

    def _information(self, v: np.ndarray) -> np.ndarray:
        """JᵀJ v for v = (all blocks' unknowns, then the shared ones), from the padded rows."""
        nb = self.nb
        vb, vs = v[: self.B * nb].reshape(self.B, nb), v[self.B * nb :]
        Tb, Ts = self.table[:, :, :nb], self.table[:, :, nb:]
        u = np.einsum("blk,bk->bl", Tb, vb) + Ts @ vs
        return np.concatenate([np.einsum("blk,bl->bk", Tb, u).ravel(), np.einsum("blk,bl->k", Ts, u)])

    def solve(self, vb: np.ndarray, vs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """C·v for v = (vb (B, nb, …), vs (ks, …)) (several right-hand sides along the last axes)."""
        xs = np.tensordot(self.Sinv, vs - np.einsum("bik,bi...->k...", self.Y, vb), axes=1)
        xb = np.einsum("bij,bj...->bi...", self.Uinv, vb) - np.einsum("bik,k...->bi...", self.Y, xs)
        return xb, xs

    def null_vectors(self, structure: Structure) -> np.ndarray:
        """(n, k) the null directions of J, orthonormal: each block's own, then the shared ones with
        the blocks following them (δ_b = −Y_b δ_s)."""
        n = structure.n
        out = []
        for b, N in self.block_null:
            for k in range(N.shape[1]):
                v = np.zeros(n)
                v[structure.blocks[b]] = N[:, k]
                out.append(v)
        for k in range(self.shared_null.shape[1]):
            v = np.zeros(n)
            ds = self.shared_null[:, k]
            v[structure.shared[0]] = ds
            v[structure.blocks] = -self.Y @ ds
            out.append(v)
        if not out:
            return np.zeros((n, 0))
        Qn, _ = np.linalg.qr(np.stack(out, axis=1))
        return Qn


def _apply_rows(structure: Structure, Jc: np.ndarray, row_block: np.ndarray, v: np.ndarray) -> np.ndarray:
    """J v for the rows of a compressed Jacobian (one shared group)."""
    nb = structure.nb
    return np.einsum("ij,ij->i", Jc[:, :nb], v[structure.blocks][row_block]) + Jc[:, nb:] @ v[structure.shared[0]]


def _apply_rows_t(structure: Structure, Jc: np.ndarray, row_block: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Jᵀ u for the rows of a compressed Jacobian (one shared group)."""
    nb = structure.nb
    out = np.zeros(structure.n)
    gb = np.stack([np.bincount(row_block, weights=Jc[:, k] * u, minlength=structure.n_blocks) for k in range(nb)], 1)
    out[structure.blocks] = gb
    out[structure.shared[0]] = Jc[:, nb:].T @ u
    return out


def _largest_eigenvalues(
    matvec: Callable[[np.ndarray], np.ndarray], n: int, k: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """The k largest eigenvalues (ascending) and eigenvectors of a symmetric operator: exactly for
    small n, else by Lanczos iterations to round-off (ARPACK)."""
    k = max(1, min(k, n))
    if n <= _LANCZOS_DENSE or k >= n - 1:
        M = np.stack([matvec(e) for e in np.eye(n)], axis=1)
        w, V = np.linalg.eigh(0.5 * (M + M.T))
        return w[-k:], V[:, -k:]
    from scipy.sparse.linalg import LinearOperator, eigsh  # heavy third-party import, needed only here

    op = LinearOperator((n, n), matvec=matvec, dtype=float)
    v0 = np.cos(np.arange(n) * 0.7) + 1.5  # deterministic start
    w, V = eigsh(op, k=k, which="LA", v0=v0, tol=0)
    order = np.argsort(w)
    return w[order], V[:, order]


WEAK_EXACT = 256
"""Up to this many unknowns, :meth:`BlockCovariance.weak_directions` takes their covariance block
whole (its eigenvectors exactly); beyond, each view's block with the shared unknowns."""


class BlockCovariance:
    """The covariance (n × n) of a block-structured problem's unknowns, never formed.

    Entry (i, j) is computed on request from the blocks: U_b⁺ when both lie in block b, plus
    q_iᵀ S⁺ q_j with q = Y_b's row for a block unknown and −e for a shared one; scaled back to SI
    units and by ``chi2_scale``; inf in the rows and columns of unknowns that an unobservable
    direction moves.  Indexing follows NumPy's for an n × n array (``cov[i, j]``, rows, slices,
    integer or boolean arrays; two index arrays give the entries at their pairs, ``cov[np.ix_(a, b)]``
    a block; ``...`` and ``None`` are refused), and ``diagonal()`` and ``np.asarray(cov)`` (which
    forms the whole matrix: for small problems only) work as for an array; ``correlation()`` is the
    same for the correlation matrix.
    """

    def __init__(
        self,
        factor: _BlockFactor,
        structure: Structure,
        scales: np.ndarray,
        chi2_scale: float,
        infinite: np.ndarray,
        names: Sequence[str],
        normalized: bool = False,
    ):
        self._f = factor
        self.structure = structure
        self.scales = np.asarray(scales, dtype=float)
        self.chi2_scale = float(chi2_scale)
        self.infinite = np.asarray(infinite, dtype=bool)
        self.names = list(names)
        self.normalized = normalized
        n = structure.n
        self.shape = (n, n)
        self.ndim = 2
        self.dtype = np.dtype(float)
        block, _ = structure.block_of_unknown()
        self._block = block
        pos = np.zeros(n, dtype=np.int64)
        pos[structure.blocks] = np.arange(structure.nb)[None, :]
        pos[structure.shared[0]] = np.arange(structure.ks)
        self._pos = pos
        q = np.zeros((n, structure.ks))
        q[structure.blocks] = factor.Y
        q[structure.shared[0], np.arange(structure.ks)] = -1.0
        self._q = q
        self._std: np.ndarray | None = None
        self._information_max: float | None = None  # λmax of the scaled JᵀJ (priors included)
        self.held = np.zeros(n, dtype=bool)  # at an active hard bound: σ 0, correlations NaN

    def __len__(self) -> int:
        return self.shape[0]

    def _raw(self, I: np.ndarray, J: np.ndarray) -> np.ndarray:
        """Scaled covariance entries for broadcast index arrays I, J (no χ², no SI scales)."""
        I, J = np.broadcast_arrays(I, J)
        shape = I.shape
        I, J = I.ravel(), J.ravel()  # 1-D: einsum of two scalar indices gives a scalar, not an array
        out = np.einsum("ik,kl,il->i", self._q[I], self._f.Sinv, self._q[J])
        bi, bj = self._block[I], self._block[J]
        same = (bi == bj) & (bi >= 0)
        out[same] += self._f.Uinv[bi[same], self._pos[I][same], self._pos[J][same]]
        return out.reshape(shape)

    def _entries(self, I: np.ndarray, J: np.ndarray) -> np.ndarray:
        I, J = np.broadcast_arrays(np.asarray(I, dtype=np.int64), np.asarray(J, dtype=np.int64))
        out = self._raw(I, J) * self.scales[I] * self.scales[J] * self.chi2_scale
        bad = self.infinite[I] | self.infinite[J]
        if self.normalized:
            std = self.std()
            with np.errstate(invalid="ignore", divide="ignore"):
                out = out / (std[I] * std[J])
            held = self.held[I] | self.held[J]
            out = np.where(bad | held | ~np.isfinite(out), np.nan, out)
            return np.where((I == J) & ~bad & ~held, 1.0, out)
        return np.where(bad, np.inf, np.where(self.held[I] | self.held[J], 0.0, out))

    def diagonal(self) -> np.ndarray:
        if self.normalized:
            return np.where(self.infinite | self.held, np.nan, 1.0)
        i = np.arange(self.shape[0])
        return self._entries(i, i)

    def std(self) -> np.ndarray:
        """σ of every unknown (SI units; inf where unobservable)."""
        if self._std is None:
            i = np.arange(self.shape[0])
            d = self._raw(i, i) * self.scales**2 * self.chi2_scale
            self._std = np.where(self.infinite, np.inf, np.where(self.held, 0.0, np.sqrt(np.clip(d, 0, None))))
        return self._std

    def correlation(self) -> BlockCovariance:
        twin = BlockCovariance(self._f, self.structure, self.scales, self.chi2_scale, self.infinite, self.names, True)
        twin._std = self.std()
        twin.held = self.held
        return twin

    _INDEXING = (
        "a BlockCovariance takes cov[i, j], cov[i] (a row), slices, and integer or boolean arrays, "
        "each as NumPy indexes an n × n array (two index arrays: the entries at their pairs, "
        "broadcast together); a block is cov[np.ix_(a, b)]"
    )

    def _index(self, k: Any) -> tuple[np.ndarray, bool]:
        """One axis's index as integer positions, and whether it was a slice."""
        n = self.shape[0]
        if isinstance(k, slice):
            return np.arange(n)[k], True
        if k is None or k is Ellipsis or isinstance(k, (bool, np.bool_)):
            raise IndexError(f"{self._INDEXING}; got {k!r}")
        a = np.asarray(k)
        if a.dtype == bool:
            if a.shape != (n,):
                raise IndexError(f"a boolean index must have shape ({n},), got {a.shape}")
            return np.nonzero(a)[0], False
        if a.dtype.kind not in "iu" and not (a.size == 0 and a.dtype.kind == "f"):
            raise IndexError(f"{self._INDEXING}; got an index of type {a.dtype}")
        a = a.astype(np.int64)
        if a.size and (a.min() < -n or a.max() >= n):
            raise IndexError(f"index out of range for {n} unknowns")
        return a, False

    def __getitem__(self, key: Any) -> Any:
        """Entries as NumPy gives them from the n × n array (a scalar for two integers, a row for
        one; two index arrays broadcast to pointwise pairs, not the outer block: ``np.ix_``)."""
        if not isinstance(key, tuple):
            key = (key,)
        if any(k is Ellipsis or k is None for k in key):
            raise IndexError(f"{self._INDEXING}; got {key!r}")
        if len(key) > 2:
            raise IndexError(f"too many indices for an n × n covariance: {len(key)}")
        key = (*key, slice(None), slice(None))[:2]
        (a, a_slice), (b, b_slice) = self._index(key[0]), self._index(key[1])
        if a_slice and b_slice:
            a, b = a[:, None], b[None, :]
        elif a_slice:  # cov[:, b]: the rows a, then b's shape
            a = a.reshape((-1,) + (1,) * b.ndim)
        elif b_slice:  # cov[a, :]: a's shape, then the columns b
            a = a[..., None]
        out = self._entries(a, b)
        return out if out.ndim else float(out)

    def __iter__(self):
        n = self.shape[0]
        for i in range(n):
            yield self._entries(np.full(n, i), np.arange(n))

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        i = np.arange(self.shape[0])
        out = self._entries(i[:, None], i[None, :])
        return out if dtype is None else out.astype(dtype)

    def joint(self) -> tuple[np.ndarray, np.ndarray]:
        """Each block's unknowns with the shared ones (B, nb + ks) and their covariance (B, c, c)."""
        s = self.structure
        idx = np.concatenate([s.blocks, np.broadcast_to(s.shared[0], (s.n_blocks, s.ks))], axis=1)
        f = self._f
        YS = f.Y @ f.Sinv  # (B, nb, ks)
        top = np.concatenate([f.Uinv + YS @ np.swapaxes(f.Y, 1, 2), -YS], axis=2)
        bottom = np.concatenate([-np.swapaxes(YS, 1, 2), np.broadcast_to(f.Sinv, (s.n_blocks, s.ks, s.ks))], axis=2)
        C = np.concatenate([top, bottom], axis=1)
        sc = self.scales[idx]
        C = C * sc[:, :, None] * sc[:, None, :] * self.chi2_scale
        held = self.held[idx]
        C = np.where(held[:, :, None] | held[:, None, :], 0.0, C)
        bad = self.infinite[idx]
        C = np.where(bad[:, :, None] | bad[:, None, :], np.inf, C)
        return idx, C

    def weak_directions(
        self, fraction: float, coefficient_tol: float
    ) -> tuple[list[tuple[tuple[str, ...], float]], float]:
        """:func:`mbcal.fit._weak_directions` without the n × n matrix: the directions of the
        unknowns (those with a finite σ) whose σ exceeds ``fraction`` of their ranges (twice their
        natural scales), and the condition number of the observable part of the covariance
        (scaled by the natural scales).

        Up to :data:`WEAK_EXACT` unknowns, their covariance block exactly (as the dense
        path).  Beyond, each block's unknowns with the shared ones (:meth:`joint`: 300 views are
        300 matrices of 15 × 15, not one of 1,809 × 1,809, which took 1.2 s): a weak direction
        within a view, within the shared unknowns, or between them is found; one spread over
        several views is not (the condition number still bounds the whole)."""
        finite = ~self.infinite
        n = self.shape[0]
        if not finite.any():
            return [], 1.0
        u = np.nonzero(finite)[0]

        def cov_scaled(v: np.ndarray) -> np.ndarray:
            full = np.zeros(n)
            full[u] = v
            return self._apply(full)[u] * self.chi2_scale

        big, _ = _largest_eigenvalues(cov_scaled, len(u))
        small = self._smallest(u)
        condition = float(np.sqrt(big[-1] / small)) if big[-1] > 0 and small > 0 else 1.0
        if len(u) <= WEAK_EXACT:
            width = 2.0 * self.scales[u]
            Cs = self[np.ix_(u, u)] / np.outer(width, width)
            lam, V = np.linalg.eigh((Cs + Cs.T) / 2)
            groups = [(u, lam, V)]
        else:
            at, C = self.joint()  # (B, c) unknowns, (B, c, c) covariances in SI units
            width = 2.0 * self.scales[at]
            keep = finite[at]
            Cs = np.where(keep[:, :, None] & keep[:, None, :], C / (width[:, :, None] * width[:, None, :]), 0.0)
            lam_all, V_all = np.linalg.eigh((Cs + np.swapaxes(Cs, 1, 2)) / 2)
            groups = [(at[b], lam_all[b], V_all[b]) for b in np.nonzero((lam_all > fraction**2).any(axis=1))[0]]
        found: dict[tuple[str, ...], float] = {}
        for members, lam, V in groups:
            for k in np.argsort(-lam):
                sigma = float(np.sqrt(max(lam[k], 0.0)))
                if not sigma > fraction:
                    break
                v = V[:, k]
                big_c = np.max(np.abs(v))
                order = [j for j in np.argsort(-np.abs(v)) if abs(v[j]) >= coefficient_tol * big_c]
                names = tuple(self.names[members[j]] for j in order)
                found[names] = max(sigma, found.get(names, 0.0))  # the shared unknowns' own: once
        return sorted(found.items(), key=lambda item: -item[1]), condition

    def _apply(self, v: np.ndarray) -> np.ndarray:
        """The scaled covariance (no χ²) times v (n,): C v by the blocks."""
        s = self.structure
        xb, xs = self._f.solve(v[s.blocks], v[s.shared[0]])
        out = np.zeros(self.shape[0])
        out[s.blocks] = xb
        out[s.shared[0]] = xs
        return out

    def _smallest(self, idx: np.ndarray) -> float:
        """The smallest eigenvalue of the scaled covariance over ``idx``: χ² / λmax of the information
        matrix — exact when every unknown is observable.  Otherwise (``idx`` the observable ones)
        the covariance over them is the inverse of a Schur complement of the information matrix,
        whose largest eigenvalue is at most λmax: the value is then a lower bound, and the condition
        number an upper bound (never flattering; Lanczos iterations at that end of the spectrum of
        the covariance need not converge)."""
        top = self._information_max
        return float(self.chi2_scale / top) if top is not None and top > 0 else 0.0

    def point_uncertainties(
        self,
        problem: Problem,
        x: np.ndarray,
        cfg_idx: np.ndarray,
        idx: np.ndarray,
        items: Sequence[tuple[str, str, str | None]],
        eyes: Sequence[np.ndarray | None] | np.ndarray,
    ) -> Sequence[PointUncertainty]:
        """:func:`mbcal.observability.point_uncertainties` from each point's compressed Jacobian
        (its configuration's block and the shared unknowns: nb + ks tangents, not n)."""
        return block_point_uncertainties(problem, self.structure, self.joint()[1], x, cfg_idx, idx, items, eyes)


class StructuredLinear:
    """The problem linearised at the estimate and refitted on a subset of its rows, from the
    compressed Jacobian (the fit verdict's linear algebra, :class:`mbcal.fit._Linear`, without the
    m × n matrix): refit residuals, and the leverages J_B (JᵀJ)⁺ J_Bᵀ of any rows B from the
    blocks, a_iᵀ U_b⁺ a_j (rows of one block) + z_iᵀ S⁺ z_j with z = s − Y_bᵀ a."""

    _GROUP_ROWS = 3000  # larger groups are deleted in the unknowns' space (a second factorisation)

    def __init__(self, structure: Structure, r: np.ndarray, Jc: np.ndarray, rows: np.ndarray, rtol: float = 1e-10):
        self.structure = structure
        self.r, self.Jc = r, Jc
        self.rows = np.asarray(rows, dtype=np.int64)
        rb = structure.row_block[self.rows]
        Jk = Jc[self.rows]
        nb = structure.nb
        self._rtol = rtol
        self.f = _BlockFactor(Jk, rb, structure.n_blocks, nb, rtol)
        self.rank = self.f.rank
        rk = r[self.rows]
        g = _apply_rows_t(structure, Jk, rb, rk)
        xb, xs = self.f.solve(g[structure.blocks], g[structure.shared[0]])
        step = np.zeros(structure.n)
        step[structure.blocks], step[structure.shared[0]] = xb, xs
        self.res = rk - _apply_rows(structure, Jk, rb, step)
        self.S = float(self.res @ self.res)
        self.position = np.full(r.shape[0], -1, dtype=np.int64)
        self.position[self.rows] = np.arange(len(self.rows))
        self._a = Jk[:, :nb]
        self._z = Jk[:, nb:] - np.einsum("bik,bi->bk", self.f.Y[rb], Jk[:, :nb])
        self._rb = rb

    @property
    def dof(self) -> int:
        return len(self.rows) - self.rank

    def _hat(self, pos: np.ndarray) -> np.ndarray:
        """J_B (JᵀJ)⁺ J_Bᵀ for kept-row positions ``pos`` (…, size): (…, size, size)."""
        a, z, b = self._a[pos], self._z[pos], self._rb[pos]
        Ua = np.einsum("...ij,...j->...i", self.f.Uinv[b], a)
        same = b[..., :, None] == b[..., None, :]
        return np.einsum("...ik,...jk->...ij", Ua, a) * same + np.einsum("...ik,kl,...jl->...ij", z, self.f.Sinv, z)

    def deletions(self, blocks: RowBlocks | Sequence[np.ndarray], floor: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
        """How much S drops when each block of rows alone is set aside (and its degrees of freedom:
        the eigenvalues of I − H_BB above ``floor``)."""
        t = np.zeros(len(blocks))
        d = np.zeros(len(blocks), dtype=np.int64)
        for _, members, rows in blocks_by_size(blocks):
            t[members], d[members] = self._drop(self.position[rows], floor)
        return t, d

    def _drop(self, pos: np.ndarray, floor: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
        rB = self.res[pos]
        A = np.eye(pos.shape[-1]) - self._hat(pos)
        w, V = np.linalg.eigh(A)
        good = w > floor
        inv = np.where(good, 1.0 / np.where(good, w, 1.0), 0.0)
        proj = np.einsum("...ij,...i->...j", V, rB)
        return np.sum(inv * proj**2, axis=-1), np.sum(good, axis=-1)

    def deletion(self, block_rows: np.ndarray) -> tuple[float, int]:
        """How much S drops when these rows are also set aside, and the degrees of freedom of it."""
        pos = self.position[np.asarray(block_rows, dtype=np.int64)]
        pos = pos[pos >= 0]
        if pos.size == 0:
            return 0.0, 0
        if pos.size <= self._GROUP_ROWS:
            drop, dof = self._drop(pos)
            return float(drop), int(dof)
        # In the unknowns' space: S − S₋B = e_Bᵀe_B + gᵀ (A − J_BᵀJ_B)⁺ g with g = J_Bᵀ e_B.
        s = self.structure
        rest = np.setdiff1d(self.rows, self.rows[pos])
        eB = self.res[pos]
        g = _apply_rows_t(s, self.Jc[self.rows[pos]], s.row_block[self.rows[pos]], eB)
        other = _BlockFactor(self.Jc[rest], s.row_block[rest], s.n_blocks, s.nb, self._rtol)
        xb, xs = other.solve(g[s.blocks], g[s.shared[0]])
        t = float(eB @ eB + g[s.blocks].ravel() @ xb.ravel() + g[s.shared[0]] @ xs)
        return t, int(pos.size - (self.rank - other.rank))


def held_columns(structure: Structure, Jc: np.ndarray, held: np.ndarray) -> np.ndarray:
    """The compressed Jacobian (one shared group) with the columns of the unknowns ``held`` (n,)
    at an active hard bound set to zero (a copy): they are not estimated from the data."""
    nb = structure.nb
    out = np.array(Jc, dtype=float)
    out[:, :nb][held[structure.blocks][structure.row_block]] = 0.0
    out[:, nb:][:, held[structure.shared[0]]] = 0.0
    return out


def _free_null(null: np.ndarray, held: np.ndarray) -> np.ndarray:
    """The null directions that leave the ``held`` unknowns alone, orthonormal: a held unknown's
    zero column makes its own axis a null direction of J, which is not an unobservable one."""
    if not held.any() or not null.size:
        return null
    _, sv, vt = np.linalg.svd(null[held], full_matrices=True)
    rank = int(np.sum(sv > 1e-8))
    out = null @ vt[rank:].T
    out[held] = 0.0
    return out


def observability_structured(
    problem: Problem,
    structure: Structure,
    Jc: np.ndarray,
    *,
    names: Sequence[str],
    units: dict[str, str],
    scales: np.ndarray,
    config: ObservabilityConfig | None = None,
    chi2_scale: float = 1.0,
    active: np.ndarray | None = None,
) -> Observability:
    """:func:`mbcal.observability.analyze` of a structured problem (one shared group) from its
    compressed Jacobian ``Jc`` (measurement rows, then prior rows): the same rank, named
    unobservable and weak directions, condition number and covariance, without the n × n matrix.
    The covariance is a :class:`BlockCovariance`; ``singular_values`` holds only the largest and
    the smallest nonzero singular value of the scaled Jacobian (Lanczos iterations, not an SVD).
    ``active``: the solver's active bounds (−1, 0, +1 per unknown); those unknowns are held fixed
    as :func:`mbcal.observability.analyze` holds them (their columns set to zero)."""
    if structure.n_groups != 1:
        raise SolverError("the structured analysis needs one group of shared unknowns")
    config = config or ObservabilityConfig()
    n = structure.n
    held = np.zeros(n, dtype=bool) if active is None else np.asarray(active) != 0
    if held.any():
        Jc = held_columns(structure, Jc, held)
    S = np.asarray(scales, dtype=float)
    rb = structure.row_block
    column_scales = (S[structure.blocks], S[structure.shared[0]])
    size = problem.size
    Jm, rbm = Jc[:size], rb[:size]

    fm = _BlockFactor(Jm, rbm, structure.n_blocks, structure.nb, config.rtol, exact=True, scales=column_scales)
    smax = fm.smax
    null = fm.null_vectors(structure)  # with the held unknowns' axes: projected out of the inverse
    rank = fm.rank
    has_priors = Jc.shape[0] > size
    if has_priors:
        ft = _BlockFactor(Jc, rb, structure.n_blocks, structure.nb, config.rtol, exact=True, scales=column_scales)
        null_t = ft.null_vectors(structure)
    else:
        ft, null_t = fm, null

    def pinv(factor: _BlockFactor, basis: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        def apply(v: np.ndarray) -> np.ndarray:
            v = v - basis @ (basis.T @ v)
            xb, xs = factor.solve(v[structure.blocks], v[structure.shared[0]])
            out = np.zeros(n)
            out[structure.blocks], out[structure.shared[0]] = xb, xs
            return out - basis @ (basis.T @ out)

        return apply

    cov_m = pinv(fm, null)
    inv_big, _ = _largest_eigenvalues(cov_m, n) if rank else (np.zeros(1), None)
    smin = float(1.0 / np.sqrt(inv_big[-1])) if rank and inv_big[-1] > 0 else 0.0
    condition = float(smax / smin) if rank and smin > 0 else float("inf")
    null_t = _free_null(null_t, held)
    in_null = np.sum(null_t**2, axis=1) > 1e-12 if null_t.size else np.zeros(n, dtype=bool)
    cov = BlockCovariance(ft, structure, S, chi2_scale, in_null, names)
    cov._information_max = ft.smax**2
    cov.held = held
    free_null = _free_null(null, held)
    unobservable = [
        _combination(v, names, units, S, float("inf"), config.coefficient_tol) for v in _sparse_basis(free_null).T
    ]
    weak = []
    # σ along a direction is √χ² / (its singular value): none exceeds config.weak when even the
    # trace of the scaled covariance (the sum of all σ²) stays below it.
    trace = float(np.sum(BlockCovariance(fm, structure, np.ones(n), 1.0, np.zeros(n, bool), names).std() ** 2))
    if rank and trace * chi2_scale > config.weak**2:
        k = 8
        while True:
            lam, vecs = _largest_eigenvalues(cov_m, n, k)
            if lam[0] * chi2_scale <= config.weak**2 or k >= n - 2 or k >= 256:
                break
            k *= 2
        for i in np.argsort(lam):  # as the dense path: by growing σ
            sigma_dir = float(np.sqrt(max(lam[i], 0.0) * chi2_scale))
            if sigma_dir > config.weak and lam[i] > 0:
                weak.append(_combination(vecs[:, i], names, units, S, sigma_dir, config.coefficient_tol))
    std = cov.std()
    return Observability(
        names=list(names),
        units=units,
        scales=S,
        singular_values=np.array([smax, smin]),
        rank=rank,
        rank_with_priors=ft.rank,
        condition=condition,
        unobservable=unobservable,
        weak=weak,
        covariance=cov,
        std=std,
        correlation=cov.correlation(),
        chi2_scale=chi2_scale,
        null_space=free_null,
        n_values=int(size),
        active_bounds={} if active is None else active_sides(names, active),
    )


_CANDIDATE_RTOL = 1e-6
"""The ranking's rank decisions on scaled singular values: :func:`mbcal.observability.rank_candidates`
counts an eigenvalue of the information matrix as positive above 1e-12 of the largest."""


def rank_candidates_structured(
    obs: Observability,
    structure: Structure,
    Jc: np.ndarray,
    candidates: Sequence[tuple[dict[str, Any], np.ndarray, int]],
    *,
    top: int = 10,
) -> list[Suggestion]:
    """:func:`mbcal.observability.rank_candidates` from the blocks: the same scores (rank gained,
    relative reduction of the largest scaled σ) and the same order, without any n × n or m × n
    matrix.

    ``Jc``: the problem's compressed Jacobian (measurement rows, then prior rows, one shared
    group); ``candidates``: (record, compressed rows (s, nb + ks), block) triples — a candidate
    measurement of configuration b depends on block b and the shared unknowns only.

    Each block's scaled rows are replaced by their R factor (c × c, c = nb + ks: the same JᵀJ), so
    a candidate changes one block's c rows: its information is the base's with that block's R
    factor re-factored with the candidate's rows.  The largest σ over the directions left
    observable (the complement of the null space N the candidate leaves) is √λmax of the inverse
    of JᵀJ compressed to that complement, M⁺ − M⁺N(NᵀM⁺N)⁻¹NᵀM⁺ (M⁺ by :class:`_BlockFactor`,
    N stripped of M's own null directions), by Lanczos iterations (exactly below 64 unknowns).
    Only candidates that can reach the ``top`` (those with the largest rank gains) get a σ."""
    s = structure
    if s.n_groups != 1:
        raise SolverError("ranking candidates by blocks needs one group of shared unknowns")
    n, nb, ks, B = s.n, s.nb, s.ks, s.n_blocks
    c = nb + ks
    S = np.asarray(obs.scales, dtype=float)
    if obs.active_bounds:
        S = np.where(obs.fixed, 0.0, S)  # held at a bound: no measurement can help
    idx = np.concatenate([s.blocks, np.broadcast_to(s.shared[0], (B, ks))], axis=1)  # (B, c)
    col = S[idx]
    table = _block_table(Jc, s.row_block, B, c)
    table *= col[:, None, :]
    base: Any = np.linalg.qr(table, mode="r")  # (B, c, c)
    del table
    null = obs.null_space if obs.null_space is not None else np.zeros((n, 0))
    row_block = np.repeat(np.arange(B), c)

    def worst(rows: np.ndarray, new_null: np.ndarray) -> float:
        f = _BlockFactor(rows.reshape(-1, c), row_block, B, nb, _CANDIDATE_RTOL)

        def solve(v: np.ndarray) -> np.ndarray:
            xb, xs = f.solve(v[s.blocks], v[s.shared[0]])
            out = np.zeros_like(v)
            out[s.blocks], out[s.shared[0]] = xb, xs
            return out

        kept = new_null
        if kept.shape[1]:  # N less the directions M itself leaves out (they are in N)
            own = f.null_vectors(s)
            kept = kept - own @ (own.T @ kept)
            u, sv, _ = np.linalg.svd(kept, full_matrices=False)
            kept = u[:, sv > 0.5]
        MN = solve(kept) if kept.shape[1] else np.zeros((n, 0))
        Gi = np.linalg.inv(kept.T @ MN) if kept.shape[1] else np.zeros((0, 0))

        def compressed(v: np.ndarray) -> np.ndarray:
            return solve(v) - MN @ (Gi @ (MN.T @ v))

        lam, _ = _largest_eigenvalues(compressed, n)
        return float(np.sqrt(lam[-1])) if lam[-1] > 0 else float("inf")

    def with_candidate(candidate: tuple[np.ndarray, int], new_null: np.ndarray) -> float:
        R, b = candidate
        rows = base.copy()
        rows[b] = np.linalg.qr(np.vstack([base[b], R]), mode="r")
        return worst(rows, new_null)

    seen = []
    for record, rows, b in candidates:
        R = np.atleast_2d(rows) * col[b]
        found = null_seen(R, R @ null[idx[b]], null)
        if found is not None:
            seen.append((*found, record, (R, b)))
    return best_suggestions(seen, worst(base, null) if seen else 0.0, with_candidate, top)
