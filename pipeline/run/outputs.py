"""The outputs of a run: the MCAP and Rerun files under temporary names, and the summary.

Both files are written as ``.<name>.<run>.partial`` beside their final names (``<run>``
unique to the run) and renamed into place (``os.replace``) only when both are
complete, so an interrupted or failed run never leaves a truncated file under a final
name, and replaces existing outputs only then. A lock on ``.<session>.lock`` in the
output folder keeps a second run of the same session out while one writes; the run
that holds it removes what dead runs left behind.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import threading
import uuid
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ..errors import OutputError
from ..reconstruct.frame_task import FrameOutput
from ..reconstruct.quality import DOUBTFUL_IOU, is_doubtful, reaches_walls
from ..record.commit_marker import killed_commits, marker_path, marker_run
from ..session.folder import Session, check_utf8_path
from .interrupts import deferred_signals
from .smoothing import smooth_centerlines

if TYPE_CHECKING:  # the recorders are imported when a run opens its writers
    from ..record.mcap_log import MessageMirror

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunSummary:
    """How a run went.

    frames_failed : (frame index, reason) for every failed frame, in order.
    outputs : (path, size in bytes) of each file written.
    frames_doubtful : indices of "ok" frames whose tube re-projects poorly onto some
        camera's silhouette (``quality.is_doubtful``), in order.
    frames_at_walls : indices of "ok" frames whose hull lies against a wall of the
        workspace box other than the base's (``quality.reaches_walls``), in order.
    frames_suspect : (frame index, reason) of "ok" frames whose curve may be wrong
        (``FrameResult.suspect_reason``), in order.
    tip : the tube end the fit assumed, and how it was chosen ("" when not told).
    cameras : the cameras reconstructed with, given or refined, and why ("" when not told).
    camera_warnings : a line per camera that seems to have moved since its calibration.
    exit_code : 0 when every frame is ok or empty, 1 when some failed or none holds a tube.
    """

    frames_ok: int
    frames_empty: int
    frames_failed: list[tuple[int, str]]
    wall_s: float
    fps: float
    outputs: list[tuple[Path, int]] = field(default_factory=list)
    frames_doubtful: list[int] = field(default_factory=list)
    frames_at_walls: list[int] = field(default_factory=list)
    frames_suspect: list[tuple[int, str]] = field(default_factory=list)
    tip: str = ""
    cameras: str = ""
    camera_warnings: list[str] = field(default_factory=list)

    @property
    def frames_total(self) -> int:
        return self.frames_ok + self.frames_empty + len(self.frames_failed)

    @property
    def exit_code(self) -> int:
        # A run that found no tube anywhere produced nothing to analyse: not a success.
        return 1 if self.frames_failed or self.frames_ok == 0 else 0

    def lines(self) -> list[str]:
        """The closing summary, one line per fact; :meth:`problem_lines` among them."""
        total = self.frames_total
        out = [
            f"frames: {total} processed, {self.frames_ok} ok, {self.frames_empty} empty, "
            f"{len(self.frames_failed)} failed",
        ]
        if self.tip:
            out.append(f"  tube end: {self.tip}")
        if self.cameras:
            out.append(f"  cameras: {self.cameras}")
        out += self.problem_lines()
        out.append(f"time: {self.wall_s:.1f} s wall, {self.fps:.1f} frames/s")
        out += [f"wrote {path} ({_human_size(size)})" for path, size in self.outputs]
        return out

    def problem_lines(self) -> list[str]:
        """The summary's failure and warning lines: failed frames, suspect frames, doubtful
        frames, frames at the walls, no tube found."""
        out = [f"  failed {span}: {reason}" for span, reason in compress_failures(self.frames_failed)]
        out += [f"  {line}" for line in self.camera_warnings]
        if self.frames_suspect:
            first, why = self.frames_suspect[0]
            frames = [i for i, _ in self.frames_suspect]
            out.append(
                f"  suspect: {len(frames)} of the ok frames ({_spans(frames)}) may be wrong "
                f"(frame {first}: {why}); each frame's metrics say why (suspect_reason)"
            )
        if self.frames_doubtful:
            out.append(
                f"  doubtful: {len(self.frames_doubtful)} of the ok frames ({_spans(self.frames_doubtful)}) "
                f"re-project poorly onto a camera's silhouette (IoU < {DOUBTFUL_IOU:g}): check "
                "[silhouette] method, threshold and polarity in session.toml"
            )
        if self.frames_at_walls:
            out.append(
                f"  at the walls: in {len(self.frames_at_walls)} of the ok frames "
                f"({_spans(self.frames_at_walls)}) the hull reaches a wall of the workspace box, "
                "where the tube may go on out of sight and its curve end short: enlarge [workspace] "
                "size_mm, or move origin_mm"
            )
        if self.frames_ok == 0 and self.frames_empty:
            out.append(
                "  no tube in any frame: check [silhouette] polarity (dark or bright tube) and "
                "threshold in session.toml"
            )
        return out

    def to_dict(self) -> dict[str, Any]:
        """The summary as JSON-ready data (``process --json``): the counts, the failed frames
        with their reasons, the suspect frames with theirs, the doubtful frames and those at
        the walls, the tube end assumed, the problem lines,
        wall time (s), frames per second, the outputs (path, bytes) and the exit status."""
        return {
            "frames": {
                "processed": self.frames_total,
                "ok": self.frames_ok,
                "empty": self.frames_empty,
                "failed": len(self.frames_failed),
            },
            "failed": [{"frame": index, "reason": reason} for index, reason in self.frames_failed],
            "suspect": [{"frame": index, "reason": reason} for index, reason in self.frames_suspect],
            "doubtful": list(self.frames_doubtful),
            "at_walls": list(self.frames_at_walls),
            "tip": self.tip,
            "cameras": self.cameras,
            "problems": [line.strip() for line in self.problem_lines()],
            "wall_s": self.wall_s,
            "fps": self.fps,
            "outputs": [{"path": str(path), "bytes": size} for path, size in self.outputs],
            "exit_code": self.exit_code,
        }


# Frame spans a summary line (doubtful frames, frames at the walls) lists before "...".
_SPANS_SHOWN = 6


def _spans(frames: Sequence[int]) -> str:
    """ "2-4, 9, ..." for frames [2, 3, 4, 9, ...]: the first _SPANS_SHOWN spans."""
    spans = [span for span, _ in compress_failures([(i, "") for i in frames])]
    return ", ".join(spans[:_SPANS_SHOWN]) + (", ..." if len(spans) > _SPANS_SHOWN else "")


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


def _open_partial(path: Path) -> IO[bytes]:
    """Create the temporary file ``path`` (a seam for tests); the name is this run's alone."""
    return path.open("xb")


def _display(path: Path) -> str:
    """``path`` as printable text (bytes that are not UTF-8 shown as U+FFFD)."""
    return os.fsencode(path).decode("utf-8", "replace")


class OutputTarget:
    """Where one run writes ``<out_dir>/<name>.mcap`` and ``.rrd``: their temporary names,
    the lock that keeps other runs of the session out, the folders this run created.

    Made by :func:`prepare_outputs`; :meth:`commit` puts the pair in place,
    :meth:`release` removes the lock (and, after a failure, the folders it created
    if they are still empty).
    """

    def __init__(self, out_dir: Path, name: str, created: list[Path]) -> None:
        self.out_dir, self.name = out_dir, name
        self.mcap_path, self.rrd_path = out_dir / f"{name}.mcap", out_dir / f"{name}.rrd"
        self.run = f"{os.getpid()}-{uuid.uuid4().hex[:8]}"
        self._created = created
        self._lock_path = out_dir / f".{name}.lock"
        self._lock_fd: int | None = None

    @property
    def finals(self) -> tuple[Path, Path]:
        return self.mcap_path, self.rrd_path

    def partial(self, path: Path) -> Path:
        """This run's temporary name for the final ``path``."""
        return path.with_name(f".{path.name}.{self.run}.partial")

    def _backup(self, path: Path) -> Path:
        return path.with_name(f".{path.name}.{self.run}.old")

    def lock(self) -> None:
        """Take the session's lock in the folder, or raise OutputError if another run has it."""
        while True:
            fd = os.open(self._lock_path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                raise OutputError(
                    f"another run is writing {self.name} in {_display(self.out_dir)}; wait for it to "
                    "finish, or give this run another --out"
                ) from None
            # The previous holder removes the file as it lets go: a lock on a removed file
            # is no lock, so check that the file is still the one at the path.
            try:
                if os.path.samestat(os.fstat(fd), os.stat(self._lock_path)):
                    break
            except FileNotFoundError:
                pass
            os.close(fd)
        self._lock_fd = fd
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._finish_killed_commits()
        self._remove_stale()

    def _finish_killed_commits(self) -> None:
        """Put in place the rest of a pair whose run was killed between its renames (SIGKILL,
        power loss), as that run would have: its temporary files are complete by then, so
        the folder holds its new pair, not a new .mcap beside an old .rrd."""
        for marker in killed_commits(self.out_dir, self.name):
            run = marker_run(marker, self.name)
            for final in self.finals:
                partial = final.with_name(f".{final.name}.{run}.partial")
                if partial.exists():
                    os.replace(partial, final)
            _sync_folder(self.out_dir)
            marker.unlink()
            log.warning(
                "%s, %s: the run that wrote them was killed while putting them in place; "
                "put in place now, both are that run's",
                _display(self.mcap_path),
                self.rrd_path.name,
            )

    def _remove_stale(self) -> None:
        """Remove the temporary files of this session's earlier runs: with the lock held,
        no run is writing them (they died: SIGKILL, power loss)."""
        prefixes = tuple(f".{p.name}." for p in self.finals)
        for entry in os.scandir(self.out_dir):
            if entry.name.startswith(prefixes) and entry.name.endswith((".partial", ".old")):
                with contextlib.suppress(OSError):
                    os.unlink(entry.path)
                    log.debug("removed %s, left by a run that did not finish", entry.path)

    def commit(self) -> None:
        """Rename both temporary files into place: afterwards the folder holds the new pair,
        or, if a rename fails, the old pair (or none) as before.

        A marker file names the run while it renames, so that if it is killed between the
        two renames, the next run of the session in the folder puts the rest in place
        (:meth:`lock`), and :func:`pipeline.record.load.load_recording` warns meanwhile."""
        backups: list[tuple[Path, Path]] = []
        placed: list[Path] = []
        marker = marker_path(self.out_dir, self.name, self.run)
        try:
            for final in self.finals:
                if final.exists():
                    backup = self._backup(final)
                    try:
                        os.link(final, backup)  # the old file stays in place meanwhile
                    except OSError:  # a file system without hard links
                        os.replace(final, backup)
                    backups.append((final, backup))
            marker.touch(exist_ok=False)
            _sync_folder(self.out_dir)  # on disk before any rename
            for final in self.finals:
                os.replace(self.partial(final), final)
                placed.append(final)
            _sync_folder(self.out_dir)
            marker.unlink()
        except BaseException:
            with contextlib.suppress(OSError):
                marker.unlink()  # the old pair goes back: nothing for a later run to finish
            restored = dict(backups)
            for final in placed:
                with contextlib.suppress(OSError):
                    if final in restored:
                        os.replace(restored.pop(final), final)
                    else:
                        final.unlink()
            for final, backup in restored.items():  # moved aside but not yet replaced
                with contextlib.suppress(OSError):
                    if not final.exists():
                        os.replace(backup, final)
            raise
        finally:
            for _, backup in backups:
                with contextlib.suppress(FileNotFoundError):
                    backup.unlink()

    def release(self, *, failed: bool) -> None:
        """Let go of the lock; after a failure, remove the folders this run created if empty."""
        if self._lock_fd is not None:
            with contextlib.suppress(OSError):
                self._lock_path.unlink()  # while still held: see lock()
            os.close(self._lock_fd)
            self._lock_fd = None
        if failed:
            for folder in reversed(self._created):  # deepest first
                with contextlib.suppress(OSError):
                    folder.rmdir()


def _sync_folder(folder: Path) -> None:
    """Write ``folder``'s entries (created, renamed files) to disk, where the system can."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def prepare_outputs(out_dir: Path, name: str, force: bool) -> OutputTarget:
    """Check, before any work, that the outputs can be written, and take the folder's lock
    for ``name``. Call :meth:`OutputTarget.release` when the run ends."""
    check_utf8_path(out_dir, "choose an --out path in UTF-8", OutputError)
    for folder in (out_dir, *out_dir.parents):
        if folder.exists() and not folder.is_dir():
            where = "" if folder == out_dir else f" (in {out_dir})"
            raise OutputError(f"{folder}: is a file, not a directory{where}; give --out a directory")
    created = [f for f in (out_dir, *out_dir.parents) if not f.exists() and not f.is_symlink()][::-1]
    target = OutputTarget(out_dir, name, created)
    try:
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(
                f"{out_dir}: cannot create the output directory ({exc.strerror}); use --out"
            ) from None
        if not os.access(out_dir, os.W_OK):
            raise OutputError(f"{out_dir}: output directory is not writable; use --out to choose another")
        try:
            target.lock()
        except OSError as exc:
            raise OutputError(f"{out_dir}: cannot write in the output directory ({exc.strerror})") from None
        if not force:
            for path in target.finals:
                if path.exists():
                    raise OutputError(f"{path}: already exists; use --force to replace it")
    except BaseException:
        target.release(failed=True)
        raise
    return target


def output_error(out_dir: Path, exc: OSError) -> OutputError:
    if exc.errno == errno.ENOSPC:
        return OutputError(f"{out_dir}: disk full while writing the recordings; free space and rerun")
    return OutputError(f"{out_dir}: cannot write the recordings ({exc.strerror or exc})")


# How long the Rerun writer may take to write out what it still holds at the end of a run:
# seconds on any disk that takes writes; its flush otherwise waits for good (a full disk).
FLUSH_TIMEOUT_S = 60.0
# How long opening or closing the Rerun file may take (milliseconds on a disk that takes
# writes): on a full disk Rerun's writer is stuck, and both wait for it with no bound of
# their own and deaf to Ctrl-C, even when the run ends for another reason (the MCAP met
# the full disk first).
RERUN_WAIT_S = 10.0
# What a live run's viewer may take to receive its last frames.
VIEWER_FLUSH_S = 2.0


# Rerun streams whose writer is stuck, kept from being dropped until the process exits.
_STUCK_STREAMS: list[Any] = []


def _within(seconds: float, call: Callable[[], object]) -> bool:
    """Run ``call`` in a daemon thread: True once it has returned (re-raising here what it
    raised), False if it has not within ``seconds``; it is then left to the exit."""
    done = threading.Event()
    raised: list[BaseException] = []

    def run() -> None:
        try:
            call()
        except BaseException as exc:
            raised.append(exc)
        finally:
            done.set()

    threading.Thread(target=run, name="rerun-wait", daemon=True).start()
    if not done.wait(seconds):
        return False
    if raised:
        raise raised[0]
    return True


def _stalled_error(path: Path, what: str) -> OutputError:
    return OutputError(
        f"{path}: the Rerun recording was not {what} within {RERUN_WAIT_S:g} s (disk full, or a "
        "stalled file system?); free space or choose another --out, and rerun"
    )


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
            raise _incomplete_rrd_error(final, exc) from None


def _incomplete_rrd_error(final: Path, exc: Exception) -> OutputError:
    return OutputError(
        f"{final}: the Rerun recording could not be written completely (disk full?); "
        f"free space and rerun ({' '.join(str(exc).split())[:200]})"
    )


def _smooth(centerlines_mm: NDArray[np.float64], times_s: NDArray[np.float64]) -> NDArray[np.float64] | None:
    try:
        return np.asarray(smooth_centerlines(centerlines_mm, times_s), dtype=np.float64)
    except Exception as exc:  # the per-frame results are safe: lose the extra, not the run
        log.warning(
            "temporal smoothing failed (%s: %s); no smoothed centrelines logged", type(exc).__name__, exc
        )
        return None


class Writers:
    """The MCAP and Rerun writers of one run, their temporary files, and the tallies.

    A live run passes ``viewer_url`` (the frames are also logged, as they come, to a Rerun
    viewer at that gRPC address) and ``mirror`` (every MCAP message is also handed to it:
    the Foxglove server). ``cameras_used`` says in the MCAP's metadata which cameras the
    frames were reconstructed with (the summary's line of :mod:`pipeline.calibrate.refine`).
    """

    def __init__(
        self,
        session: Session,
        target: OutputTarget,
        *,
        images: bool,
        viewer_url: str | None = None,
        mirror: MessageMirror | None = None,
        cameras_used: str = "",
    ) -> None:
        # Imported here, not with this module: a run's parent opens its writers once
        # the workers have their first frames, so Rerun's import no longer holds them up.
        import rerun as rr

        from ..record.mcap_log import McapRecorder
        from ..record.rerun_log import RerunRecorder, default_blueprint

        self.session = session
        self.target = target
        self.mcap_path, self.rrd_path = target.mcap_path, target.rrd_path
        self._mcap_file: IO[bytes] | None = None
        self._stream: Any = None
        self._viewer_stream: Any = None
        self.viewer: RerunRecorder | None = None
        self._stalled = False  # the Rerun writer did not finish within its bound
        self.frames: list[int] = []
        self.times_ns: list[int] = []
        self.curves: list[NDArray[np.float64] | None] = []
        self.counts = {"ok": 0, "empty": 0}
        self.failed: list[tuple[int, str]] = []
        self.doubtful: list[int] = []
        self.suspect: list[tuple[int, str]] = []
        self.at_walls: list[int] = []
        try:
            self._mcap_file = _open_partial(target.partial(self.mcap_path))
            meta = {
                "session": session.name,
                "fps": repr(session.fps),
                "frame_count": str(session.frame_count),
                "centerline_points": str(session.settings.centerline.points),
                "centerline_method": session.settings.centerline.method,
                "start_time": session.settings.session.start_time.isoformat(),
            }
            if cameras_used:
                meta["cameras_used"] = cameras_used
            self.mcap = McapRecorder(
                self._mcap_file, session.cameras, images=images, metadata=meta, mirror=mirror
            )
            recording_id = uuid.uuid4()
            self._stream = rr.RecordingStream(application_id="pipeline", recording_id=recording_id)
            # Deterministic files: no wall-clock "log_time" timeline, only frame and time.
            self._stream.set_log_time_enabled(False)
            blueprint = default_blueprint(session.cameras, session.settings.workspace, fps=session.fps)
            partial_rrd = target.partial(self.rrd_path)
            if not _within(RERUN_WAIT_S, lambda: self._stream.save(partial_rrd, default_blueprint=blueprint)):
                self._stalled = True
                raise _stalled_error(self.rrd_path, "started")
            self._stream.send_recording_name(session.name)
            if viewer_url is not None:
                # A stream of its own, the same recording to the viewer: the viewer gets each
                # frame within LIVE_SEND_S, the file its frames a hundred at a time as from
                # process (the footer of an .rrd indexes every chunk: sent ten times a second,
                # its index alone grew by 15 MiB a minute).
                self._viewer_stream = rr.RecordingStream(application_id="pipeline", recording_id=recording_id)
                self._viewer_stream.set_log_time_enabled(False)
                self._viewer_stream.set_sinks(rr.GrpcSink(viewer_url), default_blueprint=blueprint)
                self._viewer_stream.send_recording_name(session.name)
                self.viewer = RerunRecorder(
                    self._viewer_stream, session.cameras, session.settings.workspace, live=True
                )
            self.rerun = RerunRecorder(self._stream, session.cameras, session.settings.workspace)
        except OSError as exc:
            self.abort()
            raise output_error(target.out_dir, exc) from None
        except BaseException:
            self.abort()
            raise
        self.committed = False

    def write(
        self, out: FrameOutput, *, time_ns: int | None = None, extra_metrics: dict[str, float] | None = None
    ) -> None:
        """One frame, at ``time_ns`` (ns since the Unix epoch; default: the session's time of
        its index); ``extra_metrics``: figures its metrics gain (a live run's latency)."""
        result = out.result
        if time_ns is None:
            time_ns = self.session.timestamp_ns(result.index)
        try:
            self.mcap.write_frame(result, time_ns, jpegs=out.jpegs, extra_metrics=extra_metrics)
        except OSError as exc:
            raise output_error(self.target.out_dir, exc) from None
        self.rerun.write_frame(result, time_ns, jpegs=out.jpegs, silhouettes_png=out.silhouettes_png)
        if self.viewer is not None:
            self.viewer.write_frame(result, time_ns, jpegs=out.jpegs, silhouettes_png=out.silhouettes_png)
        self.frames.append(result.index)
        self.times_ns.append(time_ns)
        self.curves.append(result.centerline_mm if result.status == "ok" else None)
        if result.status == "failed":
            self.failed.append((result.index, result.reason))
        else:
            self.counts[result.status] = self.counts.get(result.status, 0) + 1
        if result.status == "ok" and is_doubtful(result.iou):
            self.doubtful.append(result.index)
        if result.status == "ok" and result.suspect:
            self.suspect.append((result.index, result.suspect_reason))
        curve = result.centerline_mm
        if result.status == "ok" and curve is not None and len(curve):
            if reaches_walls(result.points_mm, self.session.settings.workspace, curve[0]):
                self.at_walls.append(result.index)

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
        try:
            self._finish()
        except OSError as exc:
            raise output_error(self.target.out_dir, exc) from None

    def _finish(self) -> None:
        wanted = self.frames and self.session.settings.centerline.smooth
        smoothed = self._smoothed() if wanted else None
        if smoothed is not None:
            self.mcap.write_smoothed(smoothed, self.times_ns)
            self.rerun.write_smoothed(smoothed, self.frames, self.times_ns)
            if self.viewer is not None:
                self.viewer.write_smoothed(smoothed, self.frames, self.times_ns)
        self.mcap.finish()
        assert self._mcap_file is not None
        self._mcap_file.flush()
        os.fsync(self._mcap_file.fileno())
        self._mcap_file.close()

        # In a thread of its own, so that Ctrl-C is heard meanwhile (Rerun's flush is not).
        def flush() -> None:
            self.rerun.finish(flush_timeout_s=FLUSH_TIMEOUT_S)

        try:
            flushed = _within(FLUSH_TIMEOUT_S + RERUN_WAIT_S, flush)
        except RuntimeError as exc:
            if "timed out" not in str(exc):  # Rerun's words for an expired bound
                # Its file writer stopped ("File-writer thread shut down prematurely"):
                # the disk filled up under it.
                raise _incomplete_rrd_error(self.rrd_path, exc) from None
            flushed = False
        if not flushed:
            self._stalled = True
            raise OutputError(
                f"{self.rrd_path}: the Rerun recording was not written within {FLUSH_TIMEOUT_S:g} s "
                "(disk full, or a stalled file system?); free space or choose another --out, and rerun"
            ) from None
        if not _within(RERUN_WAIT_S, self._stream.disconnect):
            self._stalled = True
            raise _stalled_error(self.rrd_path, "closed")
        self._close_viewer()
        _check_rrd_complete(self.target.partial(self.rrd_path), self.rrd_path)
        with deferred_signals():  # a signal between the two renames would split the pair
            self.target.commit()
            self.committed = True

    def _close_viewer(self) -> None:
        """Send the viewer what it has not got yet, within VIEWER_FLUSH_S: a viewer that went
        away costs the run its view, never its files."""
        if self.viewer is None:
            return
        try:
            self.viewer.finish(flush_timeout_s=VIEWER_FLUSH_S)
        except RuntimeError as exc:
            log.warning(
                "the Rerun viewer did not take the last frames (%s)", " ".join(str(exc).split())[:160]
            )
        self._viewer_stream.disconnect()
        self.viewer = None

    def abort(self) -> None:
        """Close everything and remove the temporary files; finished outputs are untouched."""
        with contextlib.suppress(Exception):
            if self._mcap_file is not None:
                self._mcap_file.close()
        # A stream whose writer is stuck (a full disk) would hold up the exit too, in Rerun's
        # handler at exit: leave it to the operating system.
        if self._stream is not None and not self._stalled:
            try:
                self._stalled = not _within(RERUN_WAIT_S, self._stream.disconnect)
            except Exception as exc:
                log.debug("closing the Rerun stream failed: %s", exc)
        if self._stalled:
            import rerun as rr

            rr.unregister_shutdown()
            # Dropping the stream waits for its writer too (RecordingStream.__del__): keep it.
            _STUCK_STREAMS.append(self._stream)
        if self._viewer_stream is not None:
            with contextlib.suppress(Exception):
                _within(RERUN_WAIT_S, self._viewer_stream.disconnect)
        for path in (self.mcap_path, self.rrd_path):
            with contextlib.suppress(FileNotFoundError):
                self.target.partial(path).unlink()

    def summary(self, wall_s: float) -> RunSummary:
        n = len(self.frames)
        return RunSummary(
            frames_ok=self.counts.get("ok", 0),
            frames_empty=self.counts.get("empty", 0),
            frames_failed=list(self.failed),
            wall_s=wall_s,
            fps=n / wall_s if wall_s > 0 else 0.0,
            outputs=[(p, p.stat().st_size) for p in (self.mcap_path, self.rrd_path)],
            frames_doubtful=list(self.doubtful),
            frames_at_walls=list(self.at_walls),
            frames_suspect=list(self.suspect),
        )
