"""Process a whole session: frame ranges in parallel, recordings written in frame order.

The parent builds the per-session model once, splits the frames into contiguous
ranges and hands each range to a joblib task (loky processes locally, Dask on a
cluster). A task opens the videos itself, decodes only its frames and returns,
per frame, the small :class:`~pipeline.frame_result.FrameResult` plus compressed
media (JPEG images, PNG silhouettes); no full-resolution frame crosses a process
boundary. Results come back in order and go straight into the MCAP and Rerun
writers, whose files carry temporary names until the run is complete.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import itertools
import logging
import math
import os
import signal
import struct
import sys
import time
import uuid
import warnings
import zlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import IO, Any

import cv2
import numpy as np
from numpy.typing import NDArray

from .errors import OutputError, SessionError, SettingsError
from .frame_result import FrameResult
from .session import Session
from .smoothing import smooth_centerlines
from .video import read_frames

log = logging.getLogger(__name__)

# Ranges of this many frames at most: long enough that one seek per range is
# negligible, short enough that every worker gets several (load balance, retries).
MAX_RANGE_FRAMES = 100
MIN_RANGE_FRAMES = 8
RANGES_PER_WORKER = 4
JPEG_QUALITY = 85
BACKENDS = ("loky", "threading", "dask")
DASK_CONNECT_TIMEOUT_S = 10
# Silhouettes are drawn over the camera image in Rerun: a translucent tint (RGBA).
SILHOUETTE_RGBA = (0, 200, 255, 110)

Mask = NDArray[np.bool_]
Image = NDArray[np.uint8]
# (frame index, grey images in camera order, model) -> (result, silhouettes or None)
FrameFunction = Callable[[int, Sequence[Image], Any], tuple[FrameResult, Sequence[Mask] | None]]


@dataclass(frozen=True, eq=False)
class FrameOutput:
    """What a task returns per frame: the result and small, compressed media.

    jpegs : per camera JPEG bytes of the grey frame (b"" when not decoded), or None
        when images are disabled.
    silhouettes_png : per camera RGBA PNG bytes of the tinted silhouette, or None.
    """

    result: FrameResult
    jpegs: tuple[bytes, ...] | None
    silhouettes_png: tuple[bytes, ...] | None


@dataclass(frozen=True)
class RunSummary:
    """How a run went.

    frames_failed : (frame index, reason) for every failed frame, in order.
    outputs : (path, size in bytes) of each file written.
    exit_code : 0 when every frame is ok or empty, 1 when some failed.
    """

    frames_ok: int
    frames_empty: int
    frames_failed: list[tuple[int, str]]
    wall_s: float
    fps: float
    outputs: list[tuple[Path, int]] = field(default_factory=list)

    @property
    def exit_code(self) -> int:
        return 1 if self.frames_failed else 0

    def lines(self) -> list[str]:
        """The closing summary, one line per fact."""
        total = self.frames_ok + self.frames_empty + len(self.frames_failed)
        out = [
            f"frames: {total} processed, {self.frames_ok} ok, {self.frames_empty} empty, "
            f"{len(self.frames_failed)} failed",
        ]
        out += [f"  failed {span}: {reason}" for span, reason in compress_failures(self.frames_failed)]
        out.append(f"time: {self.wall_s:.1f} s wall, {self.fps:.1f} frames/s")
        out += [f"wrote {path} ({_human_size(size)})" for path, size in self.outputs]
        return out


def compress_failures(failed: Sequence[tuple[int, str]]) -> list[tuple[str, str]]:
    """[(3, "x"), (4, "x"), (5, "x"), (9, "y")] -> [("3-5", "x"), ("9", "y")]."""
    spans: list[tuple[int, int, str]] = []
    for index, reason in sorted(failed):
        if spans and spans[-1][1] == index - 1 and spans[-1][2] == reason:
            spans[-1] = (spans[-1][0], index, reason)
        else:
            spans.append((index, index, reason))
    return [(f"{a}" if a == b else f"{a}-{b}", reason) for a, b, reason in spans]


def _human_size(size: int) -> str:
    value = float(size)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if value < 1024 or unit == "GiB":
            return f"{value:.0f} {unit}" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1024
    return f"{size} B"


# -- the per-frame work (runs in the workers) ------------------------------------------------


def reconstruct_with_silhouettes(
    index: int, images: Sequence[Image], model: Any
) -> tuple[FrameResult, Sequence[Mask] | None]:
    """The default frame function: silhouettes, then the reconstruction from them."""
    from .reconstruct import frame_silhouettes, reconstruct_from_silhouettes

    masks = frame_silhouettes(images, model)
    return reconstruct_from_silhouettes(index, images, masks, model), masks


def _png_chunk(tag: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))


def encode_silhouette(mask: Mask) -> bytes:
    """(H, W) bool silhouette -> PNG bytes: 1 bit per pixel, transparent / tinted.

    Written by hand as a 1-bit palette PNG with a transparency chunk: ~0.1 ms and
    ~200 bytes per mask, where tinting an RGBA image and encoding it with OpenCV
    takes ~5 ms (three masks a frame would cost more than decoding the frame).
    """
    height, width = mask.shape
    rows = np.packbits(np.asarray(mask, dtype=bool), axis=1)  # MSB first, as PNG wants
    raw = np.hstack([np.zeros((height, 1), np.uint8), rows]).tobytes()  # filter 0 per row
    r, g, b, a = SILHOUETTE_RGBA
    return b"".join(
        [
            b"\x89PNG\r\n\x1a\n",
            _png_chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 1, 3, 0, 0, 0)),
            _png_chunk(b"PLTE", bytes([0, 0, 0, r, g, b])),
            _png_chunk(b"tRNS", bytes([0, a])),  # palette entry 0 fully transparent
            _png_chunk(b"IDAT", zlib.compress(raw, 6)),
            _png_chunk(b"IEND", b""),
        ]
    )


def _encode_jpeg(image: Image | None) -> bytes:
    if image is None:
        return b""
    ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    return jpeg.tobytes() if ok else b""


def _one_frame(
    index: int,
    images: list[Image | None],
    model: Any,
    camera_names: Sequence[str],
    frame_fn: FrameFunction,
    encode_images: bool,
    decode_s: float,
) -> FrameOutput:
    missing = [name for name, im in zip(camera_names, images, strict=True) if im is None]
    masks: Sequence[Mask] | None = None
    if missing:
        reason = f"camera {', '.join(missing)}: frame could not be decoded (video truncated or damaged)"
        result = FrameResult.failed(index, reason)
    else:
        try:
            result, masks = frame_fn(index, [im for im in images if im is not None], model)
        except Exception as exc:  # a frame's failure is data, never the end of the run
            result = FrameResult.failed(index, f"{type(exc).__name__}: {exc}")
    t0 = time.perf_counter()
    jpegs = tuple(_encode_jpeg(im) for im in images) if encode_images else None
    pngs = None if masks is None else tuple(encode_silhouette(m) for m in masks)
    timings = {"decode": decode_s, **result.timings_s, "encode": time.perf_counter() - t0}
    return FrameOutput(dataclasses.replace(result, timings_s=timings), jpegs, pngs)


def process_range(
    model: Any,
    video_paths: Sequence[Path],
    camera_names: Sequence[str],
    start: int,
    stop: int,
    *,
    images: bool = True,
    frame_fn: FrameFunction | None = None,
) -> list[FrameOutput]:
    """Decode frames ``start <= i < stop`` of every video and process them (one task)."""
    frame_fn = frame_fn or reconstruct_with_silhouettes
    readers = [read_frames(Path(p), start, stop) for p in video_paths]
    outputs = []
    frames = zip(*readers, strict=True)
    try:
        while True:
            t0 = time.perf_counter()
            decoded = next(frames, None)
            if decoded is None:
                break
            index = decoded[0][0]
            images_ = [image for _, image in decoded]
            decode_s = time.perf_counter() - t0
            outputs.append(_one_frame(index, images_, model, camera_names, frame_fn, images, decode_s))
    finally:
        for reader in readers:
            close = getattr(reader, "close", None)  # release the decoders now, not at GC
            if close is not None:
                close()
    return outputs


# -- ranges, scheduling and retries (parent) -------------------------------------------------


def frame_ranges(start: int, stop: int, n_workers: int) -> list[tuple[int, int]]:
    """Split ``[start, stop)`` into contiguous ranges of near-equal size, several per worker.

    The number of ranges is a multiple of the number of workers where the frames
    allow it: with 9 ranges on 2 workers the last one would run alone, a ninth of
    the run on one core.
    """
    n = stop - start
    if n <= 0:
        return []
    workers = max(1, n_workers)
    count = max(math.ceil(n / MAX_RANGE_FRAMES), RANGES_PER_WORKER * workers)
    count = math.ceil(count / workers) * workers
    count = max(1, min(count, n // MIN_RANGE_FRAMES))
    bounds = np.linspace(start, stop, count + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in itertools.pairwise(bounds)]


def _effective_jobs(jobs: int) -> int:
    cpus = os.cpu_count() or 1
    return max(1, cpus + 1 + jobs) if jobs < 0 else max(1, jobs)


@contextlib.contextmanager
def _backend(backend: str, scheduler: str | None, n_jobs: int, model: Any) -> Iterator[int]:
    """joblib's parallel_config for ``backend``, yielding the number of workers; for Dask,
    a client for the run (and a local cluster when no scheduler is given)."""
    import joblib

    if backend in ("loky", "threading"):
        with joblib.parallel_config(backend=backend, n_jobs=n_jobs):
            yield n_jobs
        return
    from distributed import Client, LocalCluster

    cluster = None
    if scheduler:
        try:
            client = Client(scheduler, timeout=DASK_CONNECT_TIMEOUT_S)
        except OSError as exc:  # refused, unreachable, timed out
            raise SettingsError(
                f"cannot reach the Dask scheduler at {scheduler} ({exc}); "
                "check --scheduler and that the scheduler is running"
            ) from None
    else:
        cluster = LocalCluster(n_workers=n_jobs, threads_per_worker=1, processes=True)
        client = Client(cluster)
    try:
        # The model is scattered to the workers once, not shipped with every range.
        with joblib.parallel_config(backend="dask", client=client, scatter=[model]):
            workers = len(client.scheduler_info().get("workers", {}))
            yield max(1, workers)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _run_ranges(
    ranges: list[tuple[int, int]],
    call: Callable[[tuple[int, int]], Any],
    n_jobs: int,
) -> Iterator[tuple[tuple[int, int], list[FrameOutput] | str]]:
    """Yield ``(range, outputs)`` in range order; ``(range, reason)`` for a range given up.

    A task that dies (a killed worker, out of memory) or raises takes the pool's
    in-flight work with it. The unfinished ranges are run again in a fresh pool; if
    that breaks too, each remaining range runs alone, and one that still dies is
    given up: its frames are marked failed and the run goes on.
    """
    from joblib import Parallel

    pending = list(ranges)
    for attempt in ("parallel", "retry", "isolated"):
        if not pending:
            return
        groups = [pending] if attempt != "isolated" else [[r] for r in pending]
        survivors: list[tuple[int, int]] = []
        for group in groups:
            done = 0
            try:
                parallel = Parallel(n_jobs=n_jobs, return_as="generator")
                for outputs in parallel(call(r) for r in group):
                    yield group[done], outputs
                    done += 1
            except Exception as exc:  # TerminatedWorkerError, BrokenProcessPool, a task's error
                first, last = group[done][0], group[done][1] - 1
                reason = f"worker died twice on frames {first}-{last} ({type(exc).__name__})"
                log.warning(
                    "a worker failed on frames %d onwards (%s: %s); %s",
                    group[done][0],
                    type(exc).__name__,
                    exc,
                    "giving up on this range" if attempt == "isolated" else "retrying in a fresh pool",
                )
                if attempt == "isolated":
                    yield group[done], reason
                else:
                    survivors.extend(group[done:])
        pending = survivors


# -- outputs ---------------------------------------------------------------------------------


def _partial(path: Path) -> Path:
    return path.with_name(f".{path.name}.partial")


def _open_partial(path: Path) -> IO[bytes]:
    """Open the temporary file for ``path``'s content (a seam for tests)."""
    return _partial(path).open("wb")


def _prepare_outputs(out_dir: Path, name: str, force: bool) -> tuple[Path, Path]:
    """Check, before any work, that the outputs can be written; return their final paths."""
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(
            f"{out_dir}: cannot create the output directory ({exc.strerror}); use --out"
        ) from None
    if not os.access(out_dir, os.W_OK):
        raise OutputError(f"{out_dir}: output directory is not writable; use --out to choose another")
    mcap_path, rrd_path = out_dir / f"{name}.mcap", out_dir / f"{name}.rrd"
    if not force:
        for path in (mcap_path, rrd_path):
            if path.exists():
                raise OutputError(f"{path}: already exists; use --force to replace it")
    try:
        probe = out_dir / f".{name}.{uuid.uuid4().hex}.probe"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise OutputError(f"{out_dir}: cannot write in the output directory ({exc.strerror})") from None
    return mcap_path, rrd_path


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM ends the run like Ctrl-C: cleanly, with temporary files removed."""

    def handler(signum: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _smooth(centerlines_mm: NDArray[np.float64], times_s: NDArray[np.float64]) -> NDArray[np.float64] | None:
    try:
        return np.asarray(smooth_centerlines(centerlines_mm, times_s), dtype=np.float64)
    except Exception as exc:  # the per-frame results are safe: lose the extra, not the run
        log.warning(
            "temporal smoothing failed (%s: %s); no smoothed centrelines logged", type(exc).__name__, exc
        )
        return None


# -- the run ---------------------------------------------------------------------------------


def process_session(
    session: Session,
    *,
    out_dir: Path = Path("recordings"),
    jobs: int = -1,
    backend: str = "loky",
    scheduler: str | None = None,
    frames: tuple[int, int | None] | None = None,
    images: bool = True,
    force: bool = False,
    curve: str | None = None,
    progress: bool = True,
    frame_fn: FrameFunction | None = None,
) -> RunSummary:
    """Reconstruct every frame of ``session`` into ``out_dir/<name>.mcap`` and ``.rrd``.

    Parameters
    ----------
    session : a loaded session (:func:`pipeline.load_session`).
    out_dir : output directory, created if needed.
    jobs : parallel workers; -1 = one per core, -2 = all but one, ...
    backend : "loky" (local processes), "threading" or "dask".
    scheduler : Dask scheduler address (with backend "dask"); None starts a local cluster.
    frames : (start, stop) to process only frames start <= i < stop (stop None: to the end).
    images : store the camera images (JPEG) in the recordings.
    force : replace existing outputs (atomically, at the end of the run).
    curve : centreline method, overriding session.toml ("fit" or "polyfit").
    progress : show a progress bar on stderr.
    frame_fn : replaces the per-frame computation (tests, experiments): called as
        ``frame_fn(index, images, session)`` and returning (FrameResult, silhouettes or
        None); must be picklable (a module-level function or a partial of one).

    Raises
    ------
    OutputError : an output exists (without ``force``), the directory is not
        writable, or the disk filled up; temporary files are removed.
    KeyboardInterrupt : Ctrl-C or SIGTERM, after removing temporary files.
    """
    t0 = time.perf_counter()
    if backend not in BACKENDS:
        raise SettingsError(f"backend {backend!r} unknown; use one of {', '.join(BACKENDS)}")
    out_dir = Path(out_dir)
    start, stop = _frame_span(session, frames)
    mcap_path, rrd_path = _prepare_outputs(out_dir, session.name, force)
    if curve is not None:
        settings = session.settings
        settings = dataclasses.replace(
            settings, centerline=dataclasses.replace(settings.centerline, method=curve)
        )
        session = dataclasses.replace(session, settings=settings)

    n_jobs = _effective_jobs(jobs)
    from joblib import delayed

    if frame_fn is None:
        from .reconstruct import build_model

        model: Any = build_model(session)
    else:
        model = session  # a replacement frame function gets the session as its model
    names = tuple(c.name for c in session.cameras)
    # Absolute paths: Dask workers may run elsewhere (with the session at the same path).
    videos = tuple(p.resolve() for p in session.video_paths)

    def call(span: tuple[int, int]) -> Any:
        # The model is a positional argument of its own: loky memory-maps its arrays and
        # Dask scatters it once (joblib's dask backend scatters arguments, not closures).
        return delayed(process_range)(
            model, videos, names, span[0], span[1], images=images, frame_fn=frame_fn
        )

    try:
        writer = _Writers(session, mcap_path, rrd_path, images=images)
    except OSError as exc:  # the disk filled up before the first frame
        raise _output_error(out_dir, exc) from None
    done = 0
    try:
        with (
            _sigterm_as_interrupt(),
            _backend(backend, scheduler, n_jobs, model) as n_workers,
            _progress(stop - start, progress) as bar,
        ):
            ranges = frame_ranges(start, stop, n_workers)
            for span, outputs in _run_ranges(ranges, call, n_jobs):
                if isinstance(outputs, str):
                    outputs = [FrameOutput(FrameResult.failed(i, outputs), None, None) for i in range(*span)]
                for out in outputs:
                    writer.write(out)
                done += len(outputs)
                bar.update(len(outputs))
        writer.finish()
    except KeyboardInterrupt:
        writer.abort()
        log.warning(
            "interrupted after %d of %d frames; temporary files removed, existing outputs untouched",
            done,
            stop - start,
        )
        raise
    except OSError as exc:
        writer.abort()
        raise _output_error(out_dir, exc) from None
    except BaseException:
        writer.abort()
        raise
    finally:
        if backend == "loky":
            _release_loky_workers()
    wall = time.perf_counter() - t0
    return writer.summary(wall)


def _release_loky_workers() -> None:
    """Stop this run's worker processes.

    They hold the memory-mapped model (hundreds of MB for fine grids) and would
    otherwise idle for minutes; and a later run in the same process (another session,
    a changed environment) should start from fresh workers, not inherit these.
    """
    from joblib.externals.loky import reusable_executor

    executor = getattr(reusable_executor, "_executor", None)  # loky keeps one per process
    if executor is not None:
        with contextlib.suppress(Exception):
            executor.shutdown(wait=True)


def _output_error(out_dir: Path, exc: OSError) -> OutputError:
    if exc.errno == errno.ENOSPC:
        return OutputError(f"{out_dir}: disk full while writing the recordings; free space and rerun")
    return OutputError(f"{out_dir}: cannot write the recordings ({exc.strerror or exc})")


def _frame_span(session: Session, frames: tuple[int, int | None] | None) -> tuple[int, int]:
    n = session.frame_count
    if frames is None:
        return 0, n
    start, stop = frames
    stop = n if stop is None else min(stop, n)
    if not 0 <= start < stop:
        raise SessionError(
            f"{session.directory}: --frames {start}:{frames[1] or ''} selects no frame "
            f"(the session has {n} frames, 0-{n - 1})"
        )
    return start, stop


@contextlib.contextmanager
def _progress(total: int, enabled: bool) -> Iterator[Any]:
    from tqdm import tqdm

    bar = tqdm(
        total=total, unit="frame", file=sys.stderr, disable=not enabled, dynamic_ncols=True, smoothing=0.1
    )
    try:
        yield bar
    finally:
        bar.close()


def _check_rrd_complete(partial: Path, final: Path) -> None:
    """Rerun writes from a background thread and reports a full disk only in its log:
    read the file's footer back before giving it its final name."""
    try:
        from rerun.chunk import RrdReader
    except ImportError:  # rerun-sdk without its [catalog] extra: trust the writer
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no footer" is said again by the error below
        try:
            RrdReader(partial).store()
        except (RuntimeError, ValueError, OSError) as exc:
            raise OutputError(
                f"{final}: the Rerun recording could not be written completely (disk full?); "
                f"free space and rerun ({' '.join(str(exc).split())[:200]})"
            ) from None


class _Writers:
    """The MCAP and Rerun writers of one run, their temporary files, and the tallies."""

    def __init__(self, session: Session, mcap_path: Path, rrd_path: Path, *, images: bool) -> None:
        import rerun as rr

        from .record_mcap import McapRecorder
        from .record_rerun import RerunRecorder, default_blueprint

        self.session = session
        self.mcap_path, self.rrd_path = mcap_path, rrd_path
        self._mcap_file: IO[bytes] | None = None
        self._stream: Any = None
        self.frames: list[int] = []
        self.times_ns: list[int] = []
        self.curves: list[NDArray[np.float64] | None] = []
        self.counts = {"ok": 0, "empty": 0}
        self.failed: list[tuple[int, str]] = []
        try:
            self._mcap_file = _open_partial(mcap_path)
            meta = {
                "session": session.name,
                "fps": repr(session.fps),
                "frame_count": str(session.frame_count),
                "centerline_points": str(session.settings.centerline.points),
                "centerline_method": session.settings.centerline.method,
                "start_time": session.settings.session.start_time.isoformat(),
            }
            self.mcap = McapRecorder(self._mcap_file, session.cameras, images=images, metadata=meta)
            self._stream = rr.RecordingStream(application_id="pipeline", recording_id=uuid.uuid4())
            # Deterministic files: no wall-clock "log_time" timeline, only frame and time.
            self._stream.set_log_time_enabled(False)
            self._stream.save(
                _partial(rrd_path), default_blueprint=default_blueprint([c.name for c in session.cameras])
            )
            self._stream.send_recording_name(session.name)
            self.rerun = RerunRecorder(self._stream, session.cameras, session.settings.workspace)
        except BaseException:
            self.abort()
            raise

    def write(self, out: FrameOutput) -> None:
        result = out.result
        time_ns = self.session.timestamp_ns(result.index)
        self.mcap.write_frame(result, time_ns, jpegs=out.jpegs)
        self.rerun.write_frame(result, time_ns, jpegs=out.jpegs, silhouettes_png=out.silhouettes_png)
        self.frames.append(result.index)
        self.times_ns.append(time_ns)
        self.curves.append(result.centerline_mm if result.status == "ok" else None)
        if result.status == "failed":
            self.failed.append((result.index, result.reason))
        else:
            self.counts[result.status] = self.counts.get(result.status, 0) + 1

    def _smoothed(self) -> NDArray[np.float64] | None:
        lengths = {len(c) for c in self.curves if c is not None}
        if len(lengths) != 1:
            return None
        (n,) = lengths
        stacked = np.full((len(self.curves), n, 3), np.nan)
        for row, curve in enumerate(self.curves):
            if curve is not None:
                stacked[row] = curve
        start_ns = self.times_ns[0]
        times_s = (np.asarray(self.times_ns, dtype=np.int64) - start_ns).astype(np.float64) * 1e-9
        return _smooth(stacked, times_s)

    def finish(self) -> None:
        """Smoothing, footers, then the renames that make the outputs appear."""
        wanted = self.frames and self.session.settings.centerline.smooth
        smoothed = self._smoothed() if wanted else None
        if smoothed is not None:
            self.mcap.write_smoothed(smoothed, self.times_ns)
            self.rerun.write_smoothed(smoothed, self.frames, self.times_ns)
        self.mcap.finish()
        assert self._mcap_file is not None
        self._mcap_file.flush()
        os.fsync(self._mcap_file.fileno())
        self._mcap_file.close()
        self.rerun.finish()
        self._stream.flush()
        self._stream.disconnect()
        _check_rrd_complete(_partial(self.rrd_path), self.rrd_path)
        for path in (self.mcap_path, self.rrd_path):
            os.replace(_partial(path), path)

    def abort(self) -> None:
        """Close everything and remove the temporary files; finished outputs are untouched."""
        with contextlib.suppress(Exception):
            if self._mcap_file is not None:
                self._mcap_file.close()
        with contextlib.suppress(Exception):
            if self._stream is not None:
                self._stream.disconnect()
        for path in (self.mcap_path, self.rrd_path):
            with contextlib.suppress(FileNotFoundError):
                _partial(path).unlink()

    def summary(self, wall_s: float) -> RunSummary:
        n = len(self.frames)
        return RunSummary(
            frames_ok=self.counts.get("ok", 0),
            frames_empty=self.counts.get("empty", 0),
            frames_failed=list(self.failed),
            wall_s=wall_s,
            fps=n / wall_s if wall_s > 0 else 0.0,
            outputs=[(p, p.stat().st_size) for p in (self.mcap_path, self.rrd_path)],
        )
