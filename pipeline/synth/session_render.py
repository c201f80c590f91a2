"""Render a synthetic session directory: three videos, calibration, settings, ground truth.

The directory is in the project's input format (see CONTRACT.md) plus
``ground_truth.npz``. Frames are rendered in parallel over contiguous frame
chunks; the parent writes them in order to one mp4v video per camera.
"""

from __future__ import annotations

import io
import logging
import zipfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import tomli_w
from joblib import Parallel, delayed
from numpy.typing import NDArray
from tqdm import tqdm

from ..errors import PipelineError
from ..synth_names import SHAPES
from .images import background_texture, render_frame, threshold_for
from .raycast import project_points
from .rig import ARRANGEMENTS, SynthCamera, calibration_document, make_rig
from .shapes import shape_centerlines

log = logging.getLogger(__name__)

FPS = 30.0
BASE_MM = np.array([128.0, 128.0, 0.0])
WORKSPACE_ORIGIN_MM = np.zeros(3)
WORKSPACE_SIZE_MM = np.full(3, 256.0)
VOXEL_MM = 2.0
CENTERLINE_POINTS = 200
# Below this many frames a process pool costs more than it saves.
MIN_PARALLEL_FRAMES = 60


def _unit_tangents(centerlines_mm: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit tangents of polylines, (..., N, 3) -> (..., N, 3); second-order at the ends."""
    tangent = np.gradient(centerlines_mm, axis=-2, edge_order=2)
    return tangent / np.linalg.norm(tangent, axis=-1, keepdims=True)


def tube_surface_points(
    centerlines_mm: NDArray[np.float64], radius_mm: float, *, ring: int = 16
) -> NDArray[np.float64]:
    """Points on the rims of the tube's cross-section discs (perpendicular to the tangent).

    centerlines_mm : (..., N, 3) float64 -> (..., N * ring, 3) float64 mm.
    """
    tangent = _unit_tangents(centerlines_mm)
    helper = np.where(np.abs(tangent[..., 2:3]) < 0.9, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    n1 = np.cross(tangent, helper)
    n1 /= np.linalg.norm(n1, axis=-1, keepdims=True)
    n2 = np.cross(tangent, n1)
    a = np.linspace(0.0, 2.0 * np.pi, ring, endpoint=False)[:, None]
    offsets = np.cos(a) * n1[..., None, :] + np.sin(a) * n2[..., None, :]  # (..., N, ring, 3)
    points = centerlines_mm[..., None, :] + radius_mm * offsets
    return points.reshape(*centerlines_mm.shape[:-2], -1, 3)


def check_poses(centerlines_mm: NDArray[np.float64], radius_mm: float, cameras: list[SynthCamera]) -> None:
    """Raise PipelineError unless every frame's tube lies inside the workspace cube and
    inside every camera's image, and never runs into itself.

    centerlines_mm : (F, N, 3) float64, world frame.
    """
    # A disc of radius r perpendicular to the unit tangent T reaches r * sqrt(1 - T_i^2)
    # along axis i; the discs (with the flat caps) sweep the whole tube, so this bound is exact.
    reach = radius_mm * np.sqrt(np.clip(1.0 - _unit_tangents(centerlines_mm) ** 2, 0.0, None))
    lo, hi = WORKSPACE_ORIGIN_MM, WORKSPACE_ORIGIN_MM + WORKSPACE_SIZE_MM
    # 1e-3 mm: the base disc lies exactly on the floor z = 0, and finite-difference
    # tangents tilt it by ~(kappa h)^2, far below 1e-3 mm at its rim.
    outside = np.any((centerlines_mm - reach < lo - 1e-3) | (centerlines_mm + reach > hi + 1e-3), axis=(1, 2))
    if outside.any():
        raise PipelineError(
            f"synthetic frame {int(np.argmax(outside))}: the tube leaves the "
            f"{WORKSPACE_SIZE_MM[0]:.0f} mm workspace; use a shorter length or a smaller radius"
        )
    # Self-contact: points more than 4 radii apart along the tube (farther than any of
    # our bends can bring back within a diameter) must stay a diameter apart.
    sub = centerlines_mm[:, ::4]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(sub[0], axis=0), axis=1))])
    apart = np.abs(arc[:, None] - arc[None]) > 4.0 * radius_mm
    gaps = np.linalg.norm(sub[:, :, None] - sub[:, None], axis=-1)
    touching = np.any(apart & (gaps < 2.0 * radius_mm), axis=(1, 2))
    if touching.any():
        raise PipelineError(
            f"synthetic frame {int(np.argmax(touching))}: the tube runs into itself; use a smaller radius"
        )
    # In view: rims of every other disc (2.5 mm apart) at 12 points; the workspace
    # itself projects 30 px or more inside every image, so this sampling is ample.
    pts = tube_surface_points(centerlines_mm[:, ::2], radius_mm, ring=12)
    for cam in cameras:
        uv = project_points(cam, pts)
        off = np.any((uv < 0) | (uv > [cam.width - 1, cam.height - 1]), axis=(1, 2))
        if off.any():
            raise PipelineError(
                f"synthetic frame {int(np.argmax(off))}: the tube leaves the image of camera {cam.name}"
            )


def session_document(*, polarity: str, radius_mm: float) -> dict[str, Any]:
    """session.toml suited to the render: workspace defaults and a threshold between
    the tube's and the background's grey levels."""
    return {
        "workspace": {
            "origin_mm": WORKSPACE_ORIGIN_MM.tolist(),
            "size_mm": WORKSPACE_SIZE_MM.tolist(),
            "voxel_mm": VOXEL_MM,
        },
        "silhouette": {"method": "threshold", "threshold": threshold_for(polarity), "polarity": polarity},
        "manipulator": {"base_mm": BASE_MM.tolist(), "radius_mm": float(radius_mm)},
    }


def write_npz_deterministic(path: Path, arrays: dict[str, Any]) -> None:
    """Like numpy.savez, but with fixed zip timestamps so equal arrays give equal bytes."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, value in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(value), allow_pickle=False)
            zf.writestr(zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0)), buf.getvalue())


def _render_chunk(
    cameras: list[SynthCamera],
    centerlines_mm: NDArray[np.float64],
    radius_mm: float,
    backgrounds: list[NDArray[np.float64]],
    polarity: str,
    seed: int,
    first_frame: int,
) -> NDArray[np.uint8]:
    """Frames ``first_frame ...`` of every camera: (n, C, H, W) uint8."""
    return np.stack(
        [
            np.stack(
                render_frame(
                    cameras,
                    line,
                    radius_mm,
                    backgrounds,
                    polarity=polarity,
                    seed=seed,
                    frame_index=first_frame + i,
                )
            )
            for i, line in enumerate(centerlines_mm)
        ]
    )


def _validate(
    shape: str, frames: int, polarity: str, radius_mm: float, arrangement: str, length_mm: float
) -> None:
    if shape not in SHAPES:
        raise PipelineError(f"unknown synthetic shape {shape!r}; use one of {', '.join(SHAPES)}")
    if frames < 1:
        raise PipelineError(f"--frames must be at least 1, got {frames}")
    if polarity not in ("dark", "bright"):
        raise PipelineError(f"polarity must be 'dark' or 'bright', got {polarity!r}")
    if not 0 < radius_mm <= 20:
        raise PipelineError(f"radius_mm must be in (0, 20] mm, got {radius_mm}")
    if arrangement not in ARRANGEMENTS:
        raise PipelineError(f"unknown arrangement {arrangement!r}; use one of {', '.join(ARRANGEMENTS)}")
    if not 50 <= length_mm <= 250:
        raise PipelineError(f"length_mm must be in [50, 250] mm to fit the workspace, got {length_mm}")


def render_session(
    out_dir: Path,
    *,
    shape: str = "bend_rotate",
    frames: int = 900,
    seed: int = 0,
    polarity: str = "dark",
    radius_mm: float = 6.0,
    arrangement: str = "oblique",
    length_mm: float = 250.0,
    progress: bool = True,
    jobs: int = -1,
) -> None:
    """Render a synthetic three-camera session with its ground truth into ``out_dir``.

    Writes calibration.toml, cam0.mp4 .. cam2.mp4 (320x240, 30 fps, mp4v), session.toml,
    background/<cam>.png and ground_truth.npz (see the README). The same arguments
    give byte-identical ground truth and identical frames.

    Parameters
    ----------
    out_dir : the session directory to write (created; existing files are replaced).
    shape : one of pipeline.synth_names.SHAPES.
    frames : number of frames (30 fps).
    seed : background textures and sensor noise.
    polarity : "dark" tube on a light scene, or "bright" (the negative).
    radius_mm, length_mm : the tube.
    arrangement : camera placement, "oblique" or "ninety" (see pipeline.synth.rig).
    progress : show a progress bar.
    jobs : worker processes (-1: one per core).
    """
    _validate(shape, frames, polarity, radius_mm, arrangement, length_mm)
    out_dir = Path(out_dir)
    cameras = make_rig(arrangement)
    centerlines = shape_centerlines(
        shape, frames, base_mm=BASE_MM, length_mm=length_mm, points=CENTERLINE_POINTS
    )
    check_poses(centerlines, radius_mm, cameras)

    try:
        (out_dir / "background").mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PipelineError(f"{out_dir}: cannot create the session directory: {exc.strerror}") from None
    (out_dir / "calibration.toml").write_bytes(
        tomli_w.dumps(
            calibration_document(
                cameras, metadata={"source": "pipeline synth (true cameras)", "arrangement": arrangement}
            )
        ).encode()
    )
    (out_dir / "session.toml").write_bytes(
        tomli_w.dumps(session_document(polarity=polarity, radius_mm=radius_mm)).encode()
    )
    backgrounds = [
        background_texture(cam.width, cam.height, seed=seed, camera_index=i) for i, cam in enumerate(cameras)
    ]
    for cam, bg in zip(cameras, backgrounds, strict=True):
        grey = 255.0 - bg if polarity == "bright" else bg
        cv2.imwrite(str(out_dir / "background" / f"{cam.name}.png"), np.rint(grey).astype(np.uint8))
    write_npz_deterministic(
        out_dir / "ground_truth.npz",
        {
            "centerlines": centerlines,
            "timestamps_s": np.arange(frames) / FPS,
            "radius_mm": np.float64(radius_mm),
            "base_mm": BASE_MM,
            "shape": np.str_(shape),
            "fps": np.float64(FPS),
            "camera_names": np.array([c.name for c in cameras]),
            "K": np.stack([c.K for c in cameras]),
            "dist": np.stack([c.dist for c in cameras]),
            "R": np.stack([c.R for c in cameras]),
            "t": np.stack([c.t for c in cameras]),
            "image_size": np.array([cameras[0].width, cameras[0].height]),
        },
    )
    _write_videos(out_dir, cameras, centerlines, radius_mm, backgrounds, polarity, seed, progress, jobs)
    log.info("wrote synthetic session %s (%s, %d frames)", out_dir, shape, frames)


def _write_videos(
    out_dir: Path,
    cameras: list[SynthCamera],
    centerlines: NDArray[np.float64],
    radius_mm: float,
    backgrounds: list[NDArray[np.float64]],
    polarity: str,
    seed: int,
    progress: bool,
    jobs: int,
) -> None:
    frames = len(centerlines)
    fourcc = cv2.VideoWriter.fourcc(*"mp4v")
    writers = []
    for cam in cameras:
        path = out_dir / f"{cam.name}.mp4"
        writer = cv2.VideoWriter(str(path), fourcc, FPS, (cam.width, cam.height), True)
        if not writer.isOpened():
            raise PipelineError(f"{path}: OpenCV cannot write an mp4v video here")
        writers.append(writer)
    n_jobs = 1 if frames < MIN_PARALLEL_FRAMES else jobs
    # Small chunks keep the progress bar lively and the parent's memory low; each
    # holds ~30 frames x 3 cameras (7 MB).
    chunk = 30 if n_jobs != 1 else frames
    starts = range(0, frames, chunk)
    tasks = (
        delayed(_render_chunk)(cameras, centerlines[s : s + chunk], radius_mm, backgrounds, polarity, seed, s)
        for s in starts
    )
    try:
        with tqdm(total=frames, unit="frame", desc="rendering", disable=not progress) as bar:
            if n_jobs == 1:
                # One frame at a time, so the bar moves even without workers.
                results: Any = (
                    _render_chunk(cameras, centerlines[f : f + 1], radius_mm, backgrounds, polarity, seed, f)
                    for f in range(frames)
                )
            else:
                results = Parallel(n_jobs=n_jobs, return_as="generator")(tasks)
            for block in results:
                for views in block:
                    for writer, img in zip(writers, views, strict=True):
                        writer.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
                bar.update(len(block))
    finally:
        for writer in writers:
            writer.release()
