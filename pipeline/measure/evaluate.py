"""Accuracy of reconstructed centrelines against ground truth.

The figures are the ones the accuracy targets are set for: the symmetric distance between
the reconstructed and true centrelines (mean and 95th percentile, every point of
both curves pooled over every ok frame), the tip and base errors, the length
error in percent, the failed frames, and the tip jitter (RMS of the second time
difference of the tip position), reconstructed against true.

:func:`evaluate_centerlines` works on arrays in millimetres;
:func:`evaluate_recording` reads an MCAP and a ground_truth.npz and is the only
place here that converts the recording's metres to millimetres.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import EvaluationError, refuse_unfinished_render
from ..geometry.polyline import polyline_arclength
from ..session.folder import check_not_dangling

if TYPE_CHECKING:
    from ..reconstruct.radius_profile import RadiusProfile

log = logging.getLogger(__name__)

# A true centreline farther than this from the world origin (mm) is no workspace's: the
# distances to it would overflow, and every figure be empty.
MAX_TRUTH_MM = 1e6
# A true centreline shorter than this (mm, the median over frames) is no robot's: a ground
# truth in metres (a 250 mm tube as 0.25), whose every frame would read as a miss.
MIN_TRUTH_LENGTH_MM = 1.0

FloatArray = NDArray[np.float64]

# The accuracy targets, shown beside the figures in format_report.
TARGETS = {
    "mean_mm": 0.2,
    "p95_mm": 0.5,
    "tip_median_mm": 0.5,
    "length_error_pct": 0.5,
    "failed_frames": 0,
    "jitter_ratio": 1.5,
}

# Two samples further apart than this many median time steps are not consecutive
# (frames missing from the recording): no second difference is taken across them.
_GAP_FACTOR = 1.5

# Bound on the (points x segments x 3) temporaries of centerline_distances.
_MAX_CHUNK_ELEMENTS = 4_000_000

# A frame whose curve is farther than this from the truth anywhere is wrong, not
# merely imprecise: the suspect flag should name it.
OFF_MM = 2.0


@dataclass(frozen=True)
class EvaluationReport:
    """Accuracy of one set of centrelines against the truth; lengths in mm.

    Attributes
    ----------
    label : what was evaluated ("per-frame", "smoothed", ...).
    frames : number of frames evaluated.
    failed_frames : frames without a centreline (NaN rows), but for the empty ones below.
    failed_indices : their frame indices.
    empty_frames, empty_indices : frames the recording holds as empty (no tube seen, where
        the truth has one), apart from the failed ones; set by :func:`evaluate_recording`.
    mean_mm, p95_mm : mean and 95th percentile of the symmetric centreline
        distance, pooled over both directions and every ok frame.
    tip_median_mm, tip_p95_mm : |pred[-1] - truth[-1]| over ok frames.
    base_mean_mm : mean |pred[0] - truth[0]| over ok frames.
    length_error_pct : mean |L_pred - L_true| / L_true, in percent.
    tip_jitter_mm, truth_tip_jitter_mm : RMS norm of the tip's second time
        difference (mm per frame step squared), over runs of consecutive ok frames.
    jitter_ratio : tip_jitter_mm / truth_tip_jitter_mm (NaN if the true tip is still).
    off_indices : ok frames whose curve is more than ``OFF_MM`` from the truth somewhere
        (either way: a reconstructed point from the true curve, or a true one from it).
    off_flagged : how many of those the recording flagged suspect; None when not known.
    good_flagged : how many of the other ok frames it flagged suspect; None when not known.
    smoothed : the same figures for the temporally smoothed centrelines, if any.
    cameras : the cameras the recording was reconstructed with ("given" or "refined ...");
        "" when the recording does not say.
    tube_end : the tube end the recording's fit assumed, and how it was chosen; "" when
        the recording does not say.
    radius : the tube's radius along it read from the session's frames (the recording's
        :attr:`pipeline.record.load.Recording.radius_profile`, described); "" when the
        recording does not say.
    radius_error_mm : the median |radius read - true radius| over the stretch the recording
        read, mm (spacer disks aside); NaN when the recording or the ground truth has none.
    complete : False where the recording ended before its footer (a run killed while
        writing), or is damaged: the figures are those of the frames it holds.
    damaged : True where bytes inside the recording are not its own (a disk or copy
        error): the figures are those of the frames before the damage.
    other_session : the recording's session, where it is not the ground truth's (by their
        folders' names; a warning says so): the figures may compare two sessions.
    other_videos : the videos beside the ground truth that are not those the recording
        was made from (rendered or filmed again since; a warning says so), comma-separated.
    """

    label: str
    frames: int
    failed_frames: int
    failed_indices: tuple[int, ...]
    mean_mm: float
    p95_mm: float
    tip_median_mm: float
    tip_p95_mm: float
    base_mean_mm: float
    length_error_pct: float
    tip_jitter_mm: float
    truth_tip_jitter_mm: float
    jitter_ratio: float
    off_indices: tuple[int, ...] = ()
    off_flagged: int | None = None
    good_flagged: int | None = None
    smoothed: EvaluationReport | None = None
    cameras: str = ""
    tube_end: str = ""
    radius: str = ""
    radius_error_mm: float = math.nan
    complete: bool = True
    damaged: bool = False
    other_session: str = ""
    other_videos: str = ""
    empty_frames: int = 0
    empty_indices: tuple[int, ...] = ()

    @property
    def frames_off(self) -> int:
        """Ok frames more than ``OFF_MM`` from the truth somewhere."""
        return len(self.off_indices)

    @property
    def good_frames(self) -> int:
        """Ok frames within ``OFF_MM`` of the truth everywhere."""
        return self.frames - self.failed_frames - self.empty_frames - len(self.off_indices)

    def with_empty(self, empty: set[int]) -> EvaluationReport:
        """This report with the frames of ``empty`` (frame indices the recording holds as
        empty) counted apart from the failed ones."""
        held = tuple(i for i in self.failed_indices if i in empty)
        failed = tuple(i for i in self.failed_indices if i not in empty)
        return dataclasses.replace(
            self, failed_frames=len(failed), failed_indices=failed, empty_frames=len(held), empty_indices=held
        )

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (JSON-ready: NaN becomes None, the smoothed report nests, without the
        recording's own fields, which are the top level's)."""
        data = _json_ready(dataclasses.asdict(self))
        if data["smoothed"] is not None:
            for key in _RECORDING_FIELDS:
                del data["smoothed"][key]
        return data

    def to_json(self) -> str:
        """The report as indented JSON (strict: no NaN literals)."""
        return json.dumps(self.to_dict(), indent=2)


# What a report says of its recording rather than of a set of curves: the smoothed
# report's JSON leaves them to the top level's.
_RECORDING_FIELDS = (
    "smoothed",
    "cameras",
    "tube_end",
    "radius",
    "radius_error_mm",
    "complete",
    "damaged",
    "other_session",
    "other_videos",
)


def _json_ready(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _json_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_ready(v) for v in value]
    return value


def centerline_distances(a_mm: ArrayLike, b_mm: ArrayLike) -> FloatArray:
    """Distance from each point of ``a_mm`` to the polyline ``b_mm``.

    Exact: each point is projected on every segment of ``b_mm`` (not only on its
    vertices), so two parallel lines 1 mm apart are 1 mm apart everywhere.

    Parameters
    ----------
    a_mm : (N, 3) float64 points, mm.
    b_mm : (M, 3) float64 polyline vertices in order, mm; M >= 1.

    Returns
    -------
    (N,) float64 distances, mm.
    """
    a = np.asarray(a_mm, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(b_mm, dtype=np.float64).reshape(-1, 3)
    if len(b) == 0:
        raise ValueError("centerline_distances: the polyline b_mm has no vertices")
    if len(b) == 1:
        return np.asarray(np.linalg.norm(a - b[0], axis=1), dtype=np.float64)
    start = b[:-1]
    seg = b[1:] - start  # (S, 3)
    seg_sq = np.einsum("ij,ij->i", seg, seg)
    # Zero-length segments (repeated vertices) project everything onto their start.
    inv_sq = np.divide(1.0, seg_sq, out=np.zeros_like(seg_sq), where=seg_sq > 0)
    out = np.empty(len(a))
    chunk = max(1, _MAX_CHUNK_ELEMENTS // (3 * len(seg)))
    for lo in range(0, len(a), chunk):
        rel = a[lo : lo + chunk, None, :] - start[None]  # (n, S, 3)
        t = np.clip(np.einsum("nsk,sk->ns", rel, seg) * inv_sq, 0.0, 1.0)
        gap = rel - t[..., None] * seg[None]
        out[lo : lo + chunk] = np.sqrt(np.einsum("nsk,nsk->ns", gap, gap).min(axis=1))
    return out


def polyline_length(points_mm: ArrayLike) -> float:
    """Length (mm) of the polyline through ``points_mm`` : (N, 3) float64, mm."""
    return float(polyline_arclength(np.asarray(points_mm, dtype=np.float64))[-1])


def tip_jitter(tips_mm: ArrayLike, *, timestamps_s: ArrayLike | None = None) -> float:
    """RMS norm of the second time difference of a tip track, mm per frame step squared.

    Parameters
    ----------
    tips_mm : (F, 3) float64 tip positions, mm; NaN rows for frames without a tip.
    timestamps_s : (F,) float64, s; optional. With timestamps, steps longer than
        1.5 median steps break the track (missing frames), and uneven steps use the
        non-uniform second difference rescaled to the median step, so the figure
        equals ``x[i+1] - 2 x[i] + x[i-1]`` whenever frames are evenly spaced.

    Returns
    -------
    float, mm; NaN if no three consecutive frames have a tip.
    """
    x = np.asarray(tips_mm, dtype=np.float64).reshape(-1, 3)
    if len(x) < 3:
        return float("nan")
    if timestamps_s is None:
        t = np.arange(len(x), dtype=np.float64)
    else:
        t = np.asarray(timestamps_s, dtype=np.float64).reshape(-1)
        if t.shape != (len(x),):
            raise ValueError(f"tip_jitter: {len(t)} timestamps for {len(x)} tips")
    h = np.diff(t)
    step = float(np.median(h))
    if not step > 0:
        return float("nan")
    h_prev, h_next = h[:-1], h[1:]
    ok: NDArray[np.bool_] = np.asarray(np.isfinite(x).all(axis=1))
    usable = ok[:-2] & ok[1:-1] & ok[2:] & (h_prev > 0) & (h_next > 0)
    usable &= (h_prev <= _GAP_FACTOR * step) & (h_next <= _GAP_FACTOR * step)
    if not usable.any():
        return float("nan")
    hp, hn = h_prev[usable, None], h_next[usable, None]
    x0, x1, x2 = x[:-2][usable], x[1:-1][usable], x[2:][usable]
    second = 2.0 * step**2 * ((x2 - x1) / hn - (x1 - x0) / hp) / (hp + hn)
    return float(np.sqrt(np.mean(np.einsum("ij,ij->i", second, second))))


def evaluate_centerlines(
    pred_mm: ArrayLike,
    truth_mm: ArrayLike,
    *,
    timestamps_s: ArrayLike | None = None,
    frame_indices: ArrayLike | None = None,
    label: str = "per-frame",
) -> EvaluationReport:
    """Compare predicted centrelines with the true ones, frame by frame.

    Parameters
    ----------
    pred_mm : (F, N, 3) float64 predicted centrelines ordered base -> tip, world
        frame, mm; a frame with any NaN is a failed frame.
    truth_mm : (F, M, 3) float64 true centrelines ordered base -> tip, mm.
    timestamps_s : (F,) float64 frame times, s; optional (see :func:`tip_jitter`).
    frame_indices : (F,) int frame indices used to name failed frames; default 0..F-1.
    label : name of this set of centrelines in the report.

    Returns
    -------
    EvaluationReport
    """
    pred = np.asarray(pred_mm, dtype=np.float64)
    truth = np.asarray(truth_mm, dtype=np.float64)
    if pred.ndim != 3 or truth.ndim != 3 or pred.shape[2] != 3 or truth.shape[2] != 3:
        raise ValueError(f"expected (F, N, 3) and (F, M, 3) arrays, got {pred.shape} and {truth.shape}")
    if len(pred) != len(truth):
        raise ValueError(f"{len(pred)} predicted frames but {len(truth)} true frames")
    if truth.shape[1] == 0:
        raise ValueError(f"the true centrelines have no points (shape {truth.shape})")
    if pred.shape[1] == 0:  # no curve in any frame: every frame failed, as NaN rows say
        pred = np.full((len(pred), 1, 3), np.nan)
    frames = len(pred)
    index = np.arange(frames) if frame_indices is None else np.asarray(frame_indices).reshape(-1)
    ok: NDArray[np.bool_] = np.asarray(np.isfinite(pred).all(axis=(1, 2)))

    pooled = [
        np.concatenate([centerline_distances(p, q), centerline_distances(q, p)])
        for p, q in zip(pred[ok], truth[ok], strict=True)
    ]
    worst = np.array([d.max() for d in pooled])
    distances = np.concatenate(pooled) if pooled else np.zeros(0)
    tip_err = np.linalg.norm(pred[ok, -1] - truth[ok, -1], axis=1)
    base_err = np.linalg.norm(pred[ok, 0] - truth[ok, 0], axis=1)
    length_pred = np.array([polyline_length(p) for p in pred[ok]])
    length_true = np.array([polyline_length(q) for q in truth[ok]])

    tips = np.where(ok[:, None], pred[:, -1], np.nan)
    jitter = tip_jitter(tips, timestamps_s=timestamps_s)
    # The truth's jitter over the same frames, so the ratio compares like with like.
    truth_jitter = tip_jitter(np.where(ok[:, None], truth[:, -1], np.nan), timestamps_s=timestamps_s)
    return EvaluationReport(
        label=label,
        frames=frames,
        failed_frames=int((~ok).sum()),
        failed_indices=tuple(int(i) for i in index[~ok]),
        mean_mm=_stat(np.mean, distances),
        p95_mm=_stat(lambda d: np.percentile(d, 95), distances),
        tip_median_mm=_stat(np.median, tip_err),
        tip_p95_mm=_stat(lambda d: np.percentile(d, 95), tip_err),
        base_mean_mm=_stat(np.mean, base_err),
        length_error_pct=_stat(np.mean, 100.0 * np.abs(length_pred - length_true) / length_true),
        tip_jitter_mm=jitter,
        truth_tip_jitter_mm=truth_jitter,
        jitter_ratio=jitter / truth_jitter if truth_jitter > 0 else float("nan"),
        off_indices=tuple(int(i) for i in index[ok][worst > OFF_MM]),
    )


def _stat(func: Any, values: FloatArray) -> float:
    return float(func(values)) if len(values) else float("nan")


def _truth_file(path: Path) -> Path:
    """The ground truth file ``path`` names: itself, or the ground_truth.npz of the session
    folder it is (a broken link is no folder)."""
    return path / "ground_truth.npz" if path.is_dir() else path


@dataclass(frozen=True)
class GroundTruth:
    """What a synthetic session's ground_truth.npz holds that evaluate compares with.

    centerlines_mm : (F, M, 3) float64, base -> tip, world frame, mm.
    timestamps_s : (F,) float64, s, or None if the file has none.
    video_fingerprints : video file name -> fingerprint of the videos rendered with it
        (empty where the file does not say).
    radius_mm : (M,) float64, the tube's radius along its first frame's centreline, mm;
        None where the file does not hold it (rendered before it kept the radius).
    """

    centerlines_mm: FloatArray
    timestamps_s: FloatArray | None = None
    video_fingerprints: dict[str, str] = dataclasses.field(default_factory=dict)
    radius_mm: FloatArray | None = None


_T = TypeVar("_T")


def _optional(data: Any, key: str, convert: Callable[[Any], _T]) -> _T | None:
    """``convert(data[key])`` from an open .npz; None where it is missing or unreadable."""
    try:
        return convert(data[key]) if key in data else None
    except (ValueError, TypeError):
        return None


def load_ground_truth(path: Path | str) -> GroundTruth:
    """Read a synthetic session's ground truth: ``path`` is its ground_truth.npz, or the
    session directory holding one. EvaluationError, naming the file, where it cannot be read
    or holds no centrelines in millimetres."""
    path = Path(path)
    file = _truth_file(path)
    refuse_unfinished_render(file.parent, EvaluationError)
    check_not_dangling(file, EvaluationError)
    if file.exists() and not file.is_file():
        raise EvaluationError(
            f"{file}: is not a regular file (a pipe or device); give the ground_truth.npz file"
        )
    if not file.is_file():
        where = f"{path} holds no ground_truth.npz" if path.is_dir() else f"{path} does not exist"
        raise EvaluationError(f"ground truth: {where}; give a ground_truth.npz or the session directory")
    try:
        with open(file, "rb") as head:
            if head.read(4) != b"PK\x03\x04":  # every .npz is a zip archive
                raise EvaluationError(
                    f"{file}: is not a ground_truth.npz (a NumPy .npz archive); give the one "
                    "`pipeline synth` wrote, or the session directory that holds it"
                )
        with np.load(file) as data:
            if "centerlines" not in data:
                raise EvaluationError(f"{file}: no 'centerlines' array; is this a synthetic ground truth?")
            raw = data["centerlines"]
            if raw.dtype.kind not in "iuf":  # booleans, complex numbers, text, records
                raise EvaluationError(
                    f"{file}: 'centerlines' holds {raw.dtype} values, expected numbers (mm); "
                    "render the session again (pipeline synth)"
                )
            centerlines = np.asarray(raw, dtype=np.float64)
            timestamps = (
                np.asarray(data["timestamps_s"], dtype=np.float64).reshape(-1)
                if "timestamps_s" in data
                else None
            )
            # What only adds to the comparison: where unreadable, as though not there.
            named = _optional(data, "video_fingerprints", lambda a: [str(e) for e in a]) or []
            radius = _optional(data, "radius_profile_mm", lambda a: np.asarray(a, dtype=np.float64))
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:  # cut short or damaged
        raise EvaluationError(f"{file}: not a readable .npz file ({exc})") from None
    if centerlines.ndim != 3 or centerlines.shape[2] != 3:
        raise EvaluationError(f"{file}: 'centerlines' has shape {centerlines.shape}, expected (F, M, 3)")
    if 0 in centerlines.shape[:2]:
        what = "frames" if len(centerlines) == 0 else "points"
        raise EvaluationError(
            f"{file}: 'centerlines' holds no {what} (shape {centerlines.shape}); render the session again"
        )
    if centerlines.shape[1] < 2:
        raise EvaluationError(
            f"{file}: 'centerlines' holds 1 point a frame; a centreline needs 2 or more, base to tip"
        )
    if not np.isfinite(centerlines).all():
        raise EvaluationError(
            f"{file}: 'centerlines' holds non-finite values; render the session again (pipeline synth)"
        )
    farthest = float(np.abs(centerlines).max())
    if farthest > MAX_TRUTH_MM:
        raise EvaluationError(
            f"{file}: 'centerlines' reach {farthest:.3g} mm from the origin, beyond any workspace "
            f"({MAX_TRUTH_MM:g} mm); is this a ground truth in millimetres? render the session again"
        )
    steps = np.linalg.norm(np.diff(centerlines, axis=1), axis=2)
    length = float(np.median(steps.sum(axis=1)))
    if length < MIN_TRUTH_LENGTH_MM:
        raise EvaluationError(
            f"{file}: its centrelines are {length:.3g} mm long (the median); ground truths are in "
            "millimetres: is this one in metres? render the session again (pipeline synth)"
        )
    if radius is not None:  # one profile, or one a frame: the first frame's
        radius = radius.reshape(-1, radius.shape[-1])[0] if radius.ndim and radius.size else None
    return GroundTruth(
        centerlines,
        timestamps,
        dict(entry.partition("=")[::2] for entry in named),
        radius if radius is not None and radius.shape == centerlines.shape[1:2] else None,
    )


def _changed_videos(recorded: dict[str, str], ground_truth: Path) -> str:
    """The videos (comma-separated names) in the ground truth's folder whose fingerprints are
    not the ``recorded`` ones (file name -> fingerprint); "" where all that are there match."""
    from ..session.video import video_fingerprint

    folder = ground_truth if ground_truth.is_dir() else ground_truth.parent
    changed = [
        name
        for name, fingerprint in recorded.items()
        if (folder / name).is_file() and video_fingerprint(folder / name) not in ("", fingerprint)
    ]
    return ", ".join(changed)


def _not_rendered_with(recorded: dict[str, str], rendered: dict[str, str]) -> str:
    """The videos (comma-separated names) the ground truth names as ``rendered`` with it (file
    name -> fingerprint, wherever the file was copied) whose fingerprints are not the
    ``recorded`` ones; "" where they match, or the truth does not say."""
    # A camera's video recorded under another name (cam0.avi for the cam0.mp4 rendered: a
    # copy re-encoded) is another video too.
    by_camera = {Path(name).stem: fingerprint for name, fingerprint in recorded.items()}
    return ", ".join(
        name
        for name, fingerprint in rendered.items()
        if recorded.get(name, by_camera.get(Path(name).stem, fingerprint)) != fingerprint
    )


def _truth_session(ground_truth: Path) -> str:
    """The session a ground truth belongs to: its folder's name (the session directory given,
    or the one holding ground_truth.npz); "" for a file of another name."""
    if ground_truth.is_dir():
        return ground_truth.resolve().name
    return ground_truth.resolve().parent.name if ground_truth.name == "ground_truth.npz" else ""


def _radius_error(profile: RadiusProfile | None, truth: GroundTruth) -> float:
    """The median |radius read - true radius| (mm) of the recording's radius profile over
    the arc lengths it read, the truth's radius taken along its first frame's centreline; NaN
    where either has none."""
    if profile is None or truth.radius_mm is None:
        return math.nan
    arc_mm = polyline_arclength(truth.centerlines_mm[0])
    inside = profile.arc_mm <= arc_mm[-1]
    if not inside.any():
        return math.nan
    true_mm = np.interp(profile.arc_mm[inside], arc_mm, truth.radius_mm)
    return float(np.median(np.abs(profile.radius_mm[inside] - true_mm)))


def _why_no_frames(complete: bool, damaged: bool) -> str:
    """Why a recording holds no frames, for its error line: "" for a whole file."""
    from ..record.load import REWRITE, damage_line

    if damaged:
        return f" ({damage_line('before its first frame')}; {REWRITE})"
    return "" if complete else " (cut short before its first frame: the run did not finish)"


def evaluate_recording(recording: Path | str, ground_truth: Path | str) -> EvaluationReport:
    """Evaluate an MCAP recording against a synthetic session's ground truth.

    Frames are matched by frame index, so a recording of part of a session
    (``--frames``) is compared with the right true frames. When the recording
    holds smoothed centrelines, they are evaluated too (``report.smoothed``).

    Parameters
    ----------
    recording : the .mcap written by ``python -m pipeline process``.
    ground_truth : ground_truth.npz, or the session directory holding it.

    Returns
    -------
    EvaluationReport (label "per-frame"), with ``smoothed`` set when present.
    """
    from ..record.load import load_recording

    recording = Path(recording)
    check_not_dangling(recording, EvaluationError)
    if recording.is_dir():
        if Path(ground_truth).suffix == ".mcap":
            raise EvaluationError(
                f"{recording}: is a folder and {ground_truth} a recording: give the recording first, "
                "then the ground truth (evaluate RECORDING.mcap GROUND_TRUTH)"
            )
        raise EvaluationError(f"{recording}: is a folder; give the recording's .mcap file in it")
    if recording.suffix.lower() == ".npz":
        raise EvaluationError(
            f"{recording}: is a ground truth (.npz), not a recording: give the recording first, "
            "then the ground truth (evaluate RECORDING.mcap GROUND_TRUTH)"
        )
    if not recording.exists():  # anything else there (a named pipe) is named by load_recording
        raise EvaluationError(f"recording {recording} does not exist; run `python -m pipeline process` first")
    ground = load_ground_truth(ground_truth)
    truth_mm, truth_times = ground.centerlines_mm, ground.timestamps_s
    # The recording's warnings, said once it is known to hold frames; without frames, the
    # error's line says why instead (_why_no_frames).
    held: list[str] = []
    rec = load_recording(recording, on_warning=held.append)
    indices = np.asarray(rec.frame_indices, dtype=np.int64).reshape(-1)
    if len(indices) == 0:
        why = _why_no_frames(rec.complete, rec.damaged)
        raise EvaluationError(f"{recording}: the recording holds no frames{why}")
    for warning in held:  # a recording cut short after some frames: said, and evaluated
        log.warning("%s", warning)
    outside = indices[(indices < 0) | (indices >= len(truth_mm))]
    if len(outside):
        raise EvaluationError(
            f"{recording}: frame {int(outside[0])} is beyond the ground truth's {len(truth_mm)} frames; "
            "is this the ground truth of the same session?"
        )
    truth_session = _truth_session(Path(ground_truth))
    other_session = rec.session if rec.session and truth_session and rec.session != truth_session else ""
    if other_session:
        log.warning(
            "%s is a recording of session %r, the ground truth that of %r: compare a recording "
            "with its own session's ground truth",
            recording,
            rec.session,
            truth_session,
        )
    other_videos = _changed_videos(rec.videos, Path(ground_truth))
    if other_videos:
        log.warning(
            "%s was made from other videos than %s beside the ground truth (the session was "
            "rendered or filmed again since?): process the session again to compare them",
            recording,
            other_videos,
        )
    elif other_videos := _not_rendered_with(rec.videos, ground.video_fingerprints):
        log.warning(
            "%s was made from other videos than those the ground truth was rendered with (%s): "
            "compare a recording with its own session's ground truth",
            recording,
            other_videos,
        )
    truth = truth_mm[indices]
    if truth_times is not None and len(truth_times) == len(truth_mm):
        times = truth_times[indices]
    else:
        times = np.asarray(rec.timestamps_ns, dtype=np.float64) * 1e-9
    if len(indices) < len(truth_mm):
        log.info("%s: %d of the ground truth's %d frames recorded", recording, len(indices), len(truth_mm))

    # The MCAP stores metres (the Foxglove convention); everything here is millimetres.
    def to_mm(centerlines_m: ArrayLike) -> FloatArray:
        return np.asarray(centerlines_m, dtype=np.float64) * 1000.0

    report = evaluate_centerlines(
        to_mm(rec.centerlines_m), truth, timestamps_s=times, frame_indices=indices, label="per-frame"
    )
    suspect = {int(m["frame"]) for m in rec.metrics if m.get("suspect")}
    # Frames in which no camera's silhouette held the tube (a camera covered): not failures.
    empty = {int(i) for i, status in zip(indices, rec.statuses, strict=True) if status == "empty"}
    report = report.with_empty(empty)
    off = set(report.off_indices)
    report = dataclasses.replace(
        report,
        off_flagged=len(off & suspect),
        good_flagged=len(suspect - off - set(report.failed_indices) - empty),
        cameras=rec.cameras,
        tube_end=rec.tube_end,
        radius="" if rec.radius_profile is None else rec.radius_profile.describe(),
        radius_error_mm=_radius_error(rec.radius_profile, ground),
        complete=rec.complete,
        damaged=rec.damaged,
        other_session=other_session,
        other_videos=other_videos,
    )
    if rec.smoothed_centerlines_m is not None:
        smoothed = evaluate_centerlines(
            to_mm(rec.smoothed_centerlines_m),
            truth,
            timestamps_s=times,
            frame_indices=indices,
            label="smoothed",
        )
        report = dataclasses.replace(report, smoothed=smoothed.with_empty(empty))
    return report


_ROWS = (
    ("mean_mm", "centreline mean (mm)", "{:.3f}"),
    ("p95_mm", "centreline p95 (mm)", "{:.3f}"),
    ("tip_median_mm", "tip median (mm)", "{:.3f}"),
    ("tip_p95_mm", "tip p95 (mm)", "{:.3f}"),
    ("base_mean_mm", "base mean (mm)", "{:.3f}"),
    ("length_error_pct", "length error (%)", "{:.2f}"),
    ("failed_frames", "failed frames", "{:d}"),
    ("empty_frames", "empty frames (no tube seen)", "{:d}"),
    ("tip_jitter_mm", "tip jitter (mm/frame^2)", "{:.4f}"),
    ("truth_tip_jitter_mm", "true tip jitter (mm/frame^2)", "{:.4f}"),
    ("jitter_ratio", "jitter ratio", "{:.2f}"),
    ("frames_off", f"frames > {OFF_MM:g} mm off", "{:d}"),
    ("off_flagged", "  of those flagged suspect", "{:d}"),
    ("good_flagged", "other frames flagged suspect", "{:d}"),
)


def _cell(fmt: str, value: object) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return fmt.format(value)


def _align(row: list[str], widths: list[int]) -> list[str]:
    # Names left-aligned, numbers right-aligned.
    return [
        cell.ljust(w) if i == 0 else cell.rjust(w)
        for i, (cell, w) in enumerate(zip(row, widths, strict=True))
    ]


def format_report(report: EvaluationReport) -> str:
    """A plain-text table of the report (and its smoothed twin), with the targets."""
    columns = [report] if report.smoothed is None else [report, report.smoothed]
    header = ["", *(r.label for r in columns), "target"]
    rows = [header]
    for key, name, fmt in _ROWS:
        target = TARGETS.get(key)
        rows.append(
            [
                name,
                *(_cell(fmt, getattr(r, key)) for r in columns),
                "" if target is None else f"<= {target}",
            ]
        )
    widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
    lines = ["  ".join(_align(row, widths)) for row in rows]
    lines.insert(1, "-" * len(lines[0]))
    lines.insert(0, f"{report.frames} frame{'' if report.frames == 1 else 's'} evaluated")
    if report.radius:
        error = (
            ""
            if math.isnan(report.radius_error_mm)
            else f"; {report.radius_error_mm:.3f} mm off the truth (median)"
        )
        lines.insert(1, f"tube radius: {report.radius}{error}")
    if report.tube_end:
        lines.insert(1, f"tube end: {report.tube_end}")
    if report.cameras:
        lines.insert(1, f"cameras: {report.cameras}")
    if report.failed_indices:
        shown = ", ".join(str(i) for i in report.failed_indices[:20])
        more = " ..." if len(report.failed_indices) > 20 else ""
        lines.append(f"failed frames: {shown}{more}")
    if report.empty_indices:
        shown = ", ".join(str(i) for i in report.empty_indices[:20])
        more = " ..." if len(report.empty_indices) > 20 else ""
        lines.append(f"empty frames: {shown}{more}")
    return "\n".join(lines)
