"""The ``mbcal`` command line.

Every command prints errors a user can cause as ``path:line:col: message`` with the source
line and a caret, and exits with status 2 — never with a traceback.  Exit status 0 is
success; 1 means the command ran but the result is not trustworthy (not observable, not
converged); 130 means interrupted.
"""

from __future__ import annotations

import argparse
import os
import sys
import textwrap
from collections.abc import Callable, Sequence

from mbcal.errors import MbcalError

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
    from mbcal.language import load_model

    for i, path in enumerate(args.models):
        model = load_model(path)
        if not args.quiet:
            if i:
                print()
            print(model.summary())
    if args.quiet:
        return EXIT_OK
    print(f"\nok: {len(args.models)} model{'s' if len(args.models) != 1 else ''} checked")
    return EXIT_OK


# ---- scene ------------------------------------------------------------------------------------


def parse_assignments(items: Sequence[str]) -> dict[str, float]:
    """``NAME=VALUE[unit]`` strings → {name: SI value}; units as in models (``5cm``, ``30deg``)."""
    from mbcal.units import UNITS

    out: dict[str, float] = {}
    for item in items:
        if "=" not in item:
            raise MbcalError(f"--set expects NAME=VALUE, got '{item}'")
        name, text = (s.strip() for s in item.split("=", 1))
        number, factor = text, 1.0
        for unit in sorted(UNITS, key=len, reverse=True):
            if text.endswith(unit) and text[: -len(unit)].strip():
                candidate = text[: -len(unit)].strip()
                try:
                    float(candidate)
                except ValueError:
                    continue
                number, factor = candidate, UNITS[unit][0]
                break
        try:
            value = float(number) * factor
        except ValueError:
            raise MbcalError(f"--set {name}: '{text}' is not a number (units: {', '.join(UNITS)})") from None
        if value != value or value in (float("inf"), float("-inf")):
            raise MbcalError(f"--set {name}: value must be finite")
        out[name] = value
    return out


def cmd_scene(args: argparse.Namespace) -> int:
    from mbcal.fileio import atomic_write, check_output
    from mbcal.language import load_model
    from mbcal.modeling import modeler, parameter_vector

    out = check_output(args.output, [args.model], overwrite=True)
    fmt = out.suffix.lower().lstrip(".")
    if fmt not in ("glb", "gltf", "obj", "stl", "ply", "off"):
        raise MbcalError(f"cannot export '{out.suffix}': use .glb, .obj, .stl, .ply or .off")
    model = load_model(args.model)
    values = parse_assignments(args.set or [])
    scene = modeler(model, parameter_vector(model, values))
    tm = scene.to_trimesh(points=args.points)
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


# ---- the parser ---------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``mbcal`` command."""
    from mbcal import __version__

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
    p.add_argument("-q", "--quiet", action="store_true", help="print nothing on success")

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
    p.add_argument("--set", action="append", metavar="NAME=VALUE",
                   help="parameter value, with a unit if wanted (lever.angle=45deg); repeatable")
    p.add_argument("--points", action="store_true", help="mark every named point with a small sphere")
    p.add_argument("-q", "--quiet", action="store_true", help="print nothing on success")

    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_BAD_INPUT
    try:
        return int(args.func(args))
    except MbcalError as err:
        print(err.render(), file=sys.stderr)
        return err.exit_code
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        # Output piped into a program that stopped reading (| head): not an error.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_OK


def entry() -> None:  # pragma: no cover - the console script
    sys.exit(main())


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
