"""Video files: probing (OpenCV and PyAV), and reading a contiguous range of frames (PyAV).

Frames are read with PyAV rather than OpenCV because placing each one by the
container's index, not by a count of packets, needs the packets' byte positions.

Kept apart from the array code: everything downstream receives (H, W) uint8 grey
images and never a path.
"""

from __future__ import annotations

import bisect
import dataclasses
import functools
import hashlib
import logging
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from fractions import Fraction
from pathlib import Path

import av
import cv2
import numpy as np
from numpy.typing import NDArray

from ..errors import VideoError
from .grey_levels import full_scale_level, grey_8bit

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mkv", ".mov", ".m4v", ".webm", ".ts", ".mts", ".m2ts")

log = logging.getLogger(__name__)

# An AVI packet starts after its chunk's header (fourcc and size), where idx1 points.
_CHUNK_HEADER_BYTES = 8
# H.264 and HEVC show a frame at most 16 frames after it is decoded.
_MAX_REORDER_FRAMES = 16
# A video whose frame intervals stray from their median by more than this fraction of it
# has a variable frame rate (a phone's, a screen recording's): its frames are numbered at
# its average rate, so a frame may land on a neighbour's index.
VFR_TOLERANCE = 0.1
# The frame timestamps looked at for it (a minute at 30 fps): the container's index where it
# has one, else the first packets demuxed; nothing is decoded.
VFR_FRAMES = 1800

# A damaged or half-copied video is reported by us, once, naming the file; OpenCV's and
# FFmpeg's own lines ("moov atom not found", "overread 8") would bury that message and
# repeat for every bad frame. FFmpeg reads its level when first used, so this also holds
# in worker processes; set OPENCV_FFMPEG_LOGLEVEL yourself (e.g. 24) to see them again.
_USER_FFMPEG_LEVEL = os.environ.get("OPENCV_FFMPEG_LOGLEVEL")  # a level you set stays yours
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET
cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


def _pyav_log_level(setting: str) -> int | None:
    """PyAV's log level for an OPENCV_FFMPEG_LOGLEVEL value (the same FFmpeg scale); None: quiet."""
    try:
        level = int(setting)
    except ValueError:
        return None
    return level if level >= 0 else None


def _set_pyav_level(setting: str) -> None:
    """PyAV's and FFmpeg's own levels from an OPENCV_FFMPEG_LOGLEVEL value. Quiet means
    both: with PyAV's logging off, FFmpeg prints to the terminal at its own level
    (swscale's "deprecated pixel format used" on MJPEG frames, among others)."""
    level = _pyav_log_level(setting)
    av.logging.set_level(level)
    av.logging.set_libav_level(level if level is not None else -8)  # AV_LOG_QUIET


# PyAV is quiet unless told otherwise; the same variable makes it pass FFmpeg's lines
# to the "libav" loggers. Read at import, so it holds in worker processes too.
_set_pyav_level(os.environ["OPENCV_FFMPEG_LOGLEVEL"])


def show_ffmpeg_messages() -> None:
    """Let FFmpeg's warnings through (``--debug``), in OpenCV and PyAV, here and in workers started later.

    Call it before the first video is opened: OpenCV reads its level once. A level
    set in OPENCV_FFMPEG_LOGLEVEL before this module was imported is left as it is.
    """
    if _USER_FFMPEG_LEVEL is None:
        os.environ["OPENCV_FFMPEG_LOGLEVEL"] = "24"  # AV_LOG_WARNING
    _set_pyav_level(os.environ["OPENCV_FFMPEG_LOGLEVEL"])


@dataclass(frozen=True)
class VideoInfo:
    """``creation_time``: when the container says the recording was made (timezone-aware),
    or None where it does not say. ``variable_rate``: how its frame intervals vary ("" for
    a constant rate). ``notes``: what the reader does not follow (a rotation tag, a second
    video stream, a variable rate), a line each naming the file. ``streams``: its video
    streams, of which the first is read (0 where they could not be counted)."""

    path: Path
    width: int
    height: int
    fps: float
    frame_count: int
    creation_time: datetime | None = None
    variable_rate: str = ""
    notes: tuple[str, ...] = ()
    streams: int = 1
    grey_full_scale: int | None = None


# A video's fingerprint reads this many bytes at each end of the file (with its size).
_FINGERPRINT_BYTES = 1 << 16


def video_fingerprint(path: Path) -> str:
    """A short text that changes when the video's content does (its size, and a hash of its
    first and last 64 KiB: a video rendered or filmed again differs there), and not when
    it is copied or moved; "" where the file cannot be read."""
    try:
        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            digest = hashlib.sha256(f"{size}:".encode())
            digest.update(f.read(_FINGERPRINT_BYTES))
            f.seek(max(size - _FINGERPRINT_BYTES, 0))
            digest.update(f.read(_FINGERPRINT_BYTES))
    except OSError:
        return ""
    return digest.hexdigest()[:16]


def probe_video(path: Path) -> VideoInfo:
    """Open ``path`` and read its size, fps and frame count; VideoError if it is not a video.

    The file is opened once by OpenCV and once by PyAV. A file probed before and unchanged
    since (the same path, device and inode, size and modification time) is not opened
    again: a session's checks and a replay's reading share one probe.
    """
    try:
        stat = os.stat(path)
    except OSError:
        return _probe(Path(path))  # not a file: OpenCV's open names it
    return _probe_unchanged(str(path), (stat.st_dev, stat.st_ino), stat.st_size, stat.st_mtime_ns)


@functools.lru_cache(maxsize=64)
def _probe_unchanged(path: str, file_id: tuple[int, int], size_bytes: int, mtime_ns: int) -> VideoInfo:
    """:func:`_probe` of ``path`` while it is this file (device, inode) of this size and mtime."""
    return _probe(Path(path))


def _probe(path: Path) -> VideoInfo:
    """Size, fps, frame count and notes of the video ``path``: OpenCV's view of its first
    video stream, and PyAV's one reading of its container (:func:`_read_container`)."""
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    try:
        if not cap.isOpened():
            raise VideoError(
                f"{path}: cannot be opened as a video (empty, unreadable, copied half-way "
                "or not a video); re-copy or re-export it"
            )
        facts = _read_container(path)
        if facts.still_kind:
            raise VideoError(
                f"{path}: is a still {facts.still_kind} image, not a video; put the camera's video here"
            )
        if facts.bare_kind:
            # Its frame rate and frame count would be FFmpeg's guesses (25 fps, none).
            raise VideoError(
                f"{path}: its {path.suffix} header is damaged or missing (only a bare {facts.bare_kind} "
                "stream is left, without its frame rate or timing); re-copy or re-export it"
            )
        # The frames as stored, which the reader (PyAV) gives: not turned by a rotation tag.
        cap.set(cv2.CAP_PROP_ORIENTATION_AUTO, 0)
        rotation_deg = float(cap.get(cv2.CAP_PROP_ORIENTATION_META) or 0.0)
        width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        ok, _ = cap.read()
        if not ok or width <= 0 or height <= 0:
            raise VideoError(f"{path}: holds no decodable frame; re-copy or re-export it")
        if not fps > 0:
            raise VideoError(f"{path}: has no frame rate; re-export it with a fixed fps")
    finally:
        cap.release()
    count = facts.packet_count or count
    notes = []
    full_scale = _deep_grey_full_scale(path) if facts.pixel_format in DEEP_GREY else None
    if full_scale is not None and full_scale < _FULL_16_BITS:
        # A camera's 10- or 12-bit values stored in 16-bit samples as they are: read as
        # 16-bit levels, every frame would be nearly black.
        notes.append(
            f"{path}: a 16-bit grey video whose first frame holds {full_scale.bit_length()}-bit "
            f"values; every frame is read as its levels x 255 / {full_scale} (a later frame "
            "brighter than that depth reads as white where it is)"
        )
    if rotation_deg % 360:
        notes.append(
            f"{path}: carries a {rotation_deg % 360:g}-degree rotation tag that is not applied; the "
            f"calibration must be of the frames as stored ({width}x{height})"
        )
    if facts.streams > 1:
        notes.append(f"{path}: holds {facts.streams} video streams; the first ({width}x{height}) is read")
    variable = describe_variable_rate(facts.stamps_s, facts.tick_s)
    if variable:
        notes.append(
            f"{path}: has a variable frame rate ({variable}); frame i is taken as the one at "
            f"i / {fps:g} s, its average rate: re-export it at a constant rate if its frames "
            "look out of step with the other cameras'"
        )
    return VideoInfo(
        path=Path(path),
        width=width,
        height=height,
        fps=fps,
        frame_count=max(count, 1),
        creation_time=_parse_creation_time(path, facts.creation_text),
        variable_rate=variable,
        notes=tuple(notes),
        streams=facts.streams,
        grey_full_scale=full_scale,
    )


# 16-bit grey pixel formats, and the level of their full range.
DEEP_GREY = frozenset({"gray16le", "gray16be"})
_FULL_16_BITS = 65535


def _deep_grey_full_scale(path: Path) -> int | None:
    """The level that stands for white in the 16-bit grey video ``path``: 2**bits - 1 of
    the shallowest stored depth that holds its first frame's brightest pixel (as a 16-bit
    background image is read: :func:`~pipeline.session.grey_levels.full_scale_level`);
    None where no frame decodes."""
    try:
        with av.open(str(path)) as container:
            for frame in container.decode(video=0):
                return int(full_scale_level(frame.to_ndarray()))
    except (av.error.FFmpegError, OSError):
        pass
    return None


# FFmpeg's demuxers of bare video streams, which carry no frame rate or timestamps of
# their own; and the file names of containers, which always do.
BARE_STREAMS = frozenset({"m4v", "h264", "hevc", "mpegvideo", "h263", "mjpeg", "rawvideo", "vc1", "av1"})
CONTAINER_SUFFIXES = frozenset({".mp4", ".mov", ".avi", ".mkv", ".webm"})


@dataclass(frozen=True, eq=False)
class _ContainerFacts:
    """What one PyAV opening of a video file reads, nothing decoded; the defaults stand
    where the file cannot be opened.

    ``still_kind``: the kind of still image ("PNG", ...) the file holds under a video's
    name, "" for anything else. ``bare_kind``: the codec of a bare video stream (no
    container: FFmpeg's raw demuxers, ``BARE_STREAMS``) under a container's name (a
    header overwritten or cut off), "" for anything else. ``streams``: its video
    streams (0 where the first cannot be demuxed as far as its timestamps are read).
    ``stamps_s``, ``tick_s``: the first stream's frame timestamps (s, ascending, at most
    VFR_FRAMES) and their tick (s).
    ``packet_count``: its packets, where the container keeps no frame count, or an MP4
    keeps one of frames its edit list hides (None where it keeps one, or where the stream
    cannot be demuxed to its end). ``creation_text``: the container's creation_time tag,
    else its first video stream's ("" for none). ``pixel_format``: the first video stream's
    pixel format as its codec states it ("gray16le", ...; "" where it states none).
    """

    still_kind: str = ""
    bare_kind: str = ""
    streams: int = 0
    stamps_s: NDArray[np.float64] = dataclasses.field(default_factory=lambda: np.zeros(0))
    tick_s: float = 0.0
    packet_count: int | None = None
    creation_text: str = ""
    pixel_format: str = ""


def _read_container(path: Path) -> _ContainerFacts:
    """:class:`_ContainerFacts` of ``path`` from one PyAV opening.

    The timestamps come from the container's index where it has an entry per frame
    (MP4, AVI; nothing is read), else from the first packets demuxed (Matroska). The
    packets are counted where the container keeps no frame count (Matroska, WebM):
    OpenCV estimates that count as its duration x fps, and a Matroska duration runs from
    time 0: at 30 fps a stream that starts 2 s in would count 60 frames too many, each
    then failing as cut short.
    """
    try:
        with av.open(str(path)) as container:
            name = container.format.name
            # FFmpeg's demuxers of single images are all named "<kind>_pipe" (png_pipe, ...);
            # a GIF's is "gif", and a GIF, animated or not, is no camera's recording.
            still = name.removesuffix("_pipe").upper() if name.endswith("_pipe") or name == "gif" else ""
            bare = name if name in BARE_STREAMS and path.suffix.lower() in CONTAINER_SUFFIXES else ""
            streams = container.streams.video
            text = container.metadata.get("creation_time") or (
                streams[0].metadata.get("creation_time") if streams else None
            )
            if not streams:
                return _ContainerFacts(still_kind=still, bare_kind=bare, creation_text=text or "")
            stream = streams[0]
            time_base = float(stream.time_base or Fraction(1, 1000))
            index = _FrameIndex.of(stream)
            edited = "mp4" in name.split(",") and _hides_frames(stream)
            ticks, count = _demuxed(
                container, stream, ticks_wanted=index is None, count_wanted=stream.frames <= 0 or edited
            )
            if index is not None:
                ticks = [index[k].timestamp for k in range(min(stream.frames, VFR_FRAMES))]
            return _ContainerFacts(
                still_kind=still,
                bare_kind=bare,
                streams=len(streams) if ticks is not None else 0,
                stamps_s=np.sort(np.asarray(ticks or [], dtype=np.float64)) * time_base,
                tick_s=time_base if ticks is not None else 0.0,
                packet_count=count,
                creation_text=text or "",
                pixel_format=stream.codec_context.pix_fmt or "",
            )
    except (av.error.FFmpegError, OSError):
        return _ContainerFacts()


def _hides_frames(stream: av.video.stream.VideoStream) -> bool:
    """Whether an MP4 ``stream`` keeps a count of more frames than its duration shows at its
    average rate (by more than one): an edit list hides some (a trim made without
    re-encoding), which the demuxer drops, and the reader with it."""
    if stream.frames <= 0 or not (stream.duration and stream.time_base and stream.average_rate):
        return False
    shown = float(stream.duration * stream.time_base * stream.average_rate)
    return stream.frames > shown + 1.0


def _demuxed(
    container: av.container.InputContainer,
    stream: av.video.stream.VideoStream,
    *,
    ticks_wanted: bool,
    count_wanted: bool,
) -> tuple[list[int] | None, int | None]:
    """The timestamps of ``stream``'s first VFR_FRAMES packets (if ``ticks_wanted``) and
    the count of all its packets (if ``count_wanted``), from one pass of demuxing that
    stops once it has what is wanted; each None where not wanted, or where the demuxer
    fails before it is read."""
    if not (ticks_wanted or count_wanted):
        return None, None
    ticks: list[int] = []
    count = 0
    try:
        for packet in container.demux(stream):
            if packet.pts is not None and len(ticks) < VFR_FRAMES:
                ticks.append(packet.pts)
            count += packet.size > 0
            if not count_wanted and len(ticks) >= VFR_FRAMES:
                break
    except (av.error.FFmpegError, OSError):
        return (ticks if ticks_wanted and len(ticks) >= VFR_FRAMES else None), None
    return (ticks if ticks_wanted else None), (count if count_wanted else None)


def describe_variable_rate(stamps_s: NDArray[np.float64], tick_s: float = 0.0) -> str:
    """How the intervals between frame timestamps ``stamps_s`` ((N,) float64 s, ascending)
    vary ("frames 20.0-46.7 ms apart, median 33.3 ms"), where one strays from their median
    by more than VFR_TOLERANCE of it and by more than a tick of the container's clock
    (``tick_s``: Matroska counts whole ms, so a constant 120 fps reads 8, 8, 9 ms apart);
    "" for a constant rate (or too few frames to tell)."""
    intervals = np.diff(stamps_s)
    if len(intervals) < 2:
        return ""
    median = float(np.median(intervals))
    allowed = max(VFR_TOLERANCE * median, 1.5 * tick_s)
    if not median > 0 or np.abs(intervals - median).max() <= allowed:
        return ""
    return (
        f"frames {intervals.min() * 1e3:.1f}-{intervals.max() * 1e3:.1f} ms apart, "
        f"median {median * 1e3:.1f} ms"
    )


def _parse_creation_time(path: Path, text: str) -> datetime | None:
    """The container's creation_time tag ``text`` of ``path`` (MP4/MOV, Matroska; the
    container's own, else its first video stream's) as a timezone-aware date-time (UTC
    where it names no zone); None for "" or text that is not ISO 8601."""
    if not text:
        return None
    try:
        stamp = datetime.fromisoformat(text)
    except ValueError:
        log.debug("%s: creation_time %r is not ISO 8601; ignored", path, text)
        return None
    return stamp if stamp.tzinfo else stamp.replace(tzinfo=UTC)


def read_frames(
    path: Path, start: int, stop: int, *, problems: dict[int, str] | None = None
) -> Iterator[tuple[int, NDArray[np.uint8] | None]]:
    """Yield ``(index, grey image or None)`` for every frame ``start <= index < stop``, in order.

    Parameters
    ----------
    path : the video file.
    start, stop : frame range; frame ``i`` is the one the container times at ``i / fps``.
    problems : where given, each frame that gets None has its reason put here (frame
        index -> reason, set before the None is yielded) instead of in the log.

    Yields
    ------
    index : int, ``start``, ``start + 1``, ... ``stop - 1``.
    image : (H, W) uint8 grey image (OpenCV's BGR-to-grey of the decoded picture), or
        None where the file cannot provide that frame: cut short, a packet lost in
        damaged bytes or rejected by the decoder, or an inter-coded frame that would be
        decoded from a damaged reference. Why goes into ``problems``, or (without it) is
        logged once per call, naming the frames.

    Notes
    -----
    Each frame is placed by its timestamp, never by counting packets: an AVI has no
    timestamps of its own and FFmpeg numbers its packets as they come, so one chunk
    lost in damaged bytes would shift every later frame by one. Where the container
    indexes every frame (AVI idx1, MP4 sample tables), a packet takes the timestamp of
    the index entry it starts at instead.
    """
    if stop <= start:
        return
    logged = problems is None
    found: dict[int, str] = {} if problems is None else problems
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError) as exc:  # probe_video reports this before a run
        if logged:
            log.warning("%s: cannot be opened (%s); frames %d-%d failed", path, exc, start, stop - 1)
        for i in range(start, stop):
            found[i] = f"cannot be opened ({exc})"
            yield i, None
        return
    try:
        expected = start
        if container.streams.video:
            stream = container.streams.video[0]
            # A 16-bit grey video's depth is its first frame's, whichever frames are read.
            deep = stream.codec_context.pix_fmt in DEEP_GREY
            full_scale = _deep_grey_full_scale(path) if deep else None
            for index, image in _decode(container, stream, start, stop, found, full_scale):
                if index < expected:  # a repeated timestamp: keep the first
                    continue
                for lost in range(expected, index):
                    found.setdefault(lost, "missing from the stream")
                    yield lost, None
                yield index, image
                expected = index + 1
        for i in range(expected, stop):
            found.setdefault(i, "not in the file (cut short?)")
            yield i, None
    finally:
        container.close()
        if logged:
            _log_problems(path, {i: r for i, r in found.items() if start <= i < stop})


class _FrameIndex:
    """The container's own index of a video stream: one entry per frame, in file order.

    Byte positions ascend with the entries (AVI idx1 and MP4 sample tables list the
    frames as they are stored, in decoding order). Entries are read as they are
    needed (one per packet, a few more after damage), never all at once: a range of
    a long video costs no more than one of a short one.
    """

    def __init__(self, entries: av.index.IndexEntries) -> None:
        self._entries = entries
        self._count = len(entries)

    @classmethod
    def of(cls, stream: av.video.stream.VideoStream) -> _FrameIndex | None:
        """The index of ``stream``, or None unless it has an entry for each of its frames.

        Matroska's cues list only some keyframes, but its blocks carry timestamps the
        demuxer passes on. An AVI cut short has lost its idx1 (the demuxer indexes
        packets as it reads them), and its count of packets is all there is.
        """
        entries = stream.index_entries
        return cls(entries) if 0 < len(entries) == stream.frames else None

    def __getitem__(self, k: int) -> av.index.IndexEntry:
        return self._entries[k]

    def locate(self, packet: av.Packet, expected: int | None) -> int | None:
        """The entry ``packet`` was read from: ``expected`` or a later one (any, if None).

        None if it starts at no entry (give or take an AVI chunk header) or is not its
        entry's size: bytes the demuxer resynchronised into after damage.
        """
        pos, size = packet.pos, packet.size
        if pos is None:
            return None
        if expected is not None and self._holds(expected, pos, size):
            return expected  # the usual case, one entry read
        first = 0 if expected is None else expected + 1
        k = bisect.bisect_right(self._entries, pos, first, self._count, key=lambda e: e.pos) - 1
        return k if k >= first and self._holds(k, pos, size) else None

    def _holds(self, k: int, pos: int, size: int) -> bool:
        """Whether a packet of ``size`` bytes read at byte ``pos`` is entry ``k``."""
        if not 0 <= k < self._count:
            return False
        entry = self._entries[k]
        return 0 <= pos - entry.pos <= _CHUNK_HEADER_BYTES and size == entry.size


@dataclass(frozen=True)
class _Clock:
    """Frame index <-> timestamp (in the stream's time base) of a video stream."""

    start_ts: int
    frames_per_tick: float

    @classmethod
    def of(cls, stream: av.video.stream.VideoStream) -> _Clock:
        rate = stream.average_rate or stream.guessed_rate or 30
        # PyAV types time_base as optional; a demuxed stream always has one.
        return cls(stream.start_time or 0, float((stream.time_base or Fraction(1, 1000)) * rate))

    def index(self, timestamp: int) -> int:
        return round((timestamp - self.start_ts) * self.frames_per_tick)

    def timestamp(self, index: int) -> int:
        return self.start_ts + math.floor(index / self.frames_per_tick)


def _packets(
    container: av.container.InputContainer,
    stream: av.video.stream.VideoStream,
    clock: _Clock,
    start: int,
    problems: dict[int, str],
) -> Iterator[tuple[av.Packet, bool, bool]]:
    """Yield ``(packet, keyframe, after_loss)`` from a keyframe at or before ``start`` on.

    A seek goes by decoding timestamps, so with B-frames it can land on a keyframe
    shown after ``start``, and a damaged keyframe sends the demuxer past it: then
    the seek is made again from further back, and last from the top of the file.
    """
    index = _FrameIndex.of(stream)
    for landing in sorted({start, max(start - _MAX_REORDER_FRAMES, 0), 0}, reverse=True):
        if start > 0:
            container.seek(clock.timestamp(landing), stream=stream, backward=True)
        # Where a seek lands is the demuxer's choice: the first packet is found in the index.
        packets = _retimed(
            container.demux(stream), index, clock, problems, next_entry=0 if start == 0 else None
        )
        first = next(packets, None)
        if first is None:
            return
        if landing > 0 and first[0].pts is not None and clock.index(first[0].pts) > start:
            continue
        yield first
        yield from packets
        return


def _retimed(
    packets: Iterator[av.Packet],
    index: _FrameIndex | None,
    clock: _Clock,
    problems: dict[int, str],
    *,
    next_entry: int | None,
) -> Iterator[tuple[av.Packet, bool, bool]]:
    """Yield ``(packet, keyframe, after_loss)`` for ``packets`` in file order.

    Packets carry their true timestamps: the index's, where it has one entry per
    frame, else the demuxer's. ``after_loss`` is True for the first packet after
    packets lost in damaged bytes, which go into ``problems`` (frame index -> reason).
    ``next_entry`` is the index entry the first packet should be (None: any). The
    last packet is the empty one that flushes the decoder.
    """
    after_loss = False
    for packet in packets:
        if index is None or not packet.size:
            yield packet, packet.is_keyframe, False
            continue
        k = index.locate(packet, next_entry)
        if k is None:  # bytes the demuxer resynchronised into: no frame of the index
            after_loss = True
            continue
        for lost in range(k if next_entry is None else next_entry, k):
            problems.setdefault(clock.index(index[lost].timestamp), "lost in damaged bytes")
            after_loss = True
        next_entry = k + 1
        entry = index[k]
        shift = entry.timestamp - packet.dts if packet.dts is not None else 0
        if shift:  # the index's timestamp, not the demuxer's count of the packets it found
            packet.dts = entry.timestamp
            if packet.pts is not None:
                packet.pts += shift
        yield packet, entry.is_keyframe, after_loss
        after_loss = False


def _decode(
    container: av.container.InputContainer,
    stream: av.video.stream.VideoStream,
    start: int,
    stop: int,
    problems: dict[int, str],
    full_scale: int | None,
) -> Iterator[tuple[int, NDArray[np.uint8]]]:
    """Yield ``(index, grey image)`` for the frames from ``start`` that decode cleanly, ascending;
    ``full_scale``: of a 16-bit grey stream (see :class:`Greyer`).

    Frames that do not come out are left out (the caller fills the gaps with None)
    and their reason goes into ``problems`` (frame index -> reason). An inter-coded
    frame is not decoded after damage until the next keyframe: its picture would be
    built on a damaged reference.
    """
    stream.codec_context.options = {"err_detect": "explode"}  # a damaged packet fails, not a garbled picture
    clock = _Clock.of(stream)
    grey = Greyer(full_scale)
    broken = True  # no reference picture until a keyframe: at the start, after a seek or damage
    keyframe_pts: int | None = None  # of the last keyframe sent to the decoder
    keyframe_out = True  # its own picture came out (a damaged one the decoder takes may give none)
    previous = start - 1
    for packet, keyframe, after_loss in _packets(container, stream, clock, start, problems):
        broken = broken or after_loss
        if packet.size:
            if keyframe:
                broken = False
                keyframe_pts, keyframe_out = packet.pts, packet.pts is None
            elif broken:
                if packet.pts is not None:
                    problems.setdefault(clock.index(packet.pts), "its reference frame was damaged")
                continue
        try:
            frames = packet.decode()
        except av.error.FFmpegError as exc:
            if packet.pts is not None:
                problems.setdefault(clock.index(packet.pts), f"rejected by the decoder ({exc.strerror})")
            broken = True
            continue
        for frame in frames:
            i = previous + 1 if frame.pts is None else clock.index(frame.pts)
            previous = i
            keyframe_out = keyframe_out or frame.pts == keyframe_pts
            if i >= stop:
                return
            if i < start:
                continue
            if i in problems:  # its packet was rejected: what a decoder still hands out is a remnant
                continue
            late = frame.pts is not None and keyframe_pts is not None and frame.pts > keyframe_pts
            if late and not keyframe_out and keyframe_pts is not None:
                # A later picture before the keyframe's own: the decoder took a damaged
                # keyframe without a word, and built this one on what it had before.
                problems.setdefault(clock.index(keyframe_pts), "its keyframe was damaged (no picture)")
                problems.setdefault(i, "its reference frame was damaged")
                broken = True
                continue
            if frame.is_corrupt:
                problems.setdefault(i, "decoded with errors")
                # Later frames refer to it, unless a keyframe was sent since (with
                # B-frames, a frame comes out some packets after its own).
                if keyframe_pts is None or frame.pts is None or frame.pts >= keyframe_pts:
                    broken = True
                continue
            yield i, grey(frame)


class Greyer:
    """Grey images of a stream's frames, bit for bit what OpenCV's reader gives.

    Via BGR as OpenCV converts (PyAV's own "gray" conversion differs by up to 2
    levels), in a filter graph: its output frames come from a pool, where a
    reformatted frame per picture would cost a fresh 230 kB allocation each.
    The graph is built for the first frame's size, format, colour space and range
    (a stream does not always state the last two, and the frames do).

    16-bit grey frames of fewer bits than 16 (a 10- or 12-bit camera's values stored
    as they are) are read as their levels x 255 / ``full_scale`` instead, rounded and
    clipped: ``full_scale`` is the video's (:attr:`VideoInfo.grey_full_scale`), or where
    None, decided from the first such frame seen, as a whole video's is from its first.
    """

    def __init__(self, full_scale: int | None = None) -> None:
        self._graph: av.filter.Graph | None = None  # kept: its filters die with it
        self._full_scale = full_scale

    def __call__(self, frame: av.VideoFrame) -> NDArray[np.uint8]:
        if frame.format.name in DEEP_GREY:
            levels = frame.to_ndarray()
            if self._full_scale is None:
                self._full_scale = int(full_scale_level(levels))
            if self._full_scale < _FULL_16_BITS:
                return grey_8bit(levels, self._full_scale)
        if self._graph is None:
            self._graph = av.filter.Graph()
            source = self._graph.add(
                "buffer",
                f"video_size={frame.width}x{frame.height}:pix_fmt={frame.format.name}"
                f":time_base={frame.time_base or Fraction(1, 1000)}"
                f":pixel_aspect=1/1:colorspace={int(frame.colorspace)}:range={int(frame.color_range)}",
            )
            to_bgr = self._graph.add("format", "bgr24")
            sink = self._graph.add("buffersink")
            source.link_to(to_bgr)
            to_bgr.link_to(sink)
            self._graph.configure()
            self._source, self._sink = source, sink
        self._source.push(frame)
        bgr = self._sink.pull()
        assert isinstance(bgr, av.VideoFrame)  # a video graph's output (typed Frame)
        return np.asarray(cv2.cvtColor(bgr.to_ndarray(), cv2.COLOR_BGR2GRAY), dtype=np.uint8)


def _log_problems(path: Path, problems: dict[int, str]) -> None:
    """One warning per reason, naming the frames that got None for it."""
    by_reason: dict[str, list[int]] = {}
    for i, reason in sorted(problems.items()):
        by_reason.setdefault(reason, []).append(i)
    for reason, frames in by_reason.items():
        log.warning("%s: frame(s) %s failed: %s", path, _spans(frames), reason)


def _spans(frames: list[int]) -> str:
    """``[2, 3, 4, 7]`` -> ``"2-4, 7"`` (ascending input)."""
    spans: list[list[int]] = []
    for i in frames:
        if spans and i == spans[-1][1] + 1:
            spans[-1][1] = i
        else:
            spans.append([i, i])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in spans)
