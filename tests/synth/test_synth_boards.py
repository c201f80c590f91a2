"""synth-calib renderer: layout, exactness of the rendered corners, the ninety-degree constraint."""

from __future__ import annotations

import shutil
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.cli import EXIT_BAD_INPUT, main
from pipeline.errors import PipelineError
from pipeline.synth.boards import _camera_rays, _render, _rotation, render_calibration_views
from pipeline.synth.rig import SynthCamera, make_rig


@pytest.fixture(scope="module")
def ninety(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("synth_calib_ninety")
    render_calibration_views(root, arrangement="ninety", seed=1, views=4, progress=False)
    return root


def _truth_corners(cam: SynthCamera, R: np.ndarray, t: np.ndarray, cols: int, rows: int, sq: float):
    j, i = np.mgrid[0:rows, 0:cols]
    obj = np.column_stack([i.ravel(), j.ravel(), np.zeros(i.size)]) * sq
    rvec, _ = cv2.Rodrigues(R)
    px, _ = cv2.projectPoints(obj, rvec, t, cam.K, cam.dist)
    return px.reshape(-1, 2)


def test_layout_and_board_toml(ninety) -> None:
    board = tomllib.loads((ninety / "board.toml").read_text())
    assert board == {"type": "chessboard", "inner_corners": [9, 6], "square_mm": 20.0}
    truth = tomllib.loads((ninety / "truth_calibration.toml").read_text())
    assert [truth[f"cam_{i}"]["name"] for i in range(3)] == ["cam0", "cam1", "cam2"]
    for cam in ("cam0", "cam1", "cam2"):
        assert len(list((ninety / cam / "intrinsics").glob("*.png"))) == 4
        image = cv2.imread(str(ninety / cam / "intrinsics" / "00.png"), cv2.IMREAD_UNCHANGED)
        assert image.shape == (240, 320) and image.dtype == np.uint8


def test_ninety_no_board_seen_by_all_three(ninety) -> None:
    # World board hidden from cam2; every shared board seen by exactly two cameras.
    assert sorted(p.parent.name for p in ninety.glob("*/world.png")) == ["cam0", "cam1"]
    seen: dict[str, set[str]] = {}
    for path in ninety.glob("*/shared/*.png"):
        seen.setdefault(path.stem, set()).add(path.parent.parent.name)
    assert seen and all(len(cams) == 2 for cams in seen.values())
    # cam2 is linked to the world through cam1.
    assert any(cams == {"cam1", "cam2"} for cams in seen.values())


def test_world_view_corners_project_onto_the_rendered_board(ninety) -> None:
    """The first inner corner of world.png is the world origin: the pixel there is a saddle
    (dark on one diagonal, light on the other), checked without any detector."""
    truth = tomllib.loads((ninety / "truth_calibration.toml").read_text())
    for key in ("cam_0", "cam_1"):
        t = truth[key]
        image = cv2.imread(str(ninety / t["name"] / "world.png"), cv2.IMREAD_GRAYSCALE).astype(float)
        rvec = np.array(t["rotation"])
        K, dist, tvec = np.array(t["matrix"]), np.array(t["distortions"]), np.array(t["translation"])
        # Centres of the four squares around the origin: (-+0.5, -+0.5) squares.
        offsets = np.array([[-0.5, -0.5, 0], [0.5, 0.5, 0], [0.5, -0.5, 0], [-0.5, 0.5, 0]]) * 20.0
        px, _ = cv2.projectPoints(offsets, rvec, tvec, K, dist)
        grey = [image[round(y), round(x)] for x, y in px.reshape(-1, 2)]
        # Square (-1, -1) and (0, 0) black, the other two white (board texture convention).
        assert max(grey[:2]) < 80 and min(grey[2:]) > 170


def test_render_is_exact_for_a_frontal_board() -> None:
    """Rendered edges sit where the projection puts them: a detector finds the corners to 0.05 px."""
    cam = make_rig("oblique")[0]
    rays = _camera_rays(cam)
    R = _rotation(np.array([1.0, 0.3, 0.0]), np.radians(20)) @ np.diag([1.0, -1.0, -1.0])
    t = np.array([3.0, -5.0, 500.0]) - R @ np.array([80.0, 50.0, 0.0])
    image = _render(rays, cam, R, t, 9, 6, 20.0, np.random.default_rng(0))
    found, corners = cv2.findChessboardCornersSB(image, (9, 6), flags=cv2.CALIB_CB_ACCURACY)
    assert found
    truth = _truth_corners(cam, R, t, 9, 6, 20.0)
    # The detector's numbering is not the board's: pair each true corner with the nearest found.
    err = np.linalg.norm(truth[:, None] - corners.reshape(1, -1, 2), axis=-1).min(axis=1)
    # 0.05 px: the detector alone is ~0.02 px off on this view; a quantised
    # (4x4 supersampled) render measured 0.13 px.
    assert np.sqrt(np.mean(err**2)) < 0.05


def test_rays_invert_the_distortion() -> None:
    cam = make_rig("ninety")[2]
    rays = _camera_rays(cam).reshape(-1, 2)
    pts = np.column_stack([rays, np.ones(len(rays))])
    px, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width]
    centres = px.reshape(cam.height, cam.width, -1, 2).mean(axis=2)
    # Sub-pixel offsets are symmetric about the pixel centre; distortion bends them by << 1e-3 px.
    assert np.abs(centres - np.stack([xs, ys], axis=-1)).max() < 1e-3


def test_fixed_seed_gives_identical_images(ninety, tmp_path) -> None:
    again = tmp_path / "again"
    render_calibration_views(again, arrangement="ninety", seed=1, views=4, progress=False)
    files = sorted(p.relative_to(ninety) for p in ninety.rglob("*.png"))
    assert files == sorted(p.relative_to(again) for p in again.rglob("*.png"))
    assert all((ninety / f).read_bytes() == (again / f).read_bytes() for f in files)


def test_symmetric_board_is_refused(tmp_path) -> None:
    with pytest.raises(ValueError, match="cols \\+ rows must be odd"):
        render_calibration_views(tmp_path, board=(8, 6), progress=False)


def test_synth_calib_writes_into_a_new_or_empty_folder_or_over_its_own_render_only(
    ninety, tmp_path, capsys: pytest.CaptureFixture[str]
) -> None:
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("my notes\n")
    assert main(["synth-calib", str(mine)]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err.splitlines() == [
        f"error: {mine}: holds files and is not an earlier synth-calib output (no "
        "truth_calibration.toml); give synth-calib a new or empty directory"
    ]
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]
    assert main(["synth-calib", str(mine / "notes.txt")]) == EXIT_BAD_INPUT
    assert "notes.txt: is a file; give synth-calib a directory" in capsys.readouterr().err
    unmounted = tmp_path / "unmounted"
    unmounted.symlink_to(tmp_path / "drive" / "calib")
    for command in ("synth-calib", "synth"):
        assert main([command, str(unmounted)]) == EXIT_BAD_INPUT
        assert capsys.readouterr().err == (
            f"error: {unmounted}: is a symbolic link to {tmp_path / 'drive' / 'calib'}, which does not "
            f"exist; fix the link (mount the drive), or give {command} another folder\n"
        )
    # Over its own render (it holds truth_calibration.toml): the same files again.
    before = {p: p.read_bytes() for p in ninety.rglob("*.png")}
    render_calibration_views(ninety, arrangement="ninety", seed=1, views=4, progress=False)
    assert {p: p.read_bytes() for p in ninety.rglob("*.png")} == before


def test_a_negative_seed_is_refused_before_anything_is_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["synth-calib", str(tmp_path / "new"), "--seed", "-1"]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err.splitlines() == ["error: --seed must be 0 or more, got -1"]
    assert not (tmp_path / "new").exists()


def test_a_folder_synth_calib_cannot_create_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "notes.txt").write_text("mine")
    target = tmp_path / "notes.txt" / "calib"  # under a file: no folder can be made there
    assert main(["synth-calib", str(target)]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err.splitlines() == [
        f"error: {target}: cannot create the folder (Not a directory); give synth-calib a folder "
        "you can write in"
    ]


def test_a_render_over_an_earlier_one_leaves_none_of_its_images(ninety, tmp_path: Path) -> None:
    # The oblique rig's world board is seen by cam2 and its shared sets differ: left behind,
    # calibrate would take them for the ninety rig's.
    earlier = tmp_path / "calib"
    render_calibration_views(earlier, arrangement="oblique", seed=2, views=6, progress=False)
    render_calibration_views(earlier, arrangement="ninety", seed=1, views=4, progress=False)

    def files(root: Path) -> dict[str, bytes]:
        return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}

    assert files(earlier) == files(ninety)
    assert sorted(p.name for p in (earlier / "cam2").iterdir()) == ["intrinsics", "shared"]


def test_an_image_that_cannot_be_written_over_an_earlier_render_is_named(
    ninety, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    earlier = tmp_path / "calib"
    shutil.copytree(ninety, earlier)
    blocked = earlier / "cam0" / "intrinsics" / "01.png"
    blocked.unlink()
    blocked.mkdir()  # OpenCV cannot write there, and says so only by returning False
    assert main(["synth-calib", str(earlier), "--arrangement", "ninety", "--seed", "1"]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err.splitlines() == [
        f"error: {blocked}: cannot be written (OpenCV wrote no image: a full disk, or a folder in its "
        f"place?); the board images in {earlier} are incomplete: render them again; free space, or give "
        "another directory"
    ]


def test_an_image_that_cannot_be_written_into_a_new_folder_leaves_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    written: list[str] = []

    def full_disk_after_two(path: str, image: object) -> bool:
        written.append(path)
        return len(written) <= 2

    monkeypatch.setattr("pipeline.synth.boards.cv2.imwrite", full_disk_after_two)
    target = tmp_path / "calib"
    with pytest.raises(
        PipelineError, match=r"intrinsics/02\.png: cannot be written .*; nothing written; free space"
    ):
        render_calibration_views(target, arrangement="ninety", views=4, progress=False)
    assert not target.exists()


def test_an_interrupted_render_into_a_new_folder_leaves_nothing_and_says_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pipeline.errors import Interrupted

    written: list[str] = []

    def interrupted_after_two(path: str, image: object) -> bool:
        if len(written) == 2:
            raise KeyboardInterrupt  # Ctrl-C, SIGTERM or a hang-up, as the run turns them
        written.append(path)
        Path(path).write_bytes(b"png")
        return True

    monkeypatch.setattr("pipeline.synth.boards.cv2.imwrite", interrupted_after_two)
    target = tmp_path / "calib"
    with pytest.raises(Interrupted, match=r"^interrupted; nothing written$"):
        render_calibration_views(target, arrangement="ninety", views=4, progress=False)
    assert not target.exists()


def test_an_interrupted_render_over_an_earlier_one_is_refused_by_calibrate(
    ninety, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    earlier = tmp_path / "calib"
    shutil.copytree(ninety, earlier)
    real_imwrite = cv2.imwrite
    written: list[str] = []

    def interrupted_after_two(path: str, image: object) -> bool:
        if len(written) == 2:
            raise KeyboardInterrupt
        written.append(path)
        return bool(real_imwrite(path, image))

    monkeypatch.setattr("pipeline.synth.boards.cv2.imwrite", interrupted_after_two)
    assert main(["synth-calib", str(earlier), "--arrangement", "oblique"]) == 130
    assert (
        capsys.readouterr()
        .err.strip()
        .endswith(f"the board images in {earlier} are incomplete: render them again")
    )
    # Two new images among the earlier ones: calibrate refuses the mix, not calibrates it.
    out = tmp_path / "calibration.toml"
    assert main(["calibrate", str(earlier), "-o", str(out)]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err.splitlines() == [
        f"error: {earlier}: a synthetic render stopped part-way here (UNFINISHED-RENDER.txt); render it again"
    ]
    assert not out.exists()
    monkeypatch.undo()
    render_calibration_views(earlier, arrangement="ninety", seed=1, views=4, progress=False)
    assert not (earlier / "UNFINISHED-RENDER.txt").exists()
