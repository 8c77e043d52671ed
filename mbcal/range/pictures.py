"""Pictures of range calibration: the scan over the model before and after, coloured by each
point's distance to the model; the manager's history of estimates with σ bands."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from mbcal.language.model import Model
from mbcal.range.fit import residuals_at
from mbcal.range.manager import Update
from mbcal.range.scans import Scan, depth_camera
from mbcal.range.simulate import render_depth
from mbcal.render.views import plot_figure, save_figure

__all__ = ["plot_scan_fit", "plot_history"]


def plot_scan_fit(
    model: Model,
    scan: Scan,
    before: Mapping[str, float],
    after: Mapping[str, float],
    path: str | os.PathLike,
    *,
    limit_mm: float = 10.0,
) -> None:
    """Two panels, the depth camera's view at ``before`` and at ``after``: the model's depth in
    grey, the scan's points on it coloured by their distance to the model (mm, clipped)."""
    info = depth_camera(model)
    assert info.intrinsics is not None
    fx, fy, cx, cy = info.intrinsics
    fig, grid = plot_figure(1, 2, figsize=(11, 3.6), layout="constrained")
    axes = grid[0]
    image: Any = None
    for ax, values, title in (
        (axes[0], before, "before: model at its nominal values"),
        (axes[1], after, "after: at the estimate"),
    ):
        depth = render_depth(model, values)
        ax.imshow(np.nan_to_num(depth, nan=np.nanmax(depth)), cmap="gray", vmin=0.3, vmax=3.0)
        d = 1000 * residuals_at(model, scan, values)
        p = scan.points
        u, v = fx * p[:, 0] / p[:, 2] + cx, fy * p[:, 1] / p[:, 2] + cy
        image = ax.scatter(u, v, c=np.minimum(d, limit_mm), s=3, cmap="turbo", vmin=0, vmax=limit_mm)
        ax.set_title(f"{title}: median {np.median(d):.2g} mm", fontsize=9)
        ax.set_xlim(-0.5, info.width - 0.5)
        ax.set_ylim(info.height - 0.5, -0.5)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(image, ax=list(axes), label="distance to the model (mm)", shrink=0.9)
    save_figure(fig, path)


def plot_history(
    history: Sequence[Update],
    names: Sequence[str],
    path: str | os.PathLike,
    *,
    truth: Mapping[str, Sequence[float]] | None = None,
    scale: Mapping[str, float] | None = None,
    units: Mapping[str, str] | None = None,
) -> None:
    """Each parameter's estimate per update with ±1σ and ±3σ bands (and the truth, when known)."""
    fig, grid = plot_figure(len(names), 1, figsize=(7, 2.2 * len(names)), layout="constrained", sharex=True)
    axes = grid[:, 0]
    seq = np.array([u.seq for u in history])
    for ax, name in zip(axes, names):
        k = (scale or {}).get(name, 1.0)
        x = k * np.array([u.values[name] for u in history])
        s = k * np.array([u.std[name] for u in history])
        ax.fill_between(seq, x - 3 * s, x + 3 * s, color="tab:blue", alpha=0.15, label="±3σ")
        ax.fill_between(seq, x - s, x + s, color="tab:blue", alpha=0.35, label="±1σ")
        ax.plot(seq, x, "o-", color="tab:blue", ms=3, label="estimate")
        if truth and name in truth:
            ax.plot(seq, k * np.asarray(truth[name]), "k--", lw=1, label="truth")
        ax.set_ylabel(f"{name} ({(units or {}).get(name, '')})", fontsize=8)
        for u in history:
            if u.drift:
                ax.axvline(u.seq, color="tab:red", lw=0.8)
    axes[0].legend(fontsize=7, ncol=4, loc="upper left")
    axes[-1].set_xlabel("update")
    save_figure(fig, path)
