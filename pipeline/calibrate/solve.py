"""Board images -> calibration.toml: intrinsics, a common world frame, joint refinement.

Input layout (camera names come from the folder names)::

    CALIB_DIR/board.toml                 optional: type = "chessboard", inner_corners = [cols, rows],
                                         square_mm; or type = "charuco", squares = [cols, rows],
                                         square_mm, marker_mm, dictionary
    CALIB_DIR/<camera>/intrinsics/*      board images (.png .jpg) or a video of the board moving
    CALIB_DIR/<camera>/world.png|jpg     the board lying where the world frame should be
    CALIB_DIR/<camera>/shared/NN.png     optional: boards seen by several cameras at the same
                                         instant (same NN); links a camera without world.png

Steps: corners per image (``pipeline.calibrate.views``), intrinsics per camera
(cv2.calibrateCamera; corners that stand out replaced by its prediction), then one joint
refinement of all cameras over every board (cv2.calibrateMultiviewExtended,
which chains cameras through pairwise shared views), and finally the world
frame: the board of world.png (origin at its first inner corner, z out of the
board).

ChArUco views show subsets of the corners. Intrinsics use each view's own
subset; the joint refinement uses, per board pose, only the corners seen by
every camera that saw it (repeated up to the board's corner count, as the solver
wants equal counts), because calibrateMultiviewExtended gives wrong results with
points marked unseen (-1, -1) inside a seen view.
"""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from ..errors import (
    CalibrationError,
    Interrupted,
    OutputError,
    refuse_unexpanded_home,
    refuse_unfinished_render,
)
from ..geometry.camera import Camera
from ..session.calibration_io import calibration_dict, cameras_from_dict, write_calibration
from ..session.toml_file import load_toml
from .boards import Board, load_board
from .result import CalibrationResult, ImageError
from .views import WORLD, View, board_size_problems, camera_dirs, detect_directory

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

MM_PER_M = 1000.0
# A camera whose view of a shared board pose leaves fewer corners than this in
# common with the other cameras' views uses that view as a pose of its own.
MIN_COMMON_CORNERS = 6
# A corner is dropped when its residual is this many times the camera's median
# residual and above CORNER_FLOOR_PX: the sector detector occasionally lands a
# corner of a steeply tilted board a pixel off, which would pull the world frame.
CORNER_FACTOR, CORNER_FLOOR_PX = 6.0, 0.4
# A camera whose mean re-projection error exceeds this is unfit for use: calibrations of
# sound images stay far below it (0.12 px on the real stereo rig, 0.02-0.03 px on renders),
# while one image of another session, or a mirrored one, among them gives tens of pixels.
MAX_CAMERA_MEAN_PX = 1.0
# ... per this many pixels of the image's diagonal, above it: a large sensor's pixels are
# small, and a sound calibration of 4000x3000 images can average more than a pixel.
MEAN_PX_PER_DIAGONAL_PX = 1.0 / 1000.0
# A world image is the odd one where the rig without it re-projects this many times better
# (RMS) than with every world image and than without any other (_without_odd_world_view).
# On synth-calib's boards (2026-12-05), leaving out the odd image gave 0.040 px against
# 0.17-5.1 px without another (another rig's world image in one camera; one turned 180
# degrees) and 0.32-18 px with all; sound renders, 0.039-0.040 px whichever is left out.
WORLD_VOTE_MARGIN = 3.0


def calibrate_directory(
    calib_dir: Path,
    output: Path,
    *,
    board: tuple[int, int] | None = None,
    square_mm: float | None = None,
    charuco: tuple[int, int] | None = None,
    shared_intrinsics: bool = False,
    drop_outliers: bool = False,
    report_dir: Path | None = None,
    force: bool = False,
) -> CalibrationResult:
    """Calibrate every camera of ``calib_dir`` and write ``output`` (calibration.toml) and a report.

    Parameters
    ----------
    calib_dir : folder in the layout of the module docstring.
    output : calibration.toml to write (aniposelib layout, mm, world frame of world.*).
    board, square_mm : inner corners (cols, rows) and square size; override board.toml.
    charuco : a ChArUco board's (cols, rows) squares; overrides board.toml (markers
        0.75 square and DICT_4X4_50 unless board.toml says).
    shared_intrinsics : one K and distortion for all cameras (identical cameras).
    drop_outliers : drop the images whose error stands out (see ``calibrate_report``) and recalibrate.
    report_dir : where the pictures go; default: next to ``output``.
    force : replace an existing calibration at ``output`` (checked before any detection).
    """
    from .report import find_outliers, write_report

    calib_dir = Path(calib_dir)
    if not calib_dir.is_dir():
        raise CalibrationError(f"{calib_dir}: not a folder; expected CALIB_DIR/<camera>/intrinsics/*.png")
    refuse_unfinished_render(calib_dir, CalibrationError)
    output = _through_link(Path(output))
    _check_output(output, force=force)
    _check_not_among_the_images(report_dir or output.parent, calib_dir)
    the_board = load_board(calib_dir, board=board, square_mm=square_mm, charuco=charuco)
    views = detect_directory(calib_dir, the_board)
    if not shared_intrinsics:
        _warn_of_shared_views_alone(views)
    result = calibrate_views(views, the_board, shared_intrinsics=shared_intrinsics)
    used = views
    world_problems: list[str] = []
    if _problems(result) or any(e.key == WORLD for e in find_outliers(result.image_errors)):
        result, used, world_problems = _without_odd_world_view(result, views, the_board, shared_intrinsics)
    outliers = find_outliers(result.image_errors)
    if drop_outliers and outliers:
        result = _without_outliers(result, used, outliers, the_board, shared_intrinsics)
        outliers = find_outliers(result.image_errors)
    result.outliers = outliers
    result.problems = (
        board_size_problems(views, the_board)
        + (_lenses_unlike(result, used, the_board) if shared_intrinsics else [])
        + world_problems
        + _problems(result)
        + _refused_by_process(result.cameras)
    )
    metadata = {
        "source": "pipeline calibrate",
        "calib_dir": str(calib_dir),
        "board": the_board.describe(),
        "rms_px": result.rms_px,
        "mean_reprojection_error_px": result.camera_mean_px(),
        "images": {c.name: sum(e.camera == c.name for e in result.image_errors) for c in result.cameras},
        "dropped": result.dropped,
        "problems": result.problems,
    }
    # The pictures first, the calibration renamed into place last: stopped before it (a
    # signal, a full disk), the run leaves the calibration that was there.
    partial = output.with_name(f".{output.name}.partial")
    report = Path(report_dir) if report_dir is not None else output.parent
    kept = f"{output} was not written" + (" (the one there is kept)" if output.exists() else "")
    written = False
    try:
        output.parent.mkdir(parents=True, exist_ok=True)
        write_calibration(partial, result.cameras, metadata)
        try:
            result.report_files = write_report(result, views, report)
        except OSError as exc:
            raise OutputError(
                f"{report}: cannot write the report pictures ({exc.strerror or exc}); {kept}; free space "
                "or give -o a folder with room for them"
            ) from None
        written = True
        partial.replace(output)
    except OSError as exc:
        raise OutputError(f"{output}: cannot write the calibration ({exc.strerror or exc})") from None
    except KeyboardInterrupt:
        # Written, and no longer under its temporary name: renamed into place.
        if not (written and not partial.exists()):
            raise Interrupted(f"interrupted; {kept}") from None
        raise Interrupted(
            f"interrupted as the calibration ended; {output} is written, with its report"
        ) from None
    finally:
        partial.unlink(missing_ok=True)
    return result


def _without_outliers(
    result: CalibrationResult,
    views: list[View],
    outliers: list[ImageError],
    board: Board,
    shared_intrinsics: bool,
) -> CalibrationResult:
    """``result`` calibrated again without its outlier images (``--drop-outliers``): the view
    of the image that stands out most dropped first, one view at a time while any stands out,
    at most as many as ``outliers`` (those that stood out at first; the world views are
    kept). A shared view goes with every camera's image of it: they saw one board pose, and
    one image that does not fit it cannot say which of them is wrong (a mirrored image kept
    alone still fits a pose of its own, and pulls its camera's focal length).

    One at a time, because one image far off (mirrored, of another rig) pulls the whole rig,
    and good images stand out beside it. On the real stereo pairs (world view 01, shared
    views 02-25), each of the 48 shared images mirrored in turn (2026-12-05): dropping every
    image that stood out at once dropped 6-9 good images in 35 of the 48 runs, and left a
    camera centre up to 1.53 mm (median 0.81) from the clean images' calibration; one view
    at a time drops none but the mirrored pair and pair 15 (which stands out among the clean
    images too), the centres within 0.95 mm (median 0.35).
    """
    from .report import find_outliers

    dropped: list[str] = []
    for _ in range(len(outliers)):
        standing_out = [e for e in find_outliers(result.image_errors) if e.key != WORLD]
        if not standing_out:
            break
        # With the worst image of each camera unfit for use: one image far off (mirrored)
        # can wreck the whole calibration, every camera's errors tens of pixels, and then
        # stand out in none (its camera's spread is as wide) while being the worst of all.
        worst = max(standing_out + _worst_of_unfit_cameras(result), key=_worst_first)
        instant = next(v.instant for v in views if (v.camera, v.key) == (worst.camera, worst.key))
        gone = [v for v in views if v.instant == instant]
        log.info(
            "dropping %s (%.3f px)%s and calibrating again",
            worst.source,
            worst.mean_px,
            f" with the {len(gone) - 1} other camera(s)' image(s) of its board pose" if len(gone) > 1 else "",
        )
        views = [v for v in views if v.instant != instant]
        result = calibrate_views(views, board, shared_intrinsics=shared_intrinsics)
        dropped += [v.source for v in gone]
    result.dropped = sorted(dropped)
    return result


def _warn_of_shared_views_alone(views: list[View]) -> None:
    """Say which cameras have no intrinsics/ image: their focal length and distortion rest on
    the few shared views. On synth-calib's boards (2026-12-05) such a camera's focal length
    came out 2.4 % off and its centre 8 mm off, at a 0.19 px re-projection error that shows
    nothing."""
    own = {v.camera for v in views if not v.shared}
    for camera in sorted({v.camera for v in views} - own):
        count = sum(v.camera == camera for v in views)
        log.warning(
            "camera %r has no intrinsics/ image the board was found in: its focal length and "
            "distortion rest on its %d world and shared views alone, which pin them loosely; add "
            "intrinsics images of the board filling the view at many angles",
            camera,
            count,
        )


def _without_odd_world_view(
    result: CalibrationResult, views: list[View], board: Board, shared_intrinsics: bool
) -> tuple[CalibrationResult, list[View], list[str]]:
    """``result`` (which does not fit one rig, or whose world images stand out among their
    cameras' images) calibrated again without the world image that the others and the
    shared views disagree with, where one does.

    Each camera's world image is left out in turn. Where the rig, without exactly one of
    them, fits (:func:`_problems`) and re-projects ``WORLD_VOTE_MARGIN`` times better than
    with all of them and than without any other, that image is the odd one (turned,
    mirrored, another placement of the board): it is left out of the world frame and
    named. Where it does so without any of several, the world images disagree and no vote
    says which is wrong: they are named together, and ``result`` stands. Returns the
    calibration, the views it used, and the problem lines to put first.
    """
    world = [v for v in views if v.key == WORLD]
    if len(world) < 2:
        return result, views, []
    without: list[tuple[View, CalibrationResult]] = []
    for odd in world:
        kept = [v for v in views if v is not odd]
        try:
            fit = calibrate_views(kept, board, shared_intrinsics=shared_intrinsics)
        except CalibrationError:  # the camera is linked to the others by its world image alone
            continue
        without.append((odd, fit))
    without.sort(key=lambda item: item[1].rms_px)
    better = [
        (odd, fit)
        for odd, fit in without
        if not _problems(fit) and fit.rms_px * WORLD_VOTE_MARGIN <= result.rms_px
    ]
    if not better:
        return result, views, []
    odd, fit = better[0]
    others = [item for item in without if item[0] is not odd]
    if all(fit.rms_px * WORLD_VOTE_MARGIN <= other.rms_px for _, other in others):
        camera = next(c for c in fit.cameras if c.name == odd.camera)
        # The world frame is the world image's board: its corners' world coordinates are the
        # board's own.
        off_px = float(
            np.linalg.norm(camera.project(board.object_points()[odd.ids]) - odd.corners_px, axis=1).mean()
        )
        return (
            fit,
            [v for v in views if v is not odd],
            [
                f"{odd.source}: its board lies {off_px:.0f} px from where the other cameras' world "
                "images and the shared views put it, so it was left out of the world frame; check "
                "that it shows the board where the world frame should be (not turned or mirrored), "
                "or remove it, and calibrate again"
            ],
        )
    sources = [odd.source for odd, _ in better]
    if len(sources) == 1:  # as good without another world image, which does not fit one rig
        sources.append(others[0][0].source)
    listed = f"{', '.join(sources[:-1])} and {sources[-1]}"
    return (
        result,
        views,
        [
            f"the world images {listed} do not agree on where the board lies: one of them is "
            "turned, mirrored or of another placement of the board; remove it, or add a world "
            "image in a third camera to tell which, and calibrate again"
        ],
    )


def _unfit_cameras(result: CalibrationResult) -> list[tuple[Camera, float, float, ImageError]]:
    """(camera, mean px, bar px, worst image) of each camera whose mean re-projection error
    exceeds its bar: ``MAX_CAMERA_MEAN_PX``, or ``MEAN_PX_PER_DIAGONAL_PX`` of its image's
    diagonal where that is more."""
    unfit = []
    means = result.camera_mean_px()
    for cam in result.cameras:
        mean = means[cam.name]
        bar = max(MAX_CAMERA_MEAN_PX, MEAN_PX_PER_DIAGONAL_PX * float(np.hypot(*cam.size_px)))
        if not mean <= bar:  # NaN too: corners projected nowhere (a lens that folds the image)
            worst = max((e for e in result.image_errors if e.camera == cam.name), key=_worst_first)
            unfit.append((cam, mean, bar, worst))
    return unfit


# --shared-intrinsics fits a camera this many times worse than its own lens does (and by
# more than _UNLIKE_PX): the cameras' lenses differ. Cameras of one lens fit about as well
# either way; synth-calib's three lenses (focal lengths 280-360 px) fit 3-11x worse shared,
# 0.07-0.33 px against 0.02-0.03, their centres up to 70 mm off.
_UNLIKE_RATIO = 2.0
_UNLIKE_PX = 0.05


def _lenses_unlike(result: CalibrationResult, views: list[View], board: Board) -> list[str]:
    """A line naming the cameras that ``result``, calibrated with one shared lens, fits
    clearly worse than their own lenses do (:data:`_UNLIKE_RATIO`)."""
    try:
        own = calibrate_views(views, board, shared_intrinsics=False).camera_mean_px()
    except CalibrationError:  # a camera too few views of its own to fit alone: nothing to compare
        return []
    shared = result.camera_mean_px()
    unlike = [
        name
        for name, mean in shared.items()
        if mean > _UNLIKE_RATIO * own[name] and mean - own[name] > _UNLIKE_PX
    ]
    if not unlike:
        return []
    figures = ", ".join(f"{name} {shared[name]:.2f} px against {own[name]:.2f}" for name in unlike)
    return [
        f"one lens shared by every camera (--shared-intrinsics) fits {', '.join(unlike)} clearly worse "
        f"than their own lenses do ({figures}): the cameras' lenses differ; calibrate without "
        "--shared-intrinsics"
    ]


def _worst_first(error: ImageError) -> float:
    """An image's error as a key for max(): NaN (no corner projected) counts as the worst."""
    return error.mean_px if np.isfinite(error.mean_px) else np.inf


def _worst_of_unfit_cameras(result: CalibrationResult) -> list[ImageError]:
    """The worst image, not a world view, of each camera :func:`_unfit_cameras` names."""
    worst = []
    for cam, _, _, _ in _unfit_cameras(result):
        mine = [e for e in result.image_errors if e.camera == cam.name and e.key != WORLD]
        if mine:
            worst.append(max(mine, key=_worst_first))
    return worst


def _problems(result: CalibrationResult) -> list[str]:
    """A line per camera of :func:`_unfit_cameras`, with its worst image."""
    lines = []
    for cam, mean, bar, worst in _unfit_cameras(result):
        lines.append(
            f"camera {cam.name!r}: mean re-projection error {mean:.1f} px (above {bar:.2g} px; "
            f"worst {worst.source}, {worst.mean_px:.1f} px): the images do not fit one rig; check the "
            "board's size (--board or --charuco, and --square-mm), look for an image of another session "
            "or camera, or a mirrored one, and calibrate again"
        )
    return lines


def _refused_by_process(cameras: Sequence[Camera]) -> list[str]:
    """Why ``process`` would refuse the calibration of ``cameras`` as it is written (its
    checks of calibration.toml: a distortion that folds the image, a field of view past a
    lens's, ...), as a line; none where it would take it."""
    try:
        cameras_from_dict(calibration_dict(list(cameras)), source="the calibration")
    except CalibrationError as exc:
        return [f"{exc}; process refuses it: calibrate again from more, and more varied, board images"]
    return []


def _through_link(output: Path) -> Path:
    """The file ``output`` names: through a link, the file it leads to (written there, the
    link kept: other sessions may share that file), made or yet to be made in a folder that
    exists; OutputError for a link into a loop or a missing folder."""
    if not output.is_symlink():
        return output
    target = Path(os.path.realpath(output))
    if target.is_symlink() or not target.parent.is_dir():
        raise OutputError(
            f"{output}: is a symbolic link to {os.readlink(output)}, which cannot be written "
            "(a loop of links, or a folder that does not exist); fix the link, or give -o the file itself"
        )
    return target


def _check_output(output: Path, *, force: bool) -> None:
    """Before calibrating: ``output`` can be written (its folder exists or can be made, and
    is writable) and takes the place of no file but an earlier calibration (a TOML file),
    and of that only with ``force``."""
    refuse_unexpanded_home(output, "-o")
    if output.is_dir():
        raise OutputError(f"{output}: is a folder; give -o a file name, e.g. {output / 'calibration.toml'}")
    if output.exists():
        try:
            doc = load_toml(output)
        except (OSError, ValueError):
            doc = {}
        if not _is_calibration(doc):
            raise OutputError(
                f"{output}: exists and is not a calibration (not TOML, or no cameras in it); remove it "
                "if it is a damaged one, or give -o another file name"
            )
        if not force:
            raise OutputError(f"{output}: already exists; use --force to replace it")
    folder = output.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    why = _cannot_create_in(folder) if folder.is_dir() else "not a folder"
    if why:
        raise OutputError(
            f"{output}: cannot be written in {folder} ({why}); give -o a file in a folder you can write to"
        )


def _check_not_among_the_images(report_dir: Path, calib_dir: Path) -> None:
    """Refuse report pictures written in a camera's folder of board images (intrinsics/,
    shared/, or the camera folder beside world.*): the next calibration would read them as
    board images (and stop at their size)."""
    report = Path(os.path.realpath(report_dir))
    for cam_dir in camera_dirs(calib_dir):
        cam = Path(os.path.realpath(cam_dir))
        if report == cam or cam in report.parents:
            raise OutputError(
                f"{report_dir}: holds board images (camera {cam_dir.name!r}), where the report's pictures "
                f"would be read as board images next time; give -o a file outside {cam_dir}"
            )


def _cannot_create_in(folder: Path) -> str:
    """Why no file can be created in ``folder``, found by creating (and removing) one; "" where
    one can. Permission bits do not tell: root passes them in /proc, where nothing is created."""
    try:
        handle, probe = tempfile.mkstemp(prefix=".pipeline-calibrate-", dir=folder)
    except OSError as exc:
        return exc.strerror or str(exc)
    os.close(handle)
    os.unlink(probe)
    return ""


def _is_calibration(doc: dict[str, object]) -> bool:
    """Whether a parsed TOML file is a calibration: it holds a camera table (``[cam_0]`` ...,
    the aniposelib layout), as a session.toml or another program's settings do not."""
    return any(key.startswith("cam_") and isinstance(value, dict) for key, value in doc.items())


def calibrate_views(views: list[View], board: Board, *, shared_intrinsics: bool = False) -> CalibrationResult:
    """Cameras in the world frame of the ``world`` views, from detected corners.

    Parameters
    ----------
    views : detections of every camera (at least one camera has a ``world`` view).
    board : the board seen.
    shared_intrinsics : one K and distortion for all cameras.
    """
    names = sorted({v.camera for v in views})
    world_cams = [n for n in names if any(v.camera == n and v.key == WORLD for v in views)]
    if not world_cams:
        raise CalibrationError(f"no camera has a world image; put CALIB_DIR/{names[0]}/world.png")
    # The multiview solver expresses everything in its camera 0: use a camera that sees the world board.
    order = [world_cams[0]] + [n for n in names if n != world_cams[0]]
    _check_connected(views, order)
    sizes = {n: next(v.size_px for v in views if v.camera == n) for n in order}
    obj = board.object_points()
    corners = _clean_corners(views, board, sizes, shared_intrinsics)
    intrinsics = _intrinsics(views, board, sizes, corners, shared_intrinsics)

    frames = _joint_frames(views)
    keys = [key for key, _ in frames]
    frame_of = {(v.camera, v.key): fi for fi, (_, seen) in enumerate(frames) for v in seen.values()}
    detection = np.zeros((len(order), len(frames)), np.uint8)
    image_points: list[list[NDArray[np.float32]]] = [[] for _ in order]
    obj_m = []
    for fi, (_, seen) in enumerate(frames):
        # The solver wants the same number of points in every frame: a frame's common
        # corners are repeated up to the board's count, which weights its corners up
        # (every frame then weighs the same) but adds no bias.
        ids = np.resize(_common_ids(list(seen.values())), board.n_corners)
        for ci, name in enumerate(order):
            pts = np.full((len(ids), 2), -1.0, np.float32)  # (-1, -1): camera did not see this pose
            view = seen.get(name)
            if view is not None:
                # Rows of this view's corners that hold the common ids (view.ids increasing).
                pts[:] = corners[(name, view.key)][np.searchsorted(view.ids, ids)]
                detection[ci, fi] = 1
            image_points[ci].append(pts)
        # Metres, not mm: the solver scales the board by its squared size, and a board
        # in mm trips its "Pattern points are collinear" guard.
        obj_m.append((obj[ids] / MM_PER_M).astype(np.float32))
    try:
        # Rs, Ts = None: outputs only (the stubs want sequences).
        rms, Ks, dists, Rs, Ts, _pairs, rvecs0, tvecs0, _ = cv2.calibrateMultiviewExtended(  # type: ignore[call-overload]
            obj_m,
            image_points,
            [sizes[n] for n in order],
            detection,
            np.full(len(order), cv2.CALIB_MODEL_PINHOLE, np.uint8),
            [intrinsics[n][0] for n in order],
            [intrinsics[n][1] for n in order],
            None,
            None,
            flagsForIntrinsics=np.zeros(len(order), np.int32),
            flags=cv2.CALIB_USE_INTRINSIC_GUESS,
        )
    except cv2.error as exc:
        raise CalibrationError(
            f"joint calibration failed ({exc.err}); check the shared and world views"
        ) from None

    # Board of frame f in camera 0: x0 = R0f X + t0f; camera i: xi = Ri x0 + Ti (Rs are
    # rotation vectors, whatever the docstring says).
    world_index = keys.index(WORLD)
    R_w, _ = cv2.Rodrigues(np.asarray(rvecs0[world_index], np.float64))
    t_w = np.asarray(tvecs0[world_index], np.float64).ravel() * MM_PER_M
    cameras = []
    for ci, name in enumerate(order):
        R_i, _ = cv2.Rodrigues(np.asarray(Rs[ci], np.float64).reshape(3))
        T_i = np.asarray(Ts[ci], np.float64).ravel() * MM_PER_M
        R = R_i @ R_w  # camera from world
        rvec, _ = cv2.Rodrigues(R)
        cameras.append(
            Camera(
                name=name,
                size_px=sizes[name],
                matrix=np.asarray(Ks[ci], np.float64),
                distortions=np.asarray(dists[ci], np.float64).ravel()[:5],
                rotation=np.asarray(rvec, np.float64).ravel(),
                translation_mm=R_i @ t_w + T_i,
            )
        )
    errors = _image_errors(views, board, cameras, order, frame_of, rvecs0, tvecs0)
    cameras.sort(key=lambda c: c.name)
    return CalibrationResult(cameras=cameras, image_errors=errors, board=board, rms_px=float(rms))


def _common_ids(seen: list[View]) -> NDArray[np.intp]:
    """(K,) increasing corner ids present in every view of ``seen``."""
    return np.asarray(sorted(set.intersection(*(set(v.ids.tolist()) for v in seen))), np.intp)


def _joint_frames(views: list[View]) -> list[tuple[str, dict[str, View]]]:
    """The board poses of the joint refinement: (instant, the views of it per camera).

    A shared instant whose cameras have fewer than MIN_COMMON_CORNERS corners in
    common (partly seen ChArUco boards) loses the cameras that saw the fewest
    corners until they do; each camera dropped keeps its view as a board pose of
    its own, so it still counts for that camera alone.
    """
    by_instant: dict[str, dict[str, View]] = {}
    for v in views:
        by_instant.setdefault(v.instant, {})[v.camera] = v
    frames = []
    for key in sorted(by_instant):
        seen = by_instant[key]
        while len(seen) > 1 and len(_common_ids(list(seen.values()))) < MIN_COMMON_CORNERS:
            weakest = min(seen, key=lambda name: len(seen[name].ids))
            log.debug("%s %s: too few corners in common with the other cameras", weakest, key)
            frames.append((f"{weakest}:{key}", {weakest: seen.pop(weakest)}))
        frames.append((key, seen))
    return frames


def _check_connected(views: list[View], order: list[str]) -> None:
    """Every camera must reach the world camera through boards seen by two cameras at once."""
    seen_by: dict[str, set[str]] = {}
    for v in views:
        if v.shared:
            seen_by.setdefault(v.key, set()).add(v.camera)
    reached, frontier = {order[0]}, [order[0]]
    while frontier:
        cam = frontier.pop()
        for cams in seen_by.values():
            if cam in cams:
                new = cams - reached
                reached |= new
                frontier.extend(new)
    for name in order:
        if name not in reached:
            raise CalibrationError(
                f"camera {name!r}: no world.png, and no shared/NN image whose board a camera "
                f"linked to the world also saw; add CALIB_DIR/{name}/world.png or shared views"
            )


def _intrinsics(
    views: list[View],
    board: Board,
    sizes: dict[str, tuple[int, int]],
    corners: dict[tuple[str, str], FloatArray],
    shared: bool,
) -> dict[str, tuple[FloatArray, FloatArray]]:
    """(K (3, 3), distortion (5,)) per camera from all its views (``corners`` per (camera, key))."""
    obj = board.object_points().astype(np.float32)
    groups = {"*": list(sizes)} if shared else {n: [n] for n in sizes}
    if shared and len(set(sizes.values())) > 1:
        each = ", ".join(f"{name} {w}x{h}" for name, (w, h) in sizes.items())
        raise CalibrationError(
            f"--shared-intrinsics needs every camera's images to have the same size ({each}); "
            "drop --shared-intrinsics to calibrate each lens on its own"
        )
    out: dict[str, tuple[FloatArray, FloatArray]] = {}
    for members in groups.values():
        mine = [v for v in views if v.camera in members]
        imgs = [corners[(v.camera, v.key)].astype(np.float32) for v in mine]
        objs = [obj[v.ids] for v in mine]
        _, K, dist, _, _ = cv2.calibrateCamera(objs, imgs, sizes[members[0]], None, None)
        for n in members:
            out[n] = (np.asarray(K, np.float64), np.asarray(dist, np.float64).ravel()[:5])
    return out


def _clean_corners(
    views: list[View], board: Board, sizes: dict[str, tuple[int, int]], shared: bool
) -> dict[tuple[str, str], FloatArray]:
    """Per view, its corners with the ones that stand out replaced by a first calibration's prediction.

    Replacing rather than leaving out: the multiview solver's pairwise
    initialisation does not cope with partly seen boards, and a handful of
    predicted corners among 54 measured ones barely weighs.
    """
    raw = {(v.camera, v.key): v.corners_px for v in views}
    intrinsics = _intrinsics(views, board, sizes, raw, shared)
    obj = board.object_points()
    predicted, residuals = {}, {}
    for v in views:
        K, dist = intrinsics[v.camera]
        _, rvec, tvec = cv2.solvePnP(obj[v.ids], v.corners_px, K, dist)
        px, _ = cv2.projectPoints(obj[v.ids], rvec, tvec, K, dist)
        predicted[(v.camera, v.key)] = px.reshape(-1, 2).astype(np.float64)
        residuals[(v.camera, v.key)] = np.linalg.norm(predicted[(v.camera, v.key)] - v.corners_px, axis=1)
    cleaned = {}
    for name in sizes:
        median = float(np.median(np.concatenate([r for (c, _), r in residuals.items() if c == name])))
        limit = max(CORNER_FACTOR * median, CORNER_FLOOR_PX)
        for (c, key), r in residuals.items():
            if c == name:
                bad = r > limit
                cleaned[(c, key)] = np.where(bad[:, None], predicted[(c, key)], raw[(c, key)])
                if bad.any():
                    log.debug("%s %s: %d corner(s) replaced", c, key, int(bad.sum()))
    return cleaned


def _image_errors(
    views: list[View],
    board: Board,
    cameras: list[Camera],
    order: list[str],
    frame_of: dict[tuple[str, str], int],
    rvecs0: list[NDArray[np.float64]],
    tvecs0: list[NDArray[np.float64]],
) -> list[ImageError]:
    """Mean re-projection error of every image under the final calibration (all corners)."""
    obj = board.object_points()
    cams = {c.name: c for c in cameras}
    R_w0, t_w0 = _world_from_cam0(cams[order[0]])
    errors = []
    for v in views:
        cam = cams[v.camera]
        fi = frame_of[(v.camera, v.key)]
        r0, t0 = rvecs0[fi], tvecs0[fi]
        if r0 is None or np.asarray(r0).size != 3:
            continue
        # Board pose in this camera: through camera 0's board pose and the camera's pose relative to it.
        R0, _ = cv2.Rodrigues(np.asarray(r0, np.float64))
        x0 = obj[v.ids] @ R0.T + np.asarray(t0, np.float64).ravel() * MM_PER_M  # camera 0 frame, mm
        px = cam.project(x0 @ R_w0.T + t_w0)
        errors.append(
            ImageError(v.camera, v.key, v.source, float(np.linalg.norm(px - v.corners_px, axis=1).mean()))
        )
    return errors


def _world_from_cam0(cam0: Camera) -> tuple[FloatArray, FloatArray]:
    """(R, t) with X_world = R @ x_cam0 + t."""
    R = cam0.camera_from_world
    return R.T, -R.T @ cam0.translation_mm
