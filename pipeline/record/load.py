"""Read a session's MCAP back into numpy arrays for analysis.

The file is read as a stream of records (never through its summary section), so a
recording whose writer was killed mid-write is read up to its last complete chunk.

Example::

    rec = pipeline.load_recording("recordings/demo.mcap")
    table = rec.metrics_table()                   # (F,) NumPy columns, one per metric
    ok = table["status"] == "ok"
    tips_m = rec.centerlines_m[ok, -1]            # (F_ok, 3) tip positions, metres
    print(table["frame"][ok][:5], tips_m[:5], table["iou/cam0"][ok].min())

Other MCAP readers decode the metrics channel (JSON) with :class:`JsonDecoderFactory`.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import struct
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zstandard
from google.protobuf.message import DecodeError
from mcap.decoder import DecoderFactory as McapDecoderFactory
from mcap.exceptions import McapError
from mcap.records import Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import CRCValidationError, StreamReader
from mcap.well_known import MessageEncoding
from mcap.writer import MCAP0_MAGIC
from mcap_protobuf.decoder import DecoderFactory
from numpy.typing import NDArray

from ..errors import RecordingError, home_meant
from ..reconstruct.radius_profile import RadiusProfile
from ..session.toml_file import require_regular_file
from .commit_marker import killed_commits
from .mcap_log import (
    CENTERLINE_TOPIC,
    METADATA_NAME,
    METRICS_SCHEMA,
    METRICS_TOPIC,
    POINTS_TOPIC,
    SMOOTHED_TOPIC,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Recording:
    """A session's reconstruction, as arrays (metres, world frame).

    Attributes
    ----------
    path : the MCAP file.
    camera_names : the cameras, in the order of the per-camera metrics.
    timestamps_ns : (F,) int64 frame times, ns since the Unix epoch.
    frame_indices : (F,) int64 frame indices in the session, increasing.
    statuses : (F,) str "ok", "empty" or "failed".
    centerlines_m : (F, N, 3) float64 curves base -> tip; NaN rows where no curve.
    points_m : F arrays (P_i, 3) float32 of occupied voxel centres.
    metrics : F dicts, the JSON of ``/reconstruction/metrics``.
    smoothed_centerlines_m : (F, N, 3) float64 after temporal smoothing, or None
        when the file has none (older run, or truncated before the end).
    complete : False when the file ended before its footer (a truncated recording).
    cameras : the cameras the frames were reconstructed with, "given" or "refined ..."
        (the refinement's summary line); "" when the file does not say.
    tube_end : the tube end the fit assumed, "flat" or "round", and how it was chosen
        (the summary's "tube end" line); "" when the file does not say.
    radius_profile : the tube's radius along it, read from the session's frames
        (:class:`pipeline.reconstruct.radius_profile.RadiusProfile`); None when the file does
        not say (each frame read its own).
    session : the name of the session recorded (its folder's); "" when the file does not say.
    damaged : True when the file ends whole (its closing magic) but bytes inside it are not
        the recording's (a disk or copy error, not a run stopped while writing): the frames
        before the damage are read, ``complete`` is False.
    videos : file name -> fingerprint of each video the frames came from
        (:func:`pipeline.session.video.video_fingerprint`); {} when the file does not say.
    """

    path: Path
    camera_names: tuple[str, ...]
    timestamps_ns: NDArray[np.int64]
    frame_indices: NDArray[np.int64]
    statuses: NDArray[np.str_]
    centerlines_m: NDArray[np.float64]
    points_m: list[NDArray[np.float32]]
    metrics: list[dict[str, Any]]
    smoothed_centerlines_m: NDArray[np.float64] | None
    complete: bool
    cameras: str = ""
    tube_end: str = ""
    radius_profile: RadiusProfile | None = None
    session: str = ""
    damaged: bool = False
    videos: dict[str, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frame_indices)

    def metrics_table(self) -> dict[str, NDArray[Any]]:
        """The per-frame metrics as columns, each an (F,) array in frame order.

        ``timestamp_ns``, ``frame`` and ``voxel_count`` int64; ``status`` and ``reason``
        str; ``length_m``, ``mean_curvature_per_m``, ``radius_m``, ``fit_residual_m``
        float64; nested figures under ``key/name``: ``tip_m/x`` (``/y``, ``/z``),
        ``iou/<camera>``, ``timings_s/<stage>``. NaN where a figure is unknown (null in
        the file, or absent from a frame). ``pandas.DataFrame(rec.metrics_table())``
        makes it a data frame.
        """
        names = dict.fromkeys(_schema_columns(self.camera_names))
        rows = [_flatten(m) for m in self.metrics]
        for row in rows:
            names.update(dict.fromkeys(row))
        table = {"timestamp_ns": self.timestamps_ns.copy()}
        table.update({name: _column([row.get(name) for row in rows]) for name in names})
        return table


class JsonDecoderFactory(McapDecoderFactory):
    """Decodes JSON channels, such as ``/reconstruction/metrics``, into dicts for the plain
    mcap reader, which has no JSON decoder of its own::

        from mcap.reader import make_reader
        from mcap_protobuf.decoder import DecoderFactory
        from pipeline.record.load import JsonDecoderFactory

        with open("recordings/demo.mcap", "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory(), JsonDecoderFactory()])
            for _, _, _, metrics in reader.iter_decoded_messages(topics=["/reconstruction/metrics"]):
                print(metrics["frame"], metrics["iou"])
    """

    def decoder_for(self, message_encoding: str, schema: Schema | None) -> Callable[[bytes], Any] | None:
        return json.loads if message_encoding == MessageEncoding.JSON else None


def _schema_columns(camera_names: Sequence[str]) -> list[str]:
    """The metrics' columns every recording has, whatever its frames hold (in schema order)."""
    names: list[str] = []
    for key in METRICS_SCHEMA["properties"]:
        if key == "tip_m":
            names += [f"{key}/{axis}" for axis in "xyz"]
        elif key == "iou":
            names += [f"{key}/{name}" for name in camera_names]
        elif key != "timings_s":  # its stages are whatever the frames recorded
            names.append(key)
    return names


def _flatten(metrics: dict[str, Any]) -> dict[str, Any]:
    """One frame's metrics with nested figures under ``key/name`` (``tip_m/x``, ``iou/cam0``)."""
    flat: dict[str, Any] = {}
    for key, value in metrics.items():
        if isinstance(value, dict):
            flat.update({f"{key}/{name}": v for name, v in value.items()})
        elif isinstance(value, list):
            flat.update({f"{key}/{axis}": v for axis, v in zip("xyz", value, strict=False)})
        elif value is not None:  # unknown: left out, as absent figures are (NaN in the column)
            flat[key] = value
    return flat


def _column(values: list[Any]) -> NDArray[Any]:
    """A column's values (None where unknown) -> bool, int64 or str when every value is one
    of those, str with "" for a missing string; otherwise float64 with NaN for unknown."""
    known = [v for v in values if v is not None]
    complete = len(known) == len(values)
    if known and all(isinstance(v, str) for v in known):
        return np.array([v if v is not None else "" for v in values], dtype=np.str_)
    if complete and known and all(isinstance(v, bool) for v in known):
        return np.array(values, dtype=bool)
    if complete and known and all(isinstance(v, int) and not isinstance(v, bool) for v in known):
        if all(_INT64.min <= v <= _INT64.max for v in known):
            return np.array(values, dtype=np.int64)
    return np.array([_as_float(v) for v in values], dtype=np.float64)


def _as_float(value: Any) -> float:
    """A figure as float64: NaN where unknown or not a number (another program's value: a
    table, a list), +-inf past float64's range."""
    if not isinstance(value, int | float):  # bool is an int
        return math.nan
    try:
        return float(value)
    except OverflowError:  # an integer past 1.8e308
        return math.inf if value > 0 else -math.inf


# What a truncated or torn file raises while its records are parsed (DecodeError: a
# message whose bytes are not the protobuf its schema names).
_TRUNCATION_ERRORS = (
    McapError,
    DecodeError,
    CRCValidationError,
    zstandard.ZstdError,
    struct.error,
    EOFError,
    ValueError,
    MemoryError,
)


# The first bytes of a Rerun .rrd file ("RRF2"; older versions wrote RRF0, RRF1).
_RRD_MAGIC = b"RRF"


def load_recording(path: Path | str | bytes, *, on_warning: Callable[[str], None] | None = None) -> Recording:
    """Read ``path`` (an MCAP written by the pipeline) into a :class:`Recording`.

    What is read but worth a word (a file cut short, the run that wrote it killed while
    putting its outputs in place, centrelines of different lengths) is a line naming the
    file, given to ``on_warning``; without it, each line is logged as a warning.
    """
    if isinstance(path, bytes):  # a path as the system gives it
        path = os.fsdecode(path)
    if not str(path):  # Path("") would be the current folder
        raise RecordingError("an empty path; give the recording's .mcap file")
    path = Path(path)
    # A line holds no %-formatting of its own: logged as it is (a path may hold a %).
    warn = on_warning if on_warning is not None else log.warning
    if killed_commits(path.parent, path.stem):
        warn(
            f"{path}: the run that wrote it was killed while putting its outputs in place: "
            f"{path.with_suffix('.rrd').name} may be an earlier run's; the next 'pipeline process' "
            f"of {path.stem} into {path.parent} puts the pair together"
        )
    try:
        require_regular_file(path)  # a named pipe would block the read until something wrote to it
        with path.open("rb") as f:
            if f.read(len(_RRD_MAGIC)) == _RRD_MAGIC:
                raise RecordingError(
                    f"{path}: is a Rerun recording (open it in the Rerun viewer); read the .mcap "
                    "written beside it"
                )
            f.seek(0)
            return _read(f, path, warn)
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read: {exc.strerror}{_what_to_give(path)}") from None


def _what_to_give(path: Path) -> str:
    """Advice for a recording ``path`` that cannot be read: a folder's .mcap files, or a ``~``
    nothing expanded (a quoted path, Python's own string)."""
    if path.is_dir():
        found = sorted(p.name for p in path.glob("*.mcap"))[:3]
        return f"; give the recording's .mcap file in it ({', '.join(found)})" if found else ""
    meant = home_meant(path)
    return f" (~ is not expanded here: give {meant})" if meant is not None else ""


def _read(stream: Any, path: Path, warn: Callable[[str], None]) -> Recording:
    """The recording in ``stream`` (the file ``path``), read up to its last complete chunk;
    ``warn`` takes a line for a file cut short."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    decoders = DecoderFactory()
    metadata: dict[str, str] = {}
    metrics: dict[int, tuple[int, dict[str, Any]]] = {}  # frame -> (log_time, metrics)
    points: dict[int, NDArray[np.float32]] = {}  # log_time -> points
    curves: dict[int, NDArray[np.float64] | None] = {}
    smoothed: dict[int, NDArray[np.float64] | None] = {}
    complete = damaged = False
    # validate_crcs: a chunk cut short fails its CRC (or its decompression) and is dropped whole.
    reader = StreamReader(stream, validate_crcs=True)
    try:
        for record in reader.records:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Metadata) and record.name == METADATA_NAME:
                metadata = dict(record.metadata)
            elif isinstance(record, Footer):
                complete = True
            elif isinstance(record, Message) and record.channel_id in channels:
                channel = channels[record.channel_id]
                topic = channel.topic
                if topic not in (METRICS_TOPIC, POINTS_TOPIC, CENTERLINE_TOPIC, SMOOTHED_TOPIC):
                    continue
                # A message the pipeline's readers cannot take is another program's where
                # neither the pipeline's metadata nor a frame came before it; after them,
                # damage the chunks' checksums missed (ValueError: read as far as it goes).
                ours = bool(metadata or metrics)
                if not 0 <= record.log_time <= _MAX_TIME_NS:
                    raise _foreign(path, topic, f"its time {record.log_time} ns is past 2262")
                if topic == METRICS_TOPIC:
                    if channel.message_encoding != MessageEncoding.JSON:
                        raise _foreign(path, topic, f"{channel.message_encoding or 'no'} encoding, not JSON")
                    frame, data = _frame_metrics(path, record.data, ours=ours)
                    metrics[frame] = (record.log_time, data)
                    continue
                decode = decoders.decoder_for(channel.message_encoding, schemas.get(channel.schema_id))
                if decode is None:
                    continue
                try:
                    message = decode(record.data)
                    if topic == POINTS_TOPIC:
                        points[record.log_time] = _points_from_cloud(message)
                    elif topic == CENTERLINE_TOPIC:
                        curves[record.log_time] = _curve_from_update(message)
                    else:
                        smoothed[record.log_time] = _curve_from_update(message)
                except _CONTENT_ERRORS as exc:
                    if ours:
                        raise ValueError(_why(exc)) from None
                    raise _foreign(path, topic, _why(exc)) from None
    except _TRUNCATION_ERRORS as exc:
        damaged = _ends_whole(stream)
        if not metrics and not metadata:
            why = " ".join(str(exc).split()) or type(exc).__name__
            if damaged:
                raise RecordingError(
                    f"{path}: {damage_line('before its first frame')}; {REWRITE} ({why})"
                ) from None
            if _starts_whole(stream):
                raise RecordingError(
                    f"{path}: an MCAP cut short before its first frame (the run that wrote it did "
                    "not finish), nothing to read; run `pipeline process` on its session again"
                ) from None
            raise RecordingError(f"{path}: {_not_mcap(path, why)}") from None
        where, read = (
            (f"after frame {max(metrics)}", "; read what precedes it")
            if metrics
            else ("before its first frame", "")
        )
        if damaged:
            warn(f"{path}: {damage_line(where)}{read}; {REWRITE}")
        else:
            warn(f"{path}: cut short {where} (the run did not finish){read}")
    else:
        if not metadata and not metrics:
            # The pipeline writes its metadata first: an MCAP without it is another program's.
            raise RecordingError(
                f"{path}: not a recording written by `pipeline process` (none of its metadata or "
                "frames); give the .mcap a run wrote"
            )
        if not complete:
            warn(f"{path}: no footer (the run did not finish); {len(metrics)} frames read")
    return _assemble(path, metadata, metrics, points, curves, smoothed, complete, damaged, warn)


def damage_line(where: str) -> str:
    """What a file that ends whole but cannot be read through ``where`` ("after frame 41",
    "before its first frame") is."""
    return f"damaged {where}: bytes inside the file are not the recording's (a disk or copy error)"


# What to do about a damaged recording.
REWRITE = "run `pipeline process` on its session again to write it anew"


def _starts_whole(stream: Any) -> bool:
    """Whether the file starts as an MCAP does, with its opening magic."""
    try:
        stream.seek(0)
        return bool(stream.read(len(MCAP0_MAGIC)) == MCAP0_MAGIC)
    except (OSError, ValueError):
        return False


def _ends_whole(stream: Any) -> bool:
    """Whether the file ends as a finished MCAP does, with its closing magic: one that does
    but cannot be read through was damaged inside, not cut short while being written."""
    try:
        # The opening magic alone (a file cut right after it) is the same bytes: a whole
        # file holds both.
        if stream.seek(0, os.SEEK_END) < 2 * len(MCAP0_MAGIC):
            return False
        stream.seek(-len(MCAP0_MAGIC), os.SEEK_END)
        return bool(stream.read(len(MCAP0_MAGIC)) == MCAP0_MAGIC)
    except (OSError, ValueError):
        return False


# Frame indices, message times and integer metrics are int64 in the Recording's arrays.
_INT64 = np.iinfo(np.int64)
_MAX_FRAME = _INT64.max


# Message times are nanoseconds (up to 2262).
_MAX_TIME_NS = _INT64.max
# What decoding another program's message as the pipeline's raises: bytes that are not
# its schema's, JSON nested past Python's recursion limit, fields it lacks.
_CONTENT_ERRORS = (
    ValueError,
    DecodeError,
    KeyError,
    AttributeError,
    TypeError,
    IndexError,
    RecursionError,
    OverflowError,
    MemoryError,
)


def _why(exc: BaseException) -> str:
    """What about a message ``exc`` says, in a few words."""
    if isinstance(exc, KeyError):
        return f"no field {exc}"
    if isinstance(exc, AttributeError):
        return f"another schema: no {exc.name}" if exc.name else "another schema"
    return (" ".join(str(exc).split()) or type(exc).__name__)[:80]


def _foreign(path: Path, topic: str, why: str) -> RecordingError:
    return RecordingError(
        f"{path}: {topic} holds a message that is not the pipeline's ({why}); give a recording "
        "written by `pipeline process`"
    )


def _frame_metrics(path: Path, data: bytes, *, ours: bool) -> tuple[int, dict[str, Any]]:
    """One ``/reconstruction/metrics`` message -> (frame index, metrics).

    RecordingError where the message is not the pipeline's metrics (JSON of an object with
    an integer ``frame`` and a string ``status``): another program's recording on the same
    topic. Bytes that are not JSON raise ValueError, as damage does, in a file that is the
    pipeline's (``ours``: its metadata or a frame came first).
    """
    try:
        metrics = json.loads(data)
    except (ValueError, RecursionError) as exc:  # not JSON, not UTF-8, nested past the limit
        if ours:
            raise ValueError(_why(exc)) from None
        reason = f"not JSON: {_why(exc)}"
    else:
        reason = _not_metrics(metrics)
        if not reason:
            return int(metrics["frame"]), metrics
    raise RecordingError(
        f"{path}: {METRICS_TOPIC} holds a message that is not the pipeline's metrics ({reason}); "
        "give a recording written by `pipeline process`"
    )


def _not_metrics(metrics: Any) -> str:
    """Why the parsed JSON ``metrics`` is not a frame's metrics; "" where it is one."""
    if not isinstance(metrics, dict):
        return "not a JSON object"
    frame = metrics.get("frame")
    if not isinstance(frame, int) or isinstance(frame, bool) or not 0 <= frame <= _MAX_FRAME:
        return f"no frame index: frame {str(frame)[:20]}"
    if not isinstance(metrics.get("status"), str):
        return f"no status in frame {frame}"
    return ""


def _points_from_cloud(cloud: Any) -> NDArray[np.float32]:
    """PointCloud with x, y, z float32 at offsets 0, 4, 8 -> (P, 3) float32 metres."""
    stride = cloud.point_stride or 12
    raw = np.frombuffer(cloud.data, dtype=np.uint8).reshape(-1, stride)
    offsets = {f.name: f.offset for f in cloud.fields}
    cols = [raw[:, offsets[a] : offsets[a] + 4].copy().view("<f4").ravel() for a in "xyz"]
    return np.column_stack(cols).astype(np.float32) if len(raw) else np.zeros((0, 3), np.float32)


def _curve_from_update(update: Any) -> NDArray[np.float64] | None:
    """SceneUpdate with one LINE_STRIP entity -> (N, 3) float64 metres; None for a deletion."""
    for entity in update.entities:
        for line in entity.lines:
            return np.array([(p.x, p.y, p.z) for p in line.points], dtype=np.float64).reshape(-1, 3)
    return None


def _camera_names(text: str) -> tuple[str, ...]:
    """The cameras of the metadata's "cameras": a JSON list of names, or (in recordings
    written before names could hold commas) the names joined by commas."""
    if text.startswith("["):
        with contextlib.suppress(ValueError):
            names = json.loads(text)
            if isinstance(names, list) and all(isinstance(n, str) for n in names):
                return tuple(names)
    return tuple(n for n in text.split(",") if n)


def _metrics_cameras(metrics: Iterable[dict[str, Any]]) -> tuple[str, ...]:
    """The cameras named by the first of ``metrics`` with per-camera IoUs; () for none."""
    for figures in metrics:
        iou = figures.get("iou")
        if isinstance(iou, dict) and iou and all(isinstance(name, str) for name in iou):
            return tuple(iou)
    return ()


def _stack(curves: dict[int, NDArray[np.float64] | None], times: list[int], n: int) -> NDArray[np.float64]:
    out = np.full((len(times), n, 3), np.nan)
    for row, t in enumerate(times):
        curve = curves.get(t)
        if curve is not None and curve.shape == (n, 3):
            out[row] = curve
    return out


def _assemble(
    path: Path,
    metadata: dict[str, str],
    metrics: dict[int, tuple[int, dict[str, Any]]],
    points: dict[int, NDArray[np.float32]],
    curves: dict[int, NDArray[np.float64] | None],
    smoothed: dict[int, NDArray[np.float64] | None],
    complete: bool,
    damaged: bool,
    warn: Callable[[str], None],
) -> Recording:
    frames = sorted(metrics)
    times = [metrics[i][0] for i in frames]
    lengths = {len(c) for c in curves.values() if c is not None}
    declared = metadata.get("centerline_points", "")
    # Without curves, the declared count sizes the (NaN) centrelines: a plausible one only.
    n = max(lengths) if lengths else int(declared) if declared.isdecimal() and len(declared) <= 5 else 0
    if len(lengths) > 1:
        warn(f"{path}: centrelines of different lengths {sorted(lengths)}; shorter ones read as NaN")
    # A file rewritten without its metadata (another tool's filter) still names them in its
    # metrics' per-camera figures, in the cameras' order.
    names = _camera_names(metadata.get("cameras", "")) or _metrics_cameras(metrics[i][1] for i in frames)
    return Recording(
        path=path,
        camera_names=names,
        timestamps_ns=np.array(times, dtype=np.int64),
        frame_indices=np.array(frames, dtype=np.int64),
        statuses=np.array([metrics[i][1]["status"] for i in frames], dtype=np.str_),
        centerlines_m=_stack(curves, times, n),
        points_m=[points.get(t, np.zeros((0, 3), np.float32)) for t in times],
        metrics=[metrics[i][1] for i in frames],
        # Written after the last frame: a file cut short may hold only part of it.
        smoothed_centerlines_m=_stack(smoothed, times, n) if smoothed and complete else None,
        complete=complete,
        cameras=metadata.get("cameras_used", ""),
        tube_end=metadata.get("tube_end", ""),
        radius_profile=RadiusProfile.from_json(metadata.get("radius_profile", "")),
        session=metadata.get("session", ""),
        damaged=damaged,
        videos=_videos(metadata.get("videos", "")),
    )


def _videos(text: str) -> dict[str, str]:
    """The recording's metadata "videos" (file name -> fingerprint, as JSON): {} where it
    has none or it is not such a table (a recording of live cameras, or another program's)."""
    try:
        table = json.loads(text) if text else {}
    except ValueError:
        return {}
    if not isinstance(table, dict):
        return {}
    return {str(k): v for k, v in table.items() if isinstance(v, str)}


def _not_mcap(path: Path, why: str) -> str:
    """Why ``path`` reads as no MCAP at all, and what to give instead: an empty file, text (a
    --json summary, say) or another kind of file."""
    try:
        with open(path, "rb") as file:
            head = file.read(64)
    except OSError:
        head = b""
    give = "give the .mcap that `pipeline process` wrote"
    if not head:
        return f"is empty (0 bytes); {give}"
    if head.lstrip()[:1] in (b"{", b"["):
        return f"is not an MCAP recording (it starts like JSON text: a --json summary?); {give}"
    return f"is not a readable MCAP recording ({why}); {give}"
