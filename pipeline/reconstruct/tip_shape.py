"""The tube's end, flat or round, chosen once per session from a few of its frames.

A flat end and a hemispherical one cover different pixels around the tip: seen
side-on, the flat end's outline is square where the round one's is a half
disc, and the round end reaches a radius past its centre (the backbone's end).
At the rigs' ~0.6 px/mm that difference is a few pixels a view, about what a
radius 10 % off or a misplaced tip also changes; so the choice is made as a
comparison of the two ends and nothing else:

- the end's radius is read once for the session: the median of every view's
  reading of the few radii of tube just behind each frame's tip
  (:func:`end_radius_readings`; the fit's own radius there can carry a spacer disk
  or the taper before it, and a radius too large favours the round end, too small
  the flat one);
- in each frame, the tip is placed by the grey levels under either end
  (:func:`pipeline.reconstruct.tip_bend.bend_tip_to_pixels`) and the two are compared on the
  pixels around the tip only (:func:`frame_evidence`), each end drawn at the radius
  within a few % of that reading that suits it best, so that a reading a little off
  does not choose; a frame whose two tips went to different places compares places,
  not ends, and is left out;
- each frame then has one bounded vote (:attr:`FrameEvidence.vote`), so that no
  one frame decides: summed raw costs let one frame whose tip was misplaced
  outweigh the others;
- the mean vote's sign chooses; where it lies within ``CLEAR_T`` standard errors
  of 0, the summary says that the frames barely tell the ends apart.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import Camera
from ..geometry.polyline import polyline_arclength
from .disks import Disks
from .frame import frame_contrasts, reconstruct_with_silhouettes
from .frame_result import FrameResult
from .frame_task import FrameMap, decode_frames, map_here
from .model import SessionModel
from .radius_profile import RadiusProfile
from .side_readings import read_sides
from .tip_bend import bend_tip_to_pixels
from .tube_drawing import Window, drawn_coverage, pixel_coverages
from .tube_fit import FIT_SPACING_MM

FloatArray = NDArray[np.float64]

# Frames sampled over the session. Each frame's vote is worth a few pixels of
# evidence at most, and a frame can miss its tip. On 40 drawn sessions (seeds 1,
# 2 of pipeline.synth.variety, 40 frames each) the summed costs of 6 frames chose
# wrong on 11, of 12 frames on 9; the votes below on 10 frames, on 1. Ten frames
# cost ~1.8 times the six of the summed costs (the radius is read on top). Where ten
# leave a close call (CLEAR_T), the nine frames halfway between them are read too and
# the choice made from all: on 32 rendered sessions (`accuracy_table` draws 2, 7 and
# 11, the demo, the bench's loop and random shape, four loops; 2026-12-02) close calls
# 11 -> 7 (three cameras 3 -> 2), wrong choices 2 -> 1; the clear sessions read no more.
# Where nineteen still leave it close, the eighteen halfway between those (ROUNDS): on the
# 19 close calls of 78 rendered sessions (`accuracy_table` draws 2, 7, 13, 41, 61 and 73,
# 28 cases of draw 91 at 40 frames; 2026-12-03) the third round makes 7 clear and right,
# none clear and wrong; over the 78, the end chosen wrongly on 4, 1 of them clear (a
# round-ended stepped shape beside a dark object), and 12 close calls (5, 1 and 18 with two
# rounds and the end's band placed by the fit's radius along the tube, see _frame_tip;
# placed so, a third round makes a spacer-disk helix clear and wrong). A fourth round (73
# frames read in all) was measured on the 9 close calls of 63 rendered sessions (90 frames
# each, the 46 of pipeline.reconstruct.quality.SUSPECT_JUMP_RADII, 17 two-camera ones and
# draw 109's loop with disks; 2026-12-03): it made 2 clear and right (a tapered loop and a
# two-camera tapered shape, good frames flagged 37 -> 0 and 72 -> 4), turned 2 two-camera
# choices from wrong to right but still close, made none clear and wrong, left 5 close,
# and cost 7-22 s a session. Left out: most close calls stay close.
# Where the cameras' refinement reconstructs its 16 frames and keeps the given cameras, the
# ends of those frames' fits take the first round's place (ReadTips; their bases are free):
# on 22 three-camera sessions of `accuracy_table` draws 2, 97, 103, 109 and 115 (2026-12-04)
# they chose as these ten did, and settled two of the three that these left close.
SAMPLE_FRAMES = 10
ROUNDS = 3
# Where the mean vote lies within this many standard errors of 0, the choice is a close
# one: the summary says so, and every frame is suspect for it (TIP_DOUBT). On the 32
# sessions above (with the second round of frames) the sign of the mean vote chose wrongly
# on 1, a close call (a round-ended loop tapered to a 2.7 mm end, -0.19 +- 0.14), and 6
# others were close calls chosen rightly, 5 of them on two cameras; on a fresh draw
# (`accuracy_table --draw 13 --cases 8 --frames 90`, same day), wrongly on 1 of its 3 close
# calls (a round-ended tube tapered to 2.7 mm, three cameras, -0.03 +- 0.10). Letting only
# a mean beyond the bar choose, with flat otherwise (sampling up to 30 frames), chose
# wrongly as often on 28 sessions: round ends whose frames barely show them went flat.
CLEAR_T = 2.0
CAPS = ("flat", "round")
# Every written frame's suspect reason where the end was a close call (TipChoice.doubt:
# not ``clear``, or chosen from no frame): the other end would put each tip up to a radius
# along the tube from where this one does, more than 2 mm on most tubes, and no frame tells
# which is right. The track does not see it (a frame's own suspect reason steers the
# prediction); the writers add it (pipeline.run.outputs.Writers). On three seeded draws
# (`accuracy_table --draw 2 --cases 10 --frames 150`, `--draw 7 --cases 8 --frames 120`,
# `--draw 13 --cases 8 --frames 90`; 2026-12-02) the flag names 70, 86 and 68 % of the
# frames more than 2 mm off (60, 64 and 55 % without this reason) and 11.4, 24.2 and
# 45.9 % of the others (4.1, 12.5 and 2.1 %): the close calls' good frames are flagged
# with their wrong ones.
TIP_DOUBT = "the tube's end, flat or round, is a close call: its tip may be a radius off along the tube"
# The bend under each end: its last radius, sought within a few mm of the fit.
_SPANS_RADII = (2.0, 1.0)
_STEPS_MM = (2.0, 1.0, 0.5, 0.25)
# The end's radius is read between these multiples of the fit's radius there
# (the fit's was 0.99-1.24 times the truth on the drawn sessions: too large
# where a spacer disk or the taper's wider part is near the tip). Each view's
# reading, interpolated between them and the median taken over every view of
# the frames, against the best of them per frame and the median over frames: on
# 24 rendered sessions (`accuracy_table --draw 2` and draw 7, the demo, the
# bench's loop and random shape, three loops; 2026-12-02) the end chosen wrongly
# on 1 instead of 3, the flat tapered loop whose tip lies by its stem read at
# 4.28 mm instead of 4.80 (truth 4.20) ...
_RADIUS_SCALES = np.round(np.arange(0.7, 1.1001, 0.05), 2)
# ... matching the pixels nearest to the axis between these many radii before
# its end, within _BAND_REACH_RADII of it: past the fitted end's uncertainty (it was
# fitted as flat, 0.6 radii long on a round end: 1.8-2.4 mm on three round ends of
# 3-3.5 mm), so that the radius is read alike whichever the end, and short of the
# nearest spacer disk (on the drawn tubes at least 1.25 radii from the end, and seen
# obliquely a disk's ellipse reaches back along the axis). On 58 sessions of
# pipeline.synth.variety.draw_cases(seed, 14), seeds 7000-7010 (90 frames each; 2026-12-04),
# the median reading of the fitted ends was 1.005 times the truth on flat ends and 1.001
# on round ones (with the band from 0.25 radii: 0.998 and 0.969, a round end read thinner
# and so nearer a flat one). Over those and 112 sessions of seeds 8000-8003 and 9000-9003
# (60 frames each), the end chosen rightly and clearly on 158 sessions against 152, wrongly
# on 2 against 2, close calls 10 against 16; on the 34 of `accuracy_table` draws 2, 97, 103
# and 109 (same day), 29, 0 and 5 against 30, 0 and 4 (round ends read clearer, thin flat
# ones closer).
_BAND_RADII = (0.6, 1.0)
_BAND_REACH_RADII = 1.6
# ... and away from the other parts of the tube: the pixels within a projected radius
# (each part's own: the taper's wider base, say) and _OTHER_EDGE_PX (their blurred edge)
# of the axis more than _OTHER_APART_RADII end radii before the band are not the end's.
_OTHER_EDGE_PX = 1.5
_OTHER_APART_RADII = 2.0
# The ends are compared on a window around the last _REGION_RADII of either's
# axis, grown by _REGION_MARGIN_RADII (projected) and a pixel or two.
_REGION_RADII = 2.0
_REGION_MARGIN_RADII = 1.5
_REGION_MARGIN_PX = 2.0
# Seen side-on, a flat end covers (2 - pi / 2) r^2 more than a round one (its two
# square corners). Where the two ends' tubes differ by more than that in a view,
# their bends took the tip to different places, and the frame compares places,
# not ends: it does not vote. On the drawn sessions (seeds 1, 2) 90 % of views
# stay under half of it, frames whose bends parted (a fit that missed the tip, a
# flat bend gone astray on a spacer disk) reach 1.5-30 times it; the latter had
# a session decided wrongly. Bounds from 0.75 to 3 times it changed no choice.
_MAX_SEPARATION = 2.0 - np.pi / 2.0
# Each end is drawn at these multiples of the end's radius read, and costs what its best
# drawing does: a radius read a few % off (a spacer disk near the end, a taper's wider
# part) does not decide for one end, a radius too large for the round one and too small
# for the flat. On 78 rendered sessions (`accuracy_table` draws 2, 7, 13, 41, 61 and 73,
# and 28 cases of draw 91 at 40 frames; 2026-12-03), with the end's band placed by the
# fit's radius along the tube, against each end drawn at the reading alone: the end
# chosen wrongly on 5 against 9, wrongly without a close call on 1 against 4 (a
# spacer-disk helix whose end radius read 1.21 times the truth is a close call, not a
# wrong choice), close calls 18 against 15. From 0.9 to 1.1 times: 8 wrong.
_DRAWN_SCALES = (0.94, 0.97, 1.0, 1.03, 1.06)
_AT_READING = _DRAWN_SCALES.index(1.0)
# The axis' last radii are sampled every this many mm (_last).
_LAST_STEP_MM = 0.25


@dataclass(frozen=True)
class FrameEvidence:
    """How well each end explains one frame's pixels around its tip.

    flat_cost, round_cost : squared coverage difference (px) between the grey
        levels and the tube drawn with that end, summed over the compared views, at
        the radius near the end's reading that makes it least (``_DRAWN_SCALES``).
    separation : squared coverage difference (px) between the two ends' tubes:
        what the costs could differ by if one of them were exact.
    views : how many views were compared.
    """

    flat_cost: float
    round_cost: float
    separation: float
    views: int

    @property
    def vote(self) -> float:
        """In [-1, 1]: -1 when the pixels are the flat end's, +1 the round one's;
        in between, where they lie between the two."""
        if self.separation <= 0:
            return 0.0
        return float(np.clip((self.flat_cost - self.round_cost) / self.separation, -1.0, 1.0))


@dataclass(frozen=True)
class TipChoice:
    """The session's tube end and its evidence.

    tip : "flat" or "round".
    frames : frames whose tips were compared.
    score : the frames' mean vote (:attr:`FrameEvidence.vote`), in [-1, 1]:
        below 0 flat, above round.
    favouring : how many of the frames voted for ``tip``.
    radius_mm : the end's radius the ends were compared with, mm.
    """

    tip: str
    frames: int
    score: float = 0.0
    favouring: int = 0
    radius_mm: float = float("nan")
    score_error: float = float("nan")

    @classmethod
    def from_votes(cls, votes: Sequence[float], radius_mm: float) -> TipChoice:
        """The choice the frames' votes (each in [-1, 1], see :attr:`FrameEvidence.vote`)
        make: "round" where their mean is above 0, else "flat"."""
        v = np.asarray(votes, dtype=np.float64)
        if not len(v):
            return cls("flat", 0, radius_mm=radius_mm)
        score = float(v.mean())
        error = float(v.std(ddof=1) / np.sqrt(len(v))) if len(v) > 1 else float("inf")
        tip = "round" if score > 0 else "flat"
        favouring = int(np.count_nonzero(v > 0 if tip == "round" else v < 0))
        return cls(tip, len(v), score=score, favouring=favouring, radius_mm=radius_mm, score_error=error)

    @property
    def clear(self) -> bool:
        """The votes' mean lies ``CLEAR_T`` standard errors or more from 0."""
        return bool(abs(self.score) >= CLEAR_T * self.score_error)

    @property
    def doubt(self) -> str:
        """Why every frame's tip is in doubt under this choice: ``TIP_DOUBT`` where it is
        not clear (or made from no frame), else ""."""
        return "" if self.clear else TIP_DOUBT

    def describe(self) -> str:
        if not self.frames:
            return f"{self.tip} (no frame showed a tip to choose by; set [manipulator] tip in session.toml)"
        if self.frames == 1:
            tally = f"chosen from 1 frame, its vote {self.score:+.2f} of +-1"
        else:
            tally = (
                f"chosen from {self.frames} frames, {self.favouring} of them for it, "
                f"mean vote {self.score:+.2f} +- {self.score_error:.2f} of +-1"
            )
        setting = (
            "[manipulator] tip in session.toml fixes it"
            if self.clear
            else "a close call: set [manipulator] tip in session.toml if you know the end"
        )
        return f"{self.tip} ({tally}, end radius {self.radius_mm:.1f} mm; {setting})"


@dataclass(frozen=True)
class FrameTip:
    """A frame's fitted tube and its views, kept for the comparison (:func:`frame_tip`)."""

    axis_mm: FloatArray
    masks: list[NDArray[np.bool_]]
    contrasts: list[NDArray[np.float32]]
    coverages: list[NDArray[np.float32]]
    radius_readings_mm: tuple[float, ...]


def sample_frames(start: int, stop: int, count: int = SAMPLE_FRAMES) -> list[int]:
    """Up to ``count`` frame indices spread evenly over ``[start, stop)``."""
    n = min(count, stop - start)
    return sorted({int(i) for i in np.linspace(start, stop - 1, n).round()}) if n > 0 else []


def sample_rounds(
    start: int, stop: int, rounds: int = ROUNDS, *, first: Sequence[int] | None = None
) -> list[list[int]]:
    """``rounds`` lists of frame indices over ``[start, stop)``, none in two: the first
    ``SAMPLE_FRAMES`` spread evenly (or ``first``, where those are read already), each
    next one twice as many less one, spread evenly, but for those of the rounds before
    (10, 19, 37 frames read in all)."""
    out: list[list[int]] = []
    count = SAMPLE_FRAMES
    for i in range(rounds):
        if i == 0 and first is not None:
            out.append(list(first))
        else:
            read = {index for frames in out for index in frames}
            out.append(sorted(set(sample_frames(start, stop, count)) - read))
        count = 2 * count - 1
    return out


@dataclass(frozen=True)
class ReadTips:
    """Tube ends read already on some of the session's frames, by reconstructions made
    for another purpose (the cameras' refinement, :mod:`pipeline.calibrate.refine`):
    ``frames`` the frames read, ``tips`` those that showed a tip (:func:`frame_tip`)."""

    frames: tuple[int, ...]
    tips: tuple[FrameTip, ...]


def choose_tip(
    model: SessionModel,
    frames: Sequence[tuple[int, Sequence[NDArray[np.uint8]]]],
    map_frames: FrameMap = map_here,
    more: Sequence[Callable[[], Sequence[tuple[int, Sequence[NDArray[np.uint8]]]]]] = (),
    known: Sequence[FrameTip] = (),
) -> TipChoice:
    """The end ("flat" or "round") that explains the tips of ``frames`` best.

    ``frames``: (index, per camera (H, W) uint8 grey image). Each is
    reconstructed from its hull (by ``map_frames``, see
    :data:`pipeline.reconstruct.frame_task.FrameMap`); frames without a curve, or whose
    tip no view shows to either end's satisfaction, are skipped. ``known``: tips read
    already, which vote with those of ``frames``. ``more``: further rounds of frames,
    each asked for only where those before it leave the choice a close one; the choice
    is then made from all the frames read.
    """
    tips = list(known) + [tip for tip in map_frames(_frame_tip, frames, model) if tip is not None]
    choice = _choice(model, tips, map_frames)
    for frames_of_round in more:
        if choice.clear:
            break
        tips += [tip for tip in map_frames(_frame_tip, frames_of_round(), model) if tip is not None]
        choice = _choice(model, tips, map_frames)
    return choice


def _choice(model: SessionModel, tips: Sequence[FrameTip], map_frames: FrameMap = map_here) -> TipChoice:
    """The choice the frames' ``tips`` make (see :func:`choose_tip`), their evidence
    weighed by ``map_frames``."""
    if not tips:
        return TipChoice("flat", 0)
    # One radius for the session: the tube's end does not change, and each
    # frame's reading can be spoilt (a missed tip, another part behind it).
    readings = [reading for tip in tips for reading in tip.radius_readings_mm]
    if not readings:
        return TipChoice("flat", 0)
    radius = float(np.median(readings))
    disks = model.disks
    rig = (model.cameras, radius, disks)
    evidence = [e for e in map_frames(_evidence, list(enumerate(tips)), rig) if e.views]
    if not evidence:
        return TipChoice("flat", 0, radius_mm=radius)
    return TipChoice.from_votes([e.vote for e in evidence], radius)


def _evidence(_: int, tip: FrameTip, rig: tuple[Sequence[Camera], float, Disks | None]) -> FrameEvidence:
    """:func:`frame_evidence` of one tip, for a :data:`FrameMap` (``rig``: the cameras, the
    end's radius, mm, and the tube's spacer disks)."""
    cameras, radius_mm, disks = rig
    return frame_evidence(tip, cameras, radius_mm, disks)


def _frame_tip(index: int, images: Sequence[NDArray[np.uint8]], model: SessionModel) -> FrameTip | None:
    """The frame reconstructed from its hull and its end read (:func:`frame_tip`); None without a curve."""
    result, masks = reconstruct_with_silhouettes(index, images, model)
    return frame_tip(result, masks, frame_contrasts(images, model), model)


def frame_tip(
    result: FrameResult,
    masks: Sequence[NDArray[np.bool_]],
    contrasts: Sequence[NDArray[np.float32]],
    model: SessionModel,
) -> FrameTip | None:
    """A reconstructed frame's fitted tube and its end's radius read from its pixels
    (``masks`` and ``contrasts``: per camera (H, W) silhouette and foreground contrast);
    None without a curve.

    The band read is placed by the radius the side readings give the end (their lower
    quartile there: the tube's own), not the fit's radius along the tube, which spacer
    disks seen at an angle widen (a helix's to 1.28 times its 7.5 mm tube): a band as much
    longer reaches into the last disk's pixels."""
    if result.status != "ok" or result.centerline_mm is None or not np.isfinite(result.radius_mm):
        return None
    coverages = pixel_coverages(contrasts, masks)
    radii = result.radii_mm if result.radii_mm is not None else result.radius_mm
    sides = read_sides(
        result.centerline_mm,
        model.cameras,
        contrasts,
        radii,
        FIT_SPACING_MM,
        session_radii=model.radius_profile,
    )
    band_radius_mm = sides.end_radius_mm if np.isfinite(sides.end_radius_mm) else float(np.ravel(radii)[-1])
    disks = model.disks
    readings = end_radius_readings(
        result.centerline_mm, model.cameras, coverages, band_radius_mm, radii_mm=result.radii_mm, disks=disks
    )
    return FrameTip(result.centerline_mm, list(masks), list(contrasts), coverages, tuple(readings))


def end_radius_readings(
    axis_mm: FloatArray,
    cameras: Sequence[Camera],
    coverages: Sequence[NDArray[np.float32]],
    radius_mm: float,
    *,
    radii_mm: FloatArray | None = None,
    disks: Disks | None = None,
) -> list[float]:
    """Each view's reading of the tube's radius just behind its end, from its pixels (mm).

    The pixels nearest to ``axis_mm`` ((K, 3) world frame, mm) between ``_BAND_RADII``
    radii before its end, within ``_BAND_REACH_RADII`` radii of it (where the end's
    shape, flat or round, does not show) hold so much tube (their summed
    ``coverages``, per view (H, W), :func:`pipeline.reconstruct.tube_drawing.pixel_coverages`);
    the reading is the radius whose tube, drawn around the axis, covers as much of
    them (interpolated between ``radius_mm`` times ``_RADIUS_SCALES``, so finer than
    their steps). A sum holds with the axis a little off to one side: the band holds
    the tube's whole width either way, and blur only moves coverage within it.
    Pixels on or at the blurred edge of another part of the tube (a loop's tip by its
    stem) are left out: that part's radius is not the end's (``radii_mm``, (K,) mm at
    each point of the axis; default ``radius_mm``). No reading from a view that does
    not see that part.
    """
    radii = np.full(len(axis_mm), radius_mm) if radii_mm is None else np.asarray(radii_mm, dtype=np.float64)
    readings = []
    for cam, coverage in zip(cameras, coverages, strict=True):
        widest = radius_mm * float(_RADIUS_SCALES[-1])
        window = _window(cam, [axis_mm], widest, cam.size_px)
        if window is None:
            continue
        band = _band(cam, axis_mm, radius_mm, window) & ~_near_other_parts(cam, axis_mm, radii, window)
        if not band.any():
            continue
        (x0, y0), (x1, y1) = window
        seen = float(coverage[y0:y1, x0:x1][band].sum())
        drawn = [
            float(
                drawn_coverage(cam, axis_mm, radius_mm * float(scale), window, cap="round", disks=disks)[
                    band
                ].sum()
            )
            for scale in _RADIUS_SCALES
        ]
        # The drawn sum grows with the radius: where it meets the seen one (clamped to the scales).
        scale = float(np.interp(seen, drawn, _RADIUS_SCALES)) if np.all(np.diff(drawn) > 0) else np.nan
        if np.isfinite(scale):
            readings.append(radius_mm * scale)
    return readings


def frame_evidence(
    tip: FrameTip, cameras: Sequence[Camera], radius_mm: float, disks: Disks | None = None
) -> FrameEvidence:
    """Each end's mismatch with one frame's pixels around its tip, the tip placed
    under each by :func:`pipeline.reconstruct.tip_bend.bend_tip_to_pixels` with the end's
    radius ``radius_mm`` and drawn at the radius near it that matches best
    (``_DRAWN_SCALES``), with the tube's spacer ``disks``; no view at all (``views`` 0)
    where the two tips went to different places (see ``_MAX_SEPARATION``)."""
    axes = [
        bend_tip_to_pixels(
            tip.axis_mm,
            cameras,
            tip.masks,
            tip.contrasts,
            radius_mm,
            spans_radii=_SPANS_RADII,
            steps_mm=_STEPS_MM,
            then_fit=False,
            coverages=tip.coverages,
            cap=cap,
            disks=disks,
        )
        for cap in CAPS
    ]
    # Per end, per radius scale: the cost summed over the views.
    costs = np.zeros((len(CAPS), len(_DRAWN_SCALES)))
    separation = 0.0
    views = 0
    for cam, coverage in zip(cameras, tip.coverages, strict=True):
        window = _window(cam, axes, radius_mm, cam.size_px)
        if window is None:
            continue
        (x0, y0), (x1, y1) = window
        pixels = coverage[y0:y1, x0:x1]
        # Per end, per scale; the ends are told apart at the radius read.
        drawn = [
            [
                drawn_coverage(cam, axis, radius_mm * scale, window, cap=cap, disks=disks)
                for scale in _DRAWN_SCALES
            ]
            for axis, cap in zip(axes, CAPS, strict=True)
        ]
        apart = float(np.square(drawn[0][_AT_READING] - drawn[1][_AT_READING]).sum())
        radius_px = cam.focal_px * radius_mm / float(cam.to_camera(axes[0][-1:])[0, 2])
        if apart > _MAX_SEPARATION * radius_px**2:
            return FrameEvidence(0.0, 0.0, 0.0, 0)
        costs += [[float(np.square(d - pixels).sum()) for d in per_end] for per_end in drawn]
        separation += apart
        views += 1
    flat, round_ = costs.min(axis=1).tolist()
    return FrameEvidence(flat, round_, separation, views)


def _window(
    cam: Camera, axes_mm: Sequence[FloatArray], radius_mm: float, size: tuple[int, int]
) -> Window | None:
    """Pixel window ((x0, y0), (x1, y1)) around the last ``_REGION_RADII`` radii of
    each (K, 3) axis in ``axes_mm``, grown by ``_REGION_MARGIN_RADII`` projected radii
    and ``_REGION_MARGIN_PX``; None where the camera does not see them all."""
    ends = np.vstack([_last(axis, _REGION_RADII * radius_mm) for axis in axes_mm])
    px = cam.project(ends)
    depth = cam.to_camera(ends)[:, 2]
    if not (np.isfinite(px).all() and (depth > radius_mm).all()):
        return None
    margin = _REGION_MARGIN_RADII * cam.focal_px * radius_mm / float(depth.min()) + _REGION_MARGIN_PX
    w, h = size
    x0, y0 = (max(int(np.floor(v)), 0) for v in px.min(axis=0) - margin)
    x1, y1 = (min(int(np.ceil(v)), n) for v, n in zip(px.max(axis=0) + margin, (w, h), strict=True))
    return ((x0, y0), (x1, y1)) if x1 > x0 and y1 > y0 else None


def _last(axis_mm: FloatArray, length_mm: float, step_mm: float = _LAST_STEP_MM) -> FloatArray:
    """(S, 3) points every ``step_mm`` over the last ``length_mm`` of (K, 3) ``axis_mm``, end included."""
    arc = polyline_arclength(axis_mm)
    s = np.arange(arc[-1], max(arc[-1] - length_mm, 0.0) - 1e-9, -step_mm)[::-1]
    return np.column_stack([np.interp(s, arc, axis_mm[:, i]) for i in range(3)])


def _band(cam: Camera, axis_mm: FloatArray, radius_mm: float, window: Window) -> NDArray[np.bool_]:
    """(h, w) bool over ``window``: the pixels whose nearest point of the axis' last
    few radii lies ``_BAND_RADII`` radii before its end, within ``_BAND_REACH_RADII``
    projected radii (+ a pixel) of it."""
    length = _BAND_RADII[1] + _BAND_REACH_RADII + 1.0
    points = _last(axis_mm, length * radius_mm)
    before = np.arange(len(points))[::-1] * _LAST_STEP_MM  # mm before the end
    px = cam.project(points)
    reach = _BAND_REACH_RADII * cam.focal_px * radius_mm / cam.to_camera(points)[:, 2] + 1.0
    (x0, y0), (x1, y1) = window
    ys, xs = np.mgrid[y0:y1, x0:x1]
    d2 = (xs[..., None] - px[:, 0]) ** 2 + (ys[..., None] - px[:, 1]) ** 2
    nearest = d2.argmin(axis=-1)
    near = np.sqrt(np.take_along_axis(d2, nearest[..., None], axis=-1)[..., 0]) < reach[nearest]
    lo, hi = (b * radius_mm for b in _BAND_RADII)
    return near & (before[nearest] >= lo) & (before[nearest] <= hi)


def _near_other_parts(
    cam: Camera, axis_mm: FloatArray, radii_mm: FloatArray, window: Window
) -> NDArray[np.bool_]:
    """(h, w) bool over ``window``: the pixels within a projected radius and
    ``_OTHER_EDGE_PX`` of another part of the tube than its end, the parts of (K, 3)
    ``axis_mm`` more than ``_OTHER_APART_RADII`` end radii (``radii_mm[-1]``) along it
    before the end band; ``radii_mm``: (K,) mm, the radius at each point."""
    arc = polyline_arclength(axis_mm)
    reach_back = (_BAND_RADII[1] + _BAND_REACH_RADII + _OTHER_APART_RADII) * float(radii_mm[-1])
    far = arc < arc[-1] - reach_back
    (x0, y0), (x1, y1) = window
    near = np.zeros((y1 - y0, x1 - x0), dtype=bool)
    if not far.any():
        return near
    # The far parts every quarter of a radius, each with its own radius.
    step = 0.25 * float(radii_mm[-1])
    s = np.arange(0.0, float(arc[far][-1]) + 1e-9, step)
    points = np.column_stack([np.interp(s, arc, axis_mm[:, i]) for i in range(3)])
    px = cam.project(points)
    depth = cam.to_camera(points)[:, 2]
    seen = np.isfinite(px).all(axis=1) & (depth > 0)
    reach = cam.focal_px * np.interp(s, arc, radii_mm)[seen] / depth[seen] + _OTHER_EDGE_PX
    px = px[seen]
    inside = (
        (px[:, 0] > x0 - reach) & (px[:, 0] < x1 + reach) & (px[:, 1] > y0 - reach) & (px[:, 1] < y1 + reach)
    )
    ys, xs = np.mgrid[y0:y1, x0:x1]
    for (u, v), r in zip(px[inside], reach[inside], strict=True):
        near |= (xs - u) ** 2 + (ys - v) ** 2 < r * r
    return near


def end_assumed(model: SessionModel, choice: TipChoice | None) -> str:
    """The tube end ``model``'s fit assumes and how it came to (``choice``, where frames
    chose it), for the recordings' metadata; "" where no tube is fitted (polyfit)."""
    if choice is not None:
        return choice.describe()
    if model.settings.centerline.method != "fit":
        return ""
    if model.settings.manipulator.tip == "auto":
        return f"{model.tip} (assumed, not chosen: set [manipulator] tip in session.toml)"
    return f"{model.tip} (set in session.toml)"


def with_session_tip(
    model: SessionModel,
    video_paths: Sequence[Path],
    start: int,
    stop: int,
    map_frames: FrameMap = map_here,
    read: ReadTips | None = None,
    session_radii: RadiusProfile | None = None,
) -> tuple[SessionModel, TipChoice | None]:
    """``model`` with its tube end settled and the radius along the tube read on the
    session's sample frames, ``session_radii``, to fit the frames with: the settings' "flat"
    or "round" as they are; for "auto", the end :func:`choose_tip` finds on frames spread
    over ``[start, stop)`` of the videos (and that choice, for the summary). Those frames
    are fitted as the sample frames were: with the spacer disks drawn, each reading its own
    radius. ``read``: tips read already with ``model``'s cameras, which take the first
    round's place: the later rounds, where asked for, read frames between them."""
    settings = model.settings
    settled = dataclasses.replace(model, radius_profile=session_radii)
    if settings.manipulator.tip != "auto" or settings.centerline.method != "fit":
        return settled, None
    model = dataclasses.replace(
        model, radius_profile=None if session_radii is None else session_radii.disks_alone()
    )
    known: Sequence[FrameTip] = ()
    if read is None:
        rounds = sample_rounds(start, stop)
        first = decode_frames(video_paths, rounds[0])
    else:
        rounds = sample_rounds(start, stop, first=read.frames)
        first, known = [], read.tips
    choice = choose_tip(
        model,
        first,
        map_frames,
        more=[functools.partial(decode_frames, video_paths, frames) for frames in rounds[1:]],
        known=known,
    )
    return dataclasses.replace(settled, tip=choice.tip), choice
