"""The ``mbcal`` command line.

Every command prints errors a user can cause as ``path:line:col: message`` with the source
line and a caret, and exits with status 2 — never with a traceback.  Exit status 0 is
success; 1 means the command ran but the result is not trustworthy (not observable, not
converged, an estimate that breaks the model, the fit inconsistent with the stated σ,
systematic residuals, another solution as good, an unknown held at a hard limit, or weakly
determined; --accept-poor-fit accepts all but the first three); 130 means interrupted.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import shlex
import signal
import sys
import textwrap
import threading
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn

# The command line's own process (NumPy not loaded yet): one BLAS thread unless the user says
# otherwise.  The analysis's SVDs are small, and OpenBLAS threads that spin beside XLA's on a busy
# machine made them 100× slower (issue 16, docs/performance.md); a library user's process is
# left alone.
if "numpy" not in sys.modules:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from mbcal import __version__  # noqa: E402
from mbcal._collector import end_start_up, pause_start_up  # noqa: E402
from mbcal.cache import (  # noqa: E402
    CACHE_PARTS,
    PROGRAM_PARTS,
    cache_contents,
    cache_dir,
    cache_dir_problem,
    clear_cache,
    max_part_bytes,
)
from mbcal.errors import MbcalError, MbcalWarning, suggest  # noqa: E402
from mbcal.outputs import (  # noqa: E402
    INTERRUPTED,
    all_or_nothing,
    atomic_write,
    check_output,
    check_output_folder,
    protect,
    protected_inputs,
    refuse_inputs,
)
from mbcal.text import table  # noqa: E402
from mbcal.units import DIMENSIONLESS, LENGTH, UNITS, describe, to_display  # noqa: E402

__all__ = ["main", "build_parser"]

EXIT_OK = 0
EXIT_UNTRUSTED = 1
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130

Command = Callable[[argparse.Namespace], int]


def _formatter(prog: str) -> argparse.HelpFormatter:
    return argparse.RawDescriptionHelpFormatter(prog, max_help_position=32)


def _add(sub, name: str, summary: str, description: str, example: str, func: Command) -> argparse.ArgumentParser:
    parser = sub.add_parser(
        name,
        help=summary,
        description=textwrap.dedent(description).strip(),
        epilog="example:\n" + textwrap.indent(textwrap.dedent(example).strip(), "  "),
        formatter_class=_formatter,
    )
    parser.set_defaults(func=func)
    return parser


# ---- check ------------------------------------------------------------------------------------


def cmd_check(args: argparse.Namespace) -> int:
    # Every model is checked, as a linter checks every file: the first error stopped the rest unread.
    failed = 0
    for i, path in enumerate(args.models):
        try:
            model = _load(path)
        except MbcalError as err:
            if len(args.models) == 1:
                raise
            failed += 1
            print(err.render(), file=sys.stderr)
            continue
        if not args.quiet:
            if i:
                print()
            print(model.summary())
    n = len(args.models)
    if failed:
        print(f"{failed} of {n} models failed the check", file=sys.stderr)
        return EXIT_BAD_INPUT
    if not args.quiet:
        print(f"\nok: {n} model{'s' if n != 1 else ''} checked")
    return EXIT_OK


# ---- cache ------------------------------------------------------------------------------------


def _bytes_text(n: int) -> str:
    for unit, size in (("GB", 2**30), ("MB", 2**20), ("kB", 2**10)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{n} B"


def cmd_cache(args: argparse.Namespace) -> int:
    problem = cache_dir_problem()
    if problem is not None:  # not shown as an empty cache: nothing is cached there, nothing can be
        raise MbcalError(
            f"{problem}: mbcal cannot keep its cache there, and runs without one",
            hint="set MBCAL_CACHE_DIR to a folder (it is made when missing), or MBCAL_CACHE=off",
        )
    folder = cache_dir()
    bound = max_part_bytes() if folder is not None else 0  # a bad MBCAL_CACHE_MAX_MB is said before clearing
    removed = clear_cache(folder, args.clear or None) if folder is not None and args.clear is not None else None
    parts = cache_contents(folder)
    problems = [f"{p['folder']}: {p['error']}" for p in parts if "error" in p]
    problems += [] if removed is None else list(removed.problems)
    if args.json:
        report: dict[str, Any] = {"folder": None if folder is None else str(folder), "parts": parts}
        if folder is not None:
            report["max_part_bytes"] = {part: bound for part in PROGRAM_PARTS}
        if removed is not None:
            report["removed"] = {"files": removed.files, "bytes": removed.bytes, "problems": list(removed.problems)}
        _write_json(report, args.json, [])

    def text() -> str:
        if folder is None:
            return (
                "caching is off (MBCAL_CACHE=off): nothing is kept between runs, nothing to show or clear "
                "(without it the folder is $MBCAL_CACHE_DIR, default ~/.cache/mbcal)"
            )
        lines = []
        if removed is not None:
            which = ", ".join(args.clear) if args.clear else "every part"
            lines += [f"removed {removed.files} files ({_bytes_text(removed.bytes)}) of {which}", ""]
        holds = [f"unreadable ({p['error']})" if "error" in p else p["holds"] for p in parts]
        rows = [[p["part"], p["files"], _bytes_text(p["bytes"]), h] for p, h in zip(parts, holds)]
        total = sum(p["bytes"] for p in parts)
        rows.append(["total", sum(p["files"] for p in parts), _bytes_text(total), ""])
        title = f"mbcal's cache folder: {folder} ($MBCAL_CACHE_DIR; MBCAL_CACHE=off turns it off)"
        lines.append(table(["part", "files", "size", "holds"], rows, align="lrrl", title=title))
        lines.append(
            f"programs ({', '.join(PROGRAM_PARTS)}): each part kept under {_bytes_text(bound)} "
            "($MBCAL_CACHE_MAX_MB, in MB), the least recently used removed first"
        )
        return "\n".join(lines)

    _say(args, text)
    for problem in problems:  # said even with --quiet: something was not done
        print(f"mbcal cache: {problem}", file=sys.stderr)
    return EXIT_BAD_INPUT if problems else EXIT_OK


# ---- scene ------------------------------------------------------------------------------------


def _quantity(text: str):
    """``-30deg``, ``5 cm``, ``0.2`` → (SI value, the unit's dimension or None for a plain number);
    None when it is not a number.  Units as in models."""
    for unit in sorted(UNITS, key=len, reverse=True):
        number = text[: -len(unit)].strip() if text.endswith(unit) else ""
        if number:
            try:
                return float(number) * UNITS[unit][0], UNITS[unit][1], unit
            except ValueError:
                continue
    try:
        return float(text), None, ""
    except ValueError:
        return None


def _check_dimension(given, unit: str, name: str, option: str, expected) -> None:
    """A value given with a unit where a parameter of another dimension is meant: an error."""
    if given is not None and expected is not None and given != expected:
        raise MbcalError(
            f"{option} {name}: '{unit}' is not a unit of {name}, which is {describe(expected)}",
            hint="give the value in a unit of its dimension, or as a plain number in SI units",
        )


def parse_assignments(
    items: Sequence[str], model=None, option: str = "--set", among: Sequence[str] | None = None
) -> dict[str, float]:
    """``NAME=VALUE[unit]`` strings → {name: SI value}; units as in models (``5cm``, ``30deg``).
    With the model, a unit whose dimension is not the parameter's is an error (``lever.length=3deg``).
    ``among``: the names a pattern may stand for (watch's --process-noise: the estimated unknowns);
    the unit is checked against those only, and a pattern that matches none is an error."""
    out: dict[str, float] = {}
    for item in items:
        if "=" not in item:
            raise MbcalError(f"{option} expects NAME=VALUE, got '{item}'")
        name, text = (s.strip() for s in item.split("=", 1))
        parsed = _quantity(text)
        if parsed is None:
            raise MbcalError(f"{option} {name}: '{text}' is not a number (units: {', '.join(UNITS)})")
        value, dim, unit = parsed
        if not math.isfinite(value):
            raise MbcalError(f"{option} {name}: value must be finite")
        matched = model.match_params(name.split("@", 1)[0]) if model is not None else []
        if among is not None:
            # 'lever.*=1deg' means the estimated lever.angle, not the fixed lever.length (whose
            # unit is not an angle): patterns stand for the names given only
            matched = [param for param in matched if param in among]
            if not matched:
                raise MbcalError(
                    f"{option} {name}: matches no estimated unknown",
                    hint=f"the estimated unknowns: {', '.join(among) or 'none'}",
                )
        if model is not None and dim is not None:
            for param in matched:
                # declared without a unit: what its places require (a focal length in pixels took
                # '600mm' as 0.6; a box's size takes '30cm'), else a plain number
                _check_dimension(dim, unit, param, option, model.param(param).given_dim or DIMENSIONLESS)
        if name in out:  # which one was meant? (the last won in silence)
            raise MbcalError(f"{option} {name} is given twice")
        out[name] = value
    return out


def _check_values(model, values: dict[str, float], option: str = "--set") -> dict[str, float]:
    """Values given on the command line must keep the model valid: within a parameter's hard
    limits, and sizes positive and poses finite with them (as ``mbcal check`` requires at the
    nominal values); returned as they are."""
    from mbcal.language.check import check_at_nominal  # lazy: 'mbcal --help' does not load the parser

    if not values:
        return values
    X = model.nominal.copy()
    for key, value in values.items():
        for name in model.match_params(key.split("@", 1)[0]):
            info = model.param(name)
            outside = info.outside_limits(value)
            if outside:
                raise MbcalError(f"{option} {key}: {outside}", info.span)
            if "@" not in key:  # one configuration's value: checked against the limits only
                X[model.param_index(name)] = value
    check_at_nominal(model, X, where=f"with the values of {option}")
    return values


def cmd_scene(args: argparse.Namespace) -> int:
    from mbcal.modeling import modeler, parameter_vector  # lazy: keeps JAX out of 'mbcal check'

    out = check_output(args.output, [args.model], overwrite=True)
    fmt = out.suffix.lower().lstrip(".")
    if fmt not in ("glb", "gltf", "obj", "stl", "ply", "off"):
        raise MbcalError(f"cannot export '{out.suffix}': use .glb, .obj, .stl, .ply or .off")
    model = _load(args.model, args, [args.model])
    values = _check_values(model, parse_assignments(args.set or [], model))
    scene = modeler(model, parameter_vector(model, values))
    tm = scene.to_trimesh(points=args.points)
    if not tm.geometry:
        raise MbcalError(
            f"nothing to export: {args.model} has no shapes" + ("" if args.points else " (--points adds its points)")
        )
    if fmt in ("stl", "ply", "off"):
        data = tm.to_mesh().export(file_type=fmt)  # a single mesh in world coordinates
    elif fmt == "gltf":
        raise MbcalError("use .glb for glTF (a single binary file)")
    else:
        data = tm.export(file_type=fmt)
    atomic_write(out, data if isinstance(data, bytes) else str(data))
    if not args.quiet:
        print(f"wrote {out} ({len(tm.geometry)} shapes)")
    return EXIT_OK


# ---- shared helpers -------------------------------------------------------------------------------


_ACTIVE_PROGRESS: list[Progress] = []


class Progress:
    """Progress on stderr: a ticking line on a terminal, one line per step otherwise."""

    def __init__(self, enabled: bool = True):
        _ACTIVE_PROGRESS.append(self)
        self.enabled = enabled
        self.tty = enabled and sys.stderr.isatty()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._message = ""
        self._start = 0.0

    def step(self, message: str) -> None:
        if not self.enabled:
            return
        self.done()
        self._message = message
        self._start = time.perf_counter()
        if not self.tty:
            print(f"… {message}", file=sys.stderr, flush=True)
            return
        self._stop = threading.Event()

        def tick():
            while not self._stop.wait(0.2):
                elapsed = time.perf_counter() - self._start
                print(f"\r… {self._message} ({elapsed:.1f} s)", end="", file=sys.stderr, flush=True)

        self._thread = threading.Thread(target=tick, daemon=True)
        self._thread.start()

    def abort(self) -> None:
        """Stop ticking and clear the line (an error message follows)."""
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            self._thread = None
            print("\r\033[K", end="", file=sys.stderr, flush=True)

    def clear_line(self) -> None:
        """Clear the ticking line (a warning is printed; the next tick writes it again)."""
        if self._thread is not None:
            print("\r\033[K", end="", file=sys.stderr, flush=True)

    def done(self) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            self._thread = None
            elapsed = time.perf_counter() - self._start
            print(f"\r✓ {self._message} ({elapsed:.1f} s)", file=sys.stderr, flush=True)


def _load(path: str, args: argparse.Namespace | None = None, inputs: Sequence[str] = ()):
    """The model at ``path``; with ``args``, its outputs checked again against every file the model
    reads (its includes, meshes and point files: known only once it is loaded) and ``inputs``."""
    from mbcal.language import load_model  # lazy: 'mbcal --help' does not load the parser

    model = load_model(path)
    if args is not None:
        _check_outputs(args, [*inputs, *model.files, *model.data_files])
    return model


def _solver_config(args):
    from mbcal.solver import SolverConfig  # lazy: keeps JAX out of 'mbcal check'

    # The robust loss's scale defaults to the library's (Loss.default_scale): CLI and API agree.
    return SolverConfig(
        max_iterations=args.max_iterations,
        loss=args.loss or "linear",
        loss_scale=args.loss_scale,
        structure=args.structure,  # issue 15: the Schur complement for many configurations
    )


def _check_loss_scale(args: argparse.Namespace, scans: bool) -> None:
    """--loss-scale scales a robust loss only: with the linear one (the default without scans) it
    was ignored in silence, and a plain least-squares fit looked like a robust one."""
    if args.loss_scale is None:
        return
    loss = args.loss or ("cauchy" if scans else "linear")
    if loss == "linear":
        given = "--loss linear" if args.loss else "no --loss (least squares)"
        raise MbcalError(
            f"--loss-scale is the scale of a robust loss, but {given} is given: "
            "give --loss huber or --loss cauchy with it, or leave --loss-scale out"
        )


def _structure_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--structure",
        choices=["auto", "structured", "dense"],
        default="auto",
        help="solver for many configurations with unknowns of their own: the Schur complement "
        "('structured'), the dense one, or 'auto' (structured from 8 such configurations; docs/scale.md)",
    )


def _estimate(model, patterns):
    if patterns:
        return list(patterns)
    ranged = [p.name for p in model.params if p.lower is not None and p.upper is not None and not p.per_configuration]
    if not ranged:
        raise MbcalError(
            "nothing to estimate: name the unknowns with --estimate NAME|GLOB "
            "(no parameter of the model has a search range to take by default)"
        )
    return ranged


def _write_json(data, target: str, inputs) -> None:
    text = json.dumps(data, indent=1, allow_nan=False) + "\n"
    if target == "-":
        sys.stdout.write(text)
        sys.stdout.flush()
    else:
        atomic_write(check_output(target, inputs), text)


def _say(args, text: str | Callable[[], str]) -> None:
    """The human report: stdout, or stderr when stdout carries JSON; nothing with --quiet.  A
    callable is called only when the report is shown (a summary reads every point's σ: ~40 ms
    of a quiet calibration, issue 16)."""
    if args.quiet:
        return
    text = text() if callable(text) else text
    stream = sys.stderr if getattr(args, "json", None) == "-" else sys.stdout
    print(text, file=stream)


def _background(model, camera: str, path: str, option: str) -> np.ndarray:
    """A photo to draw over: it must exist and have the camera's size."""
    from mbcal.render.views import load_image  # lazy: rendering loads only when a picture is made

    camera = model.resolve("camera", camera)
    image = load_image(path)
    info = model.cameras[model.camera_index(camera)]
    if image.shape[:2] != (info.height, info.width):
        raise MbcalError(
            f"{option}: the background is {image.shape[1]}×{image.shape[0]} pixels but camera '{camera}' is "
            f"{info.width}×{info.height}"
        )
    return image


def _photo_alone(model, value: str) -> None:
    """render's --background is a photo of the camera it renders from; solve's CAMERA=IMAGE form
    given to it (no such file, a camera's name before the '=') is refused with render's form."""
    name, eq, path = value.partition("=")
    if not eq or Path(value).exists():
        return
    try:
        camera = model.resolve("camera", name)
    except MbcalError:
        return  # not a camera's name: the file is reported missing as it is
    raise MbcalError(
        f"--background {value}: render takes the photo alone (CAMERA=IMAGE is solve's form)",
        hint=f"--camera {model.short_name('camera', camera)} --background {shlex.quote(path)}",
    )


def _image_fits(model, camera: str, path: str, what: str) -> None:
    """An image a measurement file names, checked before the work: it exists, is an image and has
    the camera's size (its header only: the pixels are read when it is drawn on)."""
    from PIL import Image, UnidentifiedImageError  # pillow: loaded when an image is checked

    try:
        with Image.open(path) as img:
            width, height = img.size
    except FileNotFoundError:
        raise MbcalError(
            f"{what}: image not found: {path}", hint="image paths in a JSON file are relative to its folder"
        ) from None
    except (UnidentifiedImageError, OSError) as err:
        raise MbcalError(f"{what}: cannot read image {path}: {err}") from None
    info = model.cameras[model.camera_index(camera)]
    if (height, width) != (info.height, info.width):
        raise MbcalError(
            f"{what}: {path} is {width}×{height} pixels but camera '{camera}' is {info.width}×{info.height}"
        )


def _distinct(paths: Sequence[str]) -> None:
    """The same input file named twice would be read twice: its ids clash ("duplicate id 'hub'
    (first at the very same place)") or, for scans, its points count twice."""
    seen: dict[Path, str] = {}
    for path in paths:
        key = Path(path).resolve()
        if key in seen:
            raise MbcalError(f"{path} is given twice" + (f" (as {seen[key]})" if seen[key] != path else ""))
        seen[key] = path


_OUTPUT_OPTIONS = {"json": "--json", "write_model": "--write-model", "plot": "--plot", "output": "-o/--output"}
_OPTION_ATTRS = {option: attr for attr, option in _OUTPUT_OPTIONS.items()}


def _check_outputs(args, inputs) -> None:
    """Validate every output path before any work is done (nothing is lost on a bad path): none is
    an input, none is named by two options (one would replace the other), none is empty."""
    pictures = [
        item.split("=", 1)[1]
        for option in ("background", "image")
        if isinstance(getattr(args, option, None), list)
        for item in getattr(args, option)
        if "=" in item
    ]
    protect([*inputs, *pictures])  # whatever the command writes later (an overlay) never replaces them
    claimed: dict[Path, str] = {}
    for attr, option in _OUTPUT_OPTIONS.items():
        value = getattr(args, attr, None)
        if value == "":
            raise MbcalError(f"{option} needs a file name, got an empty one")
        if value == "-" and attr != "json":
            # Only a JSON report goes to standard output; anything else would be a file named '-'.
            raise MbcalError(f"{option} needs a file name: '-' (standard output) is taken by --json only")
        if attr == "plot" and value and Path(value).suffix.lower() != ".png":  # PNG data in a .jpg was written
            raise MbcalError(f"--plot writes a PNG image: give a name ending in .png, got {value}")
        if value and value != "-":
            where = check_output(value, inputs).resolve()
            if where in claimed:
                raise MbcalError(f"{claimed[where]} and {option} both name {value}: one would replace the other")
            claimed[where] = option
    overlay = getattr(args, "overlay", None)
    if overlay == "":
        raise MbcalError("--overlay needs a folder name, got an empty one")
    if overlay == "-":
        raise MbcalError("--overlay needs a folder name: '-' (standard output) is taken by --json only")
    if overlay:
        folder = check_output_folder(overlay, "--overlay").resolve()
        if folder in claimed:
            raise MbcalError(f"{claimed[folder]} and --overlay both name {overlay}: a file and a folder")


def _check_overlays(args, planned: Sequence[str | os.PathLike[str]]) -> None:
    """The pictures --overlay will write, known before the work: none may be an input (a photo in
    that folder) nor a file another option names (``--json ov/eye_before.png`` was replaced by the
    overlay, or replaced it, without a word)."""
    refuse_inputs(planned)
    claimed = {
        Path(value).resolve(): option
        for attr, option in _OUTPUT_OPTIONS.items()
        if (value := getattr(args, attr, None)) and value != "-"
    }
    for path in planned:
        option = claimed.get(Path(path).resolve())
        if option is not None:
            raise MbcalError(
                f"{option} names {getattr(args, _OPTION_ATTRS[option])}, a picture --overlay writes: "
                "one would replace the other",
                hint="choose another name, or another folder for --overlay",
            )


# ---- solve ------------------------------------------------------------------------------------------


def _fit_config(args):
    from mbcal.fit import FitConfig  # lazy: keeps JAX out of 'mbcal check'

    threshold = getattr(args, "fit_threshold", None)
    if threshold is None:
        return None
    if not 0 < threshold < 1:
        raise MbcalError(f"--fit-threshold must lie between 0 and 1, got {threshold}")
    return FitConfig(threshold=threshold)


def cmd_solve(args: argparse.Namespace) -> int:
    from mbcal.api import calibrate, check_size  # lazy: keeps JAX out of 'mbcal check'
    from mbcal.measurements.io import read_measurements  # lazy: keeps JAX out of 'mbcal check'
    from mbcal.measurements.sets import merge_measurements  # lazy: keeps JAX out of 'mbcal check'

    # Scan files (docs/range.md): --scan FILE, or a positional file of a scan-only suffix.
    scans = [p for p in args.measurements if Path(p).suffix.lower() not in (".csv", ".txt", ".json")]
    scans += args.scan or []
    files = [p for p in args.measurements if p not in scans]
    if not files and not scans:
        raise MbcalError("solve needs measurement files (.csv, .json) or scans (--scan FILE)")
    inputs = [args.model, *files, *scans]
    _distinct(files + scans)
    check_size(args.restarts)  # before reading anything
    _check_sigmas(args)
    _check_loss_scale(args, bool(scans))
    fit = _fit_config(args)
    _check_outputs(args, inputs)
    progress = Progress(not args.quiet)
    progress.step(f"reading {args.model} and {', '.join(files + scans)}")
    model = _load(args.model, args, inputs)
    sets = [read_measurements(path, model) for path in files]
    if scans:
        from mbcal.range.fit import scan_measurements  # lazy: keeps JAX out of 'mbcal check'
        from mbcal.range.scans import load_scan  # lazy: keeps JAX out of 'mbcal check'

        loaded = [load_scan(path, model, sensor=args.sensor, sigma=args.scan_sigma) for path in scans]
        sets.append(scan_measurements(model, loaded, voxel=args.voxel, max_points=args.scan_points))
        args.loss = args.loss or "cauchy"  # scans hold points of things the model does not: robust
    data = merge_measurements(sets, model)
    known = _check_values(model, parse_assignments(args.set or [], model))
    config = _solver_config(args)
    estimate = _estimate(model, args.estimate)
    # The photos for the overlays, read and checked before the solve (a wrong one is found at once).
    backgrounds = {}
    for item in args.background or []:
        if "=" not in item:
            raise MbcalError(f"--background expects CAMERA=IMAGE, got '{item}'")
        cam, path = item.split("=", 1)
        backgrounds[cam] = _background(model, cam, path, f"--background {item}")
    if backgrounds and not args.overlay:
        raise MbcalError("--background is for the overlays: give --overlay DIR too")
    if args.overlay:  # an overlay's name taken by an input (a photo in that folder): refused now, not after the solve
        from mbcal.render.overlays import planned_overlays  # lazy: rendering loads only when a picture is made

        _check_overlays(args, planned_overlays(model, data.measurements, args.overlay))
    # calibrate says "solving: ..." once the unknowns and the values are checked (a bad --estimate,
    # a plan without values): nothing claims to compile and solve a problem that is then refused.
    result = calibrate(
        model,
        data,
        estimate,
        restarts=args.restarts,
        seed=args.seed,
        config=config,
        known=known,
        priors=not args.no_priors,
        scale_covariance=args.scale_covariance,
        camera=args.camera,
        outlier_threshold=args.outlier_threshold,
        fit=fit,
        accept_poor_fit=args.accept_poor_fit,
        progress=progress.step,
    )
    if args.overlay or args.plot:
        progress.step("drawing overlays and plots")
        if args.overlay:
            from mbcal.render.overlays import calibration_overlays  # lazy: keeps JAX out of 'mbcal check'

            calibration_overlays(result, args.overlay, backgrounds=backgrounds)
        if args.plot:
            from mbcal.render.overlays import residual_plot  # lazy: keeps JAX out of 'mbcal check'

            residual_plot(result, args.plot)
    progress.done()
    if args.json:
        _write_json(result.to_json(), args.json, inputs)
    _say(args, result.summary)  # before the model: a model refused (an estimate that breaks it) has its report
    if args.write_model:
        result.write_model(args.write_model)
    return EXIT_OK if result.ok else EXIT_UNTRUSTED


# ---- simulate ----------------------------------------------------------------------------------------


def _model_and_plan(args: argparse.Namespace):
    """Check the outputs, then read the model and the plan (or measurement file) of a command."""
    from mbcal.measurements.io import read_measurements  # lazy: keeps JAX out of 'mbcal check'

    _check_outputs(args, [args.model, args.plan])
    model = _load(args.model, args, [args.model, args.plan])
    return model, read_measurements(args.plan, model)


def cmd_simulate(args: argparse.Namespace) -> int:
    from mbcal.api import simulate  # lazy: keeps JAX out of 'mbcal check'
    from mbcal.measurements.io import write_measurements  # lazy: keeps JAX out of 'mbcal check'

    model, plan = _model_and_plan(args)
    truth = _check_values(model, parse_assignments(args.set or [], model))
    if not math.isfinite(args.noise) or args.noise < 0:
        raise MbcalError(f"--noise must be a non-negative number, got {args.noise}")
    data = simulate(model, plan, truth, noise=args.noise, seed=args.seed, drop_invisible=args.drop_invisible)
    write_measurements(data, args.output)
    dropped = len(plan) - len(data)
    _say(
        args,
        f"wrote {args.output}: {len(data)} measurements" + (f" ({dropped} not visible, left out)" if dropped else ""),
    )
    return EXIT_OK


# ---- observe ------------------------------------------------------------------------------------------


def _at_or_set(model, at: dict[str, float], known: dict[str, float]) -> None:
    """observe: a value given by --at and by --set for the same parameter (--set lever.angle=60deg
    --at lever.angle=5deg, or --set 'lever.*' beside it) is refused: --at won in silence."""
    for name in at:
        base, _, config = name.partition("@")
        for key in known:
            pattern, _, other = key.partition("@")
            if base in model.match_params(pattern) and (not config or not other or config == other):
                raise MbcalError(
                    f"--at {name} and --set {key} both give a value of {base}: give one, --at for an "
                    "unknown that --estimate names (the value to analyse at), --set for a known value"
                )


def cmd_observe(args: argparse.Namespace) -> int:
    from mbcal.api import observe  # lazy: keeps JAX out of 'mbcal check'

    model, plan = _model_and_plan(args)
    inputs = [args.model, args.plan]
    at = parse_assignments(args.at or [], model, "--at")
    known = _check_values(model, parse_assignments(args.set or [], model))
    _at_or_set(model, at, known)
    analysis = observe(
        model,
        plan,
        _estimate(model, args.estimate),
        at=at or None,
        known=known or None,
        priors=not args.no_priors,
        camera=args.camera,
        accept_poor_fit=args.accept_poor_fit,
    )
    if args.json:
        _write_json(analysis.to_json(), args.json, inputs)
    _say(args, analysis.summary)
    return EXIT_OK if analysis.ok else EXIT_UNTRUSTED


# ---- render -------------------------------------------------------------------------------------------


def cmd_render(args: argparse.Namespace) -> int:
    from mbcal.modeling import modeler, parameter_vector  # lazy: keeps JAX out of 'mbcal check'
    from mbcal.render.views import (  # lazy: rendering loads only when a picture is made
        Layer,
        draw_overlay,
        render_view,
        save_png,
        wireframe_layer,
    )

    inputs = [args.model] + ([args.background] if args.background else [])
    _check_outputs(args, inputs)
    if Path(args.output).suffix.lower() != ".png":
        raise MbcalError("render writes PNG images: give an output name ending in .png")
    model = _load(args.model, args, inputs)
    if not model.cameras:
        raise MbcalError(f"{args.model} has no camera to render from")
    camera = model.resolve("camera", args.camera) if args.camera else model.cameras[0].name
    if args.background is not None:
        _photo_alone(model, args.background)  # before the rendering
    scene = modeler(model, parameter_vector(model, _check_values(model, parse_assignments(args.set or [], model))))
    # The depth pass is for the wireframe's occlusion only.
    view = render_view(scene, camera, points=args.points and not args.wireframe, depth=bool(args.wireframe))
    if args.background is not None:
        image = _background(model, camera, args.background, "--background")
    else:
        image = view.color
    layers = []
    if args.wireframe:
        layers.append(wireframe_layer(scene, camera, view, (230, 40, 40), None))
    elif args.background is not None:
        image = (0.5 * image + 0.5 * view.color).astype("uint8")  # the model blended over the photo
    if args.points:
        pts = np.asarray(scene.camera(camera).project(scene.points))
        z = np.asarray(scene.camera(camera).to_camera(scene.points))[:, 2]
        layers.append(Layer("points", pts[z > 0], (30, 80, 220)))
    save_png(draw_overlay(image, layers, legend=False) if layers else image, args.output)
    _say(
        args, f"wrote {args.output} ({model.short_name('camera', camera)}, {view.color.shape[1]}×{view.color.shape[0]})"
    )
    return EXIT_OK


# ---- convert --------------------------------------------------------------------------------------------


def cmd_convert(args: argparse.Namespace) -> int:
    from mbcal.language import load_urdf  # lazy: 'mbcal --help' does not load the parser
    from mbcal.language.urdf import urdf_to_mdl  # lazy: as above

    if Path(args.robot).suffix.lower() != ".urdf":
        raise MbcalError(f"convert reads a URDF robot description; {args.robot} is not a .urdf file")
    out = check_output(args.output, [args.robot])
    load_urdf(args.robot)  # check it all
    atomic_write(out, urdf_to_mdl(args.robot, mesh_base=out.resolve().parent))
    _say(args, f"wrote {out}")
    return EXIT_OK


# ---- detect / calibrate-camera ------------------------------------------------------------------------


def cmd_detect(args: argparse.Namespace) -> int:
    from mbcal.measurements.io import write_measurements  # lazy: keeps JAX out of 'mbcal check'
    from mbcal.workflows.detect import detect_images  # lazy: keeps JAX out of 'mbcal check'

    _check_outputs(args, [args.target, *args.images])
    if not math.isfinite(args.sigma) or args.sigma <= 0:
        raise MbcalError(f"--sigma must be positive, got {args.sigma}")
    model = _load(args.target, args, [args.target, *args.images])
    progress = Progress(not args.quiet)
    progress.step(f"detecting the target in {len(args.images)} images")
    data, detections = detect_images(model, args.images, target=args.name, camera=args.camera, sigma=args.sigma)
    progress.done()
    write_measurements(data, args.output)
    missed = [d.image for d in detections if not d.found]
    lines = [f"wrote {args.output}: {len(data)} corners in {len(detections) - len(missed)} of {len(detections)} images"]
    lines += [f"  not found in {m}" for m in missed]
    lines += [
        f"  warning: {d.image} is the same file as {d.same_as} (a copy?): its corners are a second view of the "
        "same ones and make σ too small"
        for d in detections
        if d.same_as
    ]
    _say(args, "\n".join(lines))
    return EXIT_OK if not missed else EXIT_UNTRUSTED


def cmd_calibrate_camera(args: argparse.Namespace) -> int:
    from mbcal.api import check_size  # lazy: keeps JAX out of 'mbcal check'
    from mbcal.measurements.io import read_measurements  # lazy: keeps JAX out of 'mbcal check'
    from mbcal.measurements.sets import merge_measurements  # lazy: keeps JAX out of 'mbcal check'
    from mbcal.solver import SolverConfig  # lazy: keeps JAX out of 'mbcal check'
    from mbcal.workflows.cameras import (  # lazy: keeps JAX out of 'mbcal check'
        calibrate_cameras,
        planned_reprojections,
        reprojection_images,
    )

    inputs = [args.model, *args.measurements]
    _distinct(args.measurements)
    _check_outputs(args, inputs)
    model = _load(args.model, args, inputs)
    sets = [read_measurements(path, model) for path in args.measurements]
    data = merge_measurements(sets, model)
    if args.restarts is not None:
        check_size(args.restarts)
    images = dict(data.images)
    named_in = {key: path for path, ms in zip(args.measurements, sets) for key in ms.images}  # the last wins
    seen: dict[str, set[str]] = {}  # configuration → the cameras with corners in it
    for m in data:
        if m.kind == "image_point":
            seen.setdefault(m.config, set()).add(m.refs["camera"])
    for item in args.image or []:  # checked before the solve: a wrong one is found at once
        if "=" not in item:
            raise MbcalError(f"--image expects CONFIG=PATH or CONFIG@CAMERA=PATH, got '{item}'")
        key, path = item.split("=", 1)
        if not path.strip():
            raise MbcalError(f"--image {item}: no file name after '='")
        if key in images and key not in data.images:
            raise MbcalError(f"--image {key} is given twice")
        config, _, camera = key.partition("@")
        if config not in seen:
            raise MbcalError(
                f"--image {item}: no corners were measured in a configuration '{config}'",
                hint=suggest(config, list(seen)) or f"configurations: {', '.join(list(seen)[:10])}",
            )
        for cam in [model.resolve("camera", camera)] if camera else sorted(seen[config]):
            _background(model, cam, path, f"--image {item}")  # exists, and has the camera's size
        images[key] = path
    if args.image and not args.overlay:
        raise MbcalError("--image is for the overlays: give --overlay DIR too")
    protect(images.values())  # the measurement file's images too, not only those of --image
    if args.overlay:  # its images and outputs checked now: a calibration was thrown away after the solve
        if not images:
            csv = [path for path in args.measurements if Path(path).suffix.lower() == ".csv"]
            raise MbcalError(
                "--overlay needs the views' images, and no measurement file names them",
                hint=(f"a CSV file ({csv[0]}) carries no image paths: " if csv else "")
                + "write the corners as JSON ('mbcal detect IMAGES --target MODEL -o corners.json' names each "
                "view's image), or give --image CONFIG=PATH for each view",
            )
        for key, path in data.images.items():
            if key in images and images[key] == path:  # not replaced by --image
                config, _, camera = key.partition("@")
                for cam in [model.resolve("camera", camera)] if camera else sorted(seen.get(config, ())):
                    _image_fits(model, cam, path, f"{named_in.get(key, 'the measurement file')}: the image of {key}")
        # an overlay named like one of its images (same folder): refused now, not after the solve
        _check_overlays(args, planned_reprojections(model, data.measurements, images, args.overlay))
    progress = Progress(not args.quiet)
    progress.step("initialising (Zhang's method) and refining")
    cc = calibrate_cameras(
        model,
        data,
        args.estimate,
        initialize=not args.no_init,
        restarts=args.restarts,
        seed=args.seed,
        config=SolverConfig(structure=args.structure),  # issue 15
        fit=_fit_config(args),
        accept_poor_fit=args.accept_poor_fit,
    )
    if args.overlay:
        progress.step("drawing the reprojected corners on the images")
        reprojection_images(cc, images, args.overlay)  # images checked before the solve
    progress.done()
    if args.json:
        _write_json(cc.to_json(), args.json, inputs)
    _say(args, cc.summary)  # before the model: a model refused (an estimate that breaks it) has its report
    if args.write_model:
        cc.result.write_model(args.write_model)
    return EXIT_OK if cc.ok else EXIT_UNTRUSTED


# ---- demo -----------------------------------------------------------------------------------------------


def cmd_demo(args: argparse.Namespace) -> int:
    from mbcal.workflows.demo import run_demo  # lazy: keeps JAX out of 'mbcal check'

    return run_demo(
        out=Path(args.output),
        restarts=args.restarts,
        seed=args.seed,
        quiet=args.quiet,
        progress=Progress(not args.quiet),
    )


# ---- studio ---------------------------------------------------------------------------------------------


def cmd_studio(args: argparse.Namespace) -> int:
    import importlib.util  # only to see whether the optional extra is installed

    if any(importlib.util.find_spec(m) is None for m in ("fastapi", "uvicorn")):
        from mbcal.studio import MISSING_EXTRA  # light: a constant

        print(f"mbcal studio: {MISSING_EXTRA}", file=sys.stderr)
        return EXIT_BAD_INPUT
    from mbcal.studio.engine import Engine  # lazy: keeps JAX out of 'mbcal check'
    from mbcal.studio.server import check_address, serve_forever  # lazy: the optional web server

    check_address(args.host, args.port)  # refused before a warning or a folder
    photos = []
    for item in args.image or []:
        if "=" not in item:
            raise MbcalError(f"--image expects CAMERA=PHOTO or CAMERA@CONFIG=PHOTO, got '{item}'")
        cam, path = item.split("=", 1)
        cam, _, config = cam.partition("@")
        photos.append((cam, config or "default", path))
    for path in [args.model, *args.measurements]:
        if not Path(path).is_file():
            raise MbcalError(f"file not found: {path}")
    engine = Engine(args.model, args.measurements, photos, args.out)  # makes --out only once all is valid
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        print(
            f"mbcal studio: warning: listening on {args.host}, not only this machine; anyone who can reach it "
            "and has the URL's token can edit the session and write under --out, and the page and its "
            "token travel unencrypted (plain HTTP)",
            file=sys.stderr,
        )
    if engine.error:
        # the input to fix by name: a broken measurement file is not "the model has an error"
        what = engine.error["what"]
        print(f"mbcal studio: {what} has an error (shown in the page too):\n{engine.error['text']}", file=sys.stderr)
    end_start_up()  # a server waits: collections resume now, not at its first solve (mbcal._collector)
    return serve_forever(engine, args.host, args.port, open_browser=not args.no_browser)


# ---- kinematics -----------------------------------------------------------------------------------------


def _whole(low: int, high: int | None, what: str) -> Callable[[str], int]:
    """An argparse type: a whole number from ``low`` to ``high`` (None: no upper end)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"expected {what}, got {text}")
        return value

    return parse


_seed = _whole(0, None, "a whole number ≥ 0")  # NumPy's generators take no negative seed
_count = _whole(1, None, "a whole number ≥ 1")


def _number(low: float, strict: bool) -> Callable[[str], float]:
    """An argparse type: a finite number above ``low`` (``strict``) or from ``low`` on."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not math.isfinite(value) or value < low or (strict and value == low):
            raise argparse.ArgumentTypeError(f"expected a number {'>' if strict else '≥'} {low:g}, got {text}")
        return value

    return parse


_positive = _number(0.0, strict=True)
_nonnegative = _number(0.0, strict=False)
_port = _whole(0, 65535, "a port from 0 (any free one) to 65535")


def _sigma_length(text: str) -> float:
    """An argparse type: a point's σ, a positive length with a unit as in models (``2mm``,
    ``2 mm``, ``0.002 m``, as --set and --process-noise read them) or a plain number of metres.
    A plain number stays metres (scripts wrote ``--sigma 0.002``); a user meaning millimetres gets
    a σ a thousand times too large, which the fit's verdict names (reduced χ² < 0.1: σ stated too
    large) and the report shows with its unit."""
    parsed = _quantity(text.strip())
    if parsed is None:
        raise argparse.ArgumentTypeError(
            f"'{text}' is not a length: give a number with a unit (2mm, '2 mm', 0.002m) or a plain number of metres"
        )
    value, dim, unit = parsed
    if dim is not None and dim != LENGTH:
        raise argparse.ArgumentTypeError(f"'{unit}' in '{text}' is not a unit of length (mm, cm, m, ...)")
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive length (2mm, or a plain number of metres), got '{text}'")
    return value


def _quantities(text: str, option: str, meant: Sequence[tuple[str, Any]] = ()) -> list[float]:
    """``0,-30deg,5cm`` → SI values, units as in models; plain numbers are SI (rad, m).  ``meant``:
    (name, dimension) of each value, where a unit of another dimension is an error."""
    out = []
    for k, item in enumerate(t.strip() for t in text.split(",")):
        parsed = _quantity(item)
        if parsed is None:
            raise MbcalError(
                f"{option}: '{item}' is not a number", hint=f"numbers separated by commas, units {', '.join(UNITS)}"
            )
        value, dim, unit = parsed
        if not math.isfinite(value):
            raise MbcalError(f"{option}: values must be finite, got '{item}'")
        if k < len(meant):
            _check_dimension(dim, unit, meant[k][0], option, meant[k][1])
        out.append(value)
    return out


def cmd_kinematics(args: argparse.Namespace) -> int:
    from mbcal.kinematics import Kinematics  # lazy: keeps JAX out of 'mbcal check'

    _check_restarts(args)  # IK's starts: checked with or without --ik, before the model is read

    _check_outputs(args, [args.model])
    model = _load(args.model, args, [args.model])
    values = _check_values(model, parse_assignments(args.set or [], model))
    kin = Kinematics(model, args.point, chain=args.chain, values=values)
    if args.joints:  # --joints gives every chain variable: a --set of one was dropped in silence
        for key in values:
            held = [name for name in model.match_params(key.split("@", 1)[0]) if name in kin.joints]
            if held:
                raise MbcalError(
                    f"--set {key} gives the chain variable {held[0]}, which --joints gives too",
                    hint="give its value in --joints (without --joints, the chain starts at the --set values)",
                )
    meant = [(name, model.param(name).given_dim) for name in kin.joints]  # as --set reads them
    theta = np.asarray(_quantities(args.joints, "--joints", meant)) if args.joints else kin.theta0
    if len(theta) != kin.n:
        raise MbcalError(
            f"--joints gives {len(theta)} values, but the chain has {kin.n}: {', '.join(kin.joints)}",
            hint="name the chain with --chain, or give one value per joint",
        )
    ik = None
    if args.ik:
        target = _quantities(args.ik, "--ik", [(f"the target's {c}", LENGTH) for c in "xyz"])
        if len(target) != 3:
            raise MbcalError(f"--ik needs a position x,y,z, got {len(target)} values")
        ik = kin.ik(target, initial=theta, restarts=args.restarts, seed=args.seed, tolerance=args.tolerance)
    text, data = kin.report(theta, frame=args.axes, part=args.part, damping=args.damping, ik=ik)
    if args.json:
        _write_json(data, args.json, [args.model])
    _say(args, text)
    trouble = data["singular"] or bool(data["outside_limits"]) or (ik is not None and not ik.all_reached)
    return EXIT_UNTRUSTED if trouble else EXIT_OK


def _set_option(p: argparse.ArgumentParser, help: str) -> None:
    p.add_argument("--set", action="append", metavar="NAME=VALUE", help=help)


def _quiet_option(p: argparse.ArgumentParser, help: str = "print nothing on success") -> None:
    p.add_argument("-q", "--quiet", action="store_true", help=help)


def _verdict_options(p: argparse.ArgumentParser, *, threshold: bool = True) -> None:
    p.add_argument(
        "--accept-poor-fit",
        action="store_true",
        help="exit 0 even when the fit is inconsistent with the stated σ or weakly determined (the verdict is "
        "still reported)",
    )
    if threshold:
        p.add_argument(
            "--fit-threshold",
            type=float,
            metavar="P",
            help="the fit is inconsistent when P(χ² ≥ S) < P (default 0.001)",
        )


def _json_option(p: argparse.ArgumentParser, what: str = "the JSON report") -> None:
    p.add_argument("--json", metavar="REPORT.json", help=f"write {what} ('-' for stdout)")


def _add_solver_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--estimate",
        nargs="+",
        metavar="NAME|GLOB",
        help="parameters to estimate (names or globs such as 'room.*'; name@config for one "
        "configuration's copy); default: every parameter with a search range",
    )
    _set_option(p, "a known value that replaces the model's (lever.angle=30deg); repeatable")
    p.add_argument("--no-priors", action="store_true", help="ignore the model's prior σ of the unknowns")
    p.add_argument("--camera", metavar="NAME", help="camera whose line of sight splits point uncertainties")


def _register_commands(sub) -> None:
    p = _add(
        sub,
        "solve",
        "estimate parameters from measurements and report (S, σ, observability, residuals)",
        """
        Estimate the unknowns from a measurement file with Marquardt's method from several random
        starts (one compiled, vmapped run), then report: estimates with σ and initial values, S and
        RMS, observability (rank; unobservable combinations by name; measurements that would help),
        point uncertainties across and along the line of sight, residuals worst first, restarts.

        The verdict: S is tested against χ² with m − n degrees of freedom at the stated σ; when
        P(χ² ≥ S) < 0.001 (--fit-threshold) the fit is inconsistent and the report names what to
        suspect, worst first: outlying measurements (by id; a robust loss is recommended when they
        explain it), an object or sensor whose residuals are systematically large (a structural
        error of the model), or σ set too small.  Weakly determined directions are named too.

        Exit status: 0 converged, observable, consistent and well determined; 1 not converged, not
        observable, an estimate that breaks the model (a focal length < 0), inconsistent,
        systematic residuals, another solution as good, an unknown held at a hard limit, or weakly
        determined (--accept-poor-fit: 0 for all but the first three); 2 bad input (with
        file:line:col).
        """,
        """
        mbcal solve models/teleexistence.mdl room.csv --estimate 'room.*' \\
            --restarts 32 --json report.json --write-model calibrated.mdl --overlay overlays/
        mbcal solve models/room_depth.mdl clicks.csv depth_0000.png --estimate 'room.*' --restarts 4
        """,
        cmd_solve,
    )
    p.add_argument("model", metavar="MODEL", help="model file (.mdl or .urdf)")
    p.add_argument(
        "measurements",
        metavar="FILES",
        nargs="*",
        help="measurement files (.csv or .json), merged; files of a scan's suffix (.ply .pcd .obj .xyz .pts .npy "
        ".png .tif .tiff) are scans (docs/range.md)",
    )
    p.add_argument(
        "--scan",
        action="append",
        metavar="FILE",
        help="a point cloud or depth image as point-to-surface measurements, beside the others (a .csv or "
        ".txt cloud must be given this way); repeatable; the loss defaults to cauchy with scans",
    )
    p.add_argument(
        "--voxel", type=_nonnegative, default=0.01, metavar="M", help="scan down-sampling voxel (default 0.01 m)"
    )
    p.add_argument(
        "--scan-points", type=_count, default=2000, metavar="N", help="at most N points per scan (default 2000)"
    )
    p.add_argument(
        "--scan-sigma",
        type=_sigma_length,
        metavar="LENGTH",
        help="σ of a scan point, with a unit (2mm) or a plain number of metres (default: the scan's)",
    )
    p.add_argument("--sensor", metavar="NAME", help="the depth camera of depth-image scans (default: the only one)")
    _add_solver_options(p)
    p.add_argument("--restarts", type=int, default=32, metavar="N", help="random starting points (default 32)")
    p.add_argument("--seed", type=_seed, default=0, metavar="S", help="seed of the starting points (default 0)")
    p.add_argument("--loss", choices=["linear", "huber", "cauchy"], help="robust loss (default: linear)")
    p.add_argument(
        "--loss-scale",
        type=float,
        metavar="C",
        help="robust loss scale in σ (default 1.345 Huber, 2.385 Cauchy); needs a robust --loss",
    )
    p.add_argument("--max-iterations", type=int, default=100, metavar="N", help="iterations per restart")
    _structure_option(p)
    p.add_argument("--scale-covariance", action="store_true", help="scale the covariance by the reduced χ²")
    p.add_argument(
        "--outlier-threshold",
        type=_nonnegative,
        default=3.0,
        metavar="K",
        help="list measurements whose residual exceeds K σ (default 3)",
    )
    _verdict_options(p)
    _json_option(p)
    p.add_argument("--write-model", metavar="OUT.mdl", help="write the calibrated model (the input is untouched)")
    p.add_argument("--overlay", metavar="DIR", help="write before/after overlay images (PNG) into DIR")
    p.add_argument(
        "--background",
        action="append",
        metavar="CAMERA=IMAGE",
        help="the real image of a camera, for the overlays; repeatable (one per camera)",
    )
    p.add_argument("--plot", metavar="RESIDUALS.png", help="write a residual plot (PNG)")
    _quiet_option(p, "print nothing (use the exit status, --json)")

    p = _add(
        sub,
        "simulate",
        "synthesise measurements for a plan from given true values",
        """
        Fill a measurement plan (a measurement file without values: which kinds, sensors, points and
        configurations, with their σ) with values predicted from the model at the true values given
        with --set, plus Gaussian noise of each measurement's σ times --noise (2: twice the σ).
        """,
        """
        mbcal simulate models/teleexistence.mdl measurements/room_plan.csv \\
            --set room.y=5cm --set room.yaw=1.2deg --noise 1 --seed 3 -o room.csv
        """,
        cmd_simulate,
    )
    p.add_argument("model", metavar="MODEL")
    p.add_argument("plan", metavar="PLAN", help="measurement plan (.csv or .json)")
    _set_option(p, "a true value (room.x=2cm); repeatable")
    p.add_argument(
        "--noise", type=float, default=1.0, metavar="F", help="noise in units of each σ (default 1; 0: exact)"
    )
    p.add_argument("--seed", type=_seed, default=0, metavar="S", help="seed of the noise")
    p.add_argument(
        "--drop-invisible",
        action="store_true",
        help="leave out measurements that cannot be made (behind or outside a camera)",
    )
    p.add_argument("-o", "--output", required=True, metavar="MEASUREMENTS", help="output file (.csv or .json)")
    _quiet_option(p)

    p = _add(
        sub,
        "observe",
        "before measuring: is a plan enough? rank, σ per unknown, what is missing",
        """
        Analyse a measurement plan at the nominal values (or --at): the rank of the measurement
        Jacobian, the σ each unknown would get, the combinations that cannot be observed (by name),
        and the additional measurements that would help most.  Exit status 1 when something is
        unobservable or weakly determined (a direction whose σ exceeds half its search range, or a
        condition number above 1e10; --accept-poor-fit accepts the latter).
        """,
        "mbcal observe models/arm7.mdl measurements/arm_plan.json --estimate 'arm.offset*'",
        cmd_observe,
    )
    p.add_argument("model", metavar="MODEL")
    p.add_argument("plan", metavar="PLAN")
    _add_solver_options(p)
    p.add_argument(
        "--at",
        action="append",
        metavar="NAME=VALUE",
        help="analyse at this value of an estimated unknown instead of nominal (not with --set for it too)",
    )
    _verdict_options(p, threshold=False)
    _json_option(p, "the analysis as JSON")
    _quiet_option(p)

    p = _add(
        sub,
        "render",
        "render a model camera's view headlessly (PNG), optionally over a photo",
        """
        Render the scene from a model camera (pyrender, off screen).  With --background PHOTO the
        model is drawn over a real photo of that camera (the one of --camera); with --wireframe as
        its visible edges (occluded edges hidden).  Lines and points are projected with the
        camera's distortion; the shaded rendering itself is pinhole.
        """,
        """
        mbcal render models/teleexistence.mdl --camera eyes.left --set lever.angle=40deg -o left.png
        mbcal render models/teleexistence.mdl --camera eyes.left --background photo.png --wireframe -o overlay.png
        """,
        cmd_render,
    )
    p.add_argument("model", metavar="MODEL")
    p.add_argument("--camera", metavar="NAME", help="camera to render from (default: the first)")
    _set_option(p, "a parameter value; repeatable")
    p.add_argument(
        "--background",
        metavar="PHOTO",
        help="a real image of the camera rendered from (--camera) to draw over; not CAMERA=IMAGE as for solve",
    )
    p.add_argument("--wireframe", action="store_true", help="draw the model's visible edges")
    p.add_argument("--points", action="store_true", help="mark the named points")
    p.add_argument("-o", "--output", required=True, metavar="OUT.png")
    _quiet_option(p)

    p = _add(
        sub,
        "convert",
        "write a URDF robot as an .mdl model (joint origins and offsets as parameters)",
        """
        Translate a URDF robot description into mbcal's language: links as nested frames, each
        joint's origin as six parameters (x y z roll pitch yaw), its reading as a per-configuration
        parameter and its zero offset as an unknown.  Every command also reads .urdf files
        directly; this shows what they see.  See docs/urdf.md.
        """,
        "mbcal convert tests/data/arm7.urdf -o arm7.mdl",
        cmd_convert,
    )
    p.add_argument("robot", metavar="ROBOT.urdf")
    p.add_argument("-o", "--output", required=True, metavar="OUT.mdl")
    _quiet_option(p)

    p = _add(
        sub,
        "detect",
        "find calibration-target corners in images (OpenCV) and write a measurement file",
        """
        Detect the model's target (a chessboard, or a grid of squares like Zhang's) in every image
        with OpenCV and write its corners as image_point measurements, one configuration per
        image (named after the file).  A greyscale image of more than 8 bits (16-bit PNG or
        TIFF, float) is scaled from its darkest to its brightest pixel.  Needs OpenCV: pip install
        'mbcal[vision]'.  Exit status 1 when the target was not found in some image (they are
        listed).
        """,
        """
        mbcal detect views/*.png --target models/camera_calibration.mdl -o corners.json
        """,
        cmd_detect,
    )
    p.add_argument("images", metavar="IMAGE", nargs="+", help="images of the target, one by one (DIR/*.png)")
    p.add_argument("--target", required=True, metavar="MODEL.mdl", help="the model with the target and the camera")
    p.add_argument("--name", metavar="TARGET", help="which target of the model (default: its only one)")
    p.add_argument("--camera", metavar="NAME", help="the camera that took the images (default: the first)")
    p.add_argument("--sigma", type=float, default=0.5, metavar="PX", help="σ of a detected corner (default 0.5 px)")
    p.add_argument(
        "-o",
        "--output",
        required=True,
        metavar="CORNERS.json",
        help="measurement file: .json (it names each view's image, for calibrate-camera --overlay) or .csv",
    )
    _quiet_option(p)

    p = _add(
        sub,
        "calibrate-camera",
        "calibrate cameras (intrinsics, distortion, stereo pose) from target corners",
        """
        Camera calibration as OpenCV users know it: the target's pose in every view and the
        cameras' intrinsics and distortion (OpenCV's model) — and for a stereo rig the second
        camera's pose — start from Zhang's closed-form solution and are refined together.  The
        report gives the RMS reprojection error, the RMS per view, σ of every intrinsic (scaled by
        the residual variance, as OpenCV does) and the full calibration report; --overlay draws the
        detected and reprojected corners on every image.  Exit status 1 when the fit is inconsistent
        with the corners' σ or a direction is weakly determined (too few or too similar views);
        --accept-poor-fit reports it and exits 0.
        """,
        """
        mbcal calibrate-camera models/camera_calibration.mdl corners.json --overlay reprojection/ --json cam.json
        """,
        cmd_calibrate_camera,
    )
    p.add_argument("model", metavar="MODEL")
    p.add_argument("measurements", metavar="CORNERS", nargs="+", help="measurement files (several are merged)")
    p.add_argument(
        "--estimate",
        nargs="+",
        metavar="NAME|GLOB",
        help="unknowns (default: parameters with a search range and per-configuration ones not given)",
    )
    p.add_argument(
        "--restarts",
        type=_count,
        default=None,
        metavar="N",
        help="starts: Zhang's solution and N-1 random ones (default: Zhang's alone, and 4 when that fit does not "
        "converge or is not consistent with the stated sigma)",
    )
    p.add_argument("--seed", type=_seed, default=0, metavar="S")
    p.add_argument("--no-init", action="store_true", help="start from the model's nominal values, not Zhang's method")
    _structure_option(p)
    p.add_argument("--image", action="append", metavar="CONFIG=PATH", help="the image of a view, for --overlay")
    p.add_argument("--overlay", metavar="DIR", help="write each image with its detected and reprojected corners")
    _verdict_options(p)
    _json_option(p)
    p.add_argument("--write-model", metavar="OUT.mdl", help="write the calibrated model")
    _quiet_option(p)

    p = _add(
        sub,
        "demo",
        "the seed's room calibration end to end on bundled data, with overlay images",
        """
        The seed's first experiment (section 4.2): the factory corner's pose is off by several
        centimetres; 24 points are clicked in both images of the robot's stereo camera (simulated,
        1 px noise); mbcal estimates the six pose parameters and shows the model over the camera
        image before and after (like the seed's Figure 10), the report, and the errors of the
        lever's points across and along the line of sight beside the paper's.
        """,
        "mbcal demo -o mbcal-demo",
        cmd_demo,
    )
    p.add_argument("-o", "--output", default="mbcal-demo", metavar="DIR", help="output folder (default mbcal-demo)")
    p.add_argument("--restarts", type=_count, default=32, metavar="N")
    p.add_argument("--seed", type=_seed, default=0, metavar="S")
    _quiet_option(p)

    p = _add(
        sub,
        "studio",
        "the human interface: click model points in photos, solve, see the model snap on (web page)",
        """
        A local web page (the seed's human interface and superimposer, sections 2.6 and 3.5): each
        camera's photo with the model drawn over it; pick a model point and click where it is in the
        photo (a loupe, drag, delete, undo); coarse-align with sliders; choose the unknowns; Observe
        (rank, what is missing, which point to click next); Solve (random restarts); Save the
        measurement file, the calibrated model, the report and the overlays into --out.  Every edit
        is saved at once to --out/studio-session.json; a restart on the same --out restores it.
        Listens on 127.0.0.1 with a random token in the URL.  Needs pip install 'mbcal[studio]'.
        See docs/studio.md.
        """,
        """
        mbcal studio models/teleexistence.mdl --image eyes.left=left.png --image eyes.right=right.png --out session/
        """,
        cmd_studio,
    )
    p.add_argument("model", metavar="MODEL", help="model file (.mdl or .urdf)")
    p.add_argument("measurements", metavar="MEASUREMENTS", nargs="*", help="measurement files to start from")
    p.add_argument(
        "--image",
        action="append",
        metavar="CAMERA=PHOTO",
        help="a camera's photo (CAMERA@CONFIG=PHOTO for a configuration); repeatable",
    )
    p.add_argument("--out", default="mbcal-studio", metavar="DIR", help="the folder to write in (default mbcal-studio)")
    p.add_argument("--no-browser", action="store_true", help="print the URL instead of opening a browser")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1; others warn)")
    p.add_argument("--port", type=_port, default=0, metavar="N", help="port (default: a free one)")

    p = _add(
        sub,
        "kinematics",
        "f(θ), J and J* of a point or frame for given joint values; inverse kinematics",
        """
        The seed's kinematics model (eqs. 5-7) from any model, at its nominal values or those given
        with --set (calibrated offsets, say): the world pose x = f(θ) of a point or frame for the
        joint values θ of a chain, the Jacobian J = df/dθ (rows vx vy vz wx wy wz), J* = Jᵀ(JJᵀ)⁻¹
        (for a chain with fewer joints than rows the least-squares step (JᵀJ)⁻¹Jᵀ) and the
        manipulability.  With --ik: the joint values that put the point at a target
        (Marquardt from random starts within the joint limits), or, when it is out of reach, the
        closest pose found and its distance.

        Joint values and targets take units (30deg, 5cm); plain numbers are SI (rad, m).  Write
        --joints=-0.5,... when the first value is negative.
        Exit status: 0 ok; 1 a target out of reach, or J* not finite (singular: give --damping);
        2 bad input.
        """,
        """
        mbcal kinematics models/arm7.mdl --chain 'arm.q*' --point hand.tip \\
            --joints 0,-30deg,0,-60deg,0,20deg,0 --ik 0.3,-0.35,0.95
        """,
        cmd_kinematics,
    )
    p.add_argument("model", metavar="MODEL", help="model file (.mdl or .urdf)")
    p.add_argument("--point", required=True, metavar="NAME", help="the point or frame (a unique dotted suffix will do)")
    p.add_argument(
        "--chain",
        metavar="NAMES",
        help="the joint variables, comma-separated: parameter names, globs ('arm.q*'), frames with a joint or "
        "joints J for their reading J.q (a URDF's joint names); default: every joint between the world and the point",
    )
    p.add_argument(
        "--joints", metavar="Q1,Q2,...", help="joint values in chain order (30deg, 0.1); default: the model's values"
    )
    _set_option(p, "another parameter's value (arm.offset1=2deg); repeatable")
    p.add_argument("--axes", choices=["world", "local"], default="world", help="axes of J's rows (default world)")
    p.add_argument(
        "--part",
        choices=["position", "orientation", "full"],
        default="position",
        help="rows of J that J* and the manipulability use (default position: the seed's endpoint x)",
    )
    p.add_argument("--damping", type=float, default=0.0, metavar="λ", help="damped J* = Jᵀ(JJᵀ + λ²I)⁻¹ (default 0)")
    p.add_argument("--ik", metavar="X,Y,Z", help="a target position in the world: solve for the joint values")
    p.add_argument("--restarts", type=_count, default=16, metavar="N", help="IK starts (default 16)")
    p.add_argument("--seed", type=_seed, default=0, metavar="S", help="seed of the IK starts (default 0)")
    p.add_argument(
        "--tolerance", type=_positive, default=1e-6, metavar="M", help="IK: reached within M metres (default 1e-6)"
    )
    _json_option(p, "the result as JSON")
    _quiet_option(p, "print nothing (use the exit status, --json)")

    p = _add(
        sub,
        "fit",
        "calibrate from range data: point clouds and depth images, point-to-surface, no operator",
        """
        Estimate the unknowns from scans without an operator (seed §5): point clouds (PLY, OBJ, PCD,
        XYZ/CSV, .npy; in the world frame or --frame) and depth images (16-bit PNG in the depth
        camera's unit, float TIFF/.npy in metres) through the model's depth camera.  Each scan is
        voxel down-sampled, globally aligned when far off, cropped to the model's neighbourhood and
        fitted by point-to-surface distances with a robust loss (Cauchy).  Points that belong to no
        modelled surface are counted and written as OUT/MODEL.outliers.ply; objects whose points
        no longer fit their shape are named.  Writes OUT/MODEL.calibrated.mdl and OUT/MODEL.fit.json.

        Exit status: 0 a trustworthy fit; 1 not converged, unobservable, inliers inconsistent with
        σ, a structural misfit or mostly outliers; 2 bad input (a located error).
        """,
        """
        mbcal fit models/room_depth.mdl depth_0001.png --estimate 'room.*' --voxel 0.01 --out fitted/
        """,
        cmd_fit,
    )
    p.add_argument("model", metavar="MODEL", help="model file (.mdl or .urdf)")
    p.add_argument("scans", metavar="SCAN", nargs="+", help="point clouds or depth images")
    _range_arguments(p)
    p.add_argument("--out", metavar="DIR", help="folder for the calibrated model, the outliers PLY and the report")
    p.add_argument(
        "--json", metavar="FIT.json", help="the fit as JSON ('-': stdout; mbcal/schemas/scan_fit.schema.json)"
    )
    _quiet_option(p, "print nothing (use the exit status)")

    p = _add(
        sub,
        "watch",
        "the environment model manager: keep a model calibrated from scans appearing in a folder",
        """
        Watch a folder for scan files (oldest name first) and update the estimate with each, warm
        started and with the previous posterior as a prior (information form, widened by
        --process-noise), so it tightens over batches and follows slow drift.  After each update:
        a line in OUT/history.jsonl (estimate, σ, χ², time), OUT/state.json and the calibrated
        model OUT/MODEL.calibrated.mdl (atomic; never the input).  Flags a drift (an unknown moved
        more than --drift-k σ) and names structural misfits.  Safe to kill at any moment; a
        restart resumes from the history and skips the files already taken.  A file is taken once
        it was last modified 0.5 s ago (a copy in progress is waited for, with --once too).  A file
        that cannot be a scan by its kind (an 8-bit photo .png, a README .txt or log .csv without
        a line of three numbers) is skipped with a note, not an update; a broken scan file is a
        rejected update.  With --once the exit status is 1 when an update of that run was rejected.
        """,
        """
        mbcal watch models/room_depth.mdl --scans incoming/ --out managed/ --estimate 'room.*' \\
            --estimate lever.angle --process-noise lever.angle=0.1
        """,
        cmd_watch,
    )
    p.add_argument("model", metavar="MODEL", help="model file (.mdl or .urdf)")
    p.add_argument("--scans", required=True, metavar="DIR", help="folder where scan files appear")
    p.add_argument("--out", required=True, metavar="DIR", help="folder of the history and the calibrated model")
    _range_arguments(p)
    p.add_argument("--drift-k", type=_positive, default=3.0, metavar="K", help="drift flag at K σ (default 3)")
    p.add_argument(
        "--process-noise",
        action="append",
        metavar="GLOB=SIGMA",
        help="expected change per update of the estimated unknowns GLOB matches, with a unit (0.5deg) or SI; "
        "repeatable",
    )
    p.add_argument("--poll", type=_positive, default=1.0, metavar="S", help="seconds between looks (default 1)")
    p.add_argument(
        "--once",
        action="store_true",
        help="process the files there now (waiting for any still being written) and exit (1 if one was "
        "rejected; a folder without scans is said, exit 0)",
    )
    p.add_argument(
        "--json",
        action="store_true",
        help="print each update as one JSON object per line (the fields of OUT/history.jsonl; "
        "inf and NaN as null) instead of the text lines",
    )
    _quiet_option(p, "print nothing (with --json: only the JSON lines)")


# ---- fit / watch (range data) --------------------------------------------------------------------------


def _check_sigmas(args: argparse.Namespace) -> None:
    """--sigma and --scan-sigma of range data: a σ divides the residuals, so zero is not one."""
    for name in ("sigma", "scan_sigma"):
        v = getattr(args, name, None)
        if v is not None and not (v > 0 and v < float("inf")):
            raise MbcalError(f"--{name.replace('_', '-')} must be a positive number of metres, got {v}")


def _fit_options(args: argparse.Namespace):
    from mbcal.range.fit import FitOptions  # lazy: keeps JAX out of 'mbcal check'

    for name in ("voxel", "crop"):
        v = getattr(args, name, None)
        if v is not None and not (v >= 0 and v < float("inf")):
            raise MbcalError(f"--{name} must be a non-negative number of metres, got {v}")
    _check_sigmas(args)
    return FitOptions(
        voxel=args.voxel, crop=args.crop, loss=args.loss, restarts=args.restarts, seed=args.seed, coarse=args.coarse
    )


def _range_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--estimate", required=True, action="append", metavar="GLOB", help="unknowns (repeatable)")
    p.add_argument("--voxel", type=float, default=0.01, metavar="M", help="voxel size in metres (default 0.01; 0: off)")
    p.add_argument("--crop", type=_positive, default=0.10, metavar="M", help="keep points within M of the model (0.10)")
    p.add_argument("--loss", choices=["cauchy", "huber", "linear"], default="cauchy", help="robust loss (cauchy)")
    p.add_argument("--restarts", type=_count, default=1, metavar="N", help="starting points (default 1)")
    p.add_argument("--seed", type=_seed, default=0, metavar="S", help="seed of the starting points")
    p.add_argument("--coarse", choices=["auto", "always", "never"], default="auto", help="global alignment (auto)")
    p.add_argument("--sensor", metavar="NAME", help="the depth camera of depth images (default: the only one)")
    p.add_argument("--frame", metavar="NAME", help="frame of point clouds (default: world)")
    p.add_argument(
        "--sigma",
        type=_sigma_length,
        metavar="LENGTH",
        help="σ of a point, with a unit (2mm, '2 mm') or a plain number of METRES (default 2 mm; depth: "
        "1 mm + 0.1 %% z); a σ far too large (reduced χ² < 0.1) makes the fit not trustworthy",
    )


def _check_restarts(args: argparse.Namespace) -> None:
    """--restarts within what mbcal runs, before any file is read (as solve's): 10,000,000 was JAX's
    out-of-memory traceback in fit, watch and kinematics (and watch's empty --out)."""
    from mbcal.solver import check_size  # lazy: keeps JAX out of 'mbcal check'

    check_size(args.restarts)


def cmd_fit(args: argparse.Namespace) -> int:
    from mbcal.range.manager import fit_files  # lazy: keeps JAX out of 'mbcal check'

    _check_restarts(args)

    _distinct(args.scans)
    _check_outputs(args, [args.model, *args.scans])
    fit, written = fit_files(
        args.model,
        args.scans,
        args.estimate,
        _fit_options(args),
        out=args.out,
        sensor=args.sensor,
        frame=args.frame,
        sigma=args.sigma,
    )
    if args.json:
        _write_json(fit.to_json(), args.json, [args.model, *args.scans])
    _say(args, lambda: fit.text() + "".join(f"\nwrote {path}" for path in written))
    return 0 if fit.ok else 1


def _shown(model, name: str, value: float, std: float) -> str:
    """``room.yaw 1.49928±0.0014 deg``: a value and its σ in the parameter's display unit."""
    unit = model.param(name.split("@", 1)[0]).unit
    return f"{name} {to_display(unit, value):.6g}±{to_display(unit, std):.2g} {unit}".rstrip()


def cmd_watch(args: argparse.Namespace) -> int:
    from mbcal.range.manager import ModelManager  # lazy: keeps JAX out of 'mbcal check'

    _check_restarts(args)

    # σ per update, with a unit of the unknowns' dimension (lever.angle=0.5deg) or in SI units; read
    # with the model before the manager makes its folder, so a bad option leaves nothing behind
    model = _load(args.model)
    estimated: list[str] = []
    for pattern in args.estimate:  # a pattern that matches nothing is the manager's error (with suggestions)
        estimated += [n for n in model.match_params(pattern) if n not in estimated]
    noise = parse_assignments(args.process_noise or [], model, "--process-noise", among=estimated)
    manager = ModelManager(
        args.model,
        args.out,
        args.estimate,
        _fit_options(args),
        drift_k=args.drift_k,
        process_noise=noise,
        sensor=args.sensor,
        frame=args.frame,
        sigma=args.sigma,
    )

    rejected: list[int] = []

    def report(u) -> None:
        if not u.accepted:
            rejected.append(u.seq)
        if args.json:  # one strict JSON object per line (Update.to_json: inf and NaN are null)
            print(json.dumps(u.to_json(), allow_nan=False), flush=True)
            return
        if args.quiet:
            return
        if u.error:
            print(f"update {u.seq} (REJECTED, the scan cannot be read): {u.error}", flush=True)
            return
        flags = "".join(f"\n  drift: {d}" for d in u.drift) + "".join(f"\n  structural misfit: {m}" for m in u.misfits)
        state = "accepted" if u.accepted else "REJECTED" + (f": {'; '.join(u.doubts)}" if u.doubts else "")
        values = ", ".join(_shown(manager.model, k, v, u.std[k]) for k, v in u.values.items())
        print(f"update {u.seq} ({state}, {u.points} points, χ²/dof {u.reduced_chi2:.3g}): {values}{flags}", flush=True)

    if not args.quiet and manager.history:
        print(
            f"resumed: {len(manager.history)} updates in {manager.journal}",
            file=sys.stderr if args.json else sys.stdout,
        )
    end_start_up()  # it may wait long for the first scan: collections resume now (mbcal._collector)

    def note(line: str) -> None:  # a file beside the scans that is none (a README, a photo): no update
        if not args.quiet:
            print(line, file=sys.stderr if args.json else sys.stdout, flush=True)

    manager.watch(args.scans, poll=args.poll, once=args.once, report=report, note=note)
    # --once in a script: an update of this run that was rejected is not a success
    return EXIT_UNTRUSTED if rejected else EXIT_OK


# ---- the parser ---------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``mbcal`` command."""
    parser = argparse.ArgumentParser(
        prog="mbcal",
        description=textwrap.dedent(
            """
            mbcal — model-based measurement and calibration.

            Describe an environment in a .mdl model (objects, frames, joints, named parameters,
            points, sensors); mbcal predicts what sensors measure and estimates any parameter
            the measurements can observe, or says which ones they cannot.
            """
        ).strip(),
        epilog="run 'mbcal COMMAND --help' for the options and an example of each command",
        formatter_class=_formatter,
    )
    parser.add_argument("--version", action="version", version=f"mbcal {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = _add(
        sub,
        "check",
        "check models and print their parameters, frames, points and sensors",
        """
        Parse and check one or more models (.mdl or .urdf).  Prints a summary of each; an error
        is printed as path:line:col: message with the offending line, and the exit status is 2.
        """,
        "mbcal check models/teleexistence.mdl models/arm7.mdl",
        cmd_check,
    )
    p.add_argument("models", nargs="+", metavar="MODEL", help="model files (.mdl or .urdf)")
    _quiet_option(p, "print nothing on success")

    p = _add(
        sub,
        "scene",
        "export the 3-D scene of a model (glb, obj, stl, ply)",
        """
        Build the scene at the nominal parameter values (or those given with --set) and export
        its shapes in world coordinates.  .glb and .obj keep one node per shape; .stl, .ply and
        .off merge them into one mesh.
        """,
        "mbcal scene models/teleexistence.mdl --set lever.angle=45deg -o room.glb",
        cmd_scene,
    )
    p.add_argument("model", metavar="MODEL", help="model file (.mdl or .urdf)")
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="output file: .glb, .obj, .stl, .ply or .off")
    _set_option(p, "parameter value, with a unit if wanted (lever.angle=45deg); repeatable")
    p.add_argument("--points", action="store_true", help="mark every named point with a small sphere")
    _quiet_option(p, "print nothing on success")

    p = _add(
        sub,
        "cache",
        "show what mbcal keeps in its cache folder, or clear it",
        """
        mbcal keeps traced and compiled programs, the triangles of mesh files, its parser's
        tables and the model files it parsed in $MBCAL_CACHE_DIR (default ~/.cache/mbcal;
        MBCAL_CACHE=off turns caching off), so that the second run of a problem starts at once.
        The programs (exports, jax) are each kept under MBCAL_CACHE_MAX_MB megabytes (default
        256) and the parsed model files under 256 entries, the least recently used going first:
        this shows how many files each part holds and their size, and --clear removes them
        (only files with the names mbcal's caches give them; a later run rebuilds what it needs).
        A cache folder that is a file is an error here (exit status 2); the other commands then
        run without a cache, with a warning.
        """,
        "mbcal cache --clear exports jax",
        cmd_cache,
    )
    p.add_argument(
        "--clear",
        nargs="*",
        metavar="PART",
        choices=list(CACHE_PARTS),
        help=f"remove the cached files of these parts ({', '.join(CACHE_PARTS)}; none named: all)",
    )
    _json_option(p, "the folder and its parts as JSON")
    _quiet_option(p, "print nothing")

    _register_commands(sub)
    return parser


# Commands whose files appear as their work goes on (a model kept calibrated, the studio's Save):
# each file still written atomically, but not held back to the end as a command's outputs are.
_SERVICES = frozenset({"watch", "studio"})


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:
        # An option the command does not know: its own usage, not the top-level one.
        (_subparser(parser, getattr(args, "command", None)) or parser).error(
            f"unrecognized arguments: {' '.join(extra)}"
        )
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_BAD_INPUT
    restore = _watch_interrupts()
    show_warning = warnings.showwarning
    warnings.showwarning = _warning_printer(show_warning)
    try:
        # no write of the command replaces one of its inputs (_check_outputs); and a command's
        # outputs appear together or not at all (Ctrl-C while its overlays were drawn left the
        # report and some pictures), except where they must appear as the work goes on
        together = all_or_nothing() if args.command not in _SERVICES else contextlib.nullcontext()
        with protected_inputs(), together:
            code = int(args.func(args))
        if INTERRUPTED.is_set():  # a Ctrl-C that Python swallowed (in a finalizer): still interrupted
            raise KeyboardInterrupt
        return code
    except MbcalError as err:
        _stop_progress()
        print(err.render(), file=sys.stderr)
        return err.exit_code
    except KeyboardInterrupt:
        _stop_progress()
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        # Output piped into a program that stopped reading (| head): not an error.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_OK
    except OSError as err:
        # The system refused a read or a write that the checks before the work could not foresee
        # (a disk that filled up, a folder made read-only meanwhile): said plainly, not a traceback;
        # the atomic writes leave no partial file behind.
        _stop_progress()
        where = f": {err.filename}" if err.filename else ""
        print(f"error: {err.strerror or err}{where}", file=sys.stderr)
        return EXIT_BAD_INPUT
    finally:
        warnings.showwarning = show_warning
        restore()


def _warning_printer(fallback: Callable[..., None]) -> Callable[..., None]:
    """A ``warnings.showwarning`` that prints mbcal's own warnings
    (:class:`~mbcal.errors.MbcalWarning`, which locate themselves in their message) as
    ``warning: MESSAGE`` on standard error, even with --quiet; others as ``fallback`` does."""

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        if not issubclass(category, MbcalWarning):
            fallback(message, category, filename, lineno, file, line)
            return
        for progress in _ACTIVE_PROGRESS:
            progress.clear_line()
        print(f"warning: {message}", file=sys.stderr, flush=True)

    return show


def _subparser(parser: argparse.ArgumentParser, command: str | None) -> argparse.ArgumentParser | None:
    """The parser of ``command`` (for its usage line in an error)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) and command in action.choices:
            return action.choices[command]
    return None


def _watch_interrupts() -> Callable[[], None]:
    """Record Ctrl-C in :data:`mbcal.outputs.INTERRUPTED` as well as raising KeyboardInterrupt:
    Python only prints an interrupt that lands in a finalizer (JAX frees arrays and programs in
    them) and goes on, and the command then finished and exited 0.  Only where Ctrl-C has
    Python's default handler, in the main thread; returns the function that puts it back."""
    INTERRUPTED.clear()
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        return lambda: None

    def interrupted(signum, frame):
        INTERRUPTED.set()
        raise KeyboardInterrupt

    previous_hook = sys.unraisablehook

    def quiet(unraisable) -> None:  # the swallowed interrupt is recorded: no traceback for it
        if not (INTERRUPTED.is_set() and isinstance(unraisable.exc_value, KeyboardInterrupt)):
            previous_hook(unraisable)

    def restore() -> None:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        sys.unraisablehook = previous_hook

    signal.signal(signal.SIGINT, interrupted)
    sys.unraisablehook = quiet
    return restore


def _stop_progress() -> None:
    while _ACTIVE_PROGRESS:
        _ACTIVE_PROGRESS.pop().abort()


def entry() -> None:  # pragma: no cover - the console script of installs before mbcal.__main__.run
    pause_start_up()  # no garbage collections while the command starts (mbcal._collector)
    exit_now(main())


def exit_now(code: int) -> NoReturn:
    """End the command's process with ``code``, skipping the interpreter's teardown (issue 16).

    After a command, Python's exit ran JAX's and XLA's clean-up, a garbage collection of every
    module and the freeing of each compiled program: ~0.15 s of a 1.4 s ``mbcal calibrate-camera``.
    Every file mbcal writes is written (atomically) before ``main`` returns, so the output
    streams are flushed and the process ends at once.  Under a tracer or a profiler (coverage,
    cProfile), or with ``MBCAL_FAST_EXIT=0``, Python exits normally so that they can save.
    """
    if sys.gettrace() is not None or sys.getprofile() is not None or os.environ.get("MBCAL_FAST_EXIT") == "0":
        sys.exit(code)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe (| head): nothing more can be said
            pass
    if "logging" in sys.modules:
        sys.modules["logging"].shutdown()
    os._exit(code)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
