"""Automatic calibration from scans: point-to-surface residuals against the model's shapes.

For every scan point p (in its sensor frame, configuration c) the residual is its distance to
the nearest surface of the model, over σ::

    r_i(x) = min_s dist_s( T_world_sensor(x, c) · p_i ) / σ_i

with the exact, differentiable distance kernels of the shape registry (every shape kind and
meshes; :mod:`mbcal.geometry.raycast`).  The distance is continuous in the parameters (the
nearest surface may change, its distance does not jump), unlike the range along a ray at a
silhouette edge.  A robust loss (Cauchy, c = 2.385 σ) is the default: points of things the
model does not hold stay in the problem but pull little.

The steps of :func:`fit_scans`:

1. each scan is voxel down-sampled (``voxel``, in its own frame);
2. **coarse start**: when the points lie far from the model at the starting values (median
   distance above ``coarse_distance``) a global rigid alignment (trimmed ICP against points
   sampled on the model's surface; Kabsch steps from trimesh) moves the cloud onto the model,
   and the unknowns are fitted to that rigid motion of the shapes;
3. **crop**: points farther than ``crop`` from every modelled surface at the start are left out
   (the rest of the room, the floor far away);
4. the Marquardt solver of :mod:`mbcal.solver` with the robust loss, its random restarts, and
   the prior in information form (a previous posterior, :class:`Prior`) plus the model's σ.
   Each point is compared in the solver only with its **candidate** shapes: those within
   ``assign_margin`` of its nearest shape where they were chosen; at the solution every point is
   compared with every shape again and, where its nearest shape is not a candidate, the
   candidates are chosen again there and the solve repeats — so the residual at the reported
   solution is the distance to the nearest of all shapes.  A mesh is screened by its bounding
   box (a lower bound of its distance) and searched triangle by triangle only near it;
5. **outliers**: points farther than ``outlier_sigma`` σ from every surface at the solution
   belong to no modelled surface; they are counted, listed and can be written as a PLY;
6. the covariance from the inliers' Jacobian (and the prior), the reduced χ² of the inliers,
   and per object the share of its points beyond ``outlier_sigma`` σ: an object whose share
   exceeds ``misfit_fraction`` is named as a **structural misfit** (its shape no longer fits).

The point arrays are arguments of the compiled program (padded to a multiple of 4096 with
zero-weight rows), and so are the per-shape candidate lists (padded to size classes with an
eighth of room to grow, kept while later batches fit), so new scans of a scene reuse it: no
recompilation per batch.  The graduated first solve uses the same program (the loss with scale
k·c on r is k² times the loss with scale c on r/k: rows scaled by 1/k), and so do the probes
(one start at a time).  A fit with a prior (a warm-started manager update) skips the probes.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mbcal._jax import jax, jnp, to_device
from mbcal.cache import enable_compilation_cache
from mbcal.errors import SolverError
from mbcal.fit import DEFAULT_THRESHOLD, TOO_SMALL_REDUCED_CHI2, chi2_sf
from mbcal.geometry.raycast import distance_to_shapes, surface_distance
from mbcal.language.model import Model
from mbcal.measurements.sets import MeasurementSet
from mbcal.modeling import Needs, modeler
from mbcal.outputs import finite_or_null
from mbcal.params import ParameterSet
from mbcal.range.scans import Scan
from mbcal.solver import Loss, SolverConfig, check_size, least_squares, random_starts
from mbcal.units import at_least, whole

Array = Any

__all__ = [
    "FitOptions",
    "Prior",
    "ScanFit",
    "Misfit",
    "fit_scans",
    "scan_measurements",
    "scan_world_points",
    "residuals_at",
    "BUCKET",
    "TOO_SMALL_REDUCED_CHI2",
]

BUCKET = 4096

# TOO_SMALL_REDUCED_CHI2 (mbcal.fit's): a scan fit whose inliers' reduced χ² is below it (and
# improbably so for its dof) has σ stated too large: not trustworthy here
# (:attr:`ScanFit.sigma_too_large` gives the reasons for 0.1).


@dataclass(frozen=True)
class FitOptions:
    """How :func:`fit_scans` runs (the CLI's defaults)."""

    voxel: float = 0.01
    """Voxel size (m) of the down-sampling; 0: every point."""
    crop: float = 0.10
    """Points farther than this (m) from every modelled surface at the start are left out."""
    loss: str = "cauchy"
    """Robust loss: ``cauchy`` (default), ``huber`` or ``linear`` (plain least squares)."""
    outlier_sigma: float = 3.0
    """Points farther than this many σ from every surface at the solution are outliers."""
    misfit_fraction: float = 0.2
    """An object with more than this share of its points beyond ``outlier_sigma`` σ is a structural misfit."""
    misfit_min_points: int = 20
    """... and at least this many such points."""
    restarts: int = 1
    """Starting points: the (coarse-aligned) start, plus random ones in the search ranges."""
    probe_rounds: int = 3
    """After convergence, restart from ± ``probe_sigma`` σ along the two weakest directions and keep
    a better minimum, up to this many rounds (0: off)."""
    probe_sigma: float = 4.0
    probe_gain: float = 0.05
    """A probe's minimum is taken when it lowers the robust cost (in χ² units) by more than this."""
    graduated: float = 10.0
    """Solve first with the robust loss's scale times this (then the nominal scale); 1: off."""
    seed: int = 0
    coarse: str = "auto"
    """``auto``: align globally when the points lie far from the model; ``always``; ``never``."""
    coarse_distance: float = 0.02
    """``auto`` aligns when the median distance of the points to the model exceeds this (m)."""
    max_points: int = 60000
    """At most this many points (after down-sampling and crop) go into the fit (a seeded random subset)."""
    max_iterations: int = 60
    assign_margin: float = 0.02
    """The solver compares a point only with the shapes within this distance (m) of its nearest
    one at the start (its candidates); they are chosen again where the solution's nearest shape
    of a point is not among them."""
    priors: bool = True
    """Use the model's prior σ of the unknowns."""
    known: Mapping[str, float] | None = None

    def __post_init__(self) -> None:
        def bad(name: str, rule: str) -> SolverError:
            return SolverError(f"FitOptions.{name} must be {rule}, got {getattr(self, name)!r}")

        for name in ("voxel", "probe_sigma", "probe_gain", "assign_margin"):
            if not at_least(getattr(self, name), 0.0):
                raise bad(name, "a finite number ≥ 0")
        for name in ("crop", "outlier_sigma", "coarse_distance"):
            if not at_least(getattr(self, name), 0.0, strict=True):
                raise bad(name, "a finite number > 0")
        if not at_least(self.graduated, 1.0):
            raise bad("graduated", "a finite number ≥ 1 (1: off)")
        if not (at_least(self.misfit_fraction, 0.0, strict=True) and self.misfit_fraction <= 1):
            raise bad("misfit_fraction", "a share in (0, 1]")
        for name, low in (
            ("restarts", 1),
            ("max_points", 1),
            ("max_iterations", 1),
            ("misfit_min_points", 1),
            ("probe_rounds", 0),
            ("seed", 0),
        ):
            if not whole(getattr(self, name), low):
                raise bad(name, f"a whole number ≥ {low}")
        if self.coarse not in ("auto", "always", "never"):
            raise bad("coarse", "'auto', 'always' or 'never'")
        if self.loss not in ("cauchy", "huber", "linear"):
            raise bad("loss", "'cauchy', 'huber' or 'linear'")


@dataclass(frozen=True)
class Prior:
    """A Gaussian prior in information form: mean and information matrix Λ = Σ⁻¹ over ``names``."""

    names: tuple[str, ...]
    mean: np.ndarray
    information: np.ndarray


@dataclass(frozen=True)
class Misfit:
    """Per object: how its points fit its modelled surface."""

    object: str
    shapes: tuple[str, ...]
    points: int
    beyond: int
    rms: float
    flagged: bool

    @property
    def fraction(self) -> float:
        return self.beyond / self.points if self.points else 0.0

    def message(self, outlier_sigma: float, sigma: float) -> str:
        kinds = " and ".join(dict.fromkeys(s.split(":")[1] for s in self.shapes))
        return (
            f"{self.object}: {100 * self.fraction:.0f} % of its points are farther than {outlier_sigma:g}σ "
            f"({1000 * outlier_sigma * sigma:.3g} mm) from the modelled {kinds}; its shape no longer fits"
        )


SCAN_FIT_FORMAT = "mbcal-scan-fit-1"
"""The ``format`` of a scan fit's JSON (mbcal/schemas/scan_fit.schema.json)."""

_SI_UNIT = {"deg": "rad"}  # a parameter shown in degrees has its value in radians


@dataclass
class ScanFit:
    """What a scan fit found."""

    names: list[str]
    x: np.ndarray
    x_start: np.ndarray
    covariance: np.ndarray
    information: np.ndarray
    chi2: float
    dof: int
    points: np.ndarray  # (N, 3) world points used in the fit (at the estimate)
    residuals: np.ndarray  # (N,) distance to the nearest surface (m) at the estimate
    sigma: np.ndarray  # (N,) σ of each point (m)
    outlier: np.ndarray  # (N,) bool
    cropped: int
    far: np.ndarray  # (cropped, 3) world points left out as farther than the crop distance from the model
    total_points: int
    misfits: list[Misfit]
    coarse: np.ndarray | None  # the global alignment applied (4×4), None when not needed
    elapsed: float
    converged: bool
    outlier_sigma: float
    units: dict[str, str] = field(default_factory=dict)
    unobservable: list[str] = field(default_factory=list)
    prior_chi2: float | None = None
    """With a previous posterior as prior (a manager's update): Σ of its squared rows Lᵀ(x − m) at
    the estimate, χ² with ``prior_dof`` degrees of freedom when the update agrees with the prior."""
    prior_dof: int = 0
    nonfinite: int = 0
    """Points of the scans left out as read because a coordinate is not a finite number (NaN, inf:
    an organised cloud's missing returns, a broken export); not in ``total_points``."""
    thinned: int = 0
    """Points of the scans left out by the down-sampling (``voxel``)."""
    capped: int = 0
    """Points within the crop distance left out at random above ``FitOptions.max_points``: used,
    thinned, cropped and capped add up to ``total_points``; the outliers are counted among the
    points used and, by :attr:`near_outlier_fraction`, stand for the capped ones too."""
    determined_by_scans: bool = True
    """Whether the scans (and the model's σ priors) determine every unknown without the previous
    posterior: an estimate that contradicts that posterior is trusted only then (a room that was
    bumped, seen whole) — not when the posterior is all that pins it (a flat wall that fits a
    plane of the model at any pose)."""

    @property
    def prior_p(self) -> float | None:
        """P(χ² ≥ prior_chi2): below the verdict's threshold (0.001) the estimate contradicts the
        prior — a jump the prior (widened by the process noise) does not allow, not a drift."""
        if self.prior_chi2 is None or self.prior_dof <= 0:
            return None
        return chi2_sf(self.prior_chi2, self.prior_dof)

    @property
    def prior_consistent(self) -> bool:
        p = self.prior_p
        return p is None or p >= DEFAULT_THRESHOLD

    @property
    def jumped(self) -> bool:
        """The estimate contradicts the prior and the scans alone do not determine it: not a move
        the scans show, a pose only the prior held, moved to where some plane happens to fit."""
        return not self.prior_consistent and not self.determined_by_scans

    @property
    def values(self) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.names, self.x)}

    @property
    def std(self) -> dict[str, float]:
        return {n: float(np.sqrt(max(self.covariance[i, i], 0.0))) for i, n in enumerate(self.names)}

    @property
    def reduced_chi2(self) -> float:
        return self.chi2 / max(self.dof, 1)

    @property
    def n_outliers(self) -> int:
        """Points that belong to no modelled surface: cropped as far from the model, or farther
        than ``outlier_sigma`` σ from every surface at the estimate."""
        return int(self.outlier.sum()) + self.cropped

    @property
    def outlier_fraction(self) -> float:
        """Outliers among the points after down-sampling: the cropped ones and, among those within
        the crop distance (the capped ones too), :attr:`near_outlier_fraction` of them."""
        near = len(self.outlier) + self.capped
        return (self.cropped + self.near_outlier_fraction * near) / max(near + self.cropped, 1)

    @property
    def near_outlier_fraction(self) -> float:
        """The share of outliers among the points within the crop distance: what the verdict
        judges (half or more: not ok).  The points beyond it are what the scan sees besides the
        model (the rest of a room around a modelled machine): counted and written out, not held
        against the fit."""
        return int(self.outlier.sum()) / max(len(self.outlier), 1)

    @property
    def mostly_cropped(self) -> str:
        """A hint when nearly every point (≥ 90 %) lay beyond the crop distance at the start —
        what a scan in millimetres read as metres (1000× the room: a few points near the model's
        infinite planes remain), in another frame or of another place gives — else ""."""
        near = len(self.outlier) + self.capped
        if not self.cropped >= 9 * max(near, 1):
            return ""
        share = 100 * self.cropped / (self.cropped + near)
        return (
            f"note: {share:.4g} % of the points lay farther than the crop distance from every modelled surface at "
            "the start: is the scan of this model, in its frame, and in metres (a scan in millimetres read as metres "
            "is 1000× the size)?"
        )

    @property
    def outlier_points(self) -> np.ndarray:
        return np.vstack([self.points[self.outlier], self.far])

    @property
    def structural(self) -> list[Misfit]:
        return [m for m in self.misfits if m.flagged]

    @property
    def sigma_too_large(self) -> bool:
        """The inliers scatter far less than the stated σ: σ stated too large (a number meant in mm
        read as metres), which hides any misfit — a depth scale 10 % off fitted a room to 2 m σ with
        reduced χ² 2e-05.  Two tests, both needed:

        * reduced χ² < :data:`TOO_SMALL_REDUCED_CHI2` (0.1: the scatter is below ⅓ of σ).  Not the
          χ² lower tail alone: with thousands of points its 0.001 point is 0.97, while a correct
          σ legitimately gives well below 1 — a sensor's σ is its specification (an honest camera
          is quieter by up to 2–3×), the inliers are cut at ``outlier_sigma`` σ, and 1 mm depth
          counts are quantised; none of that reaches a factor 3 in σ;
        * P(χ²_dof ≤ χ²) < the verdict's threshold (0.001): with few degrees of freedom a small
          χ² happens by chance (χ²₁ is below 0.1 a quarter of the time).
        """
        r = self.reduced_chi2
        return bool(r < TOO_SMALL_REDUCED_CHI2 and 1.0 - chi2_sf(self.chi2, self.dof) < DEFAULT_THRESHOLD)

    @property
    def ok(self) -> bool:
        """Converged, observable, inliers consistent with σ (0.1 < reduced χ² < 2, see
        :attr:`sigma_too_large`), no structural misfit, fewer than half the points outliers, and
        not a jump only the prior had held: no :attr:`doubts`."""
        return not self.doubts

    @property
    def doubts(self) -> list[str]:
        """Why the fit is not :attr:`ok`, one phrase per reason (empty when it is)."""
        out = [] if self.converged else ["the solver did not converge"]
        out += [f"unobservable: {u}" for u in self.unobservable]
        if not self.reduced_chi2 < 2.0:  # (NaN too)
            out.append(f"the inliers scatter more than σ (reduced χ² {self.reduced_chi2:.3g})")
        elif self.sigma_too_large:
            out.append(
                f"the inliers scatter far less than σ (reduced χ² {self.reduced_chi2:.3g} < "
                f"{TOO_SMALL_REDUCED_CHI2:g}): σ stated too large, which hides a misfit"
            )
        out += [f"structural misfit of {m.object}" for m in self.structural]
        if not self.near_outlier_fraction < 0.5:
            out.append(
                f"{100 * self.near_outlier_fraction:.0f} % of the points near the model (within the crop distance) "
                f"are outliers, farther than {self.outlier_sigma:g}σ from every modelled surface"
            )
        if self.jumped:
            out.append(
                f"it contradicts the previous state (χ² {self.prior_chi2:.4g} for {self.prior_dof}, "
                f"p = {self.prior_p:.3g}), and the scan alone does not determine it"
            )
        return out

    def prior(self) -> Prior:
        """The posterior as a prior for the next update (information form)."""
        return Prior(tuple(self.names), self.x.copy(), self.information.copy())

    def text(self) -> str:
        from mbcal.text import table  # the terminal table helper

        sig = float(np.median(self.sigma)) if len(self.sigma) else 0.0
        lines = [
            f"scan fit: {len(self.points)} points used of {self.total_points} "
            f"({self.thinned} left out by the down-sampling, {self.cropped} cropped as far from the model"
            + (f", {self.capped} left out at random above the cap of {len(self.points)} points" if self.capped else "")
            + f"), σ {1000 * sig:.3g} mm",
        ]
        if self.nonfinite:
            lines.append(
                f"{self.nonfinite} point(s) of the scans left out as read: "
                "a coordinate is not a finite number (NaN, inf)"
            )
        if self.mostly_cropped:
            lines.append(self.mostly_cropped)
        if self.coarse is not None:
            t = self.coarse[:3, 3]
            ang = np.degrees(np.arccos(np.clip((np.trace(self.coarse[:3, :3]) - 1) / 2, -1, 1)))
            lines.append(f"coarse alignment: moved the cloud {100 * np.linalg.norm(t):.3g} cm and {ang:.3g}°")
        rows = []
        std = self.std
        for i, n in enumerate(self.names):
            unit = self.units.get(n, "")
            f = np.degrees if unit == "deg" else (lambda v: v)
            sigma = f"{f(std[n]):.3g}" if np.isfinite(std[n]) else "∞ (unobservable)"
            rows.append([n, f"{f(self.x_start[i]):.6g}", f"{f(self.x[i]):.6g}", sigma, unit])
        lines.append(table(["unknown", "start", "estimate", "σ", "unit"], rows))
        lines.append(
            f"inliers: reduced χ² {self.reduced_chi2:.3g} (dof {self.dof}); outliers (on no modelled surface): "
            f"{self.n_outliers} ({100 * self.outlier_fraction:.1f} %): {self.cropped} beyond the crop distance, "
            f"{int(self.outlier.sum())} within it but farther than {self.outlier_sigma:g}σ "
            f"({100 * self.near_outlier_fraction:.1f} % of the points within it: the verdict's share, "
            "under 50 % to be ok)"
        )
        for m in self.structural:
            lines.append("structural misfit: " + m.message(self.outlier_sigma, sig))
        for name in self.unobservable:
            lines.append(f"unobservable: {name}")
        if self.prior_p is not None:
            lines.append(
                f"against the prior (the previous state, widened by the process noise): χ² {self.prior_chi2:.4g} "
                f"for {self.prior_dof}, p = {self.prior_p:.3g}"
                + (
                    ""
                    if self.prior_consistent
                    else f" < {DEFAULT_THRESHOLD:g}: a move beyond the process noise"
                    + (
                        ", which the scan alone determines"
                        if self.determined_by_scans
                        else ", which the scan alone does not determine"
                    )
                )
            )
        verdict = "ok" if self.ok else "NOT trustworthy"
        if not self.converged:
            verdict += " (the solver did not converge)"
        elif self.reduced_chi2 >= 2.0:
            verdict += " (the inliers scatter more than σ: a wrong σ, or a model that does not fit)"
        elif self.sigma_too_large:
            verdict += (
                " (the inliers scatter far less than σ: σ stated too large — a number of millimetres "
                "given as metres? — which would hide a model that does not fit)"
            )
        elif self.jumped:
            verdict += " (the estimate contradicts the previous state, and the scan alone does not determine it)"
        lines.append(f"verdict: {verdict}")
        return "\n".join(lines)

    def to_json(self) -> dict[str, Any]:
        """The fit for machines (``MODEL.fit.json``, ``mbcal fit --json``): values and σ in SI
        units, named in ``units``; mbcal/schemas/scan_fit.schema.json describes every field.  JSON
        has no ∞: the σ of an unknown the scans do not determine (named in ``unobservable``) is
        null."""
        std = self.std
        return finite_or_null(
            {
                "format": SCAN_FIT_FORMAT,
                "values": self.values,
                "std": std,
                "units": {n: _SI_UNIT.get(self.units.get(n, ""), self.units.get(n, "")) for n in self.names},
                "chi2": self.chi2,
                "dof": self.dof,
                "reduced_chi2": self.reduced_chi2,
                "points": len(self.points),
                "total_points": self.total_points,
                "cropped": self.cropped,
                "thinned": self.thinned,
                "capped": self.capped,
                "nonfinite": self.nonfinite,
                "outliers": {
                    "count": self.n_outliers,
                    "fraction": self.outlier_fraction,
                    "cropped": self.cropped,
                    "beyond_sigma": int(self.outlier.sum()),
                    "near_fraction": self.near_outlier_fraction,
                },
                "structural_misfits": [m.object for m in self.structural],
                "objects": [
                    {"object": m.object, "points": m.points, "beyond": m.beyond, "rms": m.rms, "flagged": m.flagged}
                    for m in self.misfits
                ],
                "unobservable": self.unobservable,
                "prior_chi2": self.prior_chi2,
                "prior_dof": self.prior_dof,
                "prior_p": self.prior_p,
                "determined_by_scans": self.determined_by_scans,
                "converged": self.converged,
                "ok": self.ok,
                "doubts": self.doubts,
                "hint": self.mostly_cropped or None,
                "elapsed": self.elapsed,
            }
        )


# ---- the compiled functions, one set per problem structure -------------------------------------------------


class _Engine:
    """The compiled functions of one model, unknowns, configurations and scan frames.

    ``screen``: every point's distance to every shape (exact, except a mesh's: the distance to its
    bounding box, a lower bound); ``exact[s]``: a mesh's exact distance on the few points near it;
    ``residual`` / ``nearest``: each point's distance to the nearest of its *candidate* shapes,
    given per shape as an index array of the points it is a candidate for (``-1``: padding).
    """

    def __init__(self, model: Model, ps: ParameterSet, pairs: tuple[tuple[int, int], ...]):
        self.model, self.ps, self.pairs = model, ps, pairs
        self.shapes = list(model.shapes)
        self.meshes = tuple(k for k, s in enumerate(self.shapes) if s.kind == "mesh")
        self.caps: tuple[int, ...] | None = None  # the group sizes last compiled for (reused while they fit)
        C = len(ps.configurations)
        needs = Needs(frames=frozenset(f for _, f in pairs if f >= 0), shapes=None)
        n_frames = len(model.frames)
        pair_config = np.array([c for c, _ in pairs], dtype=np.int64)
        shapes = self.shapes

        def scenes(x, known):
            rows, configs = ps.views(x, known)
            return jax.vmap(lambda row, c: modeler(model, ps.view(x, row, c), needs))(rows, configs)

        def world(x, known, pts, pair):
            sc = scenes(x, known)
            out = jnp.zeros_like(pts)
            for k, (c, f) in enumerate(pairs):
                if f < 0 or f >= n_frames:
                    p = pts
                else:
                    T = sc.frame_poses[c, f]
                    p = jnp.sum(T[None, :3, :3] * pts[:, None, :], axis=2) + T[:3, 3]
                out = out + jnp.where((pair == k)[:, None], p, 0.0) if len(pairs) > 1 else p
            return sc, out

        def shape_local(sc, s, w, pair):
            """Points w (k, 3) in the frame of shape s, and its dims, in each point's configuration."""
            if C == 1:
                T, dims = sc.shape_poses[0, s], sc.shape_dims[0, s]
            else:
                cfg = jnp.asarray(pair_config)[pair]
                T, dims = sc.shape_poses[cfg, s], sc.shape_dims[cfg, s]
            d = w - T[..., :3, 3]
            return jnp.sum(d[..., :, None] * T[..., :3, :3], axis=-2), dims

        def box_bound(shape, p, dims):
            """Distance from p to the bounding box of a mesh's scaled vertices: a lower bound of
            the distance to its surface (every surface point lies in the box)."""
            V = np.asarray(shape.mesh.vertices, dtype=float).reshape(-1, 3)
            if len(V) == 0:
                return jnp.full(p.shape[:-1], jnp.inf)
            a, b = dims * V.min(axis=0), dims * V.max(axis=0)
            lo, hi = jnp.minimum(a, b), jnp.maximum(a, b)
            gap = jnp.maximum(jnp.maximum(lo - p, p - hi), 0.0)
            return jnp.sqrt(jnp.sum(gap * gap, axis=-1))

        def screen(x, known, pts, pair):
            sc, w = world(x, known, pts, pair)
            cols = []
            for s, shape in enumerate(shapes):
                p, dims = shape_local(sc, s, w, pair)
                if shape.kind == "mesh":
                    cols.append(box_bound(shape, p, dims))
                else:
                    cols.append(surface_distance(shape.kind, p, dims, shape.mesh))
            return jnp.stack(cols, axis=1), w

        def exact(s):
            def one(x, known, pts, pair):
                sc, w = world(x, known, pts, pair)
                p, dims = shape_local(sc, s, w, pair)
                return surface_distance(shapes[s].kind, p, dims, shapes[s].mesh)

            return jax.jit(one)

        def nearest(x, known, pts, pair, groups):
            sc, w = world(x, known, pts, pair)
            ds, ix = [], []
            for s, (shape, g) in enumerate(zip(shapes, groups)):
                valid = g >= 0
                gi = jnp.where(valid, g, 0)
                p, dims = shape_local(sc, s, w[gi], pair[gi])
                d = surface_distance(shape.kind, p, dims, shape.mesh)
                ds.append(jnp.where(valid, d, jnp.inf))
                ix.append(gi)
            if not ds:
                return jnp.full(pts.shape[0], jnp.inf), w
            d = jax.ops.segment_min(jnp.concatenate(ds), jnp.concatenate(ix), num_segments=pts.shape[0])
            return d, w

        def residual(x, pts, pair, weight, known, A, b, *groups):
            d, _ = nearest(x, known, pts, pair, groups)
            r = jnp.where(weight > 0, d, 0.0) * weight  # padding rows have no candidates (d = inf)
            return jnp.concatenate([r, A @ x - b])

        def shape_frames(x, known):
            sc = scenes(x, known)
            return sc.shape_poses[:, :, :3, :]

        enable_compilation_cache()
        self.residual = residual  # the same object every call: least_squares caches its program on it
        self.jacobian = jax.jit(jax.jacfwd(residual))
        self.screen = jax.jit(screen)
        self.exact = {s: exact(s) for s in self.meshes}
        self.world = jax.jit(lambda x, known, pts, pair: world(x, known, pts, pair)[1])
        self.shape_frames = jax.jit(shape_frames)


_ENGINES: dict[Any, _Engine] = {}


def _engine(model: Model, ps: ParameterSet, pairs: tuple[tuple[int, int], ...]) -> _Engine:
    key = (
        id(model),
        tuple(ps.names),
        ps.configurations,
        pairs,
        tuple(sorted(map(tuple, np.argwhere(ps._source >= 0).tolist()))),
    )
    eng = _ENGINES.get(key)
    if eng is None or eng.model is not model:
        if len(_ENGINES) > 16:
            _ENGINES.clear()
        eng = _Engine(model, ps, pairs)
        _ENGINES[key] = eng
    return eng


def _pad(n: int) -> int:
    return max(BUCKET, -(-n // BUCKET) * BUCKET)


def _size_class(n: int) -> int:
    """The padded size of an array of n entries: 16, 32, ..., 4096, then multiples of 4096 (few
    sizes, so that compiled programs are reused)."""
    c = 16
    while c < n and c < BUCKET:
        c *= 2
    return c if c >= n else -(-n // BUCKET) * BUCKET


def _padded(values: np.ndarray, size: int, fill: float | int = 0) -> np.ndarray:
    out = np.full((size, *values.shape[1:]), fill, dtype=values.dtype)
    out[: len(values)] = values
    return out


class _Points:
    """The fit's points padded for the compiled programs, and the screening of their distances."""

    def __init__(self, eng: _Engine, known: np.ndarray, pts: np.ndarray, pair: np.ndarray):
        self.eng, self.n = eng, len(pts)
        self.m = _pad(self.n)
        self.known = to_device(known)
        self.P = to_device(_padded(pts, self.m))
        self.Q = to_device(_padded(pair, self.m))
        self.pts, self.pair = pts, pair

    def screen(self, x: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
        """(n, S) distances of every point to every shape at x — exact where it can matter: a
        mesh's only where its bounding box is within ``margin`` of the nearest other shape (a
        lower bound elsewhere) — and the (n, 3) world points."""
        eng, n = self.eng, self.n
        xd = to_device(np.asarray(x, dtype=float))
        D, W = (np.array(v)[:n] for v in eng.screen(xd, self.known, self.P, self.Q))
        if eng.meshes:
            others = [k for k in range(D.shape[1]) if k not in eng.meshes]
            best = D[:, others].min(axis=1) if others else np.full(n, np.inf)
            for s in eng.meshes:
                near = np.nonzero(D[:, s] <= best + margin)[0]
                if len(near) == 0:
                    continue
                k = _size_class(len(near))
                d = eng.exact[s](
                    xd, self.known, to_device(_padded(self.pts[near], k)), to_device(_padded(self.pair[near], k))
                )
                D[near, s] = np.asarray(d)[: len(near)]
                best = np.minimum(best, D[:, s])
        return D, W

    def groups(self, D: np.ndarray, margin: float) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
        """The (n, S) candidate matrix (the shapes within ``margin`` of each point's nearest one)
        and, per shape, the points it is a candidate for, padded with −1 to a size class; the sizes
        last compiled for are kept while the counts fit in them."""
        cand = D <= D.min(axis=1, keepdims=True) + margin
        counts = cand.sum(axis=0)
        caps = self.eng.caps
        fresh = sum(_size_class(int(c)) for c in counts)
        if caps is None or len(caps) != len(counts) or np.any(counts > np.array(caps)) or sum(caps) > 2 * fresh:
            # Room to grow (an eighth, and at least 64), so that the next batches of a scene fit.
            caps = tuple(_size_class(int(c) + max(64, int(c) // 8)) for c in counts)
            self.eng.caps = caps
        return cand, tuple(_padded(np.nonzero(cand[:, s])[0], caps[s], -1) for s in range(len(caps)))


def _misassigned(D: np.ndarray, cand: np.ndarray) -> bool:
    """Whether a point's nearest shape (D at the solution) is nearer than all its candidates."""
    return bool(np.any(D.min(axis=1) < np.where(cand, D, np.inf).min(axis=1) - 1e-9))


# ---- priors ---------------------------------------------------------------------------------------------


def _prior_rows(ps: ParameterSet, prior: Prior | None, model_priors: bool) -> tuple[np.ndarray, np.ndarray]:
    """Rows A, b (2n × n, 2n) with the prior residual A x − b: the information-form prior (Λ = LLᵀ
    → Lᵀ(x − m)) and the model's σ priors (x_j − nominal_j)/σ_j."""
    n = ps.size
    A = np.zeros((2 * n, n))
    b = np.zeros(2 * n)
    if prior is not None:
        index = {name: j for j, name in enumerate(ps.names)}
        take = [(i, index[name]) for i, name in enumerate(prior.names) if name in index]
        Lam = np.zeros((n, n))
        m = np.array(ps.x0, dtype=float)
        src = np.array([i for i, _ in take], dtype=np.int64)
        dst = np.array([j for _, j in take], dtype=np.int64)
        if len(take):
            Lam[np.ix_(dst, dst)] = np.asarray(prior.information)[np.ix_(src, src)]
            m[dst] = np.asarray(prior.mean)[src]
        e, V = np.linalg.eigh(0.5 * (Lam + Lam.T))
        R = np.sqrt(np.clip(e, 0.0, None))[:, None] * V.T  # RᵀR = Λ
        A[:n] = R
        b[:n] = R @ m
    if model_priors:
        sig = ps.prior_sigma
        has = np.isfinite(sig)
        j = np.nonzero(has)[0]
        A[n + j, j] = 1.0 / sig[j]
        b[n + j] = ps.prior_mean[j] / sig[j]
    return A, b


# ---- coarse alignment -----------------------------------------------------------------------------------


def _icp(cloud: np.ndarray, target: np.ndarray, seed: int = 0) -> np.ndarray:
    """Trimmed point-to-point ICP: the rigid T (4×4) with T·cloud ≈ target, from the identity,
    with a shrinking correspondence distance (50 cm → 1 cm)."""
    from scipy.spatial import cKDTree
    from trimesh.registration import procrustes  # Kabsch's best rigid motion (no scaling, no reflection)

    rng = np.random.default_rng(seed)
    src = cloud if len(cloud) <= 4000 else cloud[rng.choice(len(cloud), 4000, replace=False)]
    tree = cKDTree(target)
    T = np.eye(4)
    # Start by matching centroids of the cloud and of the target points near it.
    for radius in (0.5, 0.3, 0.2, 0.1, 0.05, 0.03, 0.02, 0.01):
        for _ in range(12):
            moved = src @ T[:3, :3].T + T[:3, 3]
            d, idx = tree.query(moved, distance_upper_bound=radius)
            ok = np.isfinite(d)
            if ok.sum() < 10:
                break
            step, _, _ = procrustes(moved[ok], target[idx[ok]], reflection=False, translation=True, scale=False)
            T = step @ T
            if np.linalg.norm(step[:3, 3]) < 1e-5 and np.allclose(step[:3, :3], np.eye(3), atol=1e-6):
                break
    return T


def _model_samples(eng: _Engine, x: np.ndarray, known: np.ndarray, near: np.ndarray, count: int = 40000) -> np.ndarray:
    """Points on the model's surfaces (configuration 0) within 0.5 m of the box around ``near``."""
    import trimesh  # the model's meshes, sampled for the global alignment

    rows, configs = eng.ps.views(jnp.asarray(x), jnp.asarray(known))
    scene = modeler(eng.model, eng.ps.view(jnp.asarray(x), rows[0], configs[0]))
    lo, hi = near.min(axis=0) - 0.5, near.max(axis=0) + 0.5
    meshes = list(scene.to_trimesh(plane_size=2 * float(np.max(hi - lo)) + 2).dump())
    mesh = trimesh.util.concatenate(meshes)
    pts, _ = trimesh.sample.sample_surface(mesh, count, seed=0)
    keep = np.all((pts >= lo) & (pts <= hi), axis=1)
    return np.asarray(pts[keep])


def _fit_rigid_motion(eng: _Engine, x: np.ndarray, known: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Unknowns that move the model's shapes by T⁻¹ (the cloud moved by T onto the model at x)."""
    Ti = np.linalg.inv(T)
    F0 = np.asarray(eng.shape_frames(jnp.asarray(x), jnp.asarray(known)))  # (C, S, 3, 4)
    target = np.einsum("ij,csjk->csik", Ti[:3, :3], F0)
    target[..., 3] += Ti[:3, 3]

    def fun(xx, tgt, kk):
        return jnp.reshape(eng.shape_frames(xx, kk) - tgt, (-1,))

    out = least_squares(fun, x[None], args=(target, known), config=SolverConfig(max_iterations=50))
    return np.asarray(out.x_best)


# ---- the fit ----------------------------------------------------------------------------------------------


def scan_world_points(model: Model, scan: Scan, values: Mapping[str, float] | None = None) -> np.ndarray:
    """A scan's points in world coordinates for parameter values (default: nominal)."""
    if scan.frame == "world":
        return np.asarray(scan.points, dtype=float)
    scene = modeler(model, dict(values or {}), Needs.everything())
    T = np.asarray(scene.frame(scan.frame))
    return scan.points @ T[:3, :3].T + T[:3, 3]


def residuals_at(model: Model, scan: Scan, values: Mapping[str, float] | None = None) -> np.ndarray:
    """Each scan point's distance (m) to the nearest modelled surface, for parameter values."""
    scene = modeler(model, dict(values or {}), Needs.everything())
    w = scan_world_points(model, scan, values)
    return np.asarray(distance_to_shapes(scene.shape_poses, scene.shape_dims, list(model.shapes), jnp.asarray(w)))


def scan_measurements(
    model: Model,
    scans: Sequence[Scan],
    *,
    voxel: float = 0.01,
    crop: float = 0.10,
    max_points: int = 2000,
    values: Mapping[str, float] | None = None,
    seed: int = 0,
) -> MeasurementSet:
    """Scans as ``point_to_surface`` measurements, to sit beside clicked points in one problem
    (``mbcal solve MODEL clicks.csv scan.ply``).

    Each scan is down-sampled (``voxel``), its points farther than ``crop`` from every modelled
    surface at ``values`` (default: nominal) are left out, at most ``max_points`` per scan are kept
    (a seeded random subset), and each point measures its distance to the top-level object that
    holds its nearest shape there, with the scan's σ.  Points nearest to a shape fixed in the world
    (no object to name) are left out.
    """
    from mbcal.measurements.sets import measurements_from_records  # the measurement layer builds the set

    scene = modeler(model, dict(values or {}), Needs.everything())
    poses, dims = np.asarray(scene.shape_poses), np.asarray(scene.shape_dims)

    def top(frame: int) -> str | None:
        if frame < 0:
            return None
        while model.frames[frame].parent >= 0:
            frame = model.frames[frame].parent
        return model.frames[frame].name

    owner = [top(s.frame) for s in model.shapes]
    rng = np.random.default_rng(seed)
    records: list[dict[str, Any]] = []
    for k, scan in enumerate(scans, start=1):
        pts = np.asarray(scan.downsampled(voxel), dtype=float)
        sig = scan.sigmas(pts)
        world = scan_world_points(model, scan.with_points(pts), values)
        if not model.shapes:
            break
        D = np.stack(
            [
                np.asarray(surface_distance(s.kind, (world - poses[i, :3, 3]) @ poses[i, :3, :3], dims[i], s.mesh))
                for i, s in enumerate(model.shapes)
            ],
            axis=1,
        )
        nearest = np.argmin(D, axis=1)
        named = np.array([owner[j] is not None for j in nearest], dtype=bool)
        keep = np.nonzero((D.min(axis=1) <= crop) & named)[0]
        if len(keep) > max_points:
            keep = np.sort(rng.choice(keep, max_points, replace=False))
        for i in keep:
            record = {"kind": "point_to_surface", "id": f"scan{k}.{i}", "object": owner[nearest[i]], "sigma": sig[i]}
            record.update(x=pts[i, 0], y=pts[i, 1], z=pts[i, 2])
            if scan.frame != "world":
                record["frame"] = scan.frame
            records.append(record)
    if not records:
        raise SolverError(
            f"no scan point lies within {crop:g} m of a modelled object", hint="is the scan in the right frame?"
        )
    return measurements_from_records(records, model)


def fit_scans(
    model: Model,
    scans: Sequence[Scan],
    estimate: Sequence[str],
    options: FitOptions | None = None,
    *,
    initial: Mapping[str, float] | None = None,
    prior: Prior | None = None,
    per_configuration: Mapping[str, Mapping[str, float]] | None = None,
) -> ScanFit:
    """Estimate the unknowns from scans by point-to-surface residuals (see the module doc)."""
    o = options or FitOptions()
    t0 = time.perf_counter()
    if not scans:
        raise SolverError("no scans to fit")
    try:
        loss = Loss(o.loss)
    except ValueError:
        raise SolverError(f"unknown loss '{o.loss}' (cauchy, huber or linear)") from None
    configs = list(dict.fromkeys(s.config for s in scans))
    ps = ParameterSet(
        model, list(estimate), configurations=configs, per_configuration=per_configuration, overrides=o.known
    )
    if ps.size == 0:
        raise SolverError("nothing to estimate: name the unknowns (--estimate NAME|GLOB)")
    pair_keys: list[tuple[int, int]] = []
    pts_list, pair_list, sig_list = [], [], []
    total = kept_total = 0  # the scans' points, and those the down-sampling kept
    for s in scans:
        f = -1 if s.frame == "world" else model.frame_index(s.frame)
        key = (configs.index(s.config), f)
        if key not in pair_keys:
            pair_keys.append(key)
        p = np.asarray(s.downsampled(o.voxel), dtype=float)
        total += len(s)
        kept_total += len(p)
        pts_list.append(p)
        pair_list.append(np.full(len(p), pair_keys.index(key), dtype=np.int64))
        sig_list.append(s.sigmas(p))
    pairs = tuple(pair_keys)
    eng = _engine(model, ps, pairs)
    pts = np.concatenate(pts_list)
    pair = np.concatenate(pair_list)
    sig = np.concatenate(sig_list)
    known = np.asarray(ps.known)
    x = ps.x0.copy()
    if initial:
        # A name that is no estimated parameter is an error (as in calibrate); a copy of one for a
        # configuration these scans do not have (the model manager's earlier batches) is not used.
        estimated = {u.param.name for u in ps.unknowns}
        strange = [k for k in initial if k not in ps.names and k.split("@", 1)[0] not in estimated]
        if strange:
            ps.from_dict({strange[0]: initial[strange[0]]})  # raises, with the closest names
        x = ps.from_dict({k: v for k, v in initial.items() if k in ps.names}, default=x)
    x_start = x.copy()

    margin = o.assign_margin
    cloud = _Points(eng, known, pts, pair)
    D, W = cloud.screen(x, margin)
    coarse = None
    if o.coarse != "never":
        if o.coarse == "always" or float(np.median(D.min(axis=1))) > o.coarse_distance:
            target = _model_samples(eng, x, known, W)
            if len(target) >= 10:
                coarse = _icp(W, target, o.seed)
                x = _fit_rigid_motion(eng, x, known, coarse)
                D, W = cloud.screen(x, margin)
    keep = D.min(axis=1) <= o.crop
    cropped = int((~keep).sum())
    far_pts, far_pair = pts[~keep], pair[~keep]
    pts, pair, sig, D = pts[keep], pair[keep], sig[keep], D[keep]
    if len(pts) < ps.size:
        raise SolverError(
            f"only {len(pts)} scan points lie within {o.crop:g} m of the model at the start",
            hint="is the scan in the right frame? try a larger --crop, or a global alignment (--coarse always)",
        )
    capped = max(len(pts) - o.max_points, 0)
    if capped:
        sel = np.sort(np.random.default_rng(o.seed).choice(len(pts), o.max_points, replace=False))
        pts, pair, sig, D = pts[sel], pair[sel], sig[sel], D[sel]
    cloud = _Points(eng, known, pts, pair)
    n, m = cloud.n, cloud.m
    Wt = _padded(1.0 / sig, m)
    A, b = _prior_rows(ps, prior, o.priors)

    def arguments(groups: Sequence[np.ndarray], scale: float = 1.0) -> tuple[Any, ...]:
        rows = (Wt / scale, cloud.known, A / scale, b / scale, *groups)
        return (cloud.P, cloud.Q, *(to_device(r) for r in rows))

    def solve(starts: np.ndarray, args: tuple[Any, ...], cfg: SolverConfig):
        return least_squares(eng.residual, starts, args=args, config=cfg, size=m + 2 * ps.size, bounds=ps.bounds)

    config = SolverConfig(loss=loss, max_iterations=o.max_iterations, ftol=1e-12, xtol=1e-12, gtol=1e-12)

    def refine(xb: np.ndarray, args: tuple[Any, ...], probes: int) -> tuple[np.ndarray, float, bool]:
        solved = solve(xb[None], args, config)
        if solved.best < 0:
            raise SolverError("the scan fit failed: residuals are not finite at any start")
        xb = np.asarray(solved.x[0], dtype=float)
        converged = int(solved.status[0]) > 0 and int(solved.iterations[0]) < o.max_iterations
        cost = float(solved.cost[0])
        for _ in range(probes):
            # Probe along the weakest directions: the nearest surface of a point changes at edges, so
            # S is only piecewise smooth and Marquardt may stop in a shallow pocket a few σ off.
            # One start at a time: the program of the solve above, no other to compile.
            J = np.asarray(eng.jacobian(to_device(xb), *args))
            e, V = np.linalg.eigh(J.T @ J)
            best = None
            for k in range(min(2, ps.size)):
                step = o.probe_sigma * V[:, k] / np.sqrt(max(e[k], 1e-300))
                for sign in (1.0, -1.0):
                    again = solve((xb + sign * step)[None], args, config)
                    if again.best >= 0 and (best is None or float(again.cost[0]) < float(best.cost[0])):
                        best = again
            if best is None or float(best.cost[0]) >= cost - o.probe_gain:
                break
            xb, cost = np.asarray(best.x[0], dtype=float), float(best.cost[0])
            converged = int(best.status[0]) > 0 and int(best.iterations[0]) < o.max_iterations
        return xb, cost, converged

    cand, groups = cloud.groups(D, margin)
    args = arguments(groups)
    # A fit warm-started from a previous posterior (the manager) starts at a tracked minimum: no probes.
    probes = o.probe_rounds if prior is None else 0
    check_size(max(1, o.restarts), ps.size, m + 2 * ps.size)  # the batch fits in memory, or a clear error
    starts = random_starts(x, ps.lower, ps.upper, max(1, o.restarts), o.seed, limits=ps.bounds)
    # Graduated robustness: a wide loss first, so points that moved far (a lever that turned) still
    # pull before the nominal loss would dismiss them as outliers.  The loss with the scale k·c on
    # r is k² times the loss with c on r/k: the same compiled program on rows scaled by 1/k.
    graduated = loss != Loss.LINEAR and o.graduated > 1
    if graduated or len(starts) > 1:
        first = solve(starts, arguments(groups, o.graduated if graduated else 1.0), config)
        if first.best >= 0:
            x = np.asarray(first.x[first.best], dtype=float)
            D, _ = cloud.screen(x, margin)
            if _misassigned(D, cand):
                cand, groups = cloud.groups(D, margin)
                args = arguments(groups)
    xb, cost, converged = refine(x, args, probes)
    # The candidates were chosen before the solve; where the solution moved so far that a point's
    # nearest shape is no longer among them, choose them again there and solve again (at most 3 times;
    # still misassigned after that: the solution is not a minimum of S, not converged).
    for attempt in range(4):
        D, Wpts = cloud.screen(xb, margin)
        if not _misassigned(D, cand):
            break
        if attempt == 3:
            converged = False
            break
        cand, groups = cloud.groups(D, margin)
        args = arguments(groups)
        xb, cost, converged = refine(xb, args, probes)
    # Per point and shape distances at the solution: outliers, association, misfit per object.
    nearest = np.argmin(D, axis=1)
    res = D[np.arange(n), nearest]
    outlier = res > o.outlier_sigma * sig
    J = np.asarray(eng.jacobian(to_device(xb), *args))
    Jm = J[:n][~outlier]
    Jp = J[m:]
    info = Jm.T @ Jm + Jp.T @ Jp
    unobservable: list[str] = []
    e, V = np.linalg.eigh(info)
    tol = max(float(e.max()), 1e-300) * 1e-12
    if np.any(e <= tol):
        for weak in np.nonzero(e <= tol)[0]:
            v = V[:, weak]
            parts = [f"{v[j]:+.2f}·{ps.names[j]}" for j in np.argsort(-np.abs(v)) if abs(v[j]) > 0.1]
            unobservable.append(" ".join(parts))
        cov = np.linalg.pinv(info, rcond=1e-12)
        cov[np.ix_(np.abs(V[:, e <= tol]).max(axis=1) > 0.1, np.abs(V[:, e <= tol]).max(axis=1) > 0.1)] = np.inf
    else:
        cov = np.linalg.inv(info)
    rin = (res / sig)[~outlier]
    chi2 = float(np.sum(rin**2))
    prior_chi2, prior_dof, alone = None, 0, True
    if prior is not None:  # its rows are the first ps.size of A: Lᵀ(x − m)
        rows = A[: ps.size] @ xb - b[: ps.size]
        prior_chi2, prior_dof = float(rows @ rows), int(np.linalg.matrix_rank(A[: ps.size]))
        Jq = Jp[ps.size :]  # the model's σ priors, without the previous posterior
        e_alone = np.linalg.eigvalsh(Jm.T @ Jm + Jq.T @ Jq)
        alone = bool(np.all(e_alone > max(float(e_alone.max()), 1e-300) * 1e-12))
    dof = max(int((~outlier).sum()) - ps.size, 1)
    misfits = _misfits(model, nearest, outlier, res, o)
    units = {u.name: u.param.unit for u in ps.unknowns}
    return ScanFit(
        names=list(ps.names),
        x=xb,
        x_start=x_start,
        covariance=cov,
        information=info,
        chi2=chi2,
        dof=dof,
        points=Wpts,
        residuals=res,
        sigma=sig,
        outlier=outlier,
        cropped=cropped,
        thinned=total - kept_total,
        capped=capped,
        far=_world(eng, xb, known, far_pts, far_pair) if len(far_pts) else np.zeros((0, 3)),
        total_points=total,
        nonfinite=sum(s.nonfinite for s in scans),
        misfits=misfits,
        coarse=coarse,
        elapsed=time.perf_counter() - t0,
        converged=converged,
        outlier_sigma=o.outlier_sigma,
        units=units,
        prior_chi2=prior_chi2,
        prior_dof=prior_dof,
        determined_by_scans=alone,
        unobservable=unobservable,
    )


def _world(eng: _Engine, x: np.ndarray, known: np.ndarray, pts: np.ndarray, pair: np.ndarray) -> np.ndarray:
    m = _pad(len(pts))
    args = (np.asarray(x, dtype=float), known, _padded(pts, m), _padded(pair, m))
    return np.asarray(eng.world(*(to_device(a) for a in args)))[: len(pts)]


def _misfits(model: Model, nearest: np.ndarray, outlier: np.ndarray, res: np.ndarray, o: FitOptions) -> list[Misfit]:
    """Per object (the frame that declares a shape): its points, those beyond the outlier limit, the flag."""
    owner = [model.frames[s.frame].name if s.frame >= 0 else "world" for s in model.shapes]
    out = []
    for obj in dict.fromkeys(owner):
        shapes = [k for k, ow in enumerate(owner) if ow == obj]
        mine = np.isin(nearest, shapes)
        count = int(mine.sum())
        if count == 0:
            continue
        beyond = int((mine & outlier).sum())
        flagged = beyond >= o.misfit_min_points and beyond > o.misfit_fraction * count
        names = tuple(f"{model.shapes[k].name}:{model.shapes[k].kind}" for k in shapes)
        out.append(Misfit(obj, names, count, beyond, float(np.sqrt(np.mean(res[mine] ** 2))), flagged))
    return out
