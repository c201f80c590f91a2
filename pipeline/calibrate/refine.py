"""The session's cameras, refined from its own silhouettes (``[calibration] refine``).

Frames spread over the session are reconstructed with the given cameras; their
tubes and the cameras are then adjusted together
(:func:`pipeline.calibrate.adjust.adjust_cameras`) and the whole session is
reconstructed with the adjusted ones. With "auto" the adjusted cameras are used
only when they explain the silhouettes clearly better than the given ones and
move some camera's image of the tubes by more than the readings' noise; an
exact calibration is kept as it is.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from ..carve.hull import build_grid
from ..errors import OutputError
from ..geometry.camera import Camera
from ..geometry.polyline import resample_polyline
from ..reconstruct.frame import frame_contrasts, reconstruct_with_silhouettes
from ..reconstruct.frame_task import FrameMap, decode_frames, map_here
from ..reconstruct.model import SessionModel
from ..reconstruct.radius_profile import RadiusProfile
from ..reconstruct.side_readings import read_radius_profile
from ..reconstruct.tip_shape import FrameTip, ReadTips, frame_tip, sample_frames
from ..reconstruct.tube_fit import FIT_SPACING_MM
from ..session.calibration_io import write_calibration
from ..session.toml_file import load_toml
from .adjust import Adjustment, Tube, adjust_cameras, aligned_by_images, resampled_tube
from .frame_lag import CameraLag, FramesOfCamera, camera_lags
from .mount import CHECK_BASE, mount_shift, moved_to_mount

FloatArray = NDArray[np.float64]

# Frames adjusted with the cameras, spread over the session, and the adjustment's rounds:
# ROUNDS, or MAX_ROUNDS where after ROUNDS the views are left more than SETTLED_PX apart
# (_adjusted). Exact rigs and rigs 0.05-0.15 deg off come to 0.04-0.06 px in ROUNDS; a
# camera knocked by 0.8 deg or more, whose image of the tube lies off its silhouette by a
# radius or two, has most of its side readings set aside at first and comes closer round
# by round (a random shape, one camera turned 0.86 deg, 12 frames: 0.21, 0.19, 0.18, 0.20,
# 0.17, then 0.13, 0.11, 0.09 and 0.075 px at the 16th round). Compared at the same
# number of rounds (one_camera_moved), adjustments that have not settled rank alike only
# near their end: at 4, 8 and 16 rounds a camera knocked 0.8 deg came out alone at 0.94,
# 1.58 and 0.89 times every camera's, another camera alone at 0.70, 0.74 and 1.36.
SAMPLE_FRAMES = 16
ROUNDS = 4
MAX_ROUNDS = 16
SETTLED_PX = 0.06
# "auto" refines only on frames where the tube took at least this many poses, each
# _POSE_APART_MM from the others: frames of a tube that stands still repeat one view
# of it, on which the cameras' 9 parameters each fit the readings' noise (an exact rig
# of three cameras, six frames of one straight pose: 0.16 px apart before, 0.01 px
# after, and cameras 1.4-2.4 px off). Little motion is enough: the straight case of
# the accuracy table sways by at most 3.4 mm (6 poses 1 mm apart in 16 frames), and
# refining it takes a rig 0.05 deg off from 0.66 to 0.17 mm (mean).
_MIN_POSES = 2
_POSE_APART_MM = 1.0
_POSE_POINTS = 16
# "auto" uses the adjusted cameras when the silhouettes' inconsistency (px) falls by
# this factor and some camera's image of the tubes moves by more than _AUTO_MOVE_PX.
# With exact cameras (renders of five shapes, both rigs) the adjustment moves each
# image by 0.02-0.04 px and the inconsistency falls by less than 1.3x.
_AUTO_GAIN = 1.5
_AUTO_MOVE_PX = 0.1
# Where "auto" keeps the given cameras, it still moves the world frame to the mount where
# they see the tube's base farther than this (mm) from base_mm: the silhouettes cannot see
# a rig moved as a whole, which the base can. With exact cameras the base is read within a
# few tenths of a mm (docs/calibration.md).
_AUTO_SHIFT_MM = 1.0
# A camera whose image of the tubes moves by more than this (px) is named in a warning:
# more than a calibration that passed its report (0.1-0.3 px RMS) is off by.
MOVED_PX = 0.5
# One camera bumped since the rig was calibrated: adjusted with the others, its correction
# is shared out over the rig (the prior weighs each camera's share, and the world frame is
# then where the rig's poses average out), and the exact cameras come out millimetres off.
# Adjusted alone, the others kept as given, it leaves the silhouettes as consistent as
# every camera adjusted, and no other camera alone does. Taken where the best camera alone
# leaves them at most ONE_CAMERA_FIT times as far apart as every camera adjusted, and the
# next best at least ONE_CAMERA_APART times the best. On 19 renders with one camera turned
# 0.3-1.2 deg about its centre (90 frames, seven shapes, both rigs; docs/calibration.md has
# eleven; 2026-12-06) the turned camera alone came to 0.84-1.04 times every camera's and
# the next best to 1.14-5 times it on 17 (mean 0.17-4.27 -> 0.08-0.37 mm); on two, two or
# three cameras alone fit alike, and every camera was adjusted as before. With every camera off
# (`--calib-error` 0.05-0.2 deg, 16 renders of 90-150 frames) the best alone came to
# 1.08-2.1 times every camera's, or all three alike on straight tubes; none was taken. Not
# a sure test: on 12 sample frames of a 30-frame random shape 0.15 deg off one camera
# alone came to 1.04, the next 1.22.
ONE_CAMERA_FIT = 1.05
ONE_CAMERA_APART = 1.1


@dataclass(frozen=True)
class CameraChange:
    """How one camera was corrected: its turn (deg) and the shift of its centre (mm), the
    change of its focal length (%) and principal point (px), and the RMS motion (px) of its
    image of the tubes it was refined on."""

    name: str
    turn_deg: float
    shift_mm: float
    focal_percent: float
    principal_px: float
    image_px: float

    def describe(self) -> str:
        return (
            f"{self.name} {self.image_px:.2f} px ({self.turn_deg:.3f} deg, {self.shift_mm:.2f} mm, "
            f"focal {self.focal_percent:+.2f} %, principal point {self.principal_px:.2f} px)"
        )


@dataclass(frozen=True)
class Refinement:
    """The refinement of a session's cameras and its evidence.

    applied : the adjusted cameras were used; reason : why not, when not.
    frames : frames the cameras were adjusted on.
    before_px, after_px : the silhouettes' inconsistency (RMS, px) with the given cameras
        and with the adjusted ones (:class:`pipeline.calibrate.adjust.Adjustment`).
    changes : each camera's correction, the refined camera against the given one.
    seconds : the refinement's wall time, the frames' first reconstruction included.
    mount_shift_mm : how far the refined rig was then moved to see the tube's base at
        the mount (:mod:`pipeline.calibrate.mount`); None when it was not, and
        ``mount_note`` says why. Where the given cameras are kept, ``mount_note`` says
        where they see the base, if not at the mount ("" where they do).
    alone : the one camera refined, the others kept as given ("" where every camera was).
    """

    applied: bool
    frames: int
    before_px: float
    after_px: float
    changes: tuple[CameraChange, ...]
    reason: str = ""
    seconds: float = float("nan")
    mount_shift_mm: tuple[float, float, float] | None = None
    mount_note: str = ""
    lags: tuple[CameraLag, ...] = ()
    alone: str = ""

    @classmethod
    def kept(cls, reason: str, *, mount_note: str = "", lags: tuple[CameraLag, ...] = ()) -> Refinement:
        """The given cameras kept without a refinement, for ``reason``."""
        return cls(False, 0, float("nan"), float("nan"), (), reason, mount_note=mount_note, lags=lags)

    def describe(self) -> str:
        """One line for the summary."""
        moved = f"; {self._moved_to_mount()}" if self.mount_shift_mm is not None else ""
        if not self.frames or not np.isfinite(self.before_px):
            return f"given ({self.reason}){moved}"  # a tube that held one pose, moved or not
        figures = (
            f"silhouettes {self.before_px:.3f} px apart with the given cameras, "
            f"{self.after_px:.3f} px refined, on {self.frames} frames in {self.seconds:.1f} s"
        )
        if not self.applied:
            return f"given ({self.reason}; {figures}){moved}"
        if self.mount_shift_mm is not None:
            frame = self._moved_to_mount()
        elif self.alone:
            kept = " and ".join(c.name for c in self.changes if c.name != self.alone)
            frame = f"{kept} kept as given (the world frame theirs)"
        else:
            frame = f"the world frame held by the given cameras' poses ({self.mount_note})"
        everyone = not self.alone or self.mount_shift_mm is not None  # a moved rig moves every camera
        shown = [c for c in self.changes if everyone or c.name == self.alone]
        return f"refined ({figures}): " + "; ".join(c.describe() for c in shown) + f"; {frame}"

    @property
    def changed(self) -> bool:
        """The cameras used are not the given ones: refined, or moved to the mount."""
        return self.applied or self.mount_shift_mm is not None

    def _moved_to_mount(self) -> str:
        assert self.mount_shift_mm is not None
        x, y, z = self.mount_shift_mm
        distance = float(np.linalg.norm(self.mount_shift_mm))
        return f"the world frame moved {distance:.2f} mm ({x:+.2f}, {y:+.2f}, {z:+.2f}) to the mount"

    def warnings(self) -> list[str]:
        """A line per camera that seems to have moved since it was calibrated (the run
        corrected it), or one for a rig kept as given and moved to the mount as a whole."""
        if not self.applied and self.mount_shift_mm is not None:
            distance = float(np.linalg.norm(self.mount_shift_mm))
            return [
                f"the cameras see the tube's base {distance:.1f} mm from [manipulator] base_mm, and "
                "were moved there as a whole: the rig has moved since it was calibrated, or base_mm "
                "is off; recalibrate, or correct base_mm"
            ]
        return [
            f"camera {c.name} seems to have moved since it was calibrated: its image of the tube is "
            f"{c.image_px:.1f} px off; recalibrate it, or keep [calibration] refine on"
            for c in self.changes
            if self.applied and c.image_px > MOVED_PX
        ]

    def problems(self) -> list[str]:
        """A line if the tube's base is seen far from the mount's place in the settings
        (every frame was fitted to start there, bent by as much), and one per camera whose
        video is out of step with the others' (every frame was fitted to two moments)."""
        lines = [lag.describe() for lag in self.lags]
        if self.mount_note.endswith(CHECK_BASE):
            lines.append(f"{self.mount_note} (its frames are fitted to start there)")
        return lines


def camera_change(given: Camera, refined: Camera, points_mm: FloatArray) -> CameraChange:
    """The correction from ``given`` to ``refined``, its image motion judged at ``points_mm`` (N, 3)."""
    relative = refined.camera_from_world @ given.camera_from_world.T
    turn = float(np.degrees(np.linalg.norm(cv2.Rodrigues(relative)[0])))
    motion = refined.project(points_mm) - given.project(points_mm)
    return CameraChange(
        name=given.name,
        turn_deg=turn,
        shift_mm=float(np.linalg.norm(refined.center_mm - given.center_mm)),
        focal_percent=float(100.0 * (refined.focal_px / given.focal_px - 1.0)),
        principal_px=float(np.linalg.norm(refined.matrix[:2, 2] - given.matrix[:2, 2])),
        image_px=float(np.sqrt(np.nanmean(np.sum(motion**2, axis=1)))),
    )


def sample_tubes(
    model: SessionModel,
    frames: Sequence[tuple[int, Sequence[NDArray[np.uint8]]]],
    map_frames: FrameMap = map_here,
) -> list[Tube]:
    """The tubes of ``frames`` (index, per camera grey image), each reconstructed alone
    with ``model``'s cameras and its base free; frames without a curve are left out.
    ``map_frames`` runs the frames (:data:`pipeline.reconstruct.frame_task.FrameMap`).

    Held at the mount, which is known in the given rig's world only, each tube would
    bend near its base by the calibration's error; free, its base is where the views
    see it, which is what holds the refined rig to the mount (:mod:`.mount`)."""
    samples = map_frames(_sample, frames, _base_free(model))
    return [_drawn_with(tube, model) for tube, _ in samples if tube is not None]


def refitter(
    model: SessionModel,
    frames: Sequence[tuple[int, Sequence[NDArray[np.uint8]]]],
    map_frames: FrameMap = map_here,
) -> Callable[[Sequence[Camera]], list[Tube]]:
    """A function of cameras: the tubes of ``frames`` reconstructed as :func:`sample_tubes`
    does, with those cameras instead of ``model``'s."""

    def refit(cameras: Sequence[Camera]) -> list[Tube]:
        grid = build_grid(cameras, model.settings.workspace)
        return sample_tubes(dataclasses.replace(model, cameras=tuple(cameras), grid=grid), frames, map_frames)

    return refit


def _drawn_with(tube: Tube, model: SessionModel) -> Tube:
    """``tube`` with ``model``'s spacer disks, which it was fitted with. Set here, not where
    the frame was fitted: a worker's model is mapped from a file that is gone once the
    frames are in, and the disks sent on from there would point at it."""
    disks = model.disks
    return tube if disks is None else dataclasses.replace(tube, disks=disks)


def _base_free(model: SessionModel) -> SessionModel:
    """``model`` without ``[manipulator] base_mm``: its frames fitted with the base free."""
    manipulator = dataclasses.replace(model.settings.manipulator, base_mm=None)
    return dataclasses.replace(model, settings=dataclasses.replace(model.settings, manipulator=manipulator))


def _sample(
    index: int, images: Sequence[NDArray[np.uint8]], model: SessionModel, *, tip: bool = False
) -> tuple[Tube | None, FrameTip | None]:
    """One frame's tube for :func:`sample_tubes` (``model``: its base free) and, with
    ``tip``, its end read for the session's (:func:`pipeline.reconstruct.tip_shape.frame_tip`);
    None for either without a curve."""
    result, masks = reconstruct_with_silhouettes(index, images, model)
    if result.status != "ok" or result.centerline_mm is None or not np.isfinite(result.radius_mm):
        return None, None
    contrasts = frame_contrasts(images, model)
    tube = resampled_tube(result.centerline_mm, result.radii_mm, result.radius_mm, contrasts, masks)
    return tube, frame_tip(result, masks, contrasts, model) if tip else None


def distinct_poses(tubes: Sequence[Tube], *, apart_mm: float = _POSE_APART_MM) -> int:
    """How many of ``tubes`` differ from each other by more than ``apart_mm`` (mean
    distance between points at the same fractions of their lengths), counted greedily."""
    shapes = [resample_polyline(t.points_mm, _POSE_POINTS) for t in tubes]
    kept: list[FloatArray] = []
    for shape in shapes:
        if all(np.mean(np.linalg.norm(shape - other, axis=1)) > apart_mm for other in kept):
            kept.append(shape)
    return len(kept)


def refine(
    model: SessionModel,
    tubes: Sequence[Tube],
    mode: str | bool,
    refit: Callable[[Sequence[Camera]], Sequence[Tube]],
    adjustment: Adjustment | None = None,
) -> tuple[tuple[Camera, ...], Refinement]:
    """The cameras to reconstruct with, given the refinement ``mode`` ("auto", True or
    False), and the refinement's report. Where "auto" keeps the given cameras, they are
    still moved to the mount where they see the tube's base farther than
    ``_AUTO_SHIFT_MM`` from base_mm (the rig off as a whole, which no silhouette shows).

    ``adjustment``: the cameras and ``tubes`` adjusted together, if already done.
    ``refit``: the frames' tubes reconstructed again with given cameras
    (:func:`refitter`), to read the base on (:mod:`.mount`). The adjusted tubes will
    not do: the adjustment moves each tube by linear steps, smooth along it, and leaves
    a base that the given cameras put millimetres off still 2-6 mm from where the
    adjusted cameras see it (a bend, 0.15 deg off, 16 frames), too far for the end's
    reading, which looks along the tube and a radius across it.
    """
    given = model.cameras
    base = model.settings.manipulator.base_mm
    poses = distinct_poses(tubes)
    if mode == "auto" and poses < _MIN_POSES:
        reason = (
            f"the tube took {poses} distinct pose{'s' if poses != 1 else ''} in the {len(tubes)} frames "
            f"sampled; refining needs {_MIN_POSES} or more, {_POSE_APART_MM:g} mm apart"
        )
        shift, note = _given_at_mount(given, tubes, base, to_mount=mode == "auto")
        report = Refinement(
            False,
            len(tubes),
            float("nan"),
            float("nan"),
            (),
            reason,
            mount_shift_mm=_mm(shift),
            mount_note=note,
        )
        return _moved(given, shift), report
    # The tubes' bases free, as they were reconstructed (see sample_tubes).
    adjustment = _adjusted(given, tubes) if adjustment is None else adjustment
    points = np.concatenate([t.points_mm for t in adjustment.tubes])
    gain = adjustment.before_px / max(adjustment.after_px, 1e-9)
    # What the silhouettes tell of the cameras, apart from where the rig as a whole is
    # put: an exact calibration refined moves by the readings' noise alone.
    aligned = aligned_by_images(adjustment.cameras, given, points)
    moved = max(camera_change(g, r, points).image_px for g, r in zip(given, aligned, strict=True))
    reason = ""
    if mode == "auto" and gain < _AUTO_GAIN:
        reason = f"they agree with the silhouettes to within {gain:.2f}x of the refined ones"
    elif mode == "auto" and moved <= _AUTO_MOVE_PX:
        reason = f"refining moves no camera's image by more than {moved:.2f} px"
    applied = not reason
    alone = one_camera_moved(given, tubes, adjustment) if applied else None
    if alone is not None:
        adjustment = alone[1]
        points = np.concatenate([t.points_mm for t in adjustment.tubes])
    cameras = list(adjustment.cameras)
    shift = None
    if applied and base is not None:
        shift, held_by = mount_shift(cameras, refit(cameras), np.asarray(base), refined=True)
        if alone and shift is not None and np.linalg.norm(shift) <= _AUTO_SHIFT_MM:
            # The world frame is the cameras' kept as given, which see the base where it is.
            shift = None
        if shift is not None:
            cameras = moved_to_mount(cameras, shift)
            points = points - shift
    elif not applied:
        shift, held_by = _given_at_mount(given, tubes, base, to_mount=mode == "auto")
    else:
        held_by = "no [manipulator] base_mm"
    changes = tuple(camera_change(g, r, points) for g, r in zip(given, cameras, strict=True))
    report = Refinement(
        applied,
        len(tubes),
        adjustment.before_px,
        adjustment.after_px,
        changes,
        reason,
        mount_shift_mm=_mm(shift),
        mount_note=held_by,
        alone="" if alone is None else given[alone[0]].name,
    )
    return (tuple(cameras) if applied else _moved(given, shift)), report


def _adjusted(cameras: Sequence[Camera], tubes: Sequence[Tube]) -> Adjustment:
    """The ``cameras`` and ``tubes`` adjusted together, the tubes' bases free as they were
    reconstructed (see ``ROUNDS``)."""
    return adjust_cameras(
        cameras, tubes, base_mm=None, rounds=ROUNDS, settled_px=SETTLED_PX, max_rounds=MAX_ROUNDS
    )


def one_camera_moved(
    given: Sequence[Camera], tubes: Sequence[Tube], everyone: Adjustment
) -> tuple[int, Adjustment] | None:
    """The camera that alone moved since the rig was calibrated, and the adjustment of it
    alone, the others kept as given; None where no one camera explains the silhouettes.

    A bumped camera is the common case, and the adjustment of ``everyone`` spreads its
    correction over the rig (the prior and the world frame share it out; see
    ``ONE_CAMERA_FIT``). Each camera is adjusted alone in turn: taken where it leaves the
    silhouettes as consistent as every camera adjusted (within ``ONE_CAMERA_FIT``) and
    clearly more than any other camera alone (by ``ONE_CAMERA_APART``).
    """
    # As many rounds as every camera's took: the two compared at the same stage.
    alone = [
        adjust_cameras(
            given, tubes, rounds=everyone.rounds, held=[k for k in range(len(given)) if k != moved]
        )
        for moved in range(len(given))
    ]
    best, second = np.argsort([a.after_px for a in alone])[:2]
    if alone[best].after_px > ONE_CAMERA_FIT * everyone.after_px:
        return None
    if alone[second].after_px < ONE_CAMERA_APART * alone[best].after_px:
        return None
    return int(best), alone[best]


def _given_at_mount(
    given: Sequence[Camera], tubes: Sequence[Tube], base_mm: Sequence[float] | None, *, to_mount: bool
) -> tuple[FloatArray | None, str]:
    """Where the given cameras, kept, see the ``tubes``' base end (they were reconstructed
    with them, the base free) against ``[manipulator] base_mm``: with ``to_mount``, the
    shift (3,) mm to move them by where it is farther than ``_AUTO_SHIFT_MM`` (the rig off
    as a whole, which no silhouette shows), else None; and "" where they see it there, or
    the note of :func:`~pipeline.calibrate.mount.mount_shift` (a base seen farther than a
    calibration's error puts it ends in ``CHECK_BASE``: every frame is fitted to start at
    a wrong place, silently bent). Read once a run, on the frames refined on."""
    if base_mm is None:
        return None, "no [manipulator] base_mm"
    shift, note = mount_shift(given, tubes, np.asarray(base_mm, dtype=np.float64))
    if not to_mount or shift is None or np.linalg.norm(shift) <= _AUTO_SHIFT_MM:
        return None, note
    return shift, note


def _mm(shift: FloatArray | None) -> tuple[float, float, float] | None:
    return None if shift is None else (float(shift[0]), float(shift[1]), float(shift[2]))


def _moved(cameras: tuple[Camera, ...], shift: FloatArray | None) -> tuple[Camera, ...]:
    """``cameras`` moved to the mount by ``shift`` (:func:`moved_to_mount`); themselves where None."""
    return cameras if shift is None else tuple(moved_to_mount(cameras, shift))


def sample_session(
    video_paths: Sequence[Path], start: int, stop: int
) -> Sequence[tuple[int, Sequence[NDArray[np.uint8]]]]:
    """The ``SAMPLE_FRAMES`` frames spread over ``[start, stop)`` that settle the cameras
    (:func:`refined_cameras`), the videos' order (:mod:`.video_order`) and the tube's end:
    (index, per camera (H, W) uint8 grey image), decoded once for all three."""
    return decode_frames(video_paths, sample_frames(start, stop, SAMPLE_FRAMES))


def refined_cameras(
    model: SessionModel,
    frames: Sequence[tuple[int, Sequence[NDArray[np.uint8]]]],
    map_frames: FrameMap = map_here,
    frames_of: FramesOfCamera | None = None,
) -> tuple[tuple[Camera, ...], Refinement | None, ReadTips | None, RadiusProfile | None]:
    """The cameras to reconstruct the session with, under the settings' ``[calibration]
    refine``, and the refinement's report, from its sample ``frames`` (:func:`sample_session`).
    The report, where the cameras are kept without refining (``refine = false``, two
    cameras), says why and where they see the tube's base (:func:`_kept_as_given`); it is
    None where the centreline is not the tube fit, or too few frames show the tube to refine
    on. ``map_frames`` runs their reconstructions. Given each camera's frames around them
    (``frames_of``), a camera whose video is out of step with the others' is named and the
    cameras kept as given (:mod:`.frame_lag`).

    Third, where the settings leave the tube's end to the frames (``[manipulator] tip =
    "auto"``) and the given cameras are kept: the sample frames' ends, read on the same
    reconstructions, for :func:`pipeline.reconstruct.tip_shape.with_session_tip` (their
    bases are free, which moves a fit near its base, not at its end); else None.

    Fourth, where it reconstructs them: the tube's radius along it read on those frames
    (:mod:`pipeline.reconstruct.radius_profile`, for the model's ``radius_profile``); else None."""
    started = time.perf_counter()
    mode = model.settings.calibration.refine
    if model.settings.centerline.method != "fit":
        return model.cameras, None, None, None
    if mode is False:
        report = _kept_as_given(model, frames, map_frames, "[calibration] refine = false")
        return model.cameras, report, None, None
    if len(model.cameras) < 3:
        # Each sample of a tube's sides is read once per view, across it: two views give
        # exactly the two numbers that place it, and nothing is left to tell the cameras by.
        reason = "two views of a tube's sides say nothing about the cameras; refining needs three or more"
        # Nor are they moved to the mount: two views read the base end less surely (on
        # `accuracy_table --draw 2 --cases 10 --frames 150`, 2026-12-05, exact cameras read
        # a disk tube's base 1.98 mm off along it, and moved there it came out 4.14 mm off
        # against 2.14 kept), though they gained where the calibration was off (a straight
        # tube 0.15 deg off, 2.75 -> 0.21 mm).
        tubes = sample_tubes(model, frames, map_frames)
        report = _kept_as_given(model, frames, map_frames, reason, tubes)
        return model.cameras, report, None, _two_view_disks(model, tubes)
    indexed, read, profile = _sampled(model, frames, map_frames)
    tubes = [tube for _, tube in indexed]
    if profile is not None and profile.disks is not None:
        # The cameras are judged, and the frames fitted again, with the tube's disks drawn.
        model = dataclasses.replace(model, radius_profile=profile.disks_alone())
    if len(tubes) < 3:
        few = (
            f"only {len(tubes)} of the {len(frames)} sample frames were reconstructed with them, "
            "too few to refine on"
        )
        return model.cameras, Refinement.kept(few), read, profile
    lags = [] if frames_of is None else camera_lags(model, indexed, frames_of, map_frames)
    in_step: Adjustment | None = None  # the cameras adjusted to the frames as they are
    if lags:
        # A calibration that is off can pass for a lag, and one video out of step can make
        # another look so: of the lags named, the one that refined cameras explain best, if
        # better than the frames in step.
        assert frames_of is not None
        apart = [_shifted_apart_px(model, frames, lag, frames_of, map_frames) for lag in lags]
        best = int(np.argmin(apart))
        in_step = _adjusted(model.cameras, tubes)
        if np.isfinite(apart[best]):  # else too few frames to tell: the lag test's word
            lags = [lags[best]] if apart[best] < in_step.after_px else []
    if lags:
        # The tubes were fitted to views of two moments: adjusted to them, the cameras would
        # take the difference for cameras that moved.
        reason = "a camera's video is out of step with the others'"
        report = Refinement.kept(reason, lags=tuple(lags))
        report = dataclasses.replace(report, seconds=time.perf_counter() - started)
        return model.cameras, report, read, profile
    cameras, report = refine(model, tubes, mode, refitter(model, frames, map_frames), in_step)
    report = dataclasses.replace(report, seconds=time.perf_counter() - started)
    # The ends read with the given cameras serve only them. Moved to the mount, the frames'
    # bases are held there and their ends read anew: on a bend 0.15 deg off (`synth --frames
    # 60 --calib-error 0.15 --seed 3`, 2026-12-05) the given cameras' ends mixed with the
    # moved rig's made the end a close call (-0.12 +- 0.08, every frame flagged); read anew,
    # flat, -0.26 +- 0.11, no frame flagged, at the same 0.24 mm.
    # The radius along the tube is the same whichever the cameras (a refinement moves an
    # image by tenths of a pixel): read with the given ones, it serves the refined ones too.
    return cameras, report, None if report.changed else read, profile


def _shifted_apart_px(
    model: SessionModel,
    frames: Sequence[tuple[int, Sequence[NDArray[np.uint8]]]],
    lag: CameraLag,
    frames_of: FramesOfCamera,
    map_frames: FrameMap,
) -> float:
    """How far apart (px) the views leave the sample ``frames``, their lagging camera's
    images taken ``lag.frames`` on, once the cameras are adjusted to them
    (:class:`~pipeline.calibrate.adjust.Adjustment`'s ``after_px``; inf with too few frames).

    The lag test compares a camera's silhouettes with the tube fitted to the others, drawn
    with the given cameras: where those are off, a tube that moves steadily across that view
    can match a frame or two away better, as if the video were out of step; and one video
    out of step pulls the others' tubes off too. Of the accounts, the cameras refined for
    each, the one that explains the silhouettes best stands. On a random shape whose rig
    was 0.1 deg off (`synth --shape random --arrangement oblique --seed 22 --frames 90
    --calib-error 0.1`; 2026-12-06) cam1 matched best two frames on (0.72 of the pixels, 11
    of 14 frames); refined, the frames in step came to 0.034 px apart and cam1's shifted to
    0.079. docs/calibration.md has the measures on drawn sessions.
    """
    camera = [c.name for c in model.cameras].index(lag.name)
    shifted = []
    for index, images in frames:
        moved = index + lag.frames
        image = frames_of(camera, moved, moved + 1) if moved >= 0 else []
        if image and image[0] is not None:
            shifted.append((index, [image[0] if k == camera else im for k, im in enumerate(images)]))
    tubes = sample_tubes(model, shifted, map_frames)
    return _adjusted(model.cameras, tubes).after_px if len(tubes) >= 3 else float("inf")


def _kept_as_given(
    model: SessionModel,
    frames: Sequence[tuple[int, Sequence[NDArray[np.uint8]]]],
    map_frames: FrameMap,
    reason: str,
    tubes: Sequence[Tube] | None = None,
) -> Refinement:
    """The report of cameras kept as given without a refinement (for ``reason``), with where
    they see the tube's base against ``[manipulator] base_mm``, read on the tubes of the
    sample ``frames`` as where a refinement keeps them (:func:`_given_at_mount`). On the
    51 two-camera sessions of ``accuracy_table`` draws 2, 191-231 and 307 (2026-12-05), the
    true base_mm was never called wrong (41 seen there, 10 whose base end the frames see
    unalike), and base_mm 15 mm off in x or z, or 8 mm in y, was named in those 41.
    ``tubes``: the sample frames' tubes (:func:`sample_tubes`), if fitted already."""
    note = ""
    if model.settings.manipulator.base_mm is not None:
        if tubes is None:
            tubes = sample_tubes(model, frames, map_frames)
        if len(tubes) >= 3:
            _, note = _given_at_mount(
                model.cameras, tubes, model.settings.manipulator.base_mm, to_mount=False
            )
    return Refinement.kept(reason, mount_note=note)


def _two_view_disks(model: SessionModel, tubes: Sequence[Tube]) -> RadiusProfile | None:
    """The spacer disks of the tube read on a two-camera rig's sample ``tubes``, as a
    profile of them alone (None without): two views read disks as three do, but the radius
    along the tube less surely than each frame's own (see
    :mod:`pipeline.reconstruct.radius_profile`)."""
    profile = read_radius_profile(
        [(tube.points_mm, tube.radii_mm, tube.contrasts) for tube in tubes], model.cameras, FIT_SPACING_MM
    )
    return None if profile is None else profile.disks_alone()


def sample_evidence(
    model: SessionModel,
    frames: Sequence[tuple[int, Sequence[NDArray[np.uint8]]]],
    map_frames: FrameMap = map_here,
) -> tuple[ReadTips | None, RadiusProfile | None]:
    """The tube ends and the radius along the tube that :func:`refined_cameras` reads where
    it keeps the given cameras, read the same way on the sample ``frames`` without refining:
    a run that keeps its cameras as given (a live replay) then reconstructs as ``process``
    does. Each None where it reads none (``[calibration] refine = false``; the ends where
    session.toml sets the end, or on fewer than three cameras, where the radius is the
    spacer disks alone)."""
    settings = model.settings
    refines = settings.calibration.refine is not False and settings.centerline.method == "fit"
    if refines and len(model.cameras) < 3:
        return None, _two_view_disks(model, sample_tubes(model, frames, map_frames))
    if not _samples_frames(model):
        return None, None
    _, read, profile = _sampled(model, frames, map_frames)
    return read, profile


def _samples_frames(model: SessionModel) -> bool:
    """Whether :func:`refined_cameras` reconstructs sample frames for ``model``."""
    settings = model.settings
    refines = settings.calibration.refine is not False and settings.centerline.method == "fit"
    return refines and len(model.cameras) >= 3


def _reads_tips(model: SessionModel) -> bool:
    """Whether :func:`refined_cameras` reads the sample frames' ends (the end left to the
    frames, ``[manipulator] tip = "auto"``)."""
    return _samples_frames(model) and model.settings.manipulator.tip == "auto"


def _sampled(
    model: SessionModel,
    frames: Sequence[tuple[int, Sequence[NDArray[np.uint8]]]],
    map_frames: FrameMap,
) -> tuple[list[tuple[int, Tube]], ReadTips | None, RadiusProfile | None]:
    """The tubes of ``frames`` (:func:`sample_tubes`), each with its frame's index; where
    the session reads its tube end from them (:func:`_reads_tips`), their ends read on the same
    reconstructions (else None); and the radius along the tube read on them."""
    read_tips = _reads_tips(model)

    def fitted(
        model: SessionModel,
    ) -> tuple[list[tuple[Tube | None, FrameTip | None]], list[tuple[int, Tube]], RadiusProfile | None]:
        samples = map_frames(functools.partial(_sample, tip=read_tips), frames, _base_free(model))
        tubes = [
            (index, _drawn_with(tube, model))
            for (index, _), (tube, _) in zip(frames, samples, strict=True)
            if tube is not None
        ]
        profile = read_radius_profile(
            [(tube.points_mm, tube.radii_mm, tube.contrasts) for _, tube in tubes],
            model.cameras,
            FIT_SPACING_MM,
        )
        return samples, tubes, profile

    samples, tubes, profile = fitted(model)
    if profile is not None and profile.disks is not None:
        # Fitted without them, a tube with spacer disks is bent by their outlines: the
        # frames are fitted again with the disks drawn, and the disks read again on them.
        # Fitted again while that finds more of them (up to three times), the two
        # three-camera sessions it changed of 16 with disks (`draw_cases` from seed 700,
        # 2026-12-07; dense disks found in part) came out worse: 1.730 -> 1.827 and 1.473 ->
        # 1.589 mm mean.
        samples, tubes, profile = fitted(dataclasses.replace(model, radius_profile=profile.disks_alone()))
    if not read_tips:
        return tubes, None, profile
    tips = tuple(tip for _, tip in samples if tip is not None)
    return tubes, ReadTips(tuple(index for index, _ in frames), tips), profile


_SOURCE = "pipeline process: refined from the session's silhouettes"


def remove_refined_calibration(path: Path) -> None:
    """Remove ``path`` if it is a refined calibration an earlier run wrote (its metadata
    says so); any other file is left alone."""
    try:
        if load_toml(path).get("metadata", {}).get("source") == _SOURCE:
            path.unlink()
    except (OSError, ValueError, AttributeError):
        pass


def write_refined_calibration(
    path: Path, partial: Path, cameras: Sequence[Camera], refinement: Refinement
) -> tuple[Path, int]:
    """Write the refined ``cameras`` to ``path`` (through the temporary ``partial``, renamed
    into place), with the refinement in its metadata; (path, bytes written)."""
    metadata = {
        "source": _SOURCE,
        "silhouettes_apart_px": {"given": refinement.before_px, "refined": refinement.after_px},
        "frames": refinement.frames,
    }
    try:
        write_calibration(partial, list(cameras), metadata)
        partial.replace(path)
    except OSError as exc:
        partial.unlink(missing_ok=True)
        raise OutputError(f"{path}: cannot write the refined calibration: {exc.strerror}") from None
    return path, path.stat().st_size
