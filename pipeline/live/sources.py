"""Where each camera's frames come from in a live run: a device, a stream, or a replayed video.

A :class:`Source` is what FFmpeg (through PyAV) opens for one camera. The rig's
session.toml names them in its ``[live]`` table; ``--replay`` takes a session's
videos instead and plays them at their frame rate, as if they were cameras.
"""

from __future__ import annotations

import ipaddress
import itertools
import logging
import os
import stat
import urllib.parse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import SessionError, SettingsError
from ..session.folder import Session, load_rig, load_session

log = logging.getLogger(__name__)

# FFmpeg's demuxer for Video4Linux2 devices: a device path or index is opened with it.
V4L2_FORMAT = "v4l2"


@dataclass(frozen=True)
class Source:
    """One camera's source.

    camera : the camera's name in calibration.toml.
    url : what FFmpeg opens: a device path, a URL, a named pipe or a video file.
    format : FFmpeg's input format, or None to let FFmpeg guess from ``url``.
    replay_fps : play a video file at this rate (frames/s), as a camera would deliver
        it, and end with it; None for a camera (which is retried when it stops).
    """

    camera: str
    url: str
    format: str | None = None
    replay_fps: float | None = None

    @property
    def is_replay(self) -> bool:
        return self.replay_fps is not None

    def describe(self) -> str:
        return f"camera {self.camera!r} ({self.url})"


def parse_source(camera: str, text: str) -> Source:
    """``[live]``'s value for ``camera`` -> its Source: a device index (``0`` -> ``/dev/video0``)
    or a ``/dev/video*`` or ``/dev/v4l/...`` path opened as V4L2, anything else as FFmpeg
    reads it."""
    if text.isdigit():
        return Source(camera, f"/dev/video{int(text)}", V4L2_FORMAT)
    if text.startswith(("/dev/video", "/dev/v4l/")):  # by number, or by id or path (udev's links)
        return Source(camera, text, V4L2_FORMAT)
    return Source(camera, text)


def rig_sources(rig: Session) -> list[Source]:
    """Each camera's source from the rig's ``[live]`` table, in calibration order."""
    live = rig.settings.live
    toml = rig.directory / "session.toml"
    if not live.sources:
        raise SettingsError(
            f"{toml}: no [live] table; add one naming each camera's source "
            '(cam0 = "/dev/video0", cam1 = 1, cam2 = "udp://127.0.0.1:5002"), or use --replay SESSION_DIR'
        )
    sources: dict[tuple[str | int, ...], Source] = {}  # by what each is (source_identity)
    for cam in rig.cameras:
        text = live.source(cam.name)
        if text is None:
            raise SettingsError(
                f"{toml}: [live] gives no source for camera {cam.name!r}; add "
                f'{cam.name} = "/dev/videoN" (or a device index, or a stream URL)'
            )
        source = parse_source(cam.name, _anchored(text, rig.directory))
        _check_path(toml, source)
        identity = source_identity(source.url)
        other = sources.get(identity)
        if other is not None:
            # The second reader would be refused (a device busy, a port in use) or steal
            # half the frames: the run would go on short of a camera.
            names = (
                source.url if other.url == source.url else f"{other.url} and {source.url}, one {identity[0]}"
            )
            raise SettingsError(
                f"{toml}: [live] gives cameras {other.camera!r} and {cam.name!r} the same source "
                f"({names}); each camera needs a source of its own"
            )
        sources[identity] = source
    return list(sources.values())


def _anchored(text: str, directory: Path) -> str:
    """A ``[live]`` path as the rig means it: ``~`` expanded, and relative to the rig's
    folder (where session.toml is), not to wherever the run was started; device indices
    and URLs (``file:`` ones too, FFmpeg's own) as they are."""
    if text.isdigit() or "://" in text or text.startswith("file:"):
        return text
    path = Path(text).expanduser()
    return str(path if path.is_absolute() else directory / path)


def source_identity(url: str) -> tuple[str | int, ...]:
    """What a source is, whatever it is called: a device by its device number (a udev link
    such as /dev/v4l/by-id/... and its /dev/videoN are one device), another path by its
    file (a relative path and its absolute one, a link and its target), and a path not
    there by where it leads; a UDP stream by the port it is received on here (udp://
    127.0.0.1:5000, udp://localhost:5000 and udp://0.0.0.0:5000 all take port 5000; a
    multicast group's by the group too, as groups share ports); another URL by its text.
    The first item names the kind."""
    path = local_path(url)
    if path is None:
        return _udp_port(url) or ("url", url)
    try:
        status = os.stat(path)
    except (OSError, ValueError):
        return ("path", os.path.realpath(path))
    if stat.S_ISCHR(status.st_mode) or stat.S_ISBLK(status.st_mode):
        return ("device", status.st_rdev)
    return ("file", status.st_dev, status.st_ino)


def _udp_port(url: str) -> tuple[str | int, ...] | None:
    """A ``udp://`` source's identity (see :func:`source_identity`); None for another URL,
    or one whose port cannot be read."""
    parts = urllib.parse.urlsplit(url)
    try:
        port = parts.port
    except ValueError:
        return None
    if parts.scheme.lower() != "udp" or port is None:
        return None
    host = (parts.hostname or "").strip("[]")
    try:
        multicast = ipaddress.ip_address(host).is_multicast
    except ValueError:  # a host name: not a group
        multicast = False
    return ("udp port", host, port) if multicast else ("udp port", port)


def local_path(url: str) -> str | None:
    """The path a source reads on this machine: the source itself, or an FFmpeg ``file:``
    URL's path (``file:///dev/video0``, ``file:take/cam0.mp4``); None for a stream URL."""
    if url.startswith("file:"):
        return url[len("file:") :]  # FFmpeg's own reading: the rest is the path ("///x" is /x)
    return None if "://" in url else url


def _check_path(toml: Path, source: Source) -> None:
    """Refuse a ``[live]`` path that is a folder or a regular file: no frames come from the
    one, and the other is read as fast as it decodes (and again when it ends), its frames
    matched with the other cameras' at random. A path not there (a camera unplugged, a pipe
    not made yet) is left to the run, which retries it."""
    path = local_path(source.url)
    if path is None:
        return
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return
    where = f"{toml}: [live] {source.camera} = {source.url!r}"
    if stat.S_ISDIR(mode):
        raise SettingsError(f"{where} is a folder; give a device (/dev/videoN), a stream URL or a named pipe")
    if stat.S_ISREG(mode):
        raise SettingsError(
            f"{where} is a file, not a camera (a file is read as fast as it decodes, not as "
            "it is filmed); to play a session's videos as cameras, use --replay SESSION_DIR"
        )


def replay_sources(rig: Session, replay: Session) -> list[Source]:
    """The replayed session's videos as the rig's cameras' sources, played at its rate.

    The session must hold a video for every camera of the rig (matched by name), of the
    size the rig's calibration gives it.
    """
    videos: dict[str, Path] = {c.name: p for c, p in zip(replay.cameras, replay.video_paths, strict=True)}
    sizes = {c.name: c.size_px for c in replay.cameras}  # its videos', checked when it was loaded
    sources = []
    for cam in rig.cameras:
        if cam.name not in videos:
            raise SessionError(
                f"{replay.directory}: --replay has no video for camera {cam.name!r} of the rig "
                f"(it has: {', '.join(videos)}); replay a session of this rig"
            )
        if sizes[cam.name] != cam.size_px:
            (w, h), (rw, rh) = sizes[cam.name], cam.size_px
            raise SessionError(
                f"{videos[cam.name]}: frames are {w}x{h} but the rig's calibration.toml gives camera "
                f"{cam.name!r} {rw}x{rh}; replay a session filmed at the rig's resolution"
            )
        sources.append(Source(cam.name, str(videos[cam.name]), replay_fps=replay.fps))
    return sources


def open_rig(rig_dir: Path | None, replay_dir: Path | None) -> tuple[Session, list[Source]]:
    """The rig and its cameras' sources: ``[live]``'s, or a replayed session's videos.

    ``rig_dir`` None: the replayed session is its own rig (its calibration and settings).
    """
    if replay_dir is None:
        if rig_dir is None:
            raise SessionError(
                "give the rig directory (calibration.toml, session.toml), or --replay SESSION_DIR"
            )
        rig = load_rig(rig_dir)
        return rig, rig_sources(rig)
    replay = load_session(replay_dir)
    if rig_dir is None or Path(rig_dir).resolve() == Path(replay_dir).resolve():
        return replay, replay_sources(replay, replay)
    rig = load_rig(rig_dir)
    _warn_of_another_rig(rig, replay)
    return rig, replay_sources(rig, replay)


# A replayed session's camera whose image of the workspace lies this far (px) from the rig's
# camera of that name was filmed by another rig (or before a recalibration).
_OTHER_RIG_PX = 2.0


def _warn_of_another_rig(rig: Session, replay: Session) -> None:
    """Say where the replayed session's calibration puts a camera's image of the workspace
    more than ``_OTHER_RIG_PX`` from the rig's: its videos are reconstructed with the rig's
    cameras, and a session of another rig gives curves that fit none of its views."""
    workspace = rig.settings.workspace
    # (8, 3) mm: the workspace box's corners.
    corners = np.asarray(workspace.origin_mm) + np.asarray(workspace.size_mm) * np.array(
        list(itertools.product((0.0, 1.0), repeat=3))
    )
    theirs = {cam.name: cam for cam in replay.cameras}
    for cam in rig.cameras:
        other = theirs.get(cam.name)
        if other is None or other.size_px != cam.size_px:
            continue  # named by replay_sources
        apart_px = float(np.max(np.linalg.norm(cam.project(corners) - other.project(corners), axis=1)))
        if apart_px > _OTHER_RIG_PX:
            log.warning(
                "%s: camera %r of its calibration.toml sees the workspace up to %.0f px from the rig's "
                "(%s): the replay is reconstructed with the rig's cameras; replay a session filmed "
                "with this rig, or give its own folder alone",
                replay.directory,
                cam.name,
                apart_px,
                rig.directory / "calibration.toml",
            )
            return
