"""Pictures of a calibration: the model over the camera image before and after, and residuals.

Like the seed's Figures 10 and 11: the virtual model drawn as a wireframe over the real image,
before and after calibration, with the measured points marked.  mbcal adds the residual of
every point as a line from where the model puts it to where it was measured.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from mbcal._jax import jax
from mbcal.outputs import make_output_folder
from mbcal.render.views import (
    Layer,
    draw_overlay,
    plot_figure,
    render_view,
    save_figure,
    save_png,
    shared_context,
    wireframe_layer,
)

__all__ = ["calibration_overlays", "planned_overlays", "residual_plot", "BEFORE", "AFTER", "MEASURED"]

BEFORE = (215, 40, 40)
AFTER = (20, 150, 60)
MEASURED = (30, 80, 220)
RESIDUAL = (230, 130, 0)

Backgrounds = (
    Mapping[str, np.ndarray] | Mapping[tuple[str, str], np.ndarray] | Mapping[str | tuple[str, str], np.ndarray]
)
"""Photos to draw over: by camera, or by (camera, configuration) (see :func:`calibration_overlays`)."""


def _config_scene(scenes, config: int):
    """One configuration's scene of :meth:`Problem.whole_scenes` (every configuration at once)."""
    return jax.tree_util.tree_map(lambda a: a[config], scenes)


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name)


def _image_pairs(items) -> list[tuple[str, str]]:
    """The (camera, configuration) pairs of the image points among ``items`` (measurements or
    residual rows: both have ``kind``, ``refs`` and ``config``), in their order."""
    return list(dict.fromkeys((r.refs["camera"], r.config) for r in items if r.kind == "image_point"))


def overlay_files(model, camera: str, config: str, out_dir) -> tuple[Path, Path]:
    """The before and after pictures :func:`calibration_overlays` writes for one camera and configuration."""
    stem = _safe(model.short_name("camera", camera)) + ("" if config == "default" else f"_{_safe(config)}")
    return Path(out_dir) / f"{stem}_before.png", Path(out_dir) / f"{stem}_after.png"


def planned_overlays(model, measurements, out_dir, max_images: int = 24) -> list[Path]:
    """The files :func:`calibration_overlays` will write for these measurements: known before the
    solve, so that a name that is taken (an input photo in the same folder) is refused before it."""
    return [
        path
        for camera, config in _image_pairs(measurements)[:max_images]
        for path in overlay_files(model, camera, config, out_dir)
    ]


def calibration_overlays(
    result,
    out_dir,
    *,
    backgrounds: Backgrounds | None = None,
    cameras: list[str] | None = None,
    configurations: list[str] | None = None,
    vector_scale: float = 10.0,
    max_images: int = 24,
) -> list[Path]:
    """Write before/after overlay PNGs for every camera and configuration with image points.

    Parameters
    ----------
    result : CalibrationResult
    out_dir : path
        Folder for ``<camera>_<config>_before.png`` and ``..._after.png``.
    backgrounds : mapping
        Camera name → the real image (H, W, 3), or (camera name, configuration) → the image that
        camera took in that configuration (an arm in several attitudes: one photo each), which wins
        over the camera's own.  Without one, the calibrated model's own rendering is the background.
    vector_scale : float
        The residuals after calibration are drawn this many times longer (they are small).
    """
    problem = result.problem
    model = problem.model
    out_dir = make_output_folder(out_dir)
    by_camera: dict[str, np.ndarray] = {}
    by_config: dict[tuple[str, str], np.ndarray] = {}
    for key, image in (backgrounds or {}).items():
        if isinstance(key, tuple):
            by_config[(model.resolve("camera", key[0]), key[1])] = image
        else:
            by_camera[model.resolve("camera", key)] = image
    groups: dict[tuple[str, str], list] = {pair: [] for pair in _image_pairs(result.residuals)}
    for r in result.residuals:
        if r.kind == "image_point":
            groups[(r.refs["camera"], r.config)].append(r)
    if cameras is not None:
        wanted = {model.resolve("camera", c) for c in cameras}
        groups = {k: v for k, v in groups.items() if k[0] in wanted}
    if configurations is not None:
        groups = {k: v for k, v in groups.items() if k[1] in configurations}
    before_x = problem.params.x0
    written: list[Path] = []
    configs = list(problem.params.configurations)
    predicted_before = problem.predict(before_x)
    index = {m.id: i for i, m in enumerate(problem.measurements.measurements)}
    # Compiled (issue 16; the modeler op by op took ~0.6 s a call), once for all cameras and configurations.
    whole_before, whole_after = problem.whole_scenes(before_x), problem.whole_scenes(result.x)
    with shared_context():  # one OpenGL context for every view (issue 16)
        for (camera, config), members in list(groups.items())[:max_images]:
            c = configs.index(config)
            scene_before = _config_scene(whole_before, c)
            scene_after = _config_scene(whole_after, c)
            background = by_config.get((camera, config), by_camera.get(camera))
            # The wireframes need depth only; the shaded pass is drawn only as a missing background.
            view_before = render_view(scene_before, camera, color=False)
            view_after = render_view(scene_after, camera, color=background is None)
            if background is None:
                background = (0.55 * view_after.color + 0.45 * 255).astype(np.uint8)
            measured = np.array([r.measured for r in members])
            after = np.array([r.predicted for r in members])
            before = np.array([predicted_before[problem.measurement_rows[index[r.id]]] for r in members])
            before_file, after_file = overlay_files(model, camera, config, out_dir)
            img = draw_overlay(
                background,
                [
                    wireframe_layer(scene_before, camera, view_before, BEFORE, "model before calibration"),
                    Layer(
                        "vectors", np.stack([before, measured], axis=1), RESIDUAL, 1.5, "residual (model → measured)"
                    ),
                    Layer("points", measured, MEASURED, 1.5, "measured points"),
                ],
            )
            save_png(img, before_file)
            tips = after + vector_scale * (measured - after)
            img = draw_overlay(
                background,
                [
                    wireframe_layer(scene_after, camera, view_after, AFTER, "model after calibration"),
                    Layer(
                        "vectors",
                        np.stack([after, tips], axis=1),
                        RESIDUAL,
                        1.5,
                        f"residual × {vector_scale:g} (model → measured)",
                    ),
                    Layer("points", measured, MEASURED, 1.5, "measured points"),
                ],
            )
            save_png(img, after_file)
            written += [before_file, after_file]
    return written


def residual_plot(result, path, *, title: str | None = None) -> Path:
    """A PNG of the normalised residuals (worst first) and of the image residual vectors."""
    rows = sorted(result.residuals, key=lambda r: -r.normalized if np.isfinite(r.normalized) else np.inf)
    image_rows = [r for r in result.residuals if r.kind == "image_point"]
    fig, axes = plot_figure(1, 2 if image_rows else 1, figsize=(11 if image_rows else 6, 4.2))
    ax = axes[0, 0]
    values = np.array([r.normalized for r in rows])
    # Bars of width 1, worst first (a residual that is not a number last), the ones above the
    # threshold red: drawn as two filled step outlines instead of one patch per measurement (702
    # corners: ~0.6 s of patches).
    above = int(np.count_nonzero(values > result.outlier_threshold))
    edges = np.arange(len(values) + 1) - 0.5
    for part, color in ((slice(0, above), "#d62728"), (slice(above, len(values)), "#1f77b4")):
        if part.stop > part.start:
            ax.stairs(values[part], edges[part.start : part.stop + 1], fill=True, color=color, baseline=0.0)
    ax.axhline(
        result.outlier_threshold,
        color="#d62728",
        lw=1,
        ls="--",
        label=f"outlier threshold {result.outlier_threshold:g}σ",
    )
    ax.set_xlabel("measurement (worst first)")
    ax.set_ylabel("|residual| / σ")
    ax.set_title("normalised residuals")
    ax.legend(loc="upper right", fontsize=8)
    if image_rows:
        ax = axes[0, 1]
        cams = sorted({r.refs["camera"] for r in image_rows})
        for cam in cams:
            e = np.array([r.residual for r in image_rows if r.refs["camera"] == cam])
            ax.scatter(e[:, 0], e[:, 1], s=12, label=result.problem.model.short_name("camera", cam))
        lim = max(1.0, float(np.max(np.abs([r.residual for r in image_rows]))) * 1.1)
        ax.set_xlim(-lim, lim)
        ax.set_ylim(lim, -lim)  # image v axis points down
        ax.axhline(0, color="grey", lw=0.5)
        ax.axvline(0, color="grey", lw=0.5)
        ax.set_aspect("equal")
        ax.set_xlabel("u residual (px)")
        ax.set_ylabel("v residual (px)")
        ax.set_title(f"image residuals (RMS {result.rms.get('image_point', float('nan')):.3g} px)")
        ax.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    # Laid out: no engine left, so savefig draws once (a placeholder engine, as tight_layout leaves,
    # made it draw the whole figure twice: ~0.07 s of the demo).  The picture is the same.
    fig.set_layout_engine(None)
    save_figure(fig, path)
    return Path(path)
