"""A calibration folder -> the board corners seen in each of its images.

Layout read (camera names come from the folder names)::

    CALIB_DIR/<camera>/intrinsics/*      board images (.png .jpg ...) or a video of the board moving
    CALIB_DIR/<camera>/world.png|jpg     the board lying where the world frame should be
    CALIB_DIR/<camera>/shared/NN.png     boards seen by several cameras at the same instant (same NN)
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from joblib import Parallel, delayed
from numpy.typing import NDArray

from ..errors import CalibrationError
from ..geometry.camera import WORLD_FRAME
from ..session.folder import check_not_dangling
from ..session.grey_levels import grey_8bit
from ..session.image_files import cut_short
from ..session.video import VIDEO_EXTENSIONS
from .boards import Board, detect, find_chessboard

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

# The kinds of image OpenCV decodes that cameras and their software save, and the videos
# a session's are read in.
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm", ".pnm")
VIDEO_EXTS = VIDEO_EXTENSIONS
MIN_VIEWS = 5
# An intrinsics view whose corners all lie within this many pixels of another's sees the
# same board pose (a copied file, a video of a board held still): it adds no evidence but
# the corners' noise, and weighs its pose again in the fit.
REPEAT_PX = 0.5
VIDEO_SAMPLES = 30  # frames taken, evenly spaced, from an intrinsics video
WORLD = "world"


@dataclass(frozen=True)
class View:
    """One board image of one camera: ``key`` names the instant (shared across cameras)."""

    camera: str
    key: str
    source: str  # file (or video#frame) for messages and the report
    corners_px: FloatArray  # (M, 2) float64: the corners ``ids`` (all, for a chessboard)
    size_px: tuple[int, int]
    ids: NDArray[np.intp]  # (M,) increasing indices into Board.object_points()

    @property
    def shared(self) -> bool:
        """True for world.* and shared/NN views, which may be seen by several cameras."""
        return not self.key.startswith("intrinsics/")

    @property
    def instant(self) -> str:
        """The board pose this view saw: shared by the cameras of a shared view, private otherwise."""
        return self.key if self.shared else f"{self.camera}:{self.key}"


def camera_dirs(calib_dir: Path) -> list[Path]:
    """Sub-folders of ``calib_dir`` that hold a camera's images (intrinsics/, world.* or
    shared/: a camera seen through shared views alone is one too), sorted by name."""
    folders = sorted(d for d in Path(calib_dir).iterdir() if d.is_dir())
    dirs = [
        d
        for d in folders
        if (d / "intrinsics").is_dir() or (d / "shared").is_dir() or _world_file(d) is not None
    ]
    for folder in folders:
        if not any(folder.iterdir()):
            log.warning("%s: an empty folder, so no camera's: its images were not copied in?", folder)
        _note_unread_images(folder, is_camera=folder in dirs)
    if len(dirs) < 2:
        raise CalibrationError(
            f"{calib_dir}: found {len(dirs)} camera folder(s); expected at least two "
            "CALIB_DIR/<camera>/intrinsics/ folders"
        )
    for folder in dirs:
        # Each folder names its camera, and `process` refuses this one name (see
        # pipeline.session.calibration_io): said before any image is read.
        if folder.name == WORLD_FRAME:
            raise CalibrationError(
                f"{folder}: a camera cannot be named {WORLD_FRAME!r}, the recordings' own frame (the one "
                "the hull and the centreline are in); rename the folder, and later the camera's video"
            )
    return dirs


def _note_unread_images(folder: Path, *, is_camera: bool) -> None:
    """Warn of board images at the top of ``folder`` (but its world image), which are not
    read: a camera's go in its intrinsics/ (or shared/) folder."""
    loose = [
        p
        for p in folder.iterdir()
        if p.suffix.lower() in IMAGE_EXTS and p.stem.lower() != WORLD and p.is_file()
    ]
    if loose:
        log.warning(
            "%s: %d image(s) beside %s are not read (%s); board images go in %s/intrinsics/ (one "
            "camera at a time) or shared/ (the cameras at one moment)",
            folder,
            len(loose),
            "its world image" if is_camera else "no intrinsics/ or shared/ folder",
            ", ".join(p.name for p in sorted(loose)[:3]) + (", ..." if len(loose) > 3 else ""),
            folder,
        )


def _world_file(cam_dir: Path) -> Path | None:
    """The camera's world.* image, None without one; two of them are a CalibrationError
    (one board pose defines the world frame, and which file was meant cannot be told)."""
    # Any case, as the other images' suffixes are read (world.JPG, World.png from a camera's card).
    found = sorted(
        (
            path
            for path in cam_dir.iterdir()
            if path.stem.lower() == WORLD and path.suffix.lower() in IMAGE_EXTS and path.is_file()
        ),
        key=lambda path: (IMAGE_EXTS.index(path.suffix.lower()), path.name),
    )
    if len(found) > 1:
        raise CalibrationError(
            f"{cam_dir}: holds {len(found)} world images ({', '.join(p.name for p in found)}); "
            "one board pose defines the world frame: keep one of them and remove the others"
        )
    return found[0] if found else None


def _read_grey(path: Path) -> NDArray[np.uint8]:
    """The board image at ``path`` as (H, W) uint8 grey levels, or a CalibrationError saying why not.

    A 16-bit (or floating-point) image's levels are scaled from the depth they are stored at
    (:func:`~pipeline.session.grey_levels.grey_8bit`): 8-bit values or a 10- or 12-bit
    camera's saved in 16 bits keep the board's contrast rather than reading near black.
    """
    check_not_dangling(path, CalibrationError)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise CalibrationError(
            f"{path}: cannot be read ({exc.strerror or exc}); copy the image in again or remove it"
        ) from None
    if not data:
        raise CalibrationError(f"{path}: is empty (0 bytes); copy the image in again or remove it")
    if cut_short(data, path.suffix):
        raise CalibrationError(
            f"{path}: the image is cut short ({len(data)} bytes, copied half-way?); copy it in again "
            "or remove it"
        )
    try:
        image = cv2.imdecode(
            np.frombuffer(data, np.uint8),
            cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH | cv2.IMREAD_IGNORE_ORIENTATION,
        )
    except cv2.error as exc:
        why = "more pixels than OpenCV decodes, 2**30" if "MAX_IMAGE_PIXELS" in exc.err else exc.err
        raise CalibrationError(
            f"{path}: cannot be decoded ({why}); save it as a PNG or JPEG at the camera's size"
        ) from None
    if image is None:
        raise CalibrationError(f"{path}: cannot be read as an image; save it as a PNG or JPEG, or remove it")
    return grey_8bit(image)


def _video_frames(path: Path) -> list[tuple[str, NDArray[np.uint8]]]:
    """Up to VIDEO_SAMPLES grey frames, evenly spaced, of an intrinsics video."""
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        size = path.stat().st_size if path.is_file() else 0
        why = "it is empty (0 bytes)" if size == 0 else "not a video OpenCV reads, or cut short"
        raise CalibrationError(
            f"{path}: cannot open this video ({why}); copy it in again, or remove it and use board images"
        )
    frames = []
    try:
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        wanted = set(np.linspace(0, max(count - 1, 0), min(VIDEO_SAMPLES, max(count, 1))).astype(int))
        index = 0
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            if index in wanted:
                frames.append(
                    (f"{path.name}#{index}", np.asarray(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY), np.uint8))
                )
            index += 1
    finally:
        cap.release()
    return frames


def detect_directory(calib_dir: Path, board: Board) -> list[View]:
    """Corners of every usable image of every camera of ``calib_dir``.

    An intrinsics or shared image without a board is skipped with a warning;
    a world image without one is an error (it defines the frame).
    """
    views: list[View] = []
    cam_dirs = camera_dirs(calib_dir)
    worlds = [_world_file(cam_dir) for cam_dir in cam_dirs]  # every camera's checked before detection
    _warn_unmatched_shared(cam_dirs)
    for cam_dir, world in zip(cam_dirs, worlds, strict=True):
        cam = cam_dir.name
        images: list[tuple[str, str, NDArray[np.uint8]]] = []  # key, source, image
        unread: list[Path] = []  # files of a kind not read
        intr = cam_dir / "intrinsics"
        for path in sorted(intr.iterdir()) if intr.is_dir() else []:
            if path.suffix.lower() in IMAGE_EXTS:
                images.append((f"intrinsics/{path.name}", str(path), _read_grey(path)))
            elif path.suffix.lower() in VIDEO_EXTS:
                for name, frame in _video_frames(path):
                    images.append((f"intrinsics/{name}", str(intr / name), frame))
            elif not path.name.startswith(".") and path.is_file():
                unread.append(path)
        shared = cam_dir / "shared"
        for path in _shared_images(shared) if shared.is_dir() else []:
            images.append((f"shared/{path.stem}", str(path), _read_grey(path)))
        for path in sorted(shared.iterdir()) if shared.is_dir() else []:
            if path.suffix.lower() not in IMAGE_EXTS and not path.name.startswith(".") and path.is_file():
                unread.append(path)
        if unread:
            log.warning(
                "camera %r: %d file(s) not read, of no image or video kind read (%s%s); save board "
                "images as %s, or videos as %s",
                cam,
                len(unread),
                ", ".join(str(p.relative_to(cam_dir)) for p in unread[:3]),
                ", ..." if len(unread) > 3 else "",
                "/".join(IMAGE_EXTS[:3]),
                "/".join(VIDEO_EXTS[:3]),
            )
        if world is not None:
            images.append((WORLD, str(world), _read_grey(world)))
        sizes = {(im.shape[1], im.shape[0]) for _, _, im in images}
        if len(sizes) > 1:
            first = images[0]
            odd, odd_image = next(
                (src, im) for _, src, im in images if (im.shape[1], im.shape[0]) != first[2].shape[::-1]
            )
            raise CalibrationError(
                f"camera {cam!r}: images of different sizes ({first[1]} is "
                f"{first[2].shape[1]}x{first[2].shape[0]}, {odd} {odd_image.shape[1]}x{odd_image.shape[0]}); "
                "one camera, one size"
            )
        # Threads: OpenCV releases the GIL, and images are independent.
        found = Parallel(n_jobs=-1, prefer="threads")(delayed(detect)(im, board) for _, _, im in images)
        for (key, source, image), detection in zip(images, found, strict=True):
            if detection is None:
                if key == WORLD:
                    raise CalibrationError(f"{source}: {_not_found(board)} (it defines the world frame)")
                log.warning("%s: %s, image skipped", source, _not_found(board))
                continue
            ids, corners = detection
            views.append(View(cam, key, source, corners, (image.shape[1], image.shape[0]), ids))
        views = _without_repeats(views, cam)
        usable = sum(v.camera == cam for v in views)
        if usable < MIN_VIEWS:
            raise CalibrationError(
                f"camera {cam!r}: board found in only {usable} distinct view(s) of {len(images)} images; "
                f"need at least {MIN_VIEWS} (more views, whole board visible, check --board)"
            )
    _check_not_copied_across(views)
    return views


def _shared_images(shared: Path) -> list[Path]:
    """The images of a camera's ``shared`` folder, sorted; two of one name (02.png and
    02.jpg) are a CalibrationError: a shared view is one board pose, named alike in
    every camera, and which file was meant cannot be told."""
    images = sorted(p for p in shared.iterdir() if p.suffix.lower() in IMAGE_EXTS)
    stems = [p.stem for p in images]
    twice = sorted({stem for stem in stems if stems.count(stem) > 1})
    if twice:
        named = ", ".join(p.name for p in images if p.stem == twice[0])
        raise CalibrationError(
            f"{shared}: holds {named}, two images of the shared view {twice[0]!r}; one board pose "
            "is one image per camera: keep one of them and remove the others"
        )
    return images


def _warn_unmatched_shared(cam_dirs: Sequence[Path]) -> None:
    """Name the shared/ images of each camera that no other camera has an image of the same
    name of: shared views are matched by name, and one alone links its camera to nothing
    (the real stereo pairs copied in as leftNN.jpg and rightNN.jpg: not one view shared,
    the baseline 1.1 mm off, without a word)."""
    if len(cam_dirs) < 2:
        return
    stems = {
        cam_dir.name: {p.stem for p in _shared_images(cam_dir / "shared")}
        for cam_dir in cam_dirs
        if (cam_dir / "shared").is_dir()
    }
    for cam, own in stems.items():
        others = set().union(*(theirs for name, theirs in stems.items() if name != cam))
        alone = sorted(own - others)
        if alone:
            log.warning(
                "camera %r: %d of its %d shared/ images have no image of the same name in another "
                "camera (%s%s): shared views are matched by name; name each board pose's images "
                "alike in every camera's shared/ (e.g. 02.png)",
                cam,
                len(alone),
                len(own),
                ", ".join(alone[:3]),
                ", ..." if len(alone) > 3 else "",
            )


def board_size_problems(views: Sequence[View], board: Board) -> list[str]:
    """A line where the images show a board other than ``board``'s size: a board larger
    than declared is found whole in its part (a chessboard's --board 8x5 inside a 9x6
    board), and a ChArUco board declared a row or column larger never shows its corners
    there. Either calibrates every camera consistently, with the world frame squares
    off (a 7x5 ChArUco board given as --charuco 7x6: every camera 50 mm off, exit 0)."""
    if board.kind == "charuco":
        seen = np.zeros((board.rows, board.cols), bool)
        for view in views:
            seen.flat[view.ids] = True
        edges = {
            "first row": seen[0].any(),
            "last row": seen[-1].any(),
            "first column": seen[:, 0].any(),
            "last column": seen[:, -1].any(),
        }
        unseen = [edge for edge, shown in edges.items() if not shown]
        if unseen:
            return [
                f"no image shows a corner of the {' or '.join(unseen)} of the board given "
                f"({board.describe()}): is the board smaller? count its squares again, and give "
                "--charuco COLSxROWS (squares, not inner corners)"
            ]
        return []
    # A whole chessboard one row or column larger, looked for in each camera's world view
    # (or first view).
    sources = {view.camera: view.source for view in views if view.key == WORLD}
    for view in views:
        sources.setdefault(view.camera, view.source)
    images = [_read_grey(Path(source)) for source in sources.values() if Path(source).is_file()]
    larger = [
        (cols, rows)
        for cols, rows in ((board.cols + 1, board.rows), (board.cols, board.rows + 1))
        if sum(_holds_pattern(image, (cols, rows)) for image in images) * 2 > len(images)
    ]
    if larger:
        cols, rows = larger[0]
        return [
            f"the board holds more inner corners than {board.describe()} (a {cols}x{rows} pattern "
            "was found too): count the inner corners along each side again and give --board COLSxROWS"
        ]
    return []


def _holds_pattern(image: NDArray[np.uint8], pattern: tuple[int, int]) -> bool:
    return find_chessboard(image, pattern, cv2.CALIB_CB_EXHAUSTIVE)[0]


def _check_not_copied_across(views: list[View]) -> None:
    """Refuse an intrinsics view of one camera that shows the board where another camera's
    does (every corner within ``REPEAT_PX``): two cameras never see one board alike, so one
    camera's images were copied into the other's folder. Mixed in with its own, they pull
    its lens to the other's: on ``synth-calib``'s boards (2026-12-05) cam2's images copied
    beside cam0's put cam0's focal length 9 % and its centre 50 mm off, at a 0.10 px mean
    error that shows nothing."""
    own = [v for v in views if not v.shared]
    for i, view in enumerate(own):
        for other in own[:i]:
            if other.camera != view.camera and other.size_px == view.size_px and _same_pose(other, view):
                raise CalibrationError(
                    f"{view.source}: shows the board exactly where {other.source} does, an image of "
                    f"camera {other.camera!r}: one camera's images copied into another's folder; remove "
                    "the copies (for identical cameras, calibrate with --shared-intrinsics)"
                )


def _without_repeats(views: list[View], cam: str) -> list[View]:
    """``views`` with camera ``cam``'s intrinsics views that repeat an earlier one's board pose
    (every corner within ``REPEAT_PX``) left out, and named in one warning."""
    kept: list[View] = []
    repeats: dict[str, list[str]] = {}  # the kept view's source -> the sources repeating it
    for view in views:
        if view.camera == cam and not view.shared:
            same = next((k for k in kept if k.camera == cam and not k.shared and _same_pose(k, view)), None)
            if same is not None:
                repeats.setdefault(same.source, []).append(Path(view.source).name)
                continue
        kept.append(view)
    if repeats:
        count = sum(map(len, repeats.values()))
        first, names = next(iter(repeats.items()))
        shown = ", ".join(names[:3]) + (", ..." if count > 3 else "")
        log.warning(
            "camera %r: %d intrinsics image(s) show the board where another does (%s repeat %s: "
            "copies, or a board held still), each pose counted once; move the board between views",
            cam,
            count,
            shown,
            Path(first).name,
        )
    return kept


def _same_pose(a: View, b: View) -> bool:
    """Whether two views of one camera see the board in the same place: the same corners,
    each within ``REPEAT_PX``."""
    return bool(
        np.array_equal(a.ids, b.ids)
        and a.corners_px.size > 0
        and float(np.max(np.abs(a.corners_px - b.corners_px))) <= REPEAT_PX
    )


def _not_found(board: Board) -> str:
    """Why an image gave no detection, and what to check."""
    if board.kind == "charuco":
        return (
            f"too few ChArUco corners found ({board.describe()}); show more of the board, larger, "
            "and check --charuco COLSxROWS, --square-mm and board.toml's dictionary"
        )
    return f"board {board.cols}x{board.rows} not found; show the whole board and check --board COLSxROWS"
