"""calibration.toml: exact round trip, accepted variants, and a named error for each mistake."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from conftest import rig_cameras

from pipeline.errors import CalibrationError
from pipeline.session.calibration_io import (
    calibration_dict,
    cameras_from_dict,
    read_calibration,
    write_calibration,
)


def test_round_trip_is_exact(tmp_path: Path) -> None:
    cams = rig_cameras()
    path = tmp_path / "calibration.toml"
    write_calibration(path, cams, metadata={"rig": "synthetic", "error_px": 0.1})
    back = read_calibration(path)
    assert [c.name for c in back] == ["cam0", "cam1", "cam2"]
    for a, b in zip(cams, back, strict=True):
        assert a.size_px == b.size_px
        # TOML floats are written with repr(): they read back bit for bit.
        for attr in ("matrix", "distortions", "rotation", "translation_mm"):
            np.testing.assert_array_equal(getattr(a, attr), getattr(b, attr))
    assert tomllib.loads(path.read_text())["metadata"] == {"rig": "synthetic", "error_px": 0.1}


def _doc() -> dict[str, Any]:
    return calibration_dict(rig_cameras())


def test_a_size_of_whole_floats_is_read_as_integers() -> None:
    # As aniposelib's resized cameras write it.
    cameras = cameras_from_dict(_set("cam_2", "size", [320.0, 240.0]))
    assert cameras[2].size_px == (320, 240) and all(isinstance(v, int) for v in cameras[2].size_px)


def test_rotation_matrix_is_accepted_as_rodrigues() -> None:
    doc = _doc()
    rvec = np.array(doc["cam_1"]["rotation"])
    doc["cam_1"]["rotation"] = cv2.Rodrigues(rvec)[0].tolist()
    cam = cameras_from_dict(doc)[1]
    # Rodrigues -> matrix -> Rodrigues loses only rounding (~1e-15 rad).
    np.testing.assert_allclose(cam.rotation, rvec, atol=1e-12)


@pytest.mark.parametrize("n", [4, 5, 8])
def test_distortion_lengths_opencv_accepts(n: int) -> None:
    doc = _doc()
    doc["cam_0"]["distortions"] = [0.01] * n
    assert cameras_from_dict(doc)[0].distortions.shape == (n,)


@pytest.mark.parametrize(
    ("distortions", "folds"),
    [
        ([-0.4, 0.0, 0.0, 0.0, 0.0], True),  # barrel whose radius peaks 91 % of the way to the corners
        ([-0.4, 0.2, 0.0, 0.0, 0.0], False),  # the same lens with the k2 that holds it up
        ([0.3, -2.0, 0.0, 0.0, 0.0], True),  # k2 where k3 belongs, or a sign lost
        ([0.3, 0.0, 0.0, 0.0, -1.0], False),  # a fold past the corners (radius 0.75 against 0.67)
        ([2.0, 0.5, 0.0, 0.0, 0.0, 2.1, 0.6, 0.0], False),  # a rational model's terms that cancel
        ([-0.1, 0.03, 0.0, 0.0, 0.0, 10.0, 0.0, 0.0], True),  # a denominator that outgrows the numerator
    ],
)
def test_a_distortion_that_folds_the_image_is_refused(distortions: list[float], folds: bool) -> None:
    # cam_1: 320x240 at fx = fy = 300, centred: the corners' normalised radius is 0.67.
    doc = _doc()
    doc["cam_1"]["matrix"] = [[300.0, 0.0, 159.5], [0.0, 300.0, 119.5], [0.0, 0.0, 1.0]]
    doc["cam_1"]["size"] = [320, 240]
    doc["cam_1"]["distortions"] = distortions
    if not folds:
        cameras_from_dict(doc)
        return
    with pytest.raises(
        CalibrationError, match=r"\[cam_1\] \(camera 'cam1'\) distortion \(k1 .*folds the image"
    ):
        cameras_from_dict(doc)


def test_unreadable_and_missing_files(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match=r"calibration\.toml: not found"):
        read_calibration(tmp_path / "calibration.toml")
    (tmp_path / "calibration.toml").mkdir()
    with pytest.raises(CalibrationError, match=r"calibration\.toml: cannot read"):
        read_calibration(tmp_path / "calibration.toml")


def test_syntax_error_names_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "calibration.toml"
    path.write_text("[cam_0]\nname = cam0\n")  # an unquoted string on line 2
    with pytest.raises(CalibrationError, match=r"calibration.toml: TOML syntax error: .*at line 2"):
        read_calibration(path)


def _set(table: str, key: str, value: Any) -> dict[str, Any]:
    doc = _doc()
    doc[table][key] = value
    return doc


@pytest.mark.parametrize(
    ("doc", "needles"),
    [
        ({}, ("no camera tables",)),
        ({"metadata": {"a": 1}}, ("no camera tables",)),
        ({"cam_0": 5}, ("cam_0 = ... is not in a table", "[cam_N]")),
        ({"cam_0": [5]}, ("[cam_0] must be a table",)),
        ({"cam_0": {"name": "c"}}, ("[cam_0] is missing key(s) size, matrix",)),
        (_set("cam_2", "name", ""), ("[cam_2] name", "non-empty string")),
        (_set("cam_2", "size", [320.5, 240.0]), ("camera 'cam2'", "size", "positive integers")),
        (_set("cam_2", "size", [True, 240]), ("camera 'cam2'", "size", "positive integers")),
        (_set("cam_2", "size", [320, 0]), ("camera 'cam2'", "size")),
        (_set("cam_2", "matrix", [["300", 0, 160], [0, 300, 120], [0, 0, 1]]), ("matrix", "numbers")),
        (_set("cam_2", "matrix", [[300, 0, 160], [0, 300, 120], [0, 0, 2]]), ("matrix", "fx, fy > 0")),
        (_set("cam_2", "matrix", [[300, 0, 160], [0, 300, 120], [0, 0]]), ("matrix", "numbers")),
        # A focal length in mm (8 mm), not pixels: a 174-degree view over 320 px.
        (_set("cam_2", "matrix", [[8, 0, 160], [0, 8, 120], [0, 0, 1]]), ("174-degree", "in pixels, not mm")),
        (_set("cam_2", "matrix", [[300, 0, 160], [0, 0.5, 120], [0, 0, 1]]), ("fy 0.5", "180-degree")),
        (_set("cam_2", "distortions", [0.1, 0.2, 0.3]), ("distortions", "4, 5, 8, 12 or 14")),
        (_set("cam_2", "distortions", [0.1, 0.2, 0.3, "0.4"]), ("distortions", "numbers")),
        (_set("cam_2", "rotation", [[1, 0], [0, 1]]), ("rotation", "shape")),
        (_set("cam_2", "rotation", [[2.0, 0, 0], [0, 2.0, 0], [0, 0, 2.0]]), ("not a rotation",)),
        (_set("cam_2", "translation", [0, 0, 10**400]), ("translation", "numbers")),
        (_set("cam_2", "translation", [0, 0, float("-inf")]), ("translation", "non-finite")),
        (_set("cam_1", "name", "cam2"), ("'cam2' appears more than once",)),
        # A misspelt key, which would otherwise be dropped without a word.
        (_set("cam_1", "fishye", True), ("[cam_1] has unknown key 'fishye'", "fisheye")),
        ({**_doc(), "units": "mm"}, ("units = ... is not in a table",)),
        # A misspelt value, which would otherwise pass a fisheye lens off as a standard one.
        (_set("cam_1", "fisheye", "true"), ("camera 'cam1'", "fisheye must be true or false, got 'true'")),
        (_set("cam_1", "fisheye", 1), ("fisheye must be true or false, got 1",)),
        # A name is its video's file stem, and its frame's name in the recordings.
        (_set("cam_1", "name", "top/cam1"), ("camera 'top/cam1'", "cannot hold / or", "video file")),
        (_set("cam_1", "name", ".."), ("camera '..'", "be . or ..")),
        (_set("cam_1", "name", "world"), ("camera 'world'", "the recordings' own frame")),
    ],
)
def test_mistakes_name_the_camera_and_key(doc: dict[str, Any], needles: tuple[str, ...]) -> None:
    with pytest.raises(CalibrationError) as info:
        cameras_from_dict(doc, source="rig/calibration.toml")
    message = str(info.value)
    assert message.startswith("rig/calibration.toml: ")
    for needle in needles:
        assert needle in message
