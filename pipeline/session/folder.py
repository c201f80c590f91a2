"""A session directory (VIDEO_DIR) -> a validated :class:`Session`.

Every mistake a user can make in a session directory is found here, before any
work starts, and raised as a :class:`~pipeline.errors.PipelineError` naming the
file or camera.
"""

from __future__ import annotations

import contextlib
import dataclasses
import filecmp
import glob
import logging
import math
import os
import unicodedata
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from ..errors import (
    CalibrationError,
    PipelineError,
    SessionError,
    SettingsError,
    VideoError,
    home_meant,
    refuse_unfinished_render,
)
from ..geometry.camera import Camera
from .calibration_io import read_calibration
from .grey_levels import grey_8bit
from .image_files import cut_short
from .settings import LAST_TIMESTAMP, SessionInfo, Settings, describe, load_settings
from .toml_file import require_regular_file
from .video import VIDEO_EXTENSIONS, VideoInfo, probe_video

log = logging.getLogger(__name__)

FPS_TOLERANCE = 1e-3
# Cameras started by hand stop a few frames apart: a video shorter than the longest by at
# most this many frames, or this fraction of the longest, is processed with a warning; a
# shorter one (a camera that stopped, a file cut short) is a problem the run ends with.
SHORT_VIDEO_FRAMES = 2
SHORT_VIDEO_FRACTION = 0.1
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
# SessionInfo's default, this very object, stands for "session.toml gives no start_time":
# one given as 1970-01-01 is a different object and is kept.
_NO_START_TIME = SessionInfo().start_time


@dataclass(frozen=True, eq=False)
class Session:
    """Everything needed to process one recording, validated.

    cameras[i], video_paths[i] and backgrounds[i] belong together.
    ``frame_count`` is the number of frames common to all videos.
    ``problems`` are what does not stop a run but ends it with exit status 1 (a video much
    shorter than the others), one line each, naming the file.
    """

    directory: Path
    name: str
    cameras: tuple[Camera, ...]
    video_paths: tuple[Path, ...]
    backgrounds: tuple[NDArray[np.uint8] | None, ...]
    settings: Settings
    fps: float
    frame_count: int
    frame_counts: tuple[int, ...]
    problems: tuple[str, ...] = ()

    def timestamp_ns(self, index: int) -> int:
        """Frame ``index``'s time: start_time + index / fps, in ns since the Unix epoch."""
        start = self.settings.session.start_time
        start_ns = (start - _EPOCH) // timedelta(microseconds=1) * 1000
        return start_ns + round(index * 1e9 / self.fps)


def load_session(directory: Path | str) -> Session:
    """Read and validate ``directory``: calibration.toml, one video per camera, session.toml."""
    with _readable(Path(directory), "session"):
        return _load_session(Path(directory))


def _load_session(directory: Path) -> Session:
    check_not_dangling(directory)
    check_utf8_path(directory, "rename the folder (or move the session) to a UTF-8 path")
    if directory.is_file():
        raise SessionError(f"{directory}: is a file; give the session directory that holds it")
    if directory.exists() and not directory.is_dir():
        raise SessionError(f"{directory}: is not a directory (a device or pipe); give the session directory")
    if not directory.is_dir():
        raise SessionError(f"{directory}: no such session directory{_where_looked(directory)}")
    if not any(directory.iterdir()):
        raise SessionError(f"{directory}: the session directory is empty")
    refuse_unfinished_render(directory, SessionError)
    for name in ("session.toml", "calibration.toml"):
        check_not_dangling(directory / name)
        _check_spelling(directory, name)
    settings = load_settings(directory / "session.toml")
    cameras = _rig_cameras(directory / "calibration.toml")
    videos = _find_videos(directory, [c.name for c in cameras])
    _check_distinct_videos(list(videos.values()))
    infos = [probe_video(videos[c.name]) for c in cameras]
    for cam, info in zip(cameras, infos, strict=True):
        if (info.width, info.height) != cam.size_px:
            read = f"the first of its {info.streams} video streams, the one read"
            first = f" ({read}: put the camera's stream first)" if info.streams > 1 else ""
            raise VideoError(
                f"{info.path}: frames are {info.width}x{info.height}{first} but calibration.toml gives "
                f"camera {cam.name!r} size {cam.size_px[0]}x{cam.size_px[1]}; "
                "use the calibration of this rig and resolution"
            )
    fps = _common_fps(infos)
    settings = _with_start_time(settings, infos)
    counts = tuple(i.frame_count for i in infos)
    problems = _short_videos(infos)
    if len(set(counts)) > 1 and not problems:
        log.warning(
            "videos differ in length (%s); processing the %d common frames",
            ", ".join(f"{c.name}: {n}" for c, n in zip(cameras, counts, strict=True)),
            min(counts),
        )
    backgrounds = _backgrounds(directory, cameras, settings)
    _check_workspace_visible(cameras, settings)
    _check_min_area(directory, cameras, settings)
    _check_last_timestamp(directory, settings, fps, min(counts))
    # Said once the session is known to be usable: a refused one gets its one error line.
    for info in infos:
        for note in info.notes:
            log.warning("%s", note)
    _note_rates_apart(infos, min(counts))
    if not (directory / "session.toml").exists():
        log.warning(
            "session.toml not found in %s: using the default settings (%s); write a session.toml "
            "if this rig differs",
            directory,
            describe(settings),
        )
    return Session(
        directory=directory,
        name=directory.resolve().name,
        cameras=tuple(cameras),
        # Absolute: a session loaded by a relative path is processed wherever the caller has
        # moved to since (a notebook's chdir), not looked for again from there.
        video_paths=tuple(videos[c.name].absolute() for c in cameras),
        backgrounds=backgrounds,
        settings=settings,
        fps=fps,
        frame_count=min(counts),
        frame_counts=counts,
        problems=tuple(problems),
    )


def _short_videos(infos: list[VideoInfo]) -> list[str]:
    """A line for each video whose frame count falls short of the longest by more than
    SHORT_VIDEO_FRAMES and SHORT_VIDEO_FRACTION of it: only the frames every video has are
    processed."""
    counts = [i.frame_count for i in infos]
    longest, common = max(counts), min(counts)
    allowed = max(SHORT_VIDEO_FRAMES, SHORT_VIDEO_FRACTION * longest)
    lines = []
    for i, (path, count) in enumerate((info.path, info.frame_count) for info in infos):
        if longest - count <= allowed:
            continue
        others = [n for j, n in enumerate(counts) if j != i]
        shown = f"{min(others)}" if min(others) == max(others) else f"{min(others)}-{max(others)}"
        first = "the first frame was" if common == 1 else f"the first {common} frames were"
        lines.append(
            f"{path} has {count} frame{'' if count == 1 else 's'}, the others {shown}: only "
            f"{first} processed; check the recording"
        )
    return lines


# A live rig's nominal frame rate, until its cameras say (the layout plays the ``frame``
# timeline at it; the summary gives each camera's measured rate).
LIVE_NOMINAL_FPS = 30.0


def load_rig(directory: Path | str) -> Session:
    """Read and validate a rig directory for ``pipeline live``: calibration.toml and
    session.toml (with its ``[live]`` sources), no videos.

    The session it returns has no videos and no frames; its ``fps`` is nominal
    (:data:`LIVE_NOMINAL_FPS`) and its name the directory's.
    """
    with _readable(Path(directory), "rig"):
        return _load_rig(Path(directory))


def _load_rig(directory: Path) -> Session:
    check_not_dangling(directory)
    check_utf8_path(directory, "rename the folder (or move the rig) to a UTF-8 path")
    if not directory.is_dir():
        raise SessionError(
            f"{directory}: no such rig directory; give the folder that holds calibration.toml "
            "and session.toml"
        )
    for name in ("session.toml", "calibration.toml"):
        check_not_dangling(directory / name)
        _check_spelling(directory, name)
    settings = load_settings(directory / "session.toml")
    cameras = _rig_cameras(directory / "calibration.toml")
    names = [c.name for c in cameras]
    for camera, _ in settings.live.sources:
        if camera not in names:
            raise SettingsError(
                f"{directory / 'session.toml'}: [live] names camera {camera!r}, which calibration.toml "
                f"does not have (cameras: {', '.join(names)}); fix the name or remove the line"
            )
    backgrounds = _backgrounds(directory, cameras, settings)
    _check_workspace_visible(cameras, settings)
    _check_min_area(directory, cameras, settings)
    return Session(
        directory=directory,
        name=directory.resolve().name,
        cameras=tuple(cameras),
        video_paths=(),
        backgrounds=backgrounds,
        settings=settings,
        fps=LIVE_NOMINAL_FPS,
        frame_count=0,
        frame_counts=(),
    )


def _with_start_time(settings: Settings, infos: list[VideoInfo]) -> Settings:
    """``settings`` whose start_time is session.toml's, else the earliest creation time
    the videos carry (the first camera to start recording), else the Unix epoch."""
    if settings.session.start_time is not _NO_START_TIME:
        return settings
    stamps = [i.creation_time for i in infos if i.creation_time is not None]
    if not stamps:
        return settings
    start = min(stamps)
    log.debug("session start %s: the videos' creation time", start.isoformat())
    return dataclasses.replace(settings, session=dataclasses.replace(settings.session, start_time=start))


def _where_looked(directory: Path) -> str:
    """Where a missing session ``directory`` was looked for, for its error message: a ``~``
    no shell expanded (zsh in ``make process VIDEO_DIR=~/s``, or quoted), or the folder a
    relative path is taken from (with ``make -C``, the repository's, not the caller's)."""
    meant = home_meant(directory)
    if meant is not None:
        return f" (~ is not expanded here: give {meant})"
    if not directory.is_absolute():
        try:
            return f" (looked for it in {Path.cwd()})"
        except OSError:  # the current directory was removed
            return ""
    return ""


def _rig_cameras(path: Path) -> list[Camera]:
    """The cameras of calibration.toml at ``path``: two or more, since a tube's shape is
    where the views' silhouettes meet (one view leaves its depth unknown)."""
    cameras = read_calibration(path)
    if len(cameras) < 2:
        raise CalibrationError(
            f"{path}: holds {len(cameras)} camera; a session needs two or more cameras (three "
            "are better), each with a table here and a video"
        )
    return cameras


def _find_videos(directory: Path, names: list[str]) -> dict[str, Path]:
    """Each camera's video in ``directory``: the file whose stem is the camera's name (the
    two compared in Unicode's composed form: a file copied from macOS may spell an accented
    name decomposed) and whose suffix is one of ``VIDEO_EXTENSIONS``."""
    by_spelling = {_composed(name): name for name in names}
    found: dict[str, Path] = {}
    for path in sorted(directory.iterdir()):
        name = by_spelling.get(_composed(path.stem))
        if path.name.startswith(".") and name is None:
            continue  # hidden: a file manager's own (macOS's ._cam0.mp4), not a camera's video
        if path.suffix.lower() in VIDEO_EXTENSIONS:
            check_not_dangling(path)
        if not path.is_file() or path.suffix.lower() not in VIDEO_EXTENSIONS:
            continue
        if name is None:
            raise SessionError(
                f"{path}: no camera named {path.stem!r} in calibration.toml "
                f"(cameras: {', '.join(names)}); rename the video or add its calibration"
            )
        if name in found:
            raise SessionError(
                f"{directory}: two videos for camera {name!r} ({found[name].name}, {path.name}); keep one"
            )
        found[name] = path
    kinds = ", ".join(VIDEO_EXTENSIONS)
    for name in names:
        if name in found:
            continue
        same_stem = [p for p in sorted(directory.iterdir()) if _composed(p.stem) == _composed(name)]
        for path in same_stem:
            if path.suffix.lower() in VIDEO_EXTENSIONS:  # there, but a folder, pipe or device
                raise SessionError(
                    f"{path}: is not a regular file; put the video file of camera {name!r} there"
                )
        for path in same_stem:
            if path.is_file():
                raise SessionError(
                    f"{path}: is not read as the video of camera {name!r}: a video's name ends in one of "
                    f"{kinds}; re-export it as .mp4 or .mkv, or rename it if it is one of those kinds"
                )
        raise SessionError(
            f"{directory}: camera {name!r} in calibration.toml has no video ({name} + one of {kinds})"
        )
    return found


def _composed(text: str) -> str:
    """``text`` in Unicode's composed form (NFC)."""
    return unicodedata.normalize("NFC", text)


def _check_distinct_videos(paths: list[Path]) -> None:
    """Two cameras' videos with the same bytes are one camera's video copied: its silhouette
    in two views whose cones do not meet there."""
    by_size: dict[int, list[Path]] = {}
    for path in paths:
        by_size.setdefault(path.stat().st_size, []).append(path)
    for same_size in by_size.values():
        if len(same_size) < 2:
            continue
        # Compared byte by byte, stopping at the first block that differs: two cameras'
        # videos of one size (a fixed-size codec, a triggered rig) part within kilobytes.
        for i, path in enumerate(same_size):
            for earlier in same_size[:i]:
                if filecmp.cmp(earlier, path, shallow=False):
                    raise SessionError(
                        f"{path}: is the same file as {earlier.name}, byte for byte: one camera's "
                        "video copied under the other's name, or two cameras that filmed one grey "
                        "level alone (covered lenses, lights off); put each camera's own video there"
                    )


def _common_fps(infos: list[VideoInfo]) -> float:
    fps = infos[0].fps
    for info in infos[1:]:
        if not math.isclose(info.fps, fps, rel_tol=FPS_TOLERANCE):
            if infos[0].variable_rate or info.variable_rate:  # an average rate is no camera's rate
                odd, other = (infos[0], info) if infos[0].variable_rate else (info, infos[0])
                raise VideoError(
                    f"{odd.path}: has a variable frame rate ({odd.variable_rate}; {odd.fps:.1f} fps "
                    f"on average, against {other.fps:g} fps of {other.path.name}); re-export it at a "
                    "constant rate"
                )
            raise VideoError(
                f"{info.path}: {info.fps:g} fps but {infos[0].path.name} has {fps:g} fps; "
                "record all cameras at the same rate"
            )
    return fps


def _note_rates_apart(infos: list[VideoInfo], frames: int) -> None:
    """Say where the videos' rates, within ``FPS_TOLERANCE`` of one another (29.97 and 30
    fps), part their frames by half a frame or more over the ``frames`` processed: frame i
    of every video is taken as one instant, and cameras that truly ran at those rates drift
    apart (3.6 s an hour at 29.97 and 30); cameras on one clock only label it differently."""
    slowest, fastest = min(infos, key=lambda i: i.fps), max(infos, key=lambda i: i.fps)
    apart = frames * (fastest.fps - slowest.fps) / fastest.fps
    if apart >= 0.5:
        log.warning(
            "%s runs at %g fps and %s at %g fps: frame i of each is taken as one instant, and "
            "by the last frame they are %.1f frames apart if the cameras ran at those rates; "
            "re-time the videos to one rate if so",
            slowest.path,
            slowest.fps,
            fastest.path.name,
            fastest.fps,
            apart,
        )


def _backgrounds(
    directory: Path, cameras: list[Camera], settings: Settings
) -> tuple[NDArray[np.uint8] | None, ...]:
    """Per camera its background image (None: none), all of them for method "background";
    none are read for another method (which has no use for them: a damaged one, or one of
    the cameras' former size, does not stop the run)."""
    if settings.silhouette.method != "background":
        return tuple(None for _ in cameras)
    backgrounds = tuple(_background(directory, cam) for cam in cameras)
    missing = [c.name for c, b in zip(cameras, backgrounds, strict=True) if b is None]
    if missing:
        name = missing[0]
        # An image of another kind under the camera's name: said, with what to do.
        others = sorted(p.name for p in (directory / "background").glob(f"{glob.escape(name)}.*"))
        found = f"; background/{others[0]} is there: save it as a PNG" if others else ""
        raise SessionError(
            f"{directory / 'background'}: silhouette method 'background' needs "
            f"background/{name}.png (missing for camera {name!r}{found})"
        )
    return backgrounds


def _background(directory: Path, cam: Camera) -> NDArray[np.uint8] | None:
    path = directory / "background" / f"{cam.name}.png"
    check_not_dangling(path)
    if not path.exists():
        return None
    image = _read_grey_8bit(path)
    if (image.shape[1], image.shape[0]) != cam.size_px:
        raise SessionError(
            f"{path}: is {image.shape[1]}x{image.shape[0]} but camera {cam.name!r} is "
            f"{cam.size_px[0]}x{cam.size_px[1]}; save the background at the camera's size"
        )
    return np.ascontiguousarray(image, dtype=np.uint8)


def _read_grey_8bit(path: Path) -> NDArray[np.uint8]:
    """The image at ``path`` as (H, W) uint8 grey levels, the videos' depth.

    A 16-bit image's levels are scaled from the depth they are stored at
    (:func:`~pipeline.session.grey_levels.grey_8bit`): 8-bit values saved in 16 bits
    (as some tools save them) are not scaled down to black, where every pixel would
    differ from the frames and be silhouette.
    """
    try:
        require_regular_file(path)
    except OSError:
        raise SessionError(
            f"{path}: is not a regular file; save the image as an 8-bit greyscale PNG"
        ) from None
    data = path.read_bytes()  # a PermissionError is named by the caller
    if cut_short(data, path.suffix):
        raise SessionError(
            f"{path}: the image is cut short ({len(data)} bytes, copied half-way?); save it again as "
            "an 8-bit greyscale PNG"
        )
    # One decode, to grey at the depth stored (as a calibration's board images are read).
    flags = cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH | cv2.IMREAD_IGNORE_ORIENTATION
    raw = cv2.imdecode(np.frombuffer(data, np.uint8), flags) if data else None
    if raw is None:
        raise SessionError(f"{path}: cannot be read as an image; save it as an 8-bit greyscale PNG")
    if raw.dtype not in (np.uint8, np.uint16):
        raise SessionError(
            f"{path}: holds {raw.dtype} pixels, not 8- or 16-bit grey levels; save it as an 8-bit "
            "greyscale PNG"
        )
    return grey_8bit(raw)


@contextlib.contextmanager
def _readable(directory: Path, what: str) -> Iterator[None]:
    """A file or folder of the ``what`` ("session", "rig") this user may not read is named,
    with what to do, rather than failing the run as an internal error."""
    try:
        yield
    except PermissionError as exc:
        where = exc.filename or directory
        raise SessionError(
            f"{where}: cannot be read (permission denied); give this user read access to the "
            f"{what} folder and its files, or copy them where it can read them"
        ) from None


def _check_spelling(directory: Path, name: str) -> None:
    """A file ``name`` missing from ``directory`` where one named so in other capitals is
    there (Session.toml): named, not passed over (its settings would be silently the
    defaults)."""
    if (directory / name).exists():
        return
    for other in directory.iterdir():
        if other.name.lower() == name:
            raise SessionError(f"{other}: the file must be named {name}, in lower case; rename it")


def check_not_dangling(path: Path, error: type[PipelineError] = SessionError) -> None:
    """A symbolic link to nothing, or into a loop of links, is named as such (an ``error``),
    not taken for a missing file."""
    if not path.is_symlink():
        return
    try:
        path.resolve(strict=True)
    except FileNotFoundError:
        raise error(
            f"{path}: is a symbolic link to {os.readlink(path)}, which does not exist; "
            "fix the link or copy the file in"
        ) from None
    except (RuntimeError, OSError):  # Python 3.11 raises RuntimeError for a loop
        raise error(
            f"{path}: is a symbolic link that leads back to itself ({os.readlink(path)}); "
            "fix the link or copy the file in"
        ) from None


def check_utf8_path(path: Path, what_to_do: str, error: type[PipelineError] = SessionError) -> None:
    """Refuse a path (given or absolute) holding bytes that are not UTF-8: OpenCV, PyAV and
    Rerun take paths as UTF-8 text (OpenCV crashed on other bytes), and the summary prints them."""
    for form in (path, path.absolute()):
        try:
            str(form).encode("utf-8")
        except UnicodeEncodeError:
            shown = os.fsencode(path).decode("utf-8", "replace")
            raise error(f"{shown}: the path holds bytes that are not UTF-8 text; {what_to_do}") from None


def _check_last_timestamp(directory: Path, settings: Settings, fps: float, frames: int) -> None:
    """The last frame's time must fit a ns timestamp too, not only start_time."""
    start = settings.session.start_time
    end = start + timedelta(seconds=(frames - 1) / fps)
    if end > LAST_TIMESTAMP:
        raise SettingsError(
            f"{directory / 'session.toml'}: [session] start_time {start.isoformat()} puts the last "
            f"frame at {end.isoformat()}, past 2262-04-11, the last time a nanosecond timestamp "
            "holds; give an earlier start_time"
        )


def _check_min_area(directory: Path, cameras: list[Camera], settings: Settings) -> None:
    """A smallest blob larger than a camera's whole image would remove every silhouette."""
    area = settings.silhouette.min_area_px
    for cam in cameras:
        w, h = cam.size_px
        if area > w * h:
            raise SettingsError(
                f"{directory / 'session.toml'}: [silhouette] min_area_px {area} is larger than camera "
                f"{cam.name!r}'s whole image ({w}x{h} = {w * h} px): no silhouette would be kept; "
                "give the smallest blob the tube can make (the default is 20)"
            )


def _check_workspace_visible(cameras: list[Camera], settings: Settings) -> None:
    """Every camera must see some part of the workspace, or the hull is empty by construction."""
    ws = settings.workspace
    lo = np.asarray(ws.origin_mm)
    hi = lo + np.asarray(ws.size_mm)
    # A 9^3 lattice over the box catches a camera that sees any sizeable part of it.
    axes = [np.linspace(a, b, 9) for a, b in zip(lo, hi, strict=True)]
    probe = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    for cam in cameras:
        # A camera inside the box sees part of it from behind. Most likely the calibration
        # is in another unit (cm, inches: the cameras as many times nearer the world's
        # origin), and every frame will fail; a box drawn generously around the rig works,
        # only slower. Said, not refused.
        centre = cam.center_mm
        if np.all((centre > lo) & (centre < hi)):
            log.warning(
                "camera %r sits inside the workspace box (at %s mm; origin %s mm, size %s mm): is "
                "calibration.toml's translation in another unit than mm (cm, inches)? Else shrink "
                "[workspace] in session.toml to where the tube moves",
                cam.name,
                ", ".join(f"{v:.1f}" for v in centre),
                ws.origin_mm,
                ws.size_mm,
            )
        px = cam.project(probe)
        inside = (
            np.isfinite(px).all(axis=1)
            & (px[:, 0] >= 0)
            & (px[:, 0] < cam.width)
            & (px[:, 1] >= 0)
            & (px[:, 1] < cam.height)
        )
        if not inside.any():
            raise SessionError(
                f"camera {cam.name!r} does not see the workspace (origin {ws.origin_mm} mm, "
                f"size {ws.size_mm} mm); check calibration.toml or [workspace] in session.toml"
            )
