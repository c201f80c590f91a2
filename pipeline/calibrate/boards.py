"""Calibration boards: their description (board.toml), their 3-D corners and their detection.

Board frame: inner corner (i, j) -- column i, row j -- is at (i * square_mm,
j * square_mm, 0); z leaves the printed face; the square diagonally outside
corner (0, 0) is black. A detection is always returned in this order, whatever
order the detector found the corners in, so that every camera numbers the
corners of one board the same way and world.png defines an unambiguous frame.

A ChArUco board of C x R squares (``cv2.aruco.CharucoBoard``, as printed by its
``generateImage``) has (C - 1) x (R - 1) inner corners in the same frame: seen
from the printed face x runs right and y up, so corner (0, 0) is the bottom-left
inner corner of the printed image (OpenCV's own frame has y down and z into the
board; ours keeps z out of it, so a world board on the floor has z up). Its
corners are identified by the markers, so a view may show any subset of them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from ..errors import CalibrationError
from ..session.toml_file import check_keys, read_toml

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

# Corners are searched again on an up-sampled crop around the board, by 3 for
# squares under 25 px, 2 under 40 px; larger squares are localised well as they are.
UPSAMPLE_BELOW_PX = ((25.0, 3), (40.0, 2))
# ChArUco markers are decoded on the image up-sampled (cubic) to about this width:
# at 320x240 a marker cell spans 1-3 px, which the decoder often misses natively.
CHARUCO_UPSAMPLED_WIDTH = 1000
# Inner corners a side beyond any printed chessboard: OpenCV's detector cannot take a
# size past 2**31 at all, and searches long for a large one it will not find.
MAX_INNER_CORNERS = 200
MARKER_RATIO = 0.75  # default marker side / square side
DEFAULT_DICTIONARY = "DICT_4X4_50"
# Fewer ChArUco corners than this in a view: the view is not used (a pose from
# a handful of corners is poorly determined).
MIN_CHARUCO_CORNERS = 6
# Saddle-point refinement of ChArUco corners (see _refine_saddles): window radius and
# Gaussian blur in squares (nearest-corner spacing), and the passes.
SADDLE_RADIUS, SADDLE_SIGMA, SADDLE_PASSES = 0.1, 0.06, 3


@dataclass(frozen=True)
class Board:
    """A chessboard or ChArUco board: ``cols`` x ``rows`` inner corners, squares of ``square_mm``.

    ``kind`` is "chessboard" or "charuco"; a ChArUco board also has markers of
    ``marker_mm`` from the cv2.aruco ``dictionary`` (e.g. "DICT_4X4_50").
    """

    cols: int
    rows: int
    square_mm: float
    kind: str = "chessboard"
    marker_mm: float = 0.0
    dictionary: str = ""

    @property
    def squares(self) -> tuple[int, int]:
        """(cols, rows) squares: one more than the inner corners each way."""
        return self.cols + 1, self.rows + 1

    def describe(self) -> str:
        """Short text for messages and metadata, e.g. "chessboard 9x6, 20 mm"."""
        if self.kind == "charuco":
            c, r = self.squares
            return (
                f"charuco {c}x{r} squares, {self.square_mm:g} mm, markers {self.marker_mm:g} mm "
                f"{self.dictionary}"
            )
        return f"chessboard {self.cols}x{self.rows}, {self.square_mm:g} mm"

    @property
    def pattern_size(self) -> tuple[int, int]:
        """(cols, rows), OpenCV's patternSize."""
        return self.cols, self.rows

    @property
    def n_corners(self) -> int:
        return self.cols * self.rows

    def object_points(self) -> FloatArray:
        """(cols * rows, 3) float64 corners in the board frame, mm, row by row."""
        j, i = np.mgrid[0 : self.rows, 0 : self.cols]
        return np.column_stack([i.ravel(), j.ravel(), np.zeros(i.size)]) * self.square_mm


# board.toml's keys: a chessboard's, then a ChArUco board's (square_mm is both's).
BOARD_KEYS = ("type", "inner_corners", "square_mm", "squares", "marker_mm", "dictionary")


def load_board(
    calib_dir: Path,
    *,
    board: tuple[int, int] | None = None,
    square_mm: float | None = None,
    charuco: tuple[int, int] | None = None,
) -> Board:
    """The board of ``calib_dir``: board.toml if present, overridden by the flags.

    ``board`` is a chessboard's (cols, rows) inner corners, ``charuco`` a ChArUco
    board's (cols, rows) squares; either overrides board.toml's type and size.
    """
    if board is not None and charuco is not None:
        raise CalibrationError(f"{calib_dir}: give --board (a chessboard) or --charuco, not both")
    path = Path(calib_dir) / "board.toml"
    doc: dict[str, object] = {}
    if path.exists() and not path.is_file():
        raise CalibrationError(f"{path}: is not a file (a folder?); write the board's description there")
    if path.is_file():
        doc = read_toml(path, error=CalibrationError)
        check_keys(doc, BOARD_KEYS, str(path), error=CalibrationError)
    if charuco is not None:
        kind: object = "charuco"
    elif board is not None:
        kind = "chessboard"
    else:
        kind = doc.get("type", "chessboard")
    if kind == "charuco":
        return _load_charuco(calib_dir, path, doc, charuco, square_mm)
    if kind != "chessboard":
        raise CalibrationError(f"{path}: board type {kind!r} is not supported; use 'chessboard' or 'charuco'")
    described = str(doc.get("type", "chessboard"))
    if described != "chessboard":
        doc = {}  # --board overrides a ChArUco board.toml entirely
    cols_rows, square = board, square_mm
    square_from = f"{calib_dir}: --square-mm"
    if cols_rows is not None and square is None and described != "chessboard":
        raise CalibrationError(
            f"{path}: describes a {described} board, and --board {cols_rows[0]}x{cols_rows[1]} asks "
            f"for a chessboard without its --square-mm; drop --board to use {path.name}, or give "
            "--square-mm S too"
        )
    if doc:
        corners = doc.get("inner_corners")
        if (
            cols_rows is not None
            and isinstance(corners, list)
            and list(cols_rows[::-1]) == corners != list(cols_rows)
        ):
            # Taken as given (the flag overrides), but a board read the other way round
            # turns the world frame a quarter turn and moves its origin a board's side.
            log.warning(
                "--board %dx%d is %s's %dx%d the other way round: the world frame turns with it; "
                "give --board %dx%d, or none, for the board.toml's frame",
                *cols_rows,
                path,
                *corners,
                *corners,
            )
        if cols_rows is None and corners is not None:
            if not (
                isinstance(corners, list) and len(corners) == 2 and all(isinstance(v, int) for v in corners)
            ):
                raise CalibrationError(f"{path}: inner_corners must be [cols, rows] integers")
            cols_rows = (corners[0], corners[1])
        if square is None and "square_mm" in doc:
            square = doc["square_mm"]  # type: ignore[assignment]
            square_from = f"{path}: square_mm"
    if cols_rows is None or square is None:
        raise CalibrationError(
            f"{calib_dir}: board unknown; write {path.name} (type, inner_corners, square_mm) "
            "or pass --board COLSxROWS --square-mm S"
        )
    cols, rows = cols_rows
    if cols < 2 or rows < 2:
        raise CalibrationError(f"{calib_dir}: board {cols}x{rows} needs at least 2x2 inner corners")
    if max(cols, rows) > MAX_INNER_CORNERS:
        raise CalibrationError(
            f"{calib_dir}: board {cols}x{rows} has more inner corners than a printed board "
            f"(at most {MAX_INNER_CORNERS} a side); give the inner corners, e.g. --board 9x6"
        )
    if (cols + rows) % 2 == 0:
        # Both corner squares at the ends of a diagonal then have the same colour:
        # a board turned by 180 degrees looks the same and the world frame is ambiguous.
        raise CalibrationError(
            f"{calib_dir}: board {cols}x{rows} looks the same turned by 180 degrees; "
            "use a board with one odd and one even number of inner corners (e.g. 9x6)"
        )
    if not _plausible_square(square):
        number = isinstance(square, int | float) and not isinstance(square, bool)
        raise CalibrationError(
            f"{square_from} must be a finite size in mm, {_SQUARE_MM[0]:g} to {_SQUARE_MM[1]:g}, "
            f"got {square!r} ({_SQUARE_UNITS if number else 'a number, not text: square_mm = 25'})"
        )
    return Board(int(cols), int(rows), float(square))


# A board's square size (mm) is refused outside these bounds before any detection: OpenCV's
# solvers fail on a NaN, an infinity or a size like 1e-300, once the boards are detected; and
# a size in metres typed for millimetres (0.025 for a 25 mm square) would calibrate a rig a
# thousand times too small, which only fails later, every frame.
_SQUARE_MM = (0.5, 10000.0)
_SQUARE_UNITS = "a board's squares are in mm: 25 for 25 mm, not 0.025"


def _plausible_square(square: object) -> bool:
    """Whether ``square`` is a number (not a bool) within ``_SQUARE_MM``."""
    if isinstance(square, bool) or not isinstance(square, (int, float)):
        return False
    return _SQUARE_MM[0] <= float(square) <= _SQUARE_MM[1]


def _load_charuco(
    calib_dir: Path,
    path: Path,
    doc: dict[str, object],
    charuco: tuple[int, int] | None,
    square_mm: float | None,
) -> Board:
    """A ChArUco Board from board.toml (type = "charuco") and/or the --charuco flags."""
    if doc.get("type", "charuco") != "charuco":
        doc = {}  # --charuco overrides a chessboard board.toml entirely
    squares = charuco if charuco is not None else doc.get("squares")
    if not (
        isinstance(squares, (list, tuple)) and len(squares) == 2 and all(isinstance(v, int) for v in squares)
    ):
        raise CalibrationError(
            f"{calib_dir}: ChArUco board size unknown; write squares = [cols, rows] in {path.name} "
            "or pass --charuco COLSxROWS"
        )
    square = square_mm if square_mm is not None else doc.get("square_mm")
    if not _plausible_square(square):
        raise CalibrationError(
            f"{calib_dir}: ChArUco square size unknown or not a finite size in mm, {_SQUARE_MM[0]:g} to "
            f"{_SQUARE_MM[1]:g} ({square!r}; {_SQUARE_UNITS}); write square_mm in {path.name} or pass "
            "--square-mm S"
        )
    square = float(square)  # type: ignore[arg-type]
    # board.toml's marker size belongs to its square size: not kept when --square-mm overrides it.
    marker = doc["marker_mm"] if "marker_mm" in doc and square_mm is None else MARKER_RATIO * square
    if not isinstance(marker, (int, float)) or not 0 < marker < square:
        raise CalibrationError(
            f"{path}: marker_mm must be positive and smaller than square_mm, got {marker!r}"
        )
    dictionary = doc.get("dictionary", DEFAULT_DICTIONARY)
    if (
        not isinstance(dictionary, str)
        or not dictionary.startswith("DICT_")
        or not hasattr(cv2.aruco, dictionary)
    ):
        raise CalibrationError(f"{path}: unknown ArUco dictionary {dictionary!r}; use e.g. 'DICT_4X4_50'")
    cols, rows = squares[0], squares[1]
    if cols < 3 or rows < 3:
        raise CalibrationError(f"{calib_dir}: ChArUco board {cols}x{rows} needs at least 3x3 squares")
    board = Board(cols - 1, rows - 1, float(square), "charuco", float(marker), dictionary)
    n_markers = (cols * rows) // 2
    if n_markers > cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)).bytesList.shape[0]:
        raise CalibrationError(f"{path}: {dictionary} has too few markers for {cols}x{rows} squares")
    return board


def detect(image: NDArray[np.uint8], board: Board) -> tuple[NDArray[np.intp], FloatArray] | None:
    """Corners of ``board`` seen in a grey image, with their indices; None if not found.

    Returns
    -------
    ids : (M,) intp indices into ``board.object_points()``, increasing.
    corners_px : (M, 2) float64 pixel coordinates of those corners.
    A chessboard gives all its corners or None; a ChArUco board any subset of at
    least MIN_CHARUCO_CORNERS corners, not all on one line.
    """
    if board.kind == "charuco":
        return detect_charuco(image, board)
    corners = detect_corners(image, board)
    return None if corners is None else (np.arange(board.n_corners), corners)


def _cv_charuco(board: Board) -> cv2.aruco.CharucoBoard:
    aruco = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
    return cv2.aruco.CharucoBoard(board.squares, board.square_mm, board.marker_mm, aruco)


def detect_charuco(image: NDArray[np.uint8], board: Board) -> tuple[NDArray[np.intp], FloatArray] | None:
    """ChArUco corners in a grey image (see :func:`detect`); the board may be partly visible.

    Markers are decoded, and corners interpolated, by cv2.aruco.CharucoDetector on
    an up-sampled copy (CHARUCO_UPSAMPLED_WIDTH); the corners are then refined as
    saddle points (:func:`_refine_saddles`).
    """
    cv_board = _cv_charuco(board)
    k = max(1, min(4, CHARUCO_UPSAMPLED_WIDTH // image.shape[1]))
    big = np.asarray(
        cv2.resize(image, None, fx=k, fy=k, interpolation=cv2.INTER_CUBIC) if k > 1 else image, np.uint8
    )
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    corners, cv_ids, _, _ = cv2.aruco.CharucoDetector(cv_board, detectorParams=params).detectBoard(big)
    if cv_ids is None or len(cv_ids) < MIN_CHARUCO_CORNERS:
        return None
    if cv_board.checkCharucoCornersCollinear(cv_ids):
        return None
    big_px, converged = _refine_saddles(big, np.asarray(corners, np.float64).reshape(-1, 2))
    cv_ids = np.asarray(cv_ids).ravel()[converged]
    if len(cv_ids) < MIN_CHARUCO_CORNERS or cv_board.checkCharucoCornersCollinear(cv_ids):
        return None
    # cv2.resize maps source pixel centre x to k * x + (k - 1) / 2.
    px = (big_px[converged] - (k - 1) / 2) / k
    # OpenCV numbers corners row by row from the top of the printed image; ours
    # from the bottom (module docstring).
    ids = (board.rows - 1 - cv_ids // board.cols) * board.cols + cv_ids % board.cols
    order = np.argsort(ids)
    return ids[order].astype(np.intp), px[order]


def _refine_saddles(image: NDArray[np.uint8], corners_px: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Corners moved to the saddle point of a quadratic fitted to the blurred image around each.

    The detector's own refinement (cornerSubPix) is pulled by the markers that sit
    in the white squares: on exact 320x240 renders its corners are 0.078 px off on
    average (up to 0.36 px, and over 1 px on steep, close boards); a quadratic
    fitted within 0.1 square of the corner, where only the two squares' edges are
    seen, after a blur of 0.06 square, puts them 0.017 px off (up to 0.044 px)
    (measured on a 3x up-sampled image). A wider window would reach the corners of
    the markers, saddles too: a corner the detector put further off than the
    window (steep, close boards) is reported as not converged rather than moved.

    Parameters
    ----------
    image : (H, W) uint8 grey image.
    corners_px : (M, 2) float64 approximate corners, pixels, M >= 2.

    Returns
    -------
    corners : (M, 2) float64 refined corners.
    converged : (M,) bool, False where the last pass found no saddle in the window
        or the saddle lies further than the window's radius from the detector's
        corner (the corner is then unreliable).
    """
    gaps = np.linalg.norm(corners_px[:, None] - corners_px[None], axis=-1)
    np.fill_diagonal(gaps, np.inf)
    spacing = float(np.median(gaps.min(axis=1)))  # about one square, the shorter side when foreshortened
    r = max(2, round(SADDLE_RADIUS * spacing))
    blurred = np.asarray(
        cv2.GaussianBlur(image.astype(np.float64), (0, 0), max(0.5, SADDLE_SIGMA * spacing)), np.float64
    )
    out, ok = corners_px.copy(), np.zeros(len(corners_px), bool)
    for _ in range(SADDLE_PASSES):
        out, ok = _saddle_pass(blurred, out, r)
    return out, ok & (np.linalg.norm(out - corners_px, axis=1) <= r)


def _saddle_pass(blurred: FloatArray, corners_px: FloatArray, r: int) -> tuple[FloatArray, NDArray[np.bool_]]:
    """One Newton step to the saddle of a quadratic fitted (Gaussian-weighted) in a (2r+1)^2 window."""
    dy, dx = (a.ravel() for a in np.mgrid[-r : r + 1, -r : r + 1].astype(np.float64))
    weight = np.exp(-(dx**2 + dy**2) / (2 * (r / 1.5) ** 2))
    design = np.column_stack([dx**2, dx * dy, dy**2, dx, dy, np.ones_like(dx)]) * weight[:, None]
    fit = np.linalg.pinv(design)  # the same window for every corner: one pseudo-inverse
    out, ok = corners_px.copy(), np.zeros(len(corners_px), bool)
    h, w = blurred.shape
    for n, (x, y) in enumerate(corners_px):
        ix, iy = round(x), round(y)
        if not (r <= ix < w - r and r <= iy < h - r):
            continue
        a, b, c, d, e, _ = fit @ (blurred[iy - r : iy + r + 1, ix - r : ix + r + 1].ravel() * weight)
        hessian = np.array([[2 * a, b], [b, 2 * c]])
        if np.linalg.det(hessian) >= 0:  # an extremum, not a saddle
            continue
        sx, sy = np.linalg.solve(hessian, [-d, -e])
        if abs(sx) <= r and abs(sy) <= r:
            out[n], ok[n] = (ix + sx, iy + sy), True
    return out, ok


def find_chessboard(
    image: NDArray[np.uint8], pattern: tuple[int, int], flags: int
) -> tuple[bool, NDArray[np.float32]]:
    """``cv2.findChessboardCornersSB``, repeatable: it samples from OpenCV's global random
    generator, whose state every earlier call moves, so that the same image could give
    another answer later in the same process (a 6x4 pattern inside a 9x6 board found in 18
    of 20 calls in a row). Seeded alike at each call, an image always gives the same
    answer. Returns (found, (N, 1, 2) float32 corners where found)."""
    cv2.setRNGSeed(0)
    found, corners = cv2.findChessboardCornersSB(image, pattern, flags=flags)
    return bool(found), np.asarray(corners, dtype=np.float32)


def detect_corners(image: NDArray[np.uint8], board: Board) -> FloatArray | None:
    """Inner corners of ``board`` in a grey image, in board order; None if not found.

    Parameters
    ----------
    image : (H, W) uint8 grey image.
    board : the board to look for; the whole board must be visible.

    Returns
    -------
    (cols * rows, 2) float64 pixel coordinates, row by row (see module docstring), or None.
    """
    # EXHAUSTIVE: small boards (squares of ~5 px at 320x240) are otherwise missed.
    found, corners = find_chessboard(image, board.pattern_size, cv2.CALIB_CB_EXHAUSTIVE)
    if not found:
        # ACCURACY searches an up-sampled image: slower, but finds some boards seen
        # at a grazing angle (squares ~4 px tall) that the native search misses.
        flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
        found, corners = find_chessboard(image, board.pattern_size, flags)
    if not found:
        return None
    coarse = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    fine = _refine_upsampled(image, coarse, board)
    return canonical_order(coarse if fine is None else fine, image, board)


def _refine_upsampled(image: NDArray[np.uint8], coarse_px: FloatArray, board: Board) -> FloatArray | None:
    """Corners found again in the board's neighbourhood up-sampled (cubic); None if not needed or lost.

    The sector detector localises corners of small, tilted, anti-aliased squares
    poorly at native resolution: on exact 320x240 renders its corners are 0.09 px
    (rms; up to 0.5 px) off with CALIB_CB_ACCURACY, 0.023 px (up to 0.09 px) when
    run on a 3x cubic up-sampling (measured). cornerSubPix is no substitute: it
    moves the corners of a frontal board from 0.012 px to 0.085 px off. Only a
    crop around the board is up-sampled, to keep the cost near one native search.
    """
    spacing = float(
        np.median(np.linalg.norm(np.diff(coarse_px.reshape(board.rows, board.cols, 2), axis=1), axis=-1))
    )
    k = next((factor for limit, factor in UPSAMPLE_BELOW_PX if spacing < limit), 1)
    if k == 1:
        return None
    pad = 2.0 * spacing + 4.0
    h, w = image.shape
    x0 = int(max(0, np.floor(coarse_px[:, 0].min() - pad)))
    y0 = int(max(0, np.floor(coarse_px[:, 1].min() - pad)))
    x1 = int(min(w, np.ceil(coarse_px[:, 0].max() + pad) + 1))
    y1 = int(min(h, np.ceil(coarse_px[:, 1].max() + pad) + 1))
    resized = cv2.resize(image[y0:y1, x0:x1], None, fx=k, fy=k, interpolation=cv2.INTER_CUBIC)
    crop: NDArray[np.uint8] = np.asarray(resized, dtype=np.uint8)
    found, corners = find_chessboard(crop, board.pattern_size, cv2.CALIB_CB_ACCURACY)
    if not found:
        return None
    # cv2.resize maps source pixel centre x to k * x + (k - 1) / 2.
    fine = (np.asarray(corners, dtype=np.float64).reshape(-1, 2) - (k - 1) / 2) / k + (x0, y0)
    # The same board, possibly numbered differently: match to the coarse corners.
    if np.linalg.norm(fine[0] - coarse_px[0]) > np.linalg.norm(fine[-1] - coarse_px[0]):
        fine = fine[::-1]
    if np.abs(fine - coarse_px).max() > 0.5 * spacing:
        fine = fine.reshape(board.rows, board.cols, 2)[::-1].reshape(-1, 2)
        if np.abs(fine - coarse_px).max() > 0.5 * spacing:
            return None
    return fine


def canonical_order(corners_px: FloatArray, image: NDArray[np.uint8], board: Board) -> FloatArray:
    """Reorder detected corners into board order.

    Two choices are left open by a detector: the handedness of the grid (the board
    is seen from its printed face, so with z out of the face, columns-then-rows must
    turn clockwise in the image, x right / y down) and a 180-degree turn, settled by
    the colour of the corner squares: the one outside corner (0, 0) is black.
    """
    grid = corners_px.reshape(board.rows, board.cols, 2)
    along_row = grid[0, -1] - grid[0, 0]
    along_col = grid[-1, 0] - grid[0, 0]
    # Seen from the front (z towards the viewer) x points right and y up, so the
    # cross product of the two grid directions is negative in image axes (y down).
    # A positive one means the detector numbered the rows backwards.
    if along_row[0] * along_col[1] - along_row[1] * along_col[0] > 0:
        grid = grid[::-1]
    first = _outer_square_grey(image, grid[0, 0], grid[0, 1], grid[1, 0])
    last = _outer_square_grey(image, grid[-1, -1], grid[-1, -2], grid[-2, -1])
    if first > last:
        grid = grid[::-1, ::-1]
    return grid.reshape(-1, 2).copy()


def _outer_square_grey(
    image: NDArray[np.uint8], corner: FloatArray, next_x: FloatArray, next_y: FloatArray
) -> float:
    """Grey level at the centre of the square diagonally outside ``corner``.

    Extrapolated half a square back along both grid directions: first order is
    enough, the square is big compared with its curvature under distortion.
    """
    centre = corner - 0.5 * (next_x - corner) - 0.5 * (next_y - corner)
    x = int(np.clip(round(centre[0]), 1, image.shape[1] - 2))
    y = int(np.clip(round(centre[1]), 1, image.shape[0] - 2))
    return float(image[y - 1 : y + 2, x - 1 : x + 2].mean())
