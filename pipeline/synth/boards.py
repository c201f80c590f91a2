"""Chessboard and ChArUco calibration images of the synthetic rig, rendered exactly by ray casting.

Every pixel is supersampled: each sub-pixel's (distorted) position is undistorted
into a ray of the true camera, the ray is intersected with the board plane and
the board's texture is read there: the analytic chessboard, or the image
``cv2.aruco.CharucoBoard.generateImage`` prints, area-averaged over each
sub-pixel's footprint. Nothing here uses ``pipeline.geometry.camera``: this is the oracle
``pipeline calibrate`` is tested against.

Board frame (the same as ``pipeline.calibrate.boards`` and the world frame of world.png):
inner corner (i, j) sits at (i * square, j * square, 0); z leaves the printed
face; the square diagonally outside corner (0, 0) is black. The world board lies
on the plane z = 0 face up with corner (0, 0) at the world origin, so board frame
= world frame there. A ChArUco board of C x R squares has (C - 1) x (R - 1) inner
corners in the same frame; seen from its printed face (x right, y up) corner
(0, 0) is the bottom-left inner corner of OpenCV's generated image (see
``pipeline.calibrate.boards``), and ChArUco views may show the board only in part.

Folder layout written (the layout ``pipeline calibrate`` reads)::

    OUT_DIR/board.toml                    type, inner_corners = [cols, rows], square_mm (chessboard)
                                          type, squares = [cols, rows], square_mm, marker_mm,
                                          dictionary (charuco)
    OUT_DIR/truth_calibration.toml        the true cameras (aniposelib layout)
    OUT_DIR/<camera>/intrinsics/NN.png    boards in varied poses, one camera at a time
    OUT_DIR/<camera>/world.png            the board on z = 0 (absent for a camera that cannot see it)
    OUT_DIR/<camera>/shared/NN.png        boards seen by several cameras at the same instant (same NN)

In the "ninety" arrangement no board is seen by all three cameras: the world
board is hidden from cam2 (as if by the manipulator's base) and the shared boards
are seen by cam0+cam1 or cam1+cam2 only, so cam2 reaches the world frame through
cam1.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import tomli_w
from numpy.typing import NDArray
from tqdm import tqdm

from ..errors import Interrupted, PipelineError
from .out_dir import check_out_dir, left_behind, unfinished, write_advice, write_image
from .rig import WORKSPACE_CENTER_MM, SynthCamera, calibration_document, make_rig

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

# 2 x 2 sub-pixels for the board's outline; the squares inside are box-filtered
# analytically over each sub-pixel's footprint. Plain 4 x 4 supersampling moves
# each edge by up to 1/8 px (coverage counted in quarters), which showed as
# 0.13 px corner errors on a frontal board; the analytic filter is exact for a
# straight edge, so the corners carry no rendering bias.
SUPERSAMPLE = 2
BLACK, WHITE, BACKGROUND = 25.0, 225.0, 120.0
NOISE_SIGMA = 1.5  # grey levels: mild sensor noise
MARGIN_SQUARES = 0.7  # white border around the squares, in squares
EDGE_PX = 4.0  # every board corner (margin included) stays this far inside the image

# ChArUco: 7 x 5 squares of 50 mm (a 350 x 250 mm board, about A3), 4x4 markers of
# 0.75 square (a cell is 6.25 mm). The world board on the floor is the hard case at
# 320x240: seen from 22-34 degrees elevation ~750 mm away, a cell is ~2.6 x 1.2 px.
# With 30 mm squares only 0-2 of its 24 corners decoded there; with 50 mm, 14-24
# (measured); more squares give the partly visible views enough corners.
CHARUCO_SQUARES, CHARUCO_SQUARE_MM, CHARUCO_MARKER_RATIO = (7, 5), 50.0, 0.75
CHARUCO_DICTIONARY = "DICT_4X4_50"
# Texture pixels per square: a multiple of the marker's 6 cells at 0.75 * 48 = 36 px,
# so that square edges and marker cells fall on texture pixel edges.
TEXTURE_PX_PER_SQUARE = 48
# A partly visible ChArUco board must show this fraction of its inner corners.
MIN_VISIBLE_FRACTION = 0.6
# Intrinsics poses of ChArUco boards: every other one centred this far out towards
# the image border (1 = on it), so that the board hangs over the edge.
OVERHANG_REACH = 0.8

# Cameras that see each shared board, and how many boards per set. "ninety": cam0
# and cam2 face each other, so a board is only ever seen by neighbours.
SHARED_SETS: dict[str, tuple[tuple[tuple[int, ...], int], ...]] = {
    "oblique": (((0, 1), 4), ((1, 2), 4), ((0, 2), 4)),
    "ninety": (((0, 1), 8), ((1, 2), 8)),
}
WORLD_CAMERAS: dict[str, tuple[int, ...]] = {"oblique": (0, 1, 2), "ninety": (0, 1)}
# The true cameras, written last: the mark of a folder this module rendered into.
TRUTH_FILE = "truth_calibration.toml"


# The board images a render writes in each camera's folder (see the layout above).
_IMAGE_PARTS = ("intrinsics/*.png", "shared/*.png", "world.png")


def _remove_earlier_images(out_dir: Path, kept: set[Path]) -> None:
    """An earlier render's board images that this one does not write (another arrangement,
    board or seed: other cameras see the world board, other shared sets): left there,
    ``calibrate`` would take them for this rig's. ``out_dir`` holds no other files (see
    check_out_dir); folders left empty go too."""
    if (out_dir / TRUTH_FILE).is_file():
        log.info("%s: replacing the calibration images rendered there before", out_dir)
    for folder in [d for d in out_dir.iterdir() if d.is_dir() and not d.is_symlink()]:
        for path in [p for part in _IMAGE_PARTS for p in folder.glob(part)]:
            if path not in kept:
                path.unlink()
        for part in (folder / "intrinsics", folder / "shared", folder):
            if part.is_dir() and not any(part.iterdir()):
                part.rmdir()


def render_calibration_views(
    out_dir: Path,
    *,
    arrangement: str = "oblique",
    seed: int = 0,
    board_type: str = "chessboard",
    board: tuple[int, int] | None = None,
    square_mm: float | None = None,
    views: int = 15,
    progress: bool = True,
) -> None:
    """Render calibration images of the true cameras of ``arrangement``.

    Parameters
    ----------
    out_dir : folder to write: created, or empty, or an earlier render (it holds
        truth_calibration.toml; its files are replaced); PipelineError for a folder of
        other files. Layout in the module docstring.
    arrangement : "oblique" or "ninety" (see ``pipeline.synth.rig``).
    seed : seeds the board poses and the noise; a fixed seed gives identical files.
    board_type : "chessboard" or "charuco" (4x4 markers of 0.75 square, CHARUCO_DICTIONARY;
        its intrinsics and shared views may show the board only in part).
    board : chessboard: (cols, rows) inner corners, default (9, 6); cols + rows must be
        odd so that the board's orientation is unambiguous. ChArUco: (cols, rows)
        squares, default CHARUCO_SQUARES.
    square_mm : side of one square, mm; default 20 (chessboard), CHARUCO_SQUARE_MM (ChArUco).
    views : intrinsics views per camera.
    progress : show a progress bar.
    """
    if seed < 0:  # before anything is written
        raise PipelineError(f"--seed must be 0 or more, got {seed}")
    texture: _CharucoTexture | None = None
    if board_type == "chessboard":
        cols, rows = board or (9, 6)
        square_mm = square_mm or 20.0
        if (cols + rows) % 2 == 0:
            raise ValueError(f"board {cols}x{rows}: cols + rows must be odd (a 180-degree turn must show)")
        board_doc: dict[str, object] = {"type": "chessboard", "inner_corners": [cols, rows]}
    elif board_type == "charuco":
        squares = board or CHARUCO_SQUARES
        square_mm = square_mm or CHARUCO_SQUARE_MM
        texture = _CharucoTexture(squares, CHARUCO_DICTIONARY)
        cols, rows = squares[0] - 1, squares[1] - 1  # inner corners: the poses below need only these
        board_doc = {
            "type": "charuco",
            "squares": list(squares),
            "marker_mm": CHARUCO_MARKER_RATIO * square_mm,
            "dictionary": CHARUCO_DICTIONARY,
        }
    else:
        raise ValueError(f"board_type {board_type!r}: use 'chessboard' or 'charuco'")
    partial = texture is not None
    out_dir = Path(out_dir)
    check_out_dir(
        out_dir,
        command="synth-calib",
        contents="the board images",
        marker=TRUTH_FILE,
        kind="an earlier synth-calib output",
    )
    created = not out_dir.exists()
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PipelineError(
            f"{out_dir}: cannot create the folder ({exc.strerror or exc}); give synth-calib a folder "
            "you can write in"
        ) from None
    rng = np.random.default_rng(seed)
    cams = make_rig(arrangement)
    rays = [_camera_rays(cam) for cam in cams]
    jobs: list[tuple[Path, int, FloatArray, FloatArray]] = []  # (file, camera, R, t) camera from board

    for ci, cam in enumerate(cams):
        poses = _intrinsic_poses(cam, rng, views, cols, rows, square_mm, partial=partial)
        for k, (R, t) in enumerate(poses):
            jobs.append((out_dir / cam.name / "intrinsics" / f"{k:02d}.png", ci, R, t))
    for ci in WORLD_CAMERAS[arrangement]:
        cam = cams[ci]
        jobs.append((out_dir / cam.name / "world.png", ci, cam.R, cam.t))
    shared_index = 0
    for subset, count in SHARED_SETS[arrangement]:
        for R_w, t_w in _shared_poses(cams, subset, rng, count, cols, rows, square_mm, partial=partial):
            for ci in subset:
                cam = cams[ci]
                path = out_dir / cam.name / "shared" / f"{shared_index:02d}.png"
                jobs.append((path, ci, cam.R @ R_w, cam.R @ t_w + cam.t))
            shared_index += 1

    incomplete = f"the board images in {out_dir} are incomplete: render them again"
    try:
        with unfinished(out_dir):
            _remove_earlier_images(out_dir, {path for path, *_ in jobs})
            for path, ci, R, t in tqdm(jobs, desc="synth-calib", unit="image", disable=not progress):
                image = _render(rays[ci], cams[ci], R, t, cols, rows, square_mm, rng, texture=texture)
                path.parent.mkdir(parents=True, exist_ok=True)
                write_image(path, image)
            (out_dir / "board.toml").write_text(tomli_w.dumps({**board_doc, "square_mm": float(square_mm)}))
            truth = calibration_document(cams, metadata={"source": "synth-calib", "arrangement": arrangement})
            (out_dir / TRUTH_FILE).write_text(tomli_w.dumps(truth))
    except OSError as exc:
        # A full disk or a folder that turned read-only: a render into a new folder leaves
        # nothing; one over an earlier render leaves it incomplete (unchanged where the
        # folder took no file), and says so.
        raise PipelineError(
            f"{exc.filename or out_dir}: cannot be written ({exc.strerror or exc}); "
            f"{left_behind(out_dir, created, incomplete)}; {write_advice(exc)}"
        ) from None
    except KeyboardInterrupt:  # Ctrl-C, SIGTERM or a hang-up: the same
        raise Interrupted(f"interrupted; {left_behind(out_dir, created, incomplete)}") from None
    log.info("wrote %d calibration images to %s", len(jobs), out_dir)


def _camera_rays(cam: SynthCamera) -> FloatArray:
    """(H, W, S*S, 2) float64 normalised image coordinates (x/z, y/z) of every sub-pixel.

    Pixel centres are at integer coordinates (OpenCV); sub-pixels sit on a regular
    S x S grid inside each pixel.
    """
    s = SUPERSAMPLE
    offsets = (np.arange(s) + 0.5) / s - 0.5
    oy, ox = np.meshgrid(offsets, offsets, indexing="ij")
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
    px = np.stack(
        [xs[:, :, None] + ox.ravel()[None, None, :], ys[:, :, None] + oy.ravel()[None, None, :]], axis=-1
    )
    # A tight criterion: the default (5 iterations) leaves ~0.1 px near the corners.
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    und = cv2.undistortPoints(px.reshape(-1, 1, 2), cam.K, cam.dist, criteria=criteria)
    return np.asarray(und, dtype=np.float64).reshape(cam.height, cam.width, s * s, 2)


def _render(
    rays: FloatArray,
    cam: SynthCamera,
    R: FloatArray,
    t: FloatArray,
    cols: int,
    rows: int,
    square_mm: float,
    rng: np.random.Generator,
    *,
    texture: _CharucoTexture | None = None,
) -> NDArray[np.uint8]:
    """(H, W) uint8 image of the board at x_cam = R @ (u, v, 0) + t seen through ``rays``.

    ``cols``, ``rows`` are inner corners; ``texture`` replaces the analytic chessboard.
    """
    d = np.concatenate([rays, np.ones((*rays.shape[:-1], 1))], axis=-1)  # camera-frame directions
    normal = R[:, 2]
    denom = d @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (normal @ t) / denom
    hit = np.isfinite(s) & (s > 0)
    local = (s[..., None] * d - t) @ R  # board coordinates: R^T (x_cam - t), as row vectors
    u, v = local[..., 0] / square_mm, local[..., 1] / square_mm
    # Squares span u in [-1, cols], v in [-1, rows] (in squares); square (-1, -1) is black.
    on_squares = hit & (u >= -1) & (u < cols) & (v >= -1) & (v < rows)
    on_board = (
        hit
        & (u >= -1 - MARGIN_SQUARES)
        & (u < cols + MARGIN_SQUARES)
        & (v >= -1 - MARGIN_SQUARES)
        & (v < rows + MARGIN_SQUARES)
    )
    # Footprint of one sub-pixel in squares: derivatives across neighbouring pixels / S.
    width_u = (np.abs(np.gradient(u, axis=0)) + np.abs(np.gradient(u, axis=1))) / SUPERSAMPLE
    width_v = (np.abs(np.gradient(v, axis=0)) + np.abs(np.gradient(v, axis=1))) / SUPERSAMPLE
    grey = np.where(on_board, WHITE, BACKGROUND)
    if texture is None:
        odd_u, odd_v = _box_filtered_parity(u, width_u), _box_filtered_parity(v, width_v)
        # Black where floor(u) + floor(v) is even, i.e. both parities equal.
        black = odd_u * odd_v + (1 - odd_u) * (1 - odd_v)
        grey = np.where(on_squares, WHITE + (BLACK - WHITE) * black, grey)
    else:
        white = texture.box_mean(u, v, width_u, width_v)
        grey = np.where(on_board, BLACK + (WHITE - BLACK) * white, grey)
    image = grey.mean(axis=-1) + rng.normal(0.0, NOISE_SIGMA, size=(cam.height, cam.width))
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def _box_filtered_parity(x: FloatArray, width: FloatArray) -> FloatArray:
    """Mean of (floor(x) mod 2) over [x - width/2, x + width/2]; x, width in squares."""
    width = np.maximum(width, 1e-9)

    def primitive(y: FloatArray) -> FloatArray:  # integral of floor(y) mod 2 from 0 to y
        return np.floor(y / 2) + np.maximum(2 * (y / 2 - np.floor(y / 2)) - 1, 0)

    return (primitive(x + width / 2) - primitive(x - width / 2)) / width


class _CharucoTexture:
    """The printed ChArUco board as a texture, area-averaged through its summed-area table.

    Texture pixel k spans [k, k + 1); the squares start at pixel 0 and each is
    TEXTURE_PX_PER_SQUARE wide, surrounded by a white margin of MARGIN_SQUARES.
    """

    def __init__(self, squares: tuple[int, int], dictionary: str) -> None:
        cols, rows = squares
        aruco = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
        marker = CHARUCO_MARKER_RATIO  # in squares: the texture is drawn at 1 unit per square
        board = cv2.aruco.CharucoBoard((cols, rows), 1.0, marker, aruco)
        p = TEXTURE_PX_PER_SQUARE
        printed = board.generateImage((cols * p, rows * p), marginSize=0, borderBits=1)
        self.pad = int(np.ceil(MARGIN_SQUARES * p))
        image = np.pad(np.asarray(printed, np.float64), self.pad, constant_values=255.0)
        # sat[y, x] = sum of image[:y, :x] / 255: the integral of the texture's whiteness.
        self.sat = np.zeros((image.shape[0] + 1, image.shape[1] + 1))
        self.sat[1:, 1:] = np.cumsum(np.cumsum(image / 255.0, axis=0), axis=1)
        self.inner_rows = rows - 1

    def box_mean(self, u: FloatArray, v: FloatArray, width_u: FloatArray, width_v: FloatArray) -> FloatArray:
        """Mean whiteness (0 black .. 1 white) over [u -+ width_u / 2] x [v -+ width_v / 2].

        u, v in squares, board frame (corner (0, 0) at the origin, y up when seen
        from the printed face); the image's y runs down, hence the flip.
        """
        p = TEXTURE_PX_PER_SQUARE
        x = (u + 1) * p + self.pad
        y = (self.inner_rows - v) * p + self.pad
        hx, hy = np.maximum(width_u, 1e-9) * p / 2, np.maximum(width_v, 1e-9) * p / 2
        h, w = self.sat.shape[0] - 1, self.sat.shape[1] - 1
        x0, x1 = np.clip(x - hx, 0, w), np.clip(x + hx, 0, w)
        y0, y1 = np.clip(y - hy, 0, h), np.clip(y + hy, 0, h)
        area = (x1 - x0) * (y1 - y0)
        total = self._sat_at(x1, y1) - self._sat_at(x0, y1) - self._sat_at(x1, y0) + self._sat_at(x0, y0)
        # A footprint entirely off the texture lies off the board: drawn as background anyway.
        return np.where(area > 0, total / np.maximum(area, 1e-12), 1.0)

    def _sat_at(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """The summed-area table at continuous (x, y): bilinear, which is exact because
        the integral of a piecewise-constant texture is bilinear inside each pixel."""
        h, w = self.sat.shape[0] - 1, self.sat.shape[1] - 1
        ix = np.clip(np.floor(x).astype(np.intp), 0, w - 1)
        iy = np.clip(np.floor(y).astype(np.intp), 0, h - 1)
        fx, fy = x - ix, y - iy
        s = self.sat
        return (
            (1 - fx) * (1 - fy) * s[iy, ix]
            + fx * (1 - fy) * s[iy, ix + 1]
            + (1 - fx) * fy * s[iy + 1, ix]
            + fx * fy * s[iy + 1, ix + 1]
        )


def _board_outline(cols: int, rows: int, square_mm: float) -> FloatArray:
    """(4, 3) float64 outer corners of the board (margin included), board frame, mm."""
    lo_u, hi_u = -1 - MARGIN_SQUARES, cols + MARGIN_SQUARES
    lo_v, hi_v = -1 - MARGIN_SQUARES, rows + MARGIN_SQUARES
    return square_mm * np.array([[lo_u, lo_v, 0], [hi_u, lo_v, 0], [hi_u, hi_v, 0], [lo_u, hi_v, 0]])


def _visible_fraction(
    cam: SynthCamera, R: FloatArray, t: FloatArray, cols: int, rows: int, square_mm: float
) -> float:
    """Fraction of the inner corners inside the image (EDGE_PX to spare), 0 if the board faces away."""
    j, i = np.mgrid[0:rows, 0:cols]
    obj = np.column_stack([i.ravel(), j.ravel(), np.zeros(i.size)]) * square_mm
    pts = obj @ R.T + t
    if np.any(pts[:, 2] <= 0) or R[:, 2] @ (-pts.mean(axis=0)) <= 0:
        return 0.0
    rvec, _ = cv2.Rodrigues(R)
    px, _ = cv2.projectPoints(obj, rvec, t, cam.K, cam.dist)
    px = px.reshape(-1, 2)
    inside = (
        (px[:, 0] >= EDGE_PX)
        & (px[:, 0] <= cam.width - 1 - EDGE_PX)
        & (px[:, 1] >= EDGE_PX)
        & (px[:, 1] <= cam.height - 1 - EDGE_PX)
    )
    return float(inside.mean())


def _fully_visible(cam: SynthCamera, R: FloatArray, t: FloatArray, outline_mm: FloatArray) -> bool:
    """Whole board inside the image (with EDGE_PX to spare) and its printed face towards the camera."""
    pts = outline_mm @ R.T + t
    if np.any(pts[:, 2] <= 0) or R[:, 2] @ (-(R @ outline_mm.mean(axis=0) + t)) <= 0:
        return False
    # The outline's straight edges bow under distortion; sample them densely.
    dense = np.concatenate(
        [np.linspace(a, b, 20) for a, b in zip(outline_mm, np.roll(outline_mm, -1, 0), strict=True)]
    )
    rvec, _ = cv2.Rodrigues(R)
    px, _ = cv2.projectPoints(dense, rvec, t, cam.K, cam.dist)
    px = px.reshape(-1, 2)
    return bool(
        np.all(px >= EDGE_PX)
        and np.all(px[:, 0] <= cam.width - 1 - EDGE_PX)
        and np.all(px[:, 1] <= cam.height - 1 - EDGE_PX)
    )


def _rotation(axis: FloatArray, angle: float) -> FloatArray:
    rot, _ = cv2.Rodrigues(np.asarray(axis, dtype=np.float64) * angle)
    return np.asarray(rot, dtype=np.float64)


def _intrinsic_poses(
    cam: SynthCamera,
    rng: np.random.Generator,
    views: int,
    cols: int,
    rows: int,
    square_mm: float,
    *,
    partial: bool = False,
) -> list[tuple[FloatArray, FloatArray]]:
    """Board poses (camera from board) spread over the image, tilted up to ~50 degrees.

    The board centres cycle through the image centre, its corners and edge
    midpoints so that the distortion at the image borders is observed. With
    ``partial`` (ChArUco) every other board is pushed past the border, showing
    at least MIN_VISIBLE_FRACTION of its corners.
    """
    outline = _board_outline(cols, rows, square_mm)
    centre_b = np.array([(cols - 1) / 2, (rows - 1) / 2, 0.0]) * square_mm
    # Facing the camera: board x = camera x, board y = -camera y, board z = -camera z.
    facing = np.diag([1.0, -1.0, -1.0])
    w, h = cam.width, cam.height
    targets = [(0.5, 0.5), (0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0), (0.5, 0.0), (1.0, 0.5)]
    targets += [(0.5, 1.0), (0.0, 0.5)]
    board_width = (cols + 1 + 2 * MARGIN_SQUARES) * square_mm
    poses: list[tuple[FloatArray, FloatArray]] = []
    attempts = 0
    while len(poses) < views:
        attempts += 1
        if attempts > 200 * views:
            raise RuntimeError(f"{cam.name}: cannot place {views} boards in view")
        fill = rng.uniform(0.5, 0.8)  # board width as a fraction of the image width
        # Target 0 / 1 puts the board against the left / right (top / bottom) border.
        tx, ty = np.clip(np.array(targets[len(poses) % len(targets)]) + rng.normal(0, 0.05, 2), 0, 1)
        pixel = np.array([w * (fill / 2 + tx * (1 - fill)), h * (fill / 2 + ty * (1 - fill))])
        overhang = partial and len(poses) % 2 == 1
        if overhang:
            # Board centre near a random point of the image border.
            angle = rng.uniform(0, 2 * np.pi)
            edge = np.array([np.cos(angle), np.sin(angle)]) / np.abs([np.cos(angle), np.sin(angle)]).max()
            pixel = np.array([w, h]) * (0.5 + 0.5 * OVERHANG_REACH * edge)
        ray = cv2.undistortPoints(pixel.reshape(1, 1, 2), cam.K, cam.dist).reshape(2)
        direction = np.append(ray, 1.0)
        distance = cam.K[0, 0] * board_width / (fill * w)
        tilt_axis = np.append(rng.normal(size=2), 0.0)
        tilt = _rotation(tilt_axis / np.linalg.norm(tilt_axis), np.radians(rng.uniform(20, 45)))
        spin = _rotation(np.array([0.0, 0.0, 1.0]), np.radians(rng.uniform(-30, 30)))
        R = tilt @ facing @ spin
        t = distance * direction / np.linalg.norm(direction) - R @ centre_b
        if partial:
            # A ChArUco board need not be whole (a large one often is not); an overhanging one must not be.
            seen = _visible_fraction(cam, R, t, cols, rows, square_mm)
            ok = MIN_VISIBLE_FRACTION <= seen and not (overhang and seen == 1.0)
        else:
            ok = _fully_visible(cam, R, t, outline)
        if ok:
            poses.append((R, t))
    return poses


def _shared_poses(
    cams: list[SynthCamera],
    subset: tuple[int, ...],
    rng: np.random.Generator,
    count: int,
    cols: int,
    rows: int,
    square_mm: float,
    *,
    partial: bool = False,
) -> list[tuple[FloatArray, FloatArray]]:
    """Board poses (world from board) fully seen by every camera in ``subset`` at once.

    The board floats between the workspace centre and those cameras, facing them.
    With ``partial`` (ChArUco) each camera need only see MIN_VISIBLE_FRACTION of its corners.
    """
    outline = _board_outline(cols, rows, square_mm)
    centre_b = np.array([(cols - 1) / 2, (rows - 1) / 2, 0.0]) * square_mm
    towards = np.mean([c.center - WORKSPACE_CENTER_MM for c in (cams[i] for i in subset)], axis=0)
    towards = towards / np.linalg.norm(towards)
    poses: list[tuple[FloatArray, FloatArray]] = []
    attempts = 0
    while len(poses) < count:
        attempts += 1
        if attempts > 2000 * count:
            raise RuntimeError(f"cannot place a board seen by cameras {subset}")
        centre = WORKSPACE_CENTER_MM + towards * rng.uniform(150, 300) + rng.normal(0, 30, 3)
        # Facing the bisector of the directions to the cameras: equally oblique to each.
        to_cams = [cams[i].center - centre for i in subset]
        normal = np.sum([d / np.linalg.norm(d) for d in to_cams], axis=0) + rng.normal(0, 0.1, 3)
        z = normal / np.linalg.norm(normal)
        x = np.cross(rng.normal(size=3), z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z], axis=1)
        t = centre - R @ centre_b
        in_cams = [(cams[i], cams[i].R @ R, cams[i].R @ t + cams[i].t) for i in subset]
        if partial:
            seen = all(
                _visible_fraction(c, Rc, tc, cols, rows, square_mm) >= MIN_VISIBLE_FRACTION
                for c, Rc, tc in in_cams
            )
        else:
            seen = all(_fully_visible(c, Rc, tc, outline) for c, Rc, tc in in_cams)
        if seen:
            poses.append((R, t))
    return poses
