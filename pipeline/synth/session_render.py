"""Render a synthetic session directory: the videos, calibration, settings, ground truth.

The directory is in the project's input format (see CONTRACT.md) plus
``ground_truth.npz``. Frames are rendered in parallel over contiguous frame
chunks; the parent writes them in order to one mp4v video per camera.
"""

from __future__ import annotations

import dataclasses
import errno
import io
import logging
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import tomli_w
from joblib import Parallel, delayed
from numpy.typing import NDArray
from tqdm import tqdm

from ..errors import Interrupted, PipelineError
from ..session.video import video_fingerprint
from .calib_error import MAX_ERROR_DEG, perturbed_rig
from .distractor import paint_distractor, place_distractor
from .images import background_texture, flicker_gains, render_frame, threshold_for
from .names import IMAGE_SIZES, PROFILES, RANDOM_SHAPE, SHAPES, TIPS
from .out_dir import check_out_dir, left_behind, unfinished, write_advice, write_image
from .poses import out_of_view, outside_box, self_contact
from .radius_profiles import Disks, RadiusProfile, disks_of, radius_along
from .random_shapes import draw_shape, shape_at
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


def check_poses(
    centerlines_mm: NDArray[np.float64],
    radius_mm: float | NDArray[np.float64],
    cameras: list[SynthCamera],
    *,
    tip: str = "flat",
    disks: Disks | None = None,
) -> None:
    """Raise PipelineError unless every frame's tube lies inside the workspace cube and
    inside every camera's image, and never runs into itself.

    centerlines_mm : (F, N, 3) float64, world frame; radius_mm : one radius or (N,) per point.
    """
    lo, hi = WORKSPACE_ORIGIN_MM, WORKSPACE_ORIGIN_MM + WORKSPACE_SIZE_MM
    outside = outside_box(centerlines_mm, radius_mm, lo, hi, tip=tip, disks=disks)
    if outside.any():
        raise PipelineError(
            f"synthetic frame {int(np.argmax(outside))}: the tube leaves the "
            f"{WORKSPACE_SIZE_MM[0]:.0f} mm workspace; use a shorter length or a smaller radius"
        )
    # Self-contact: points more than 4 radii apart along the tube (farther than any of
    # our bends can bring back within a diameter) must stay a diameter apart.
    widest = max(float(np.max(radius_mm)), 0.0 if disks is None else disks.radius_mm)
    touching = self_contact(centerlines_mm, min_gap_mm=2.0 * widest, min_arc_mm=4.0 * widest)
    if touching.any():
        raise PipelineError(
            f"synthetic frame {int(np.argmax(touching))}: the tube runs into itself; use a smaller radius"
        )
    for cam in cameras:
        off = out_of_view(centerlines_mm, radius_mm, cam, tip=tip, disks=disks)
        if off.any():
            raise PipelineError(
                f"synthetic frame {int(np.argmax(off))}: the tube leaves the image of camera {cam.name}"
            )


# The thinnest tube rendered (mm): thinner ones need voxels too fine for the workspace's
# grid (the session.toml written has voxels of at most the tube's radius).
MIN_RADIUS_MM = 0.5
# A tube narrower than this in every view is more than process can find: `synth --radius-mm 1
# --frames 10` (0.7-1.2 px wide at 320x240; 2026-12-05) had 8 frames of 10 empty at 1 mm
# voxels, and 10 ok but 35 mm off with min_area_px 4; `--radius-mm 1.5` (1.1-1.8 px) came
# within 0.11 mm on all of 30 frames at 1.5 mm voxels. synth warns of such a render.
MIN_WIDTH_PX = 1.5


def width_px(cameras: Sequence[SynthCamera], centerlines_mm: NDArray[np.float64], radius_mm: float) -> float:
    """How wide (px) a tube of ``radius_mm`` looks at the middle of its (F, N, 3) mm
    centrelines, in the camera that sees it widest."""
    centre = centerlines_mm.reshape(-1, 3).mean(axis=0)
    return max(2.0 * radius_mm * float(cam.K[0, 0]) / float((cam.R @ centre + cam.t)[2]) for cam in cameras)


def session_document(*, polarity: str, radius_mm: float) -> dict[str, Any]:
    """session.toml suited to the render: the workspace's defaults, with voxels of at most
    the tube's radius (the size a thin tube's silhouette needs, docs/troubleshooting.md),
    and a threshold between the tube's and the background's grey levels."""
    return {
        "workspace": {
            "origin_mm": WORKSPACE_ORIGIN_MM.tolist(),
            "size_mm": WORKSPACE_SIZE_MM.tolist(),
            "voxel_mm": min(VOXEL_MM, float(radius_mm)),
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


@dataclass(frozen=True)
class Look:
    """What a frame's images need besides the pose, fixed for a session.

    radii_mm : (N,) radius at each centreline point; tip, disks : see :class:`Tube`;
    backgrounds : per camera (H, W) grey levels (polarity "dark"); gains : (F,) flicker.
    """

    radii_mm: NDArray[np.float64] | float
    tip: str
    disks: Disks | None
    backgrounds: list[NDArray[np.float64]]
    polarity: str
    seed: int
    gains: NDArray[np.float64]


def _render_chunk(
    cameras: list[SynthCamera], centerlines_mm: NDArray[np.float64], look: Look, first_frame: int
) -> NDArray[np.uint8]:
    """Frames ``first_frame ...`` of every camera: (n, C, H, W) uint8."""
    return np.stack(
        [
            np.stack(
                render_frame(
                    cameras,
                    line,
                    look.radii_mm,
                    look.backgrounds,
                    polarity=look.polarity,
                    seed=look.seed,
                    frame_index=first_frame + i,
                    tip=look.tip,
                    disks=look.disks,
                    gain=float(look.gains[first_frame + i]),
                )
            )
            for i, line in enumerate(centerlines_mm)
        ]
    )


@dataclass(frozen=True)
class SceneOptions:
    """The tube and scene options beyond the named shapes' originals (defaults: as the originals).

    tip : "flat" or "round"; profile : a name from PROFILES or a full RadiusProfile (its
    radius is replaced by ``radius_mm``); cameras : 3 or 2; size : (width, height) px;
    distractor : a dark blob in one view's background; flicker : per-frame brightness;
    calib_error_deg : the error of the calibration.toml written (see
    :mod:`pipeline.synth.calib_error`; the videos are filmed with the true cameras,
    which ground_truth.npz keeps); bumped_camera : the index of the one camera off by it
    (turned about its centre), or None for every camera off.
    """

    tip: str = "flat"
    profile: str | RadiusProfile = "uniform"
    cameras: int = 3
    size: tuple[int, int] = (320, 240)
    distractor: bool = False
    flicker: bool = False
    calib_error_deg: float = 0.0
    bumped_camera: int | None = None


def _validate(
    shape: str,
    frames: int,
    seed: int,
    polarity: str,
    radius_mm: float,
    arrangement: str,
    length_mm: float,
    options: SceneOptions,
) -> None:
    if shape not in (*SHAPES, RANDOM_SHAPE):
        names = ", ".join((*SHAPES, RANDOM_SHAPE))
        raise PipelineError(f"unknown synthetic shape {shape!r}; use one of {names}")
    if not 1 <= frames <= MAX_FRAMES:
        raise PipelineError(f"--frames must be in [1, {MAX_FRAMES}] (an hour at 30 fps), got {frames}")
    if seed < 0:
        raise PipelineError(f"--seed must be 0 or more, got {seed}")
    if polarity not in ("dark", "bright"):
        raise PipelineError(f"polarity must be 'dark' or 'bright', got {polarity!r}")
    if not MIN_RADIUS_MM <= radius_mm <= 20:
        raise PipelineError(f"radius_mm must be in {MIN_RADIUS_MM:g}-20 mm, got {radius_mm}")
    if arrangement not in ARRANGEMENTS:
        raise PipelineError(f"unknown arrangement {arrangement!r}; use one of {', '.join(ARRANGEMENTS)}")
    if not 50 <= length_mm <= 250:
        raise PipelineError(f"length_mm must be in [50, 250] mm to fit the workspace, got {length_mm}")
    if options.tip not in TIPS:
        raise PipelineError(f"unknown tip {options.tip!r}; use one of {', '.join(TIPS)}")
    kind = options.profile if isinstance(options.profile, str) else options.profile.kind
    if kind not in PROFILES:
        raise PipelineError(f"unknown radius profile {kind!r}; use one of {', '.join(PROFILES)}")
    if options.cameras not in (2, 3):
        raise PipelineError(f"a synthetic rig has 2 or 3 cameras, got {options.cameras}")
    if tuple(options.size) not in IMAGE_SIZES:
        sizes = ", ".join(f"{w}x{h}" for w, h in IMAGE_SIZES)
        raise PipelineError(f"image size must be one of {sizes}, got {options.size[0]}x{options.size[1]}")
    if not 0.0 <= options.calib_error_deg <= MAX_ERROR_DEG:
        raise PipelineError(
            f"--calib-error must be in [0, {MAX_ERROR_DEG:g}] degrees, got {options.calib_error_deg}"
        )
    if options.bumped_camera is not None:
        if not options.calib_error_deg:
            raise PipelineError("--bumped-camera needs --calib-error DEG: how far that camera is turned")
        if not 0 <= options.bumped_camera < options.cameras:
            last, got = options.cameras - 1, options.bumped_camera
            raise PipelineError(f"--bumped-camera must be a camera's index, 0-{last}, got {got}")


# The longest session rendered: an hour at 30 fps (its ground truth alone is ~1 GB).
MAX_FRAMES = 108_000
# The session's ground truth, written by this module alone: the mark of a folder it rendered into.
TRUTH_FILE = "ground_truth.npz"


def _remove_earlier_views(out_dir: Path, names: set[str]) -> None:
    """An earlier render's videos and backgrounds of cameras this rig has not (a render of
    three cameras replaced by one of two): left there, they would be taken for the rig's.
    ``out_dir`` holds no other files (see check_out_dir)."""
    if (out_dir / TRUTH_FILE).is_file():
        log.info("%s: replacing the synthetic session rendered there before", out_dir)
    for path in [*out_dir.glob("*.mp4"), *(out_dir / "background").glob("*.png")]:
        if path.stem not in names:
            path.unlink()


def _profile(options: SceneOptions, radius_mm: float) -> RadiusProfile:
    if isinstance(options.profile, RadiusProfile):
        return dataclasses.replace(options.profile, radius_mm=radius_mm)
    return RadiusProfile(options.profile, radius_mm)


def session_centerlines(
    shape: str, frames: int, *, seed: int, length_mm: float, profile: RadiusProfile, tip: str
) -> tuple[NDArray[np.float64], float]:
    """The ground-truth centrelines (F, CENTERLINE_POINTS, 3) mm of a session and the
    backbone's length (mm): a named shape's (``length_mm`` long), or for RANDOM_SHAPE the
    random shape drawn from ``seed`` (with its own length)."""
    if shape != RANDOM_SHAPE:
        lines = shape_centerlines(
            shape, frames, base_mm=BASE_MM, length_mm=length_mm, points=CENTERLINE_POINTS
        )
        return lines, length_mm
    drawn = draw_shape(
        seed,
        profile=profile,
        tip=tip,
        base_mm=BASE_MM,
        box_lo_mm=WORKSPACE_ORIGIN_MM,
        box_hi_mm=WORKSPACE_ORIGIN_MM + WORKSPACE_SIZE_MM,
        points=CENTERLINE_POINTS,
    )
    frame_t = np.arange(frames, dtype=np.float64)
    return shape_at(drawn, frame_t, base_mm=BASE_MM, points=CENTERLINE_POINTS), drawn.length_mm


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
    options: SceneOptions = SceneOptions(),
    progress: bool = True,
    jobs: int = -1,
) -> None:
    """Render a synthetic session with its ground truth into ``out_dir``.

    Writes calibration.toml, cam0.mp4 .. (30 fps, mp4v), session.toml,
    background/<cam>.png and ground_truth.npz (see docs/input.md). The same arguments
    give byte-identical ground truth and identical frames.

    Parameters
    ----------
    out_dir : the session directory to write: created, or empty, or an earlier render
        (whose files are replaced); PipelineError for a folder of other files.
    shape : one of pipeline.synth.names.SHAPES, or RANDOM_SHAPE (drawn from ``seed``).
    frames : number of frames (30 fps).
    seed : background textures, sensor noise, and for the random shape, the shape.
    polarity : "dark" tube on a light scene, or "bright" (the negative).
    radius_mm : the tube's nominal radius (at the base); length_mm : the named shapes' length.
    arrangement : camera placement, "oblique" or "ninety" (see pipeline.synth.rig).
    options : tube end, radius profile, camera count, image size, distractor, flicker.
    progress : show a progress bar.
    jobs : worker processes (-1: one per core).
    """
    _validate(shape, frames, seed, polarity, radius_mm, arrangement, length_mm, options)
    out_dir = Path(out_dir)
    # Into a new or empty directory, or over an earlier render: never a folder of the user's own files.
    check_out_dir(
        out_dir, command="synth", contents="the session", marker=TRUTH_FILE, kind="a synthetic session"
    )
    cameras = make_rig(arrangement, size=options.size, cameras=options.cameras)
    profile = _profile(options, radius_mm)
    centerlines, length = session_centerlines(
        shape, frames, seed=seed, length_mm=length_mm, profile=profile, tip=options.tip
    )
    radii = radius_along(profile, np.linspace(0.0, length, CENTERLINE_POINTS))
    disks = disks_of(profile, length)
    check_poses(centerlines, radii, cameras, tip=options.tip, disks=disks)
    wide_px = width_px(cameras, centerlines, float(radii.min()))
    if wide_px < MIN_WIDTH_PX:
        log.warning(
            "a tube of radius %g mm is about %.1f px wide at its narrowest in these %dx%d images: too "
            "thin for process to find (it needs %g px or more); render it at --size 1280x960, or thicker",
            float(radii.min()),
            wide_px,
            cameras[0].width,
            cameras[0].height,
            MIN_WIDTH_PX,
        )

    created = not out_dir.exists()
    incomplete = f"the session in {out_dir} is incomplete: render it again"
    try:
        try:
            (out_dir / "background").mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            what = "write in" if out_dir.is_dir() else "create"
            raise PipelineError(
                f"{out_dir}: cannot {what} the session directory ({exc.strerror}); "
                "give a folder you can write to"
            ) from None
        with unfinished(out_dir):
            _remove_earlier_views(out_dir, {cam.name for cam in cameras})
            if options.calib_error_deg:
                bumped = options.bumped_camera
                given = perturbed_rig(cameras, options.calib_error_deg, seed=seed, bumped=bumped)
                which = "" if bumped is None else f", {cameras[bumped].name} alone turned"
                source = (
                    f"pipeline synth (true cameras with a {options.calib_error_deg:g} deg calibration "
                    f"error{which})"
                )
            else:
                given, source = cameras, "pipeline synth (true cameras)"
            (out_dir / "calibration.toml").write_bytes(
                tomli_w.dumps(
                    calibration_document(given, metadata={"source": source, "arrangement": arrangement})
                ).encode()
            )
            (out_dir / "session.toml").write_bytes(
                tomli_w.dumps(session_document(polarity=polarity, radius_mm=radius_mm)).encode()
            )
            backgrounds = [
                background_texture(cam.width, cam.height, seed=seed, camera_index=i)
                for i, cam in enumerate(cameras)
            ]
            blob = None
            if options.distractor:
                widest = max(float(radii.max()), 0.0 if disks is None else disks.radius_mm)
                blob = place_distractor(cameras, centerlines, widest, seed=seed)
                backgrounds[blob.camera_index] = paint_distractor(backgrounds[blob.camera_index], blob)
            for cam, bg in zip(cameras, backgrounds, strict=True):
                grey = 255.0 - bg if polarity == "bright" else bg
                path = out_dir / "background" / f"{cam.name}.png"
                write_image(path, np.rint(grey).astype(np.uint8))
            gains = flicker_gains(seed, frames) if options.flicker else np.ones(frames)
            truth = {
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
                "tip": np.str_(options.tip),
                "profile": np.str_(profile.kind),
                "radius_profile_mm": np.broadcast_to(radii, (frames, CENTERLINE_POINTS)),
                "length_mm": np.float64(length),
                "disk_arc_mm": np.zeros(0) if disks is None else disks.arc_mm,
                "disk_radius_mm": np.float64(0.0 if disks is None else disks.radius_mm),
                "disk_thickness_mm": np.float64(0.0 if disks is None else disks.thickness_mm),
                "distractor_camera": np.int64(-1 if blob is None else blob.camera_index),
                "flicker_gain": gains,
                "calib_error_deg": np.float64(options.calib_error_deg),
                "bumped_camera": np.int64(-1 if options.bumped_camera is None else options.bumped_camera),
            }
            write_npz_deterministic(out_dir / TRUTH_FILE, truth)  # first: the folder's mark
            # A uniform tube is drawn at its plain radius (the profile's values are that radius).
            uniform = profile.kind == "uniform"
            look = Look(
                radius_mm if uniform else radii, options.tip, disks, backgrounds, polarity, seed, gains
            )
            _write_videos(out_dir, cameras, centerlines, look, progress, jobs)
            # Which videos this truth is of, wherever the file is copied: evaluate compares
            # them with those a recording was made from.
            truth["video_fingerprints"] = np.array(
                [f"{cam.name}.mp4={video_fingerprint(out_dir / f'{cam.name}.mp4')}" for cam in cameras]
            )
            write_npz_deterministic(out_dir / TRUTH_FILE, truth)
        log.info(
            "wrote synthetic session %s (%s, %d frame%s)", out_dir, shape, frames, "" if frames == 1 else "s"
        )
    except OSError as exc:
        # A full disk or a folder that turned read-only: a render into a new folder leaves
        # nothing; one over an earlier render leaves it incomplete (unchanged where the
        # folder took no file), and says so.
        raise PipelineError(
            f"{out_dir}: cannot write the session ({exc.strerror or exc}); "
            f"{left_behind(out_dir, created, incomplete)}; {write_advice(exc)}"
        ) from None
    except KeyboardInterrupt:
        raise Interrupted(f"interrupted; {left_behind(out_dir, created, incomplete)}") from None


def _write_videos(
    out_dir: Path,
    cameras: list[SynthCamera],
    centerlines: NDArray[np.float64],
    look: Look,
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
    # holds ~30 frames x 3 cameras (7 MB at 320x240).
    chunk = 30 if n_jobs != 1 else frames
    starts = range(0, frames, chunk)
    tasks = (delayed(_render_chunk)(cameras, centerlines[s : s + chunk], look, s) for s in starts)
    try:
        with tqdm(total=frames, unit="frame", desc="rendering", disable=not progress) as bar:
            if n_jobs == 1:
                # One frame at a time, so the bar moves even without workers.
                results: Any = (
                    _render_chunk(cameras, centerlines[f : f + 1], look, f) for f in range(frames)
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
    # OpenCV's writer says nothing when the disk fills: a video cut short is found by reading it.
    for cam in cameras:
        path = out_dir / f"{cam.name}.mp4"
        capture = cv2.VideoCapture(str(path))
        written = int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) if capture.isOpened() else 0
        capture.release()
        if written != frames:
            raise OSError(errno.EIO, f"{path.name} holds {written} of its {frames} frames (a full disk?)")
