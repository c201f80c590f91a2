"""pipeline calibrate with ChArUco boards: detection of partly visible boards, targets on synth renders."""

from __future__ import annotations

import re
import shutil
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import assert_meets_calibration_targets

from pipeline.calibrate.boards import Board, detect_charuco, load_board
from pipeline.calibrate.solve import CalibrationResult, calibrate_directory
from pipeline.cli import build_parser
from pipeline.errors import CalibrationError
from pipeline.synth.boards import (
    _camera_rays,
    _CharucoTexture,
    _intrinsic_poses,
    _render,
    render_calibration_views,
)
from pipeline.synth.rig import make_rig

# The synth-calib ChArUco board: 7 x 5 squares of 50 mm, markers 37.5 mm.
BOARD = Board(6, 4, 50.0, "charuco", 37.5, "DICT_4X4_50")


@pytest.fixture(scope="module", params=["ninety", "oblique"])
def synth(request, tmp_path_factory) -> tuple[Path, CalibrationResult]:
    root = tmp_path_factory.mktemp(f"charuco_{request.param}")
    # 10 intrinsics views per camera (not 15) to keep the test short; the targets still hold.
    render_calibration_views(root, arrangement=request.param, board_type="charuco", views=10, progress=False)
    result = calibrate_directory(root, root / "out" / "calibration.toml")
    return root, result


def test_detects_a_partly_visible_board_exactly() -> None:
    cam = make_rig("oblique")[1]
    # Odd-numbered ChArUco intrinsics poses hang over the image border.
    R, t = _intrinsic_poses(cam, np.random.default_rng(3), 2, 6, 4, 50.0, partial=True)[1]
    image = _render(
        _camera_rays(cam),
        cam,
        R,
        t,
        6,
        4,
        50.0,
        np.random.default_rng(0),
        texture=_CharucoTexture((7, 5), "DICT_4X4_50"),
    )
    found = detect_charuco(image, BOARD)
    assert found is not None
    ids, corners = found
    rvec, _ = cv2.Rodrigues(R)
    truth_all, _ = cv2.projectPoints(BOARD.object_points(), rvec, t, cam.K, cam.dist)
    truth_all = truth_all.reshape(-1, 2)
    inside = np.all((truth_all >= 0) & (truth_all <= (cam.width - 1, cam.height - 1)), axis=1)
    assert not inside.all(), "the pose should show only part of the board"
    assert 6 <= len(ids) and set(ids.tolist()) <= set(np.flatnonzero(inside).tolist())
    errors = np.linalg.norm(corners - truth_all[ids], axis=1)
    # Saddle-refined corners are ~0.02 px off on these exact renders (0.044 px worst of
    # 124 measured); a wrong id or a marker corner taken for a square corner is >= 3 px off.
    assert errors.max() < 0.1


def test_no_board_in_the_image_gives_none() -> None:
    assert detect_charuco(np.full((240, 320), 120, np.uint8), BOARD) is None


def test_synth_charuco_meets_the_targets(synth) -> None:
    root, result = synth
    # Measured with 10 views per camera: <= 0.024 px, 0.074 %, 0.39 mm, 0.083 deg
    # (targets: conftest's assert_meets_calibration_targets).
    assert_meets_calibration_targets(result.cameras, result.camera_mean_px(), root / "truth_calibration.toml")
    doc = tomllib.loads((root / "out" / "calibration.toml").read_text())
    assert doc["metadata"]["board"].startswith("charuco 7x5 squares, 50 mm")


def test_a_board_given_a_row_larger_than_it_is_named(synth, tmp_path) -> None:
    # Its markers are decoded all the same, and its corners placed a square off: every
    # camera's centre 50 mm off, at the re-projection error of the right board.
    root, result = synth
    assert result.problems == []
    wrong = calibrate_directory(root, tmp_path / "calibration.toml", charuco=(7, 6))
    assert any(
        line.startswith("no image shows a corner of the first row of the board given (charuco 7x6 squares")
        and "count its squares again" in line
        for line in wrong.problems
    )


def test_world_without_charuco_corners_is_an_error(synth, tmp_path) -> None:
    root, _ = synth
    copy = tmp_path / "calib"
    shutil.copytree(root, copy, ignore=shutil.ignore_patterns("out"))
    cv2.imwrite(str(copy / "cam0" / "world.png"), np.full((240, 320), 120, np.uint8))
    with pytest.raises(
        CalibrationError, match=r"cam0/world\.png: too few ChArUco corners found .*world frame"
    ):
        calibrate_directory(copy, tmp_path / "calibration.toml")


def test_board_toml_and_flags(synth, tmp_path) -> None:
    root, _ = synth
    assert tomllib.loads((root / "board.toml").read_text()) == {
        "type": "charuco",
        "squares": [7, 5],
        "marker_mm": 37.5,
        "dictionary": "DICT_4X4_50",
        "square_mm": 50.0,
    }
    assert load_board(root) == BOARD
    # --charuco with --square-mm and no board.toml: markers 0.75 square, DICT_4X4_50.
    assert load_board(tmp_path, charuco=(5, 4), square_mm=40.0) == Board(
        4, 3, 40.0, "charuco", 30.0, "DICT_4X4_50"
    )
    # --board overrides a ChArUco board.toml.
    assert load_board(root, board=(9, 6), square_mm=20.0) == Board(9, 6, 20.0)
    # ... given whole: without its square size, the board.toml is named, not called missing.
    with pytest.raises(CalibrationError, match=r"board\.toml: describes a charuco board, and --board 9x6"):
        load_board(root, board=(9, 6))
    with pytest.raises(CalibrationError, match="not both"):
        load_board(root, board=(9, 6), charuco=(7, 5))
    (tmp_path / "board.toml").write_text(
        'type = "charuco"\nsquares = [7, 5]\nsquare_mm = 30.0\ndictionary = "DICT_9X9"\n'
    )
    with pytest.raises(CalibrationError, match="unknown ArUco dictionary 'DICT_9X9'"):
        load_board(tmp_path)


@pytest.mark.parametrize("square", [float("nan"), float("inf"), 1e-300, -5.0, 0.0, 0.025])
def test_a_square_size_that_is_no_size_is_refused_before_any_detection(tmp_path: Path, square: float) -> None:
    for flags in ({"board": (9, 6)}, {"charuco": (7, 5)}):
        with pytest.raises(CalibrationError, match="square"):
            load_board(tmp_path, square_mm=square, **flags)
    (tmp_path / "board.toml").write_text(
        f'type = "chessboard"\ninner_corners = [9, 6]\nsquare_mm = {square!r}\n'
    )
    with pytest.raises(
        CalibrationError,
        match=r"board\.toml: square_mm must be a finite size in mm, 0\.5 to 10000, got .* \(a board's",
    ):
        load_board(tmp_path)
    (tmp_path / "board.toml").write_text('type = "chessboard"\ninner_corners = [9, 6]\nsquare_mm = "20"\n')
    with pytest.raises(CalibrationError, match=r"board\.toml: square_mm .* got '20' \(a number, not text"):
        load_board(tmp_path)


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ('type = "charuco"\nsquares = [7, 5]\nsquare_mm = 50.0\ndictonary = "DICT_5X5_100"\n', "dictonary"),
        ('type = "chessboard"\ninner_corners = [9, 6]\nsquare_m = 20.0\n', "square_m"),
    ],
    ids=["charuco-dictonary", "chessboard-square_m"],
)
def test_an_unknown_board_toml_key_is_named_with_the_nearest_name(
    tmp_path: Path, text: str, needle: str
) -> None:
    # A misspelt key would fall back to its default (DICT_4X4_50, the --square-mm flag) without a word.
    path = tmp_path / "board.toml"
    path.write_text(text)
    nearest = {"dictonary": "dictionary", "square_m": "square_mm"}[needle]
    with pytest.raises(
        CalibrationError,
        match=re.escape(f"{path}: unknown key {needle!r} (did you mean {nearest!r}?); allowed: "),
    ):
        load_board(tmp_path, square_mm=20.0)


def test_cli_synth_calib_board_option() -> None:
    args = build_parser().parse_args(["synth-calib", "out", "--board", "charuco"])
    assert args.board == "charuco"
    assert build_parser().parse_args(["synth-calib", "out"]).board == "chessboard"


@pytest.mark.parametrize(
    ("encoding", "needle"), [("utf-16", "is not UTF-8 text; save it as UTF-8"), ("utf-8-sig", None)]
)
def test_board_toml_in_another_encoding_is_named_or_read(
    tmp_path: Path, encoding: str, needle: str | None
) -> None:
    """Windows editors save UTF-16, or UTF-8 with a byte-order mark (read as UTF-8)."""
    path = tmp_path / "board.toml"
    path.write_text('type = "chessboard"\ninner_corners = [9, 6]\nsquare_mm = 20.0\n', encoding=encoding)
    if needle is None:
        assert load_board(tmp_path).describe() == "chessboard 9x6, 20 mm"
        return
    with pytest.raises(CalibrationError, match=re.escape(f"{path}: {needle}")):
        load_board(tmp_path)


@pytest.mark.parametrize("rows", [201, 2**31])
def test_a_board_larger_than_any_printed_one_is_refused_before_any_detection(
    tmp_path: Path, rows: int
) -> None:
    with pytest.raises(
        CalibrationError, match=rf"board 3x{rows} has more inner corners than a printed board"
    ):
        load_board(tmp_path, board=(3, rows), square_mm=20.0)
