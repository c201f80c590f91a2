"""pipeline calibrate: synthetic renders against the true cameras, real stereo images against OpenCV."""

from __future__ import annotations

import dataclasses
import logging
import re
import shutil
import struct
import tomllib
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import assert_meets_calibration_targets, rig_cameras, rotation_angle_deg

from pipeline.calibrate.boards import detect_corners, find_chessboard, load_board
from pipeline.calibrate.report import format_table
from pipeline.calibrate.solve import CalibrationResult, calibrate_directory, calibrate_views, detect_directory
from pipeline.calibrate.views import _read_grey
from pipeline.errors import CalibrationError, OutputError
from pipeline.session.calibration_io import read_calibration
from pipeline.session.folder import _read_grey_8bit
from pipeline.synth.boards import render_calibration_views

STEREO = Path("/work/shared/data/stereo-chessboard")
if not STEREO.is_dir():
    STEREO = Path(__file__).resolve().parents[3] / "shared" / "data" / "stereo-chessboard"


@pytest.fixture(scope="module", params=["oblique", "ninety"])
def synth(request, tmp_path_factory) -> tuple[Path, CalibrationResult]:
    root = tmp_path_factory.mktemp(f"calib_{request.param}")
    render_calibration_views(root, arrangement=request.param, seed=0, views=10, progress=False)
    result = calibrate_directory(root, root / "out" / "calibration.toml")
    return root, result


def test_synth_calibration_meets_the_targets(synth) -> None:
    root, result = synth
    # Measured with 10 views per camera: <= 0.030 px, 0.155 %, 0.77 mm, 0.082 deg
    # (targets: conftest's assert_meets_calibration_targets).
    assert_meets_calibration_targets(result.cameras, result.camera_mean_px(), root / "truth_calibration.toml")


def test_output_toml_and_report(synth) -> None:
    root, result = synth
    out = root / "out"
    doc = tomllib.loads((out / "calibration.toml").read_text())
    assert set(doc["metadata"]["mean_reprojection_error_px"]) == {"cam0", "cam1", "cam2"}
    assert [c.name for c in read_calibration(out / "calibration.toml")] == ["cam0", "cam1", "cam2"]
    assert (out / "reprojection_errors.png").is_file()
    # One world-axes picture per camera that has a world image.
    worlds = sorted(p.parent.name for p in root.glob("*/world.png"))
    assert sorted(p.stem.removeprefix("world_axes_") for p in out.glob("world_axes_*.png")) == worlds
    table = format_table(result)
    assert "cam2" in table and "world" in table


def test_world_axes_land_on_the_board(synth) -> None:
    """The world origin projects onto the first inner corner detected in world.png."""
    root, result = synth
    board = load_board(root)
    for cam in result.cameras:
        world = root / cam.name / "world.png"
        if not world.is_file():
            continue
        corners = detect_corners(cv2.imread(str(world), cv2.IMREAD_GRAYSCALE), board)
        assert corners is not None
        origin = cam.project(np.zeros((1, 3)))[0]
        # Half a pixel: the corner of a board seen at a grazing angle is located to ~0.15 px.
        assert np.linalg.norm(origin - corners[0]) < 0.5


@pytest.fixture(scope="module")
def small_rig(tmp_path_factory) -> Path:
    """Two cameras, 6 intrinsics views each: the base for the bad-input cases."""
    root = tmp_path_factory.mktemp("calib_small")
    render_calibration_views(root, arrangement="oblique", seed=3, views=6, progress=False)
    shutil.rmtree(root / "cam2")
    for cam in ("cam0", "cam1"):
        shutil.rmtree(root / cam / "shared")
    return root


def _copy(src: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "calib"
    shutil.copytree(src, dst)
    return dst


def test_missing_world_without_link_is_named(small_rig, tmp_path) -> None:
    root = _copy(small_rig, tmp_path)
    (root / "cam1" / "world.png").unlink()
    with pytest.raises(CalibrationError, match=r"camera 'cam1': no world\.png"):
        calibrate_directory(root, tmp_path / "c.toml")


def test_board_not_in_world_image(small_rig, tmp_path) -> None:
    root = _copy(small_rig, tmp_path)
    cv2.imwrite(str(root / "cam0" / "world.png"), np.full((240, 320), 128, np.uint8))
    with pytest.raises(CalibrationError, match=r"cam0/world.png: board 9x6 not found"):
        calibrate_directory(root, tmp_path / "c.toml")


def test_two_world_images_are_refused_before_detection(small_rig, tmp_path, monkeypatch) -> None:
    root = _copy(small_rig, tmp_path)
    world = root / "cam1" / "world.png"
    cv2.imwrite(str(world.with_suffix(".jpg")), cv2.imread(str(world)))

    def no_detection(*_args: object) -> None:
        raise AssertionError("an image was searched for corners")

    monkeypatch.setattr("pipeline.calibrate.views.detect", no_detection)
    with pytest.raises(CalibrationError, match=r"cam1: holds 2 world images \(world\.png, world\.jpg\)"):
        calibrate_directory(root, tmp_path / "c.toml")


def test_a_world_image_named_in_capitals_is_read(small_rig, tmp_path) -> None:
    # Cameras' cards write WORLD.JPG; the other images' suffixes are read in any case too.
    root = _copy(small_rig, tmp_path)
    world = root / "cam1" / "world.png"
    cv2.imwrite(str(root / "cam1" / "World.JPG"), cv2.imread(str(world)))
    world.unlink()
    result = calibrate_directory(root, tmp_path / "c.toml")
    expected = calibrate_directory(_copy(small_rig, tmp_path / "as_png"), tmp_path / "c2.toml")
    assert [c.name for c in result.cameras] == [c.name for c in expected.cameras]
    cam1 = next(c for c in result.cameras if c.name == "cam1")
    cam1_png = next(c for c in expected.cameras if c.name == "cam1")
    assert np.allclose(cam1.center_mm, cam1_png.center_mm, atol=1.0)  # a JPEG's loss, no more


def test_too_few_views(small_rig, tmp_path) -> None:
    root = _copy(small_rig, tmp_path)
    for path in sorted((root / "cam1" / "intrinsics").glob("*.png"))[:3]:
        path.unlink()
    with pytest.raises(CalibrationError, match="camera 'cam1': board found in only 4 distinct view"):
        calibrate_directory(root, tmp_path / "c.toml")


def test_a_camera_folder_named_world_is_refused_before_any_image_is_read(
    small_rig, tmp_path, monkeypatch
) -> None:
    from pipeline.calibrate import views

    root = _copy(small_rig, tmp_path)
    (root / "cam1").rename(root / "world")
    monkeypatch.setattr(views, "_read_grey", lambda path: pytest.fail(f"{path} was read"))
    with pytest.raises(
        CalibrationError, match=r"world: a camera cannot be named 'world'.*; rename the folder"
    ):
        calibrate_directory(root, tmp_path / "c.toml")
    assert not (tmp_path / "c.toml").exists()


def test_images_that_are_not_read_and_an_empty_camera_folder_are_named(small_rig, tmp_path, caplog) -> None:
    root = _copy(small_rig, tmp_path)
    for path in sorted((root / "cam1" / "intrinsics").glob("*.png"))[:2]:
        shutil.copy(path, root / "cam1" / f"loose{path.name}")
    (root / "cam2").mkdir()
    (root / "stray").mkdir()
    shutil.copy(root / "cam0" / "world.png", root / "stray" / "board.png")
    with caplog.at_level(logging.WARNING):
        calibrate_directory(root, tmp_path / "c.toml")
    text = caplog.text
    assert (
        f"{root / 'cam1'}: 2 image(s) beside its world image are not read (loose00.png, loose01.png)" in text
    )
    assert f"{root / 'cam2'}: an empty folder, so no camera's" in text
    assert f"{root / 'stray'}: 1 image(s) beside no intrinsics/ or shared/ folder are not read" in text


def test_a_calibration_written_among_a_cameras_images_is_refused(small_rig, tmp_path) -> None:
    # Its report pictures would be read as board images by the next calibration.
    root = _copy(small_rig, tmp_path)
    for inside in (root / "cam0" / "intrinsics" / "c.toml", root / "cam1" / "c.toml"):
        with pytest.raises(OutputError, match=r"holds board images \(camera 'cam[01]'\), where the report"):
            calibrate_directory(root, inside)
        assert not inside.exists()
    assert not list(root.glob("*/**/*.toml"))


def test_a_board_size_given_the_other_way_round_is_named(small_rig, caplog) -> None:
    # The flag overrides board.toml, as documented; read the other way round, the board
    # turns the world frame a quarter turn: said, in case it was a slip.
    with caplog.at_level(logging.WARNING):
        assert load_board(small_rig, board=(6, 9), square_mm=20.0).cols == 6
    (line,) = [m for m in caplog.messages if "other way round" in m]
    assert line.startswith("--board 6x9 is ") and "board.toml's 9x6 the other way round" in line
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        load_board(small_rig, board=(9, 6), square_mm=20.0)
    assert not caplog.messages


def test_copies_of_one_view_count_once(small_rig, tmp_path, caplog) -> None:
    # Byte copies of one image (or a video of a board held still) add no pose: counted
    # once, and named; with too few poses left, the camera is not calibrated on them.
    root = _copy(small_rig, tmp_path)
    images = sorted((root / "cam1" / "intrinsics").glob("*.png"))
    for i in range(3):
        shutil.copyfile(images[0], root / "cam1" / "intrinsics" / f"copy{i}.png")
    board = load_board(root)
    with caplog.at_level(logging.WARNING):
        views = detect_directory(root, board)
    assert sum(v.camera == "cam1" for v in views) == len(images) + 1  # its 6 poses and world.png
    (line,) = [m for m in caplog.messages if "show the board where another does" in m]
    assert line.startswith("camera 'cam1': 3 intrinsics image(s)") and f"repeat {images[0].name}" in line
    for path in images[1:4]:
        path.unlink()
    with pytest.raises(CalibrationError, match="camera 'cam1': board found in only 4 distinct view"):
        calibrate_directory(root, tmp_path / "c.toml")


def test_inconsistent_image_sizes(small_rig, tmp_path) -> None:
    root = _copy(small_rig, tmp_path)
    path = root / "cam0" / "intrinsics" / "00.png"
    cv2.imwrite(str(path), cv2.resize(cv2.imread(str(path)), (640, 480)))
    with pytest.raises(
        CalibrationError,
        match=r"camera 'cam0': images of different sizes \(.*00\.png is 640x480, .*\.png 320x240\)",
    ):
        calibrate_directory(root, tmp_path / "c.toml")
    # A folder where board.toml goes is named, not read as no board description.
    (root / "cam0" / "intrinsics" / "00.png").unlink()
    (root / "board.toml").unlink(missing_ok=True)
    (root / "board.toml").mkdir()
    with pytest.raises(CalibrationError, match=r"board\.toml: is not a file \(a folder\?\)"):
        calibrate_directory(root, tmp_path / "c.toml")


def _png_header_only(width: int, height: int) -> bytes:
    """A whole PNG file (signature, IHDR, empty IDAT, IEND) announcing ``width`` x ``height`` grey pixels."""

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", b"") + chunk(b"IEND", b"")


def _cut(path: Path, suffix: str) -> Path:
    """``path`` saved as ``suffix`` and cut to half its bytes, in place of the original."""
    image = cv2.imread(str(path))
    path.unlink()
    path = path.with_suffix(suffix)
    cv2.imwrite(str(path), image)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    return path


@pytest.mark.parametrize(
    ("damage", "needle"),
    [
        ("empty", "is empty (0 bytes)"),
        ("cut png", "is cut short"),
        ("cut jpeg", "is cut short"),
        ("too many pixels", "more pixels than OpenCV decodes"),
        ("dangling link", "is a symbolic link to /nowhere/03.png, which does not exist"),
    ],
)
def test_an_image_that_cannot_be_read_whole_is_named(small_rig, tmp_path, damage: str, needle: str) -> None:
    root = _copy(small_rig, tmp_path)
    path = root / "cam1" / "intrinsics" / "03.png"
    if damage == "empty":
        path.write_bytes(b"")
    elif damage.startswith("cut"):
        path = _cut(path, ".png" if damage == "cut png" else ".jpg")
    elif damage == "too many pixels":
        path.write_bytes(_png_header_only(40000, 40000))
    else:
        path.unlink()
        path.symlink_to("/nowhere/03.png")
    with pytest.raises(CalibrationError, match=re.escape(f"{path}: ") + ".*" + re.escape(needle)):
        calibrate_directory(root, tmp_path / "c.toml")
    assert not (tmp_path / "c.toml").exists()


@pytest.mark.parametrize("ext", [".png", ".jpg"])
def test_an_image_with_bytes_after_its_end_is_read(small_rig, tmp_path, ext: str) -> None:
    """A phone's trailer after the image's end (a motion photo's video) is no cut."""
    root = _copy(small_rig, tmp_path)
    for path in sorted((root / "cam1" / "intrinsics").glob("*.png")):
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        path.unlink()
        ok, encoded = cv2.imencode(ext, image, [cv2.IMWRITE_JPEG_QUALITY, 98] if ext == ".jpg" else [])
        assert ok
        trailer = bytes(range(256)) * 400  # 100 kB holding no end marker of either kind
        path.with_suffix(ext).write_bytes(encoded.tobytes() + trailer)
    result = calibrate_directory(root, tmp_path / "c.toml")
    assert result.camera_mean_px()["cam1"] < 0.2


def test_16_bit_images_holding_8_bit_values_are_read_at_their_contrast(small_rig, tmp_path) -> None:
    """Some tools save 8-bit (or 10- and 12-bit) grey levels in 16-bit PNGs: scaled by 256 they are black."""
    root = _copy(small_rig, tmp_path)
    for path in (root / "cam1").rglob("*.png"):
        cv2.imwrite(str(path), cv2.imread(str(path), cv2.IMREAD_GRAYSCALE).astype(np.uint16))
    result = calibrate_directory(root, tmp_path / "c.toml")
    assert sum(e.camera == "cam1" for e in result.image_errors) == 7  # 6 intrinsics views and world.png
    assert result.camera_mean_px()["cam1"] < 0.2


@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("top", [255, 4095, 30000, 65535])
def test_a_16_bit_board_image_reads_at_a_backgrounds_levels(tmp_path, top: int, channels: int) -> None:
    """One rule for both, grey or colour: a board image is not stretched to its brightest pixel."""
    path = tmp_path / "board.png"
    levels = np.linspace(0, top, 64 * 48).reshape(48, 64).astype(np.uint16)
    cv2.imwrite(str(path), levels if channels == 1 else np.dstack([levels, levels // 2, levels]))
    as_board = _read_grey(path)
    np.testing.assert_array_equal(as_board, _read_grey_8bit(path))
    if channels == 1:
        assert int(as_board.max()) == (117 if top == 30000 else 255)


def _with_exif_orientation(jpeg: bytes, orientation: int) -> bytes:
    """``jpeg`` with an EXIF segment whose Orientation tag asks viewers to turn it."""
    tiff = b"MM" + struct.pack(">HI", 42, 8) + struct.pack(">H", 1)
    tiff += struct.pack(">HHIHH", 0x112, 3, 1, orientation, 0) + struct.pack(">I", 0)
    segment = b"\xff\xe1" + struct.pack(">H", len(tiff) + 8) + b"Exif\0\0" + tiff
    return jpeg[:2] + segment + jpeg[2:]


def test_webp_images_are_read_and_files_of_other_kinds_are_named(small_rig, tmp_path, caplog) -> None:
    # A kind not read and not named leaves its camera to its world view alone (8 mm off on
    # these boards), under a warning that the board was not found.
    root = _copy(small_rig, tmp_path)
    for path in (root / "cam1" / "intrinsics").glob("*.png"):
        cv2.imwrite(str(path.with_suffix(".webp")), cv2.imread(str(path)), [cv2.IMWRITE_WEBP_QUALITY, 101])
        path.unlink()
    (root / "cam1" / "intrinsics" / "07.heic").write_bytes(b"\0" * 100)
    (root / "cam1" / "intrinsics" / ".DS_Store").write_bytes(b"\0" * 100)  # hidden: no word of it
    with caplog.at_level(logging.WARNING):
        result = calibrate_directory(root, tmp_path / "c.toml")
    assert sum(e.camera == "cam1" for e in result.image_errors) == 7  # 6 intrinsics views and world.png
    assert (
        "camera 'cam1': 1 file(s) not read, of no image or video kind read (intrinsics/07.heic)"
        in caplog.text
    )
    assert ".DS_Store" not in caplog.text


def test_images_are_read_as_stored_whatever_their_exif_orientation(tmp_path) -> None:
    # Video frames are read as stored (their rotation tags are not applied): a board image
    # turned on reading would calibrate its camera upside down against the frames.
    levels = np.arange(48 * 64, dtype=np.uint8).reshape(48, 64)
    plain = cv2.imencode(".jpg", levels, [cv2.IMWRITE_JPEG_QUALITY, 100])[1].tobytes()
    (tmp_path / "plain.jpg").write_bytes(plain)
    (tmp_path / "turned.jpg").write_bytes(_with_exif_orientation(plain, 3))
    assert cv2.imread(str(tmp_path / "turned.jpg"), cv2.IMREAD_GRAYSCALE).shape == (48, 64)
    assert not np.array_equal(
        cv2.imread(str(tmp_path / "turned.jpg"), cv2.IMREAD_GRAYSCALE), _read_grey(tmp_path / "plain.jpg")
    )
    np.testing.assert_array_equal(_read_grey(tmp_path / "turned.jpg"), _read_grey(tmp_path / "plain.jpg"))
    np.testing.assert_array_equal(
        _read_grey_8bit(tmp_path / "turned.jpg"), _read_grey_8bit(tmp_path / "plain.jpg")
    )


def test_a_camera_with_shared_views_alone_is_calibrated_and_said_to_be_loose(tmp_path, caplog) -> None:
    """cam2 keeps only shared/ (no intrinsics/, no world.png): it is one of the rig's cameras,
    and the run says that its lens rests on those few views."""
    root = tmp_path / "calib"
    render_calibration_views(root, arrangement="oblique", seed=0, views=6, progress=False)
    shutil.rmtree(root / "cam2" / "intrinsics")
    (root / "cam2" / "world.png").unlink()
    with caplog.at_level(logging.WARNING):
        result = calibrate_directory(root, tmp_path / "c.toml")
    assert [c.name for c in result.cameras] == ["cam0", "cam1", "cam2"]
    assert result.camera_mean_px()["cam2"] < 0.2
    warned = [r.getMessage() for r in caplog.records if "has no intrinsics/ image" in r.getMessage()]
    assert len(warned) == 1 and warned[0].startswith("camera 'cam2' has no intrinsics/ image")


def test_wrong_board_size_is_named(small_rig, tmp_path) -> None:
    # A sub-board is found in a few images at most: named as too few views, pointing at --board.
    with pytest.raises(CalibrationError, match=r"board (8x5 not found|found in only .*check --board)"):
        calibrate_directory(small_rig, tmp_path / "c.toml", board=(8, 5), square_mm=20.0)


def test_an_image_copied_from_another_cameras_folder_is_refused_naming_both(small_rig, tmp_path) -> None:
    """Two cameras never see one board alike: cam1's image beside cam0's own is a copy."""
    root = _copy(small_rig, tmp_path)
    shutil.copy(root / "cam1" / "intrinsics" / "02.png", root / "cam0" / "intrinsics" / "99.png")
    with pytest.raises(CalibrationError) as refused:
        calibrate_directory(root, tmp_path / "c.toml")
    message = str(refused.value)
    assert "cam1/intrinsics/02.png: shows the board exactly where" in message
    assert "cam0/intrinsics/99.png does, an image of camera 'cam0'" in message
    assert "copied into another's folder" in message and not (tmp_path / "c.toml").exists()


def test_a_calibration_process_would_refuse_is_a_problem_of_the_run() -> None:
    from pipeline.calibrate.solve import _refused_by_process

    cameras = rig_cameras()
    assert _refused_by_process(cameras) == []
    folded = dataclasses.replace(cameras[0], distortions=np.array([-0.9, 0.0, 0.0, 0.0, 0.0]))
    (line,) = _refused_by_process([folded, *cameras[1:]])
    assert "camera 'cam0'" in line and "folds the image" in line and "process refuses it" in line


def test_drop_outliers_removes_a_foreign_view(small_rig, tmp_path) -> None:
    """An intrinsics image from the other camera (moved by a few pixels: not a copy) stands
    out and --drop-outliers removes it."""
    root = _copy(small_rig, tmp_path)
    foreign = np.roll(cv2.imread(str(root / "cam1" / "intrinsics" / "02.png")), 4, axis=1)
    cv2.imwrite(str(root / "cam0" / "intrinsics" / "99.png"), foreign)
    kept = calibrate_directory(root, tmp_path / "a.toml")
    assert any(e.key == "intrinsics/99.png" for e in kept.outliers)
    dropped = calibrate_directory(root, tmp_path / "b.toml", drop_outliers=True)
    assert dropped.dropped == [str(root / "cam0" / "intrinsics" / "99.png")]
    assert dropped.camera_mean_px()["cam0"] < kept.camera_mean_px()["cam0"]


def test_shared_intrinsics_give_one_camera_matrix(small_rig, tmp_path) -> None:
    result = calibrate_directory(small_rig, tmp_path / "c.toml", shared_intrinsics=True)
    cam0, cam1 = result.cameras
    np.testing.assert_array_equal(cam0.matrix, cam1.matrix)
    np.testing.assert_array_equal(cam0.distortions, cam1.distortions)


def test_intrinsics_from_a_video(small_rig, tmp_path) -> None:
    """A video of the board in intrinsics/ is sampled frame by frame."""
    root = _copy(small_rig, tmp_path)
    images = sorted((root / "cam1" / "intrinsics").glob("*.png"))
    writer = cv2.VideoWriter(
        str(root / "cam1" / "intrinsics" / "board.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 5, (320, 240)
    )
    for path in images:
        writer.write(cv2.imread(str(path)))
        path.unlink()
    writer.release()
    result = calibrate_directory(root, tmp_path / "c.toml")
    keys = [e.key for e in result.image_errors if e.camera == "cam1"]
    assert [k for k in keys if k.startswith("intrinsics/")] == [f"intrinsics/board.avi#{i}" for i in range(6)]
    # Motion-JPEG at OpenCV's default quality costs some accuracy, well within the 0.2 px target.
    assert result.camera_mean_px()["cam1"] < 0.2
    # A video that is empty, or not one, is named with what to do.
    for content, why in ((b"", "it is empty"), (b"not a video at all", "not a video OpenCV reads")):
        (root / "cam1" / "intrinsics" / "board.avi").write_bytes(content)
        with pytest.raises(
            CalibrationError, match=rf"board\.avi: cannot open this video \({why}.*; copy it in"
        ):
            calibrate_directory(root, tmp_path / "c.toml", force=True)


def _stereo_folder(root: Path, *, pairs: int) -> Path:
    """A calibration folder of the first ``pairs`` real stereo pairs: pair 01 each camera's
    world view, the others shared views (links to the images)."""
    for side in ("left", "right"):
        (root / side / "shared").mkdir(parents=True)
        (root / side / "world.jpg").symlink_to(STEREO / f"{side}01.jpg")
        for i in range(2, pairs + 1):
            (root / side / "shared" / f"{i:02d}.jpg").symlink_to(STEREO / f"{side}{i:02d}.jpg")
    return root


@pytest.mark.skipif(not STEREO.is_dir(), reason="real stereo images not available")
def test_real_stereo_pairs_agree_with_opencv_stereo(tmp_path) -> None:
    """25 real pairs: pair 01 is the world view, the others shared views of both cameras."""
    root = _stereo_folder(tmp_path / "stereo", pairs=25)
    board = load_board(root, board=(9, 6), square_mm=24.0)
    views = detect_directory(root, board)
    result = calibrate_views(views, board)
    means = result.camera_mean_px()
    assert means["left"] <= 0.3 and means["right"] <= 0.3  # the target for real images
    left, right = result.cameras
    R_rel = right.camera_from_world @ left.camera_from_world.T
    t_rel = right.translation_mm - R_rel @ left.translation_mm

    # OpenCV's stereo calibration of the same detections (pairs seen by both cameras).
    by = {(v.camera, v.key): v.corners_px.astype(np.float32) for v in views}
    keys = sorted(k for c, k in by if c == "left" and ("right", k) in by)
    obj = [board.object_points().astype(np.float32)] * len(keys)
    pts_l = [by[("left", k)] for k in keys]
    pts_r = [by[("right", k)] for k in keys]
    size = (640, 512)
    K1 = cv2.calibrateCamera(obj, pts_l, size, None, None)[1]
    K2 = cv2.calibrateCamera(obj, pts_r, size, None, None)[1]
    # Independent intrinsics (k3 free, no corner cleaning): focal lengths within 0.5 %,
    # the calibration targets' intrinsics tolerance.
    assert abs(left.matrix[0, 0] / K1[0, 0] - 1) < 0.005
    assert abs(right.matrix[0, 0] / K2[0, 0] - 1) < 0.005
    # Extrinsics with our intrinsics held fixed: the same problem solved by
    # cv2.stereoCalibrate. Both minimise the same re-projection error, so they
    # should meet far below the rig's uncertainty: 0.5 % baseline, 0.05 degrees.
    rms, *_, R, T, _, _ = cv2.stereoCalibrate(
        obj,
        pts_l,
        pts_r,
        left.matrix,
        left.distortions,
        right.matrix,
        right.distortions,
        size,
        flags=cv2.CALIB_FIX_INTRINSIC,
    )
    assert rms < 0.3
    assert abs(np.linalg.norm(t_rel) / np.linalg.norm(T) - 1) < 0.005
    assert rotation_angle_deg(R_rel, R) < 0.05


@pytest.mark.skipif(not STEREO.is_dir(), reason="real stereo images not available")
def test_drop_outliers_drops_a_mirrored_image_and_its_pair_not_the_other_cameras_good_ones(
    tmp_path,
) -> None:
    """One real image mirrored (a board seen in a mirror, an export flipped) pulls the rig,
    and the other camera's good images stand out beside it until it is gone."""
    root = _stereo_folder(tmp_path / "stereo", pairs=13)
    clean = calibrate_directory(root, tmp_path / "clean.toml", board=(9, 6), square_mm=24.0)
    mirrored = root / "left" / "shared" / "03.jpg"
    mirrored.unlink()
    cv2.imwrite(str(mirrored), cv2.flip(cv2.imread(str(STEREO / "left03.jpg")), 1))
    result = calibrate_directory(root, tmp_path / "c.toml", board=(9, 6), square_mm=24.0, drop_outliers=True)
    # The mirrored image goes with its pair's other image (one board pose, which of the two
    # is wrong the pose alone cannot say), and nothing else but the pairs of the images that
    # stand out without it.
    pair = {str(mirrored), str(root / "right" / "shared" / "03.jpg")}
    standing_out = {Path(e.source).stem for e in clean.outliers}
    assert pair <= set(result.dropped)
    assert {Path(source).stem for source in result.dropped} <= {"03"} | standing_out
    assert max(result.camera_mean_px().values()) <= 0.3


@pytest.mark.slow
def test_reconstruction_with_calibrated_cameras(synth, tmp_path) -> None:
    """synth-calib -> calibrate -> process -> evaluate: calibrated cameras cost <= 0.2 mm."""
    from pipeline.measure.evaluate import evaluate_recording
    from pipeline.run.runner import process_session
    from pipeline.session.folder import load_session
    from pipeline.synth import render_session

    root, _ = synth
    arrangement = tomllib.loads((root / "truth_calibration.toml").read_text())["metadata"]["arrangement"]
    true_dir = tmp_path / "true"
    render_session(true_dir, frames=10, seed=0, arrangement=arrangement, progress=False, jobs=1)
    calibrated_dir = tmp_path / "calibrated"
    shutil.copytree(true_dir, calibrated_dir)
    shutil.copy(root / "out" / "calibration.toml", calibrated_dir / "calibration.toml")
    errors = {}
    for session_dir in (true_dir, calibrated_dir):
        out = tmp_path / f"rec_{session_dir.name}"
        process_session(load_session(session_dir), out_dir=out, jobs=1, images=False, progress=False)
        report = evaluate_recording(out / f"{session_dir.name}.mcap", session_dir / "ground_truth.npz")
        errors[session_dir.name] = report.mean_mm
    # The target: at most 0.2 mm worse in mean centreline error.
    assert errors["calibrated"] <= errors["true"] + 0.2, errors


def test_report_pictures_that_cannot_be_written_leave_the_calibration_there(
    small_rig, tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # OpenCV says False, not an exception, when it cannot write (a full disk): a picture it
    # did not write must not be listed as written. The calibration and its report are one
    # output: the calibration already there stays, not replaced by one without its report.
    from pipeline.calibrate import report
    from pipeline.errors import OutputError

    root = _copy(small_rig, tmp_path)
    calibrate_directory(root, tmp_path / "c.toml")
    before = (tmp_path / "c.toml").read_bytes()
    monkeypatch.setattr(report.cv2, "imwrite", lambda path, image: False)
    cannot = r"cannot write the report pictures .*c\.toml was not written \(the one there is kept\)"
    with pytest.raises(OutputError, match=cannot):
        calibrate_directory(root, tmp_path / "c.toml", force=True)
    assert (tmp_path / "c.toml").read_bytes() == before
    assert not list(tmp_path.glob(".*.partial"))


def test_a_calibration_interrupted_before_or_after_its_rename_says_which(
    small_rig, tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pipeline.calibrate import report
    from pipeline.errors import Interrupted

    root = _copy(small_rig, tmp_path)

    def interrupted(*args: object) -> list[Path]:
        raise KeyboardInterrupt

    monkeypatch.setattr(report, "write_report", interrupted)
    with pytest.raises(Interrupted, match=r"^interrupted; .*c\.toml was not written$"):
        calibrate_directory(root, tmp_path / "c.toml")
    assert not (tmp_path / "c.toml").exists() and not list(tmp_path.glob(".*.partial"))
    # A signal just as the calibration is renamed into place: it is there, and said to be.
    monkeypatch.undo()
    rename = Path.replace

    def renamed_then_interrupted(self: Path, target: Path) -> Path:
        done = rename(self, target)
        if Path(target).name == "c.toml":
            raise KeyboardInterrupt
        return done

    monkeypatch.setattr(Path, "replace", renamed_then_interrupted)
    with pytest.raises(Interrupted, match=r"c\.toml is written, with its report"):
        calibrate_directory(root, tmp_path / "c.toml")
    monkeypatch.undo()
    assert read_calibration(tmp_path / "c.toml")


def test_an_unexpanded_home_in_the_output_is_refused(small_rig, tmp_path) -> None:
    from pipeline.errors import OutputError

    with pytest.raises(OutputError, match=r"~ is not expanded here .*; give -o /"):
        calibrate_directory(small_rig, Path("~/c.toml"))


def test_an_output_through_a_link_writes_the_file_it_leads_to_and_a_link_to_nothing_is_named(
    small_rig, tmp_path
) -> None:
    from pipeline.errors import OutputError

    shared = tmp_path / "shared.toml"
    link = tmp_path / "link.toml"
    link.symlink_to(shared.name)
    calibrate_directory(small_rig, link)
    assert link.is_symlink() and read_calibration(shared)
    dangling = tmp_path / "dangling.toml"
    dangling.symlink_to(tmp_path / "nowhere" / "c.toml")
    with pytest.raises(
        OutputError, match=r"dangling\.toml: is a symbolic link to .*, which cannot be written"
    ):
        calibrate_directory(small_rig, dangling)
    assert dangling.is_symlink() and not (tmp_path / "nowhere").exists()
    loop = tmp_path / "loop.toml"
    loop.symlink_to(loop.name)
    with pytest.raises(OutputError, match=r"a loop of links"):
        calibrate_directory(small_rig, loop)


def test_shared_images_named_unlike_in_every_camera_are_named(small_rig, tmp_path, caplog) -> None:
    # Shared views are matched by name: left02.jpg and right02.jpg link nothing.
    root = _copy(small_rig, tmp_path)
    for cam, prefix in (("cam0", "left"), ("cam1", "right")):
        (root / cam / "shared").mkdir()
        for k, image in enumerate(sorted((root / cam / "intrinsics").glob("*.png"))[:2]):
            shutil.copy(image, root / cam / "shared" / f"{prefix}{k:02d}.png")
    shutil.copy(root / "cam0" / "shared" / "left00.png", root / "cam1" / "shared" / "left00.png")
    with caplog.at_level(logging.WARNING):
        detect_directory(root, load_board(root, board=(9, 6), square_mm=20.0))
    assert (
        "camera 'cam0': 1 of its 2 shared/ images have no image of the same name in another camera (left01)"
        in caplog.text
    )
    assert "camera 'cam1': 2 of its 3 shared/ images have no image of the same name" in caplog.text
    assert "(right00, right01): shared views are matched by name" in caplog.text


def test_one_lens_shared_by_cameras_whose_lenses_differ_is_named(small_rig, tmp_path) -> None:
    # synth-calib's cameras have focal lengths of 312 and 360 px: one lens for both put
    # their centres tens of mm off, at mean errors under the 1 px bar, exit 0.
    result = calibrate_directory(small_rig, tmp_path / "c.toml", shared_intrinsics=True)
    (line,) = [line for line in result.problems if "--shared-intrinsics" in line]
    assert line.startswith("one lens shared by every camera (--shared-intrinsics) fits cam")
    assert "the cameras' lenses differ; calibrate without --shared-intrinsics" in line


def test_two_images_of_one_shared_view_in_a_camera_are_refused(small_rig, tmp_path) -> None:
    # Both taken as view 02, one of them would stand 20 px off its pose, silently.
    root = _copy(small_rig, tmp_path)
    (root / "cam0" / "shared").mkdir()
    image = sorted((root / "cam0" / "intrinsics").glob("*.png"))[0]
    shutil.copy(image, root / "cam0" / "shared" / "02.png")
    cv2.imwrite(str(root / "cam0" / "shared" / "02.jpg"), cv2.imread(str(image)))
    with pytest.raises(
        CalibrationError, match=r"shared: holds 02\.jpg, 02\.png, two images of the shared view '02'"
    ):
        calibrate_directory(root, tmp_path / "c.toml")
    assert not (tmp_path / "c.toml").exists()


def test_a_board_given_smaller_than_it_is_is_named(small_rig, tmp_path) -> None:
    # The detector finds a 5x4 pattern inside the 9x6 board: the calibration is garbage,
    # and its first line must say why, not only that the images do not fit one rig.
    result = calibrate_directory(small_rig, tmp_path / "c.toml", board=(5, 4))
    assert result.problems[0].startswith(
        "the board holds more inner corners than chessboard 5x4, 20 mm (a 6x4 pattern was found too)"
    )
    right = calibrate_directory(small_rig, tmp_path / "right.toml")
    assert right.problems == []


def test_the_board_detector_answers_alike_every_time(small_rig) -> None:
    # OpenCV's detector draws at random from a generator every call moves: unseeded, a 5x5
    # pattern inside these 9x6 boards is found at some calls and not others.
    for cam in ("cam0", "cam1"):
        image = cv2.imread(str(small_rig / cam / "world.png"), cv2.IMREAD_GRAYSCALE)
        answers = [find_chessboard(image, (5, 5), cv2.CALIB_CB_EXHAUSTIVE) for _ in range(12)]
        assert len({found for found, _ in answers}) == 1
        for _, corners in answers[1:]:
            np.testing.assert_array_equal(corners, answers[0][1])


def test_the_unfit_bar_grows_with_the_images_diagonal() -> None:
    """1.5 px on average is unfit at 640x480, ordinary at 4000x3000 (whose bar is 5 px)."""
    from pipeline.calibrate.result import CalibrationResult, ImageError
    from pipeline.calibrate.solve import _problems
    from pipeline.geometry.camera import Camera

    def rig(size_px: tuple[int, int]) -> CalibrationResult:
        cam = Camera("cam0", size_px, np.eye(3), np.zeros(5), np.zeros(3), np.zeros(3))
        errors = [
            ImageError("cam0", f"{i:02d}", f"{i:02d}.png", mean_px) for i, mean_px in enumerate((1.0, 2.0))
        ]
        return CalibrationResult([cam], errors, board=None, rms_px=1.5)  # type: ignore[arg-type]

    (line,) = _problems(rig((640, 480)))
    assert "mean re-projection error 1.5 px (above 1 px; worst 01.png, 2.0 px)" in line
    assert "check the board's size (--board or --charuco, and --square-mm)" in line
    assert _problems(rig((4000, 3000))) == []
    # Corners projected nowhere (a board of the wrong size found inside the real one): NaN
    # errors, above any bar, the NaN image named as the worst.
    nowhere = rig((640, 480))
    nowhere.image_errors[0] = ImageError("cam0", "00", "00.png", float("nan"))
    (line,) = _problems(nowhere)
    assert "mean re-projection error nan px (above 1 px; worst 00.png, nan px)" in line


def test_a_calibration_whose_images_do_not_fit_one_rig_says_so_and_exits_1(
    tmp_path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A mirrored world image is detected like any other; against the shared views it pulls
    the cameras pixels off (about 7 px and 4 px here), which a single image's outlier flag
    alone does not call unfit."""
    from pipeline.cli import main

    root = tmp_path / "calib"
    render_calibration_views(root, arrangement="oblique", seed=3, views=6, progress=False)
    shutil.rmtree(root / "cam2")
    world = root / "cam1" / "world.png"
    cv2.imwrite(str(world), cv2.flip(cv2.imread(str(world)), 1))
    out = tmp_path / "c.toml"
    code = main(["calibrate", str(root), "-o", str(out)])
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning: ")]
    assert code == 1, warnings
    assert any("camera 'cam1': mean re-projection error" in w and "do not fit one rig" in w for w in warnings)
    # The calibration and its report are written whole, for the user to look at; it says it is unfit.
    assert tomllib.loads(out.read_text())["metadata"]["problems"]
    assert (tmp_path / "reprojection_errors.png").is_file()


@pytest.fixture(scope="module")
def three_cameras(tmp_path_factory) -> Path:
    """Three cameras' views (the oblique rig, seed 11, 6 intrinsics views each), rendered once."""
    root = tmp_path_factory.mktemp("calib_three")
    render_calibration_views(root, arrangement="oblique", seed=11, views=6, progress=False)
    return root


@pytest.mark.parametrize(
    ("odd", "turn"), [("cam0", "turned"), ("cam2", "mirrored"), ("cam1", "another rig's")]
)
def test_the_one_world_image_that_disagrees_with_the_others_is_named_and_left_out(
    three_cameras: Path, tmp_path, capsys: pytest.CaptureFixture[str], odd: str, turn: str
) -> None:
    """A world image turned 180 degrees, mirrored, or of another placement of the board moves
    the board of the world frame in that camera; against the other cameras' world images and
    the shared views, the rig cannot fit all of them. Without it the others agree: it is
    named, and the calibration written is the others' (cam0 is also the joint solver's
    reference camera). Another rig's world image here leaves every camera's mean error
    below the unfit bar (its own is about a pixel): it is found among the images that stand
    out."""
    from pipeline.cli import main

    root = _copy(three_cameras, tmp_path)
    world = root / odd / "world.png"
    if turn == "another rig's":
        render_calibration_views(tmp_path / "other", arrangement="ninety", seed=12, views=1, progress=False)
        shutil.copyfile(tmp_path / "other" / odd / "world.png", world)
    else:
        image = cv2.imread(str(world))
        cv2.imwrite(str(world), cv2.rotate(image, cv2.ROTATE_180) if turn == "turned" else cv2.flip(image, 1))
    out = tmp_path / "c.toml"
    code = main(["calibrate", str(root), "-o", str(out)])
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning: ")]
    assert code == 1, warnings
    assert warnings[0].startswith(f"warning: {world}: its board lies"), warnings
    assert not [w for w in warnings[1:] if "world.png" in w], warnings
    truth = {c.name: c for c in read_calibration(root / "truth_calibration.toml")}
    for camera in read_calibration(out):
        assert np.linalg.norm(camera.center_mm - truth[camera.name].center_mm) < 2.0, camera.name
    assert tomllib.loads(out.read_text())["metadata"]["problems"][0].startswith(f"{world}: its board lies")
