"""The pictures of docs/range.md: a rendered depth image of the room fitted (the cloud over the
model before and after, coloured by distance), and the model manager following a lever that the
operator pulls down over 12 batches, seen by a depth camera beside the valve (0.6 mm noise at
0.4 m; estimates with σ bands against the truth).

    python bench/range_pictures.py            # writes docs/images/range_fit.png, range_history.png
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

import mbcal  # noqa: E402
from mbcal.range.fit import fit_scans  # noqa: E402
from mbcal.range.manager import ModelManager  # noqa: E402
from mbcal.range.pictures import plot_history, plot_scan_fit  # noqa: E402
from mbcal.range.readers import write_depth_png  # noqa: E402
from mbcal.range.scans import load_scan  # noqa: E402
from mbcal.range.simulate import add_depth_noise, render_depth  # noqa: E402

MODEL = ROOT / "models" / "room_depth.mdl"
TRUTH = {"room.x": 0.025, "room.y": -0.02, "room.z": 0.01, "room.yaw": np.radians(2.0), "room.pitch": np.radians(-1.0)}


def main(out: Path = ROOT / "docs" / "images") -> None:
    model = mbcal.load_model(MODEL)
    with tempfile.TemporaryDirectory() as tmp:
        png = Path(tmp) / "depth.png"
        write_depth_png(png, add_depth_noise(render_depth(model, TRUTH), 1e-3, 1e-3, seed=0))
        scan = load_scan(png, model)
        fit = fit_scans(model, [scan], ["room.*"])
        print(fit.text())
        plot_scan_fit(model, scan, {}, fit.values, out / "range_fit.png")

        # A second depth camera beside the valve, across the lever's plane of rotation (docs/range.md,
        # limitations: seen face-on, a thin lever's turning moves only its silhouette).
        side = Path(tmp) / "room_side.mdl"
        side.write_text(
            f'include "{ROOT / "models" / "teleexistence.mdl"}"\n'
            "frame tripod at look_at(eye = (-0.5 m, 0.45 m, 1.25 m), target = (-0.12 m, 0.72 m, 1.1 m)) {\n"
            "  range depth_cam(width = 160, height = 90, f = 80, scale = 1 mm, min = 30 cm, max = 3 m)\n}\n"
        )
        model = mbcal.load_model(side)
        manager = ModelManager(side, Path(tmp) / "managed", ["room.*", "lever.angle"],
                               process_noise={"lever.angle": np.radians(3)})  # fmt: skip
        angles = np.radians(20.0 + 2.0 * np.arange(12))
        for k, a in enumerate(angles):
            path = Path(tmp) / f"scan_{k:02d}.png"
            depth = render_depth(model, {**TRUTH, "lever.angle": float(a)})
            write_depth_png(path, add_depth_noise(depth, 0.6e-3, 0.0, seed=k))
            u = manager.update_files([path])
            lever, sd = np.degrees(u.values["lever.angle"]), np.degrees(u.std["lever.angle"])
            print(f"update {u.seq}: lever {lever:.2f}° ± {sd:.2f}°")
        plot_history(
            manager.history,
            ["lever.angle", "room.x", "room.yaw"],
            out / "range_history.png",
            truth={"lever.angle": angles, "room.x": [TRUTH["room.x"]] * 12, "room.yaw": [TRUTH["room.yaw"]] * 12},
            scale={"lever.angle": 180 / np.pi, "room.yaw": 180 / np.pi, "room.x": 1000.0},
            units={"lever.angle": "deg", "room.yaw": "deg", "room.x": "mm"},
        )
    print(f"wrote {out / 'range_fit.png'} and {out / 'range_history.png'}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "docs" / "images")
