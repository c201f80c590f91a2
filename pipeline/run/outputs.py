"""The writers of a run: frames to the MCAP and Rerun files as they arrive, then the smoothing.

:class:`Writers` opens both recorders on the temporary names of an
:class:`~pipeline.run.output_target.OutputTarget`, writes each frame, and at the end
logs the smoothed centrelines, closes both files within bounded times (a full or stalled
disk is an error, not a hang) and has the target rename them into place.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import os
import threading
import uuid
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ..errors import OutputError
from ..reconstruct.frame_result import NO_SHARED_VOXEL
from ..reconstruct.frame_task import FrameOutput
from ..reconstruct.quality import (
    SUSPECT_LENGTH_MM,
    SUSPECT_SMOOTHED_MM,
    THIN_TUBE_PX,
    edge_residual,
    is_doubtful,
    off_length,
    off_smoothed,
    reaches_walls,
    tube_width_px,
)
from ..reconstruct.radius_profile import RadiusProfile
from ..session.folder import Session
from ..session.video import video_fingerprint
from .frame_log import FrameLog
from .interrupts import deferred_signals, outputs_in_place
from .output_target import OutputTarget, output_error
from .smoothing import smooth_centerlines
from .summary import RunSummary

if TYPE_CHECKING:  # the recorders are imported when a run opens its writers
    from ..record.mcap_log import MessageMirror

log = logging.getLogger(__name__)


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


def _leave_to_exit(stream: Any) -> None:
    """Keep a Rerun stream that cannot close (its file's writer stuck on a full disk, its
    viewer not answering) from holding up the exit: Rerun's own handler at exit, and
    dropping it (``RecordingStream.__del__``), would wait for it."""
    import rerun as rr

    rr.unregister_shutdown()
    _STUCK_STREAMS.append(stream)


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
    try:
        finished = done.wait(seconds)
    except BaseException:
        # Interrupted (Ctrl-C, SIGTERM): the call finishes first, within the same bound, so
        # that nothing it starts (the file a Rerun stream opens) outlives the clean-up.
        done.wait(seconds)
        raise
    if not finished:
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
    frames were reconstructed with (the summary's line of :mod:`pipeline.calibrate.refine`),
    ``tube_end`` which end the fit assumed and how it was chosen, ``radius_profile`` the
    tube's radius along it read from the session's frames (None: each frame's own).
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
        tube_end: str = "",
        radius_profile: RadiusProfile | None = None,
        frame_doubt: str = "",
    ) -> None:
        # Imported here, not with this module: a run's parent opens its writers once
        # the workers have their first frames, so Rerun's import no longer holds them up.
        import rerun as rr

        from ..record.mcap_log import McapRecorder
        from ..record.rerun_layout import default_blueprint
        from ..record.rerun_log import RerunRecorder

        self.session = session
        self.target = target
        self.mcap_path, self.rrd_path = target.mcap_path, target.rrd_path
        self._mcap_file: IO[bytes] | None = None
        self._stream: Any = None
        self._viewer_stream: Any = None
        self.viewer: RerunRecorder | None = None
        self._stalled = False  # the Rerun writer did not finish within its bound
        # Each frame's index, time, curve and metrics message (as written to the MCAP), for
        # the finish: on disk, so that a long live run's memory stays flat.
        self.log = FrameLog(target.out_dir)
        self.counts = {"ok": 0, "empty": 0}
        self.empty_apart = 0  # empty frames whose every view saw something (NO_SHARED_VOXEL)
        self.empty_unseen: dict[str, int] = {}  # camera -> empty frames in which it saw nothing
        self.blind: list[int] = []  # empty frames in which some cameras, not all, saw nothing
        self.blind_cameras: dict[str, int] = {}  # camera -> those frames in which it saw nothing
        self.failed: list[tuple[int, str]] = []
        self.doubtful: list[int] = []
        # camera -> doubtful frames it re-projects worst in
        self.doubtful_cameras: dict[str, int] = {}
        self.suspect: list[tuple[int, str]] = []
        self.at_walls: list[int] = []
        # Per camera, over the ok frames: the sum of the tube's width in its images (px), and
        # the frames in which it was thinner than THIN_TUBE_PX.
        self.width_px_sums = np.zeros(len(session.cameras))
        self.width_frames = 0
        self.thin_frames = np.zeros(len(session.cameras), dtype=np.int64)
        # Per ok frame, its fit's residual in pixels and in radii (quality.edge_residual).
        self.residuals: list[tuple[float, float]] = []
        # Per frame of the log, its curve's length (mm; NaN where it has none).
        self.lengths_mm: list[float] = []
        # A reason every ok frame is suspect for, written with its own (the tube's end a
        # close call: pipeline.reconstruct.tip_shape.TIP_DOUBT).
        self.frame_doubt = frame_doubt
        self.radius_profile = radius_profile  # in the metadata and the summary
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
            if session.video_paths:
                # What evaluate compares with the videos beside a ground truth: a session
                # rendered or filmed again since has others.
                meta["videos"] = json.dumps({p.name: video_fingerprint(p) for p in session.video_paths})
            if cameras_used:
                meta["cameras_used"] = cameras_used
            if tube_end:
                meta["tube_end"] = tube_end
            if radius_profile is not None:
                meta["radius_profile"] = radius_profile.to_json()
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
        # The reasons the track does not treat as a wrong curve join the frame's own here.
        doubts = (result.doubt_reason, self.frame_doubt) if result.status == "ok" else ()
        if any(doubts):
            why = "; ".join(part for part in (result.suspect_reason, *doubts) if part)
            result = dataclasses.replace(result, suspect_reason=why)
        if time_ns is None:
            time_ns = self.session.timestamp_ns(result.index)
        curve = result.centerline_mm if result.status == "ok" else None
        try:
            metrics = self.mcap.write_frame(result, time_ns, jpegs=out.jpegs, extra_metrics=extra_metrics)
            self.log.add(result.index, time_ns, curve, metrics)
            self.lengths_mm.append(result.length_mm if curve is not None else float("nan"))
        except OSError as exc:
            raise output_error(self.target.out_dir, exc) from None
        self.rerun.write_frame(result, time_ns, jpegs=out.jpegs, silhouettes_png=out.silhouettes_png)
        if self.viewer is not None:
            self.viewer.write_frame(result, time_ns, jpegs=out.jpegs, silhouettes_png=out.silhouettes_png)
        if result.status == "failed":
            self.failed.append((result.index, result.reason))
        else:
            self.counts[result.status] = self.counts.get(result.status, 0) + 1
        if result.status == "empty" and result.reason == NO_SHARED_VOXEL:
            self.empty_apart += 1
        for name in result.unseen_by if result.status == "empty" else ():
            self.empty_unseen[name] = self.empty_unseen.get(name, 0) + 1
        if result.status == "empty" and 0 < len(result.unseen_by) < len(self.session.cameras):
            self.blind.append(result.index)
            for name in result.unseen_by:
                self.blind_cameras[name] = self.blind_cameras.get(name, 0) + 1
        if result.status == "ok" and is_doubtful(result.iou):
            self.doubtful.append(result.index)
            worst = self.session.cameras[int(np.argmin(result.iou))].name
            self.doubtful_cameras[worst] = self.doubtful_cameras.get(worst, 0) + 1
        if result.status == "ok" and result.suspect:
            self.suspect.append((result.index, result.suspect_reason))
        if curve is not None and len(curve):
            if reaches_walls(result.points_mm, self.session.settings.workspace, curve[0]):
                self.at_walls.append(result.index)
            widths = self._add_widths(curve, result.radius_mm, result.tube_width_px)
            residual = edge_residual(widths, result.radius_mm, result.fit_residual_mm)
            if np.isfinite(residual).all():
                self.residuals.append(residual)

    def _add_widths(
        self, curve_mm: NDArray[np.float64], radius_mm: float, known_px: Sequence[float] = ()
    ) -> NDArray[np.float64]:
        """Count an ok frame's tube width in each camera's images: ``known_px`` (C,), the widths
        its reconstruction found at its radius, where they are all known; else at its radius,
        or the declared one where the frame read none. The (C,) widths (px)."""
        widths = np.asarray(known_px, dtype=np.float64)
        if len(widths) != len(self.session.cameras) or not np.isfinite(widths).all():
            if not np.isfinite(radius_mm):
                radius_mm = self.session.settings.manipulator.radius_mm or float("nan")
            widths = tube_width_px(self.session.cameras, curve_mm, radius_mm)
        if np.isfinite(widths).all():
            self.width_px_sums += widths
            self.width_frames += 1
            self.thin_frames += widths < THIN_TUBE_PX
        return widths

    def _smoothed(self, stacked: NDArray[np.float64]) -> NDArray[np.float64] | None:
        times_ns = np.asarray(self.log.times_ns, dtype=np.int64)
        return _smooth(stacked, (times_ns - times_ns[0]).astype(np.float64) * 1e-9)

    def _flag_after_run(self, smoothed_gaps_mm: NDArray[np.float64] | None) -> None:
        """The frames that the whole run shows may be wrong, and were not suspect yet: whose
        curves lie far from the smoothed ones (``smoothed_gaps_mm``, per frame of the log,
        where smoothed; :data:`pipeline.reconstruct.quality.SUSPECT_SMOOTHED_MM`), or whose
        lengths lie far from the run's (:func:`pipeline.reconstruct.quality.off_length`):
        their metrics written again, suspect, and their suspect plots set."""
        longer = off_length(np.asarray(self.lengths_mm, dtype=np.float64))
        already = {frame for frame, _ in self.suspect}
        for row, frame in enumerate(self.log.frames):
            reasons = []
            if smoothed_gaps_mm is not None and smoothed_gaps_mm[row] > SUSPECT_SMOOTHED_MM:
                reasons.append(f"{smoothed_gaps_mm[row]:.1f} mm from the smoothed curve")
            if abs(longer[row]) > SUSPECT_LENGTH_MM:
                reasons.append(f"length {self.lengths_mm[row]:.1f} mm, {longer[row]:+.1f} mm from the run's")
            if frame in already or not reasons:
                continue
            reason, time_ns = "; ".join(reasons), self.log.times_ns[row]
            figures = json.loads(self.log.metrics(row)) | {"suspect": True, "suspect_reason": reason}
            self.mcap.write_metrics(json.dumps(figures, allow_nan=False).encode(), time_ns)
            self.rerun.mark_suspect(frame, time_ns)
            if self.viewer is not None:
                self.viewer.mark_suspect(frame, time_ns)
            self.suspect.append((frame, reason))
        self.suspect.sort()

    def finish(self) -> None:
        """Smoothing, footers, then the renames that make the outputs appear."""
        try:
            self._finish()
        except OSError as exc:
            raise output_error(self.target.out_dir, exc) from None

    def _finish(self) -> None:
        wanted = len(self.log) and self.session.settings.centerline.smooth
        stacked = self.log.stacked_curves() if wanted else None
        smoothed = self._smoothed(stacked) if stacked is not None else None
        self._flag_after_run(
            off_smoothed(stacked, smoothed) if stacked is not None and smoothed is not None else None
        )
        if stacked is not None and smoothed is not None:
            frames, times_ns = list(self.log.frames), list(self.log.times_ns)
            self.mcap.write_smoothed(smoothed, times_ns)
            self.rerun.write_smoothed(smoothed, frames, times_ns)
            if self.viewer is not None:
                self.viewer.write_smoothed(smoothed, frames, times_ns)
        self.log.close()
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
            outputs_in_place()

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
        self.viewer = None
        self._disconnect_viewer()

    def _disconnect_viewer(self) -> None:
        """Close the viewer's connection within VIEWER_FLUSH_S: one that takes the
        connection but never answers (a hung viewer, another service on its port) would
        hold the run, deaf to Ctrl-C, for as long as it stays; it is left to the exit."""
        stream, self._viewer_stream = self._viewer_stream, None
        if stream is None:
            return
        try:
            closed = _within(VIEWER_FLUSH_S, stream.disconnect)
        except Exception as exc:
            log.debug("closing the viewer's stream failed: %s", exc)
            return
        if not closed:
            log.warning(
                "the Rerun viewer did not close its connection within %g s: left open", VIEWER_FLUSH_S
            )
            _leave_to_exit(stream)

    def abort(self) -> None:
        """Close everything and remove the temporary files; finished outputs are untouched.
        A failure to close (the full disk that ended the run fails the flushes too) does not
        stop the removals."""
        with contextlib.suppress(Exception):
            self.log.close()
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
            _leave_to_exit(self._stream)
        self._disconnect_viewer()
        for path in (self.mcap_path, self.rrd_path):
            with contextlib.suppress(OSError):  # not there (never created) or not removable
                self.target.partial(path).unlink()

    def summary(self, wall_s: float) -> RunSummary:
        """The run's summary; its outputs are the recordings once they are in place (none
        after :meth:`abort`)."""
        n = len(self.log)
        written = (self.mcap_path, self.rrd_path) if self.committed else ()
        px, radii = np.median(self.residuals, axis=0).tolist() if self.residuals else (math.nan, math.nan)
        return RunSummary(
            frames_ok=self.counts.get("ok", 0),
            frames_empty=self.counts.get("empty", 0),
            frames_failed=list(self.failed),
            frames_empty_apart=self.empty_apart,
            frames_empty_unseen=dict(self.empty_unseen),
            frames_blind=sorted(self.blind),
            blind_cameras=dict(self.blind_cameras),
            wall_s=wall_s,
            fps=n / wall_s if wall_s > 0 else 0.0,
            outputs=[(p, p.stat().st_size) for p in written],
            frames_doubtful=list(self.doubtful),
            doubtful_cameras=dict(self.doubtful_cameras),
            frames_at_walls=list(self.at_walls),
            frames_suspect=list(self.suspect),
            thin_cameras=self._thin_cameras(),
            radius="" if self.radius_profile is None else self.radius_profile.describe(),
            edge_residual_px=px,
            edge_residual_radii=radii,
        )

    def _thin_cameras(self) -> dict[str, float]:
        """Camera -> the tube's mean width in its images (px), for the cameras that see it
        thinner than THIN_TUBE_PX in most ok frames; where no frame is ok, the declared
        radius's width at the workspace's centre, if thinner."""
        cameras = self.session.cameras
        if self.width_frames:
            return {
                cam.name: float(total / self.width_frames)
                for cam, total, thin in zip(cameras, self.width_px_sums, self.thin_frames, strict=True)
                if 2 * thin > self.width_frames
            }
        declared = self.session.settings.manipulator.radius_mm
        if not declared or self.counts.get("ok", 0):
            return {}
        workspace = self.session.settings.workspace
        centre = np.asarray(workspace.origin_mm) + 0.5 * np.asarray(workspace.size_mm)
        widths = tube_width_px(cameras, centre[None], declared)
        return {cam.name: float(w) for cam, w in zip(cameras, widths, strict=True) if w < THIN_TUBE_PX}


def _open_partial(path: Path) -> IO[bytes]:
    """Create the temporary file ``path`` (a seam for tests); the name is this run's alone."""
    return path.open("xb")
