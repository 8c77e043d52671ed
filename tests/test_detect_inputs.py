"""What 'mbcal detect' is given: folders, the same image twice, images of more than 8 bits."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import mbcal
from mbcal.errors import MbcalError
from mbcal.workflows.detect import detect_images

from conftest import MODELS, shared_data

pytest.importorskip("cv2")


def zhang_image_model(tmp_path):
    """The bundled camera model with Zhang's target (8 × 8 squares) and his camera's size."""
    text = (
        (MODELS / "camera_calibration.mdl")
        .read_text()
        .replace(
            "chessboard(rows = 6, cols = 9, square = 25 mm)",
            "squares(rows = 8, cols = 8, size = 0.5 inch, pitch = 0.888889 inch)",
        )
    )
    path = tmp_path / "zhang.mdl"
    path.write_text(text)
    return path


def detect(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "mbcal", "detect", *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=600
    )


def test_a_folder_given_as_an_image_is_refused_with_the_glob_that_was_meant(tmp_path):
    """'mbcal detect DIR' said "cannot read image DIR: [Errno 21] Is a directory"."""
    model_path = zhang_image_model(tmp_path)
    folder = tmp_path / "zh dir"
    folder.mkdir()
    image = shared_data("zhang", "CalibIm1.png")
    result = detect(image, "zh dir", "--target", model_path, "-o", "corners.json", cwd=tmp_path)
    assert result.returncode == 2
    assert "zh dir is a folder, not an image" in result.stderr
    assert "give the images, e.g. 'zh dir'/*.png" in result.stderr  # the glob outside the quotes
    assert "Errno" not in result.stderr
    assert not (tmp_path / "corners.json").exists()
    with pytest.raises(MbcalError, match="is a folder, not an image"):
        detect_images(mbcal.load_model(model_path), [str(folder)])


def test_an_image_given_twice_is_refused_and_a_copy_is_named(tmp_path):
    """The same image twice became two views (CalibIm1, CalibIm1_2) of the same corners, and σ
    shrank silently; calibrate-camera already refused a file given twice."""
    model_path = zhang_image_model(tmp_path)
    image = shared_data("zhang", "CalibIm1.png")
    (tmp_path / "zh dir").mkdir()
    local = tmp_path / "zh dir" / "CalibIm1.png"
    local.write_bytes(image.read_bytes())
    twice = detect("zh dir/CalibIm1.png", "./zh dir/CalibIm1.png", "--target", model_path, "-o", "c.json", cwd=tmp_path)
    assert twice.returncode == 2
    assert "./zh dir/CalibIm1.png is given twice (as zh dir/CalibIm1.png)" in twice.stderr
    assert not (tmp_path / "c.json").exists()
    with pytest.raises(MbcalError, match="is given twice"):
        detect_images(mbcal.load_model(model_path), [str(local), str(local)])
    # a copy under another name: detected (it may be meant), but named as one
    copy = tmp_path / "zh dir" / "copy.png"
    copy.write_bytes(image.read_bytes())
    result = detect(local, copy, "--target", model_path, "-o", "c.json", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert f"warning: {copy} is the same file as {local}" in result.stdout
    _, detections = detect_images(mbcal.load_model(model_path), [str(local), str(copy)])
    assert [d.same_as for d in detections] == [None, str(local)]


def test_a_16_bit_greyscale_image_is_scaled_to_8_bits_and_its_corners_found(tmp_path):
    """A 16-bit greyscale PNG (mode I;16, a mono machine-vision camera's) was converted to RGB by
    clipping every value above 255 to white: 'board not found'.  Its own range now maps to 0-255."""
    from PIL import Image

    from mbcal.render.views import load_image

    model_path = zhang_image_model(tmp_path)
    model = mbcal.load_model(model_path)
    grey = np.asarray(Image.open(shared_data("zhang", "CalibIm1.png")).convert("L"))
    # an 8-bit image of the full range 0-255, and the same as 16 bits (×256) and as 12 bits (×16)
    full = np.rint((grey - grey.min()) * (255.0 / (grey.max() - grey.min()))).astype(np.uint16)
    Image.fromarray(full.astype(np.uint8)).save(tmp_path / "view8.png")
    Image.fromarray(full * 256).save(tmp_path / "view16.png")
    Image.fromarray(full * 16).save(tmp_path / "view12.png")
    Image.fromarray(grey.astype(np.uint16) * 256).save(tmp_path / "CalibIm1.png")  # Zhang's own range, 0-248
    assert Image.open(tmp_path / "view16.png").mode == "I;16"
    assert np.array_equal(load_image(tmp_path / "view16.png"), load_image(tmp_path / "view8.png"))
    result = detect(tmp_path / "CalibIm1.png", "--target", model_path, "-o", tmp_path / "c.json")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "256 corners in 1 of 1 images" in result.stdout
    names = ["view8.png", "view16.png", "view12.png", "CalibIm1.png"]
    _, found = detect_images(model, [str(tmp_path / name) for name in names])
    corners = [d.corners for d in found]
    assert all(c is not None and c.shape == (256, 2) for c in corners)
    assert np.array_equal(corners[1], corners[0])  # the same pixels: the same corners
    assert np.abs(corners[2] - corners[0]).max() < 0.01  # 12 bits in 16: ~0.005 px (its range is 0-4080)
    assert np.abs(corners[3] - corners[0]).max() < 0.01


def test_a_float_image_with_nan_and_a_flat_image_load_as_8_bits():
    from mbcal.render.views import _to_8_bits

    a = np.array([[0.0, np.nan], [0.5, 1.0]], dtype=np.float32)
    assert _to_8_bits(a)[..., 0].tolist() == [[0, 0], [128, 255]]
    assert _to_8_bits(np.full((2, 2), 7, dtype=np.uint16)).max() == 0
