"""Calibration boards: their description (board.toml), their 3-D corners and their detection.

Board frame: inner corner (i, j) -- column i, row j -- is at (i * square_mm,
j * square_mm, 0); z leaves the printed face; the square diagonally outside
corner (0, 0) is black. A detection is always returned in this order, whatever
order the detector found the corners in, so that every camera numbers the
corners of one board the same way and world.png defines an unambiguous frame.
"""

from __future__ import annotations

import logging
import tomllib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from .errors import CalibrationError

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

# Corners are searched again on an up-sampled crop around the board, by 3 for
# squares under 25 px, 2 under 40 px; larger squares are localised well as they are.
UPSAMPLE_BELOW_PX = ((25.0, 3), (40.0, 2))


@dataclass(frozen=True)
class Board:
    """A chessboard: ``cols`` x ``rows`` inner corners, squares of ``square_mm``."""

    cols: int
    rows: int
    square_mm: float

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


def load_board(
    calib_dir: Path, *, board: tuple[int, int] | None = None, square_mm: float | None = None
) -> Board:
    """The board of ``calib_dir``: board.toml if present, overridden by ``board``/``square_mm``."""
    path = Path(calib_dir) / "board.toml"
    cols_rows, square = board, square_mm
    if path.is_file():
        try:
            doc = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise CalibrationError(f"{path}: TOML syntax error: {exc}") from None
        kind = doc.get("type", "chessboard")
        if kind != "chessboard" and board is None:
            raise CalibrationError(f"{path}: board type {kind!r} is not supported; use 'chessboard'")
        corners = doc.get("inner_corners")
        if cols_rows is None and corners is not None:
            if not (
                isinstance(corners, list) and len(corners) == 2 and all(isinstance(v, int) for v in corners)
            ):
                raise CalibrationError(f"{path}: inner_corners must be [cols, rows] integers")
            cols_rows = (corners[0], corners[1])
        if square is None and "square_mm" in doc:
            square = doc["square_mm"]
    if cols_rows is None or square is None:
        raise CalibrationError(
            f"{calib_dir}: board unknown; write {path.name} (type, inner_corners, square_mm) "
            "or pass --board COLSxROWS --square-mm S"
        )
    cols, rows = cols_rows
    if cols < 2 or rows < 2:
        raise CalibrationError(f"{calib_dir}: board {cols}x{rows} needs at least 2x2 inner corners")
    if (cols + rows) % 2 == 0:
        # Both corner squares at the ends of a diagonal then have the same colour:
        # a board turned by 180 degrees looks the same and the world frame is ambiguous.
        raise CalibrationError(
            f"{calib_dir}: board {cols}x{rows} looks the same turned by 180 degrees; "
            "use a board with one odd and one even number of inner corners (e.g. 9x6)"
        )
    if not isinstance(square, (int, float)) or square <= 0:
        raise CalibrationError(f"{calib_dir}: square_mm must be a positive number, got {square!r}")
    return Board(int(cols), int(rows), float(square))


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
    found, corners = cv2.findChessboardCornersSB(image, board.pattern_size, flags=cv2.CALIB_CB_EXHAUSTIVE)
    if not found:
        # ACCURACY searches an up-sampled image: slower, but finds some boards seen
        # at a grazing angle (squares ~4 px tall) that the native search misses.
        flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
        found, corners = cv2.findChessboardCornersSB(image, board.pattern_size, flags=flags)
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
    crop = cv2.resize(image[y0:y1, x0:x1], None, fx=k, fy=k, interpolation=cv2.INTER_CUBIC)
    found, corners = cv2.findChessboardCornersSB(crop, board.pattern_size, flags=cv2.CALIB_CB_ACCURACY)
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
