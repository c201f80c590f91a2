"""The refined rig held to the mount: where its cameras see the tube's base end.

The silhouettes cannot tell a rig from the same rig moved with what it sees, and
the given cameras' poses hold it (:func:`pipeline.calibrate.adjust.nearest_to_given`)
only as well as three cameras' errors average out, which leaves it millimetres
from the true one (docs/calibration.md: 0.3-3.2 mm), most of it a shift. The
tube's base is mounted at ``[manipulator] base_mm``: where the refined cameras
see the base end, in each frame refined on, says how far the rig is off, and
the rig is moved by that (the median over the frames). The tubes are those of
the frames refined on, reconstructed again with the refined cameras (their base
free). The end is read as a tracked tip is, on the axis run backwards: where
each view's grey image leaves the tube along its course
(:func:`pipeline.reconstruct.tube_tip.refit_tip`), then the end's last radius
bent and lengthened until the tube drawn matches the grey levels around it
(:func:`pipeline.reconstruct.tip_bend.refine_tip_to_pixels`). Across the tube
the end stays where its sides put it; along it, the outline places it. A base
standing up towards cameras that look down on it is seen nearly end-on (0.35-0.4
px per mm along its axis at 320x240), where an edge read on one line 0.3 px off
puts the end 0.8 mm off, and the whole outline averages such errors out (the
helix of docs/calibration.md, true cameras and tubes, 16 frames, along the axis:
from the edges a median of 0.19 mm and up to 0.84 mm in a frame, from the
outline -0.01 and 0.26 mm). Across, the bend follows what each view wants of
the end where the refined cameras still disagree (a straight tube that barely
moves pins them down least), and the sides are read all along the tube. On 30
renders with a calibration 0.05 or 0.15 deg off (15 of the accuracy table's
cases, 2026-12-02), the distances from where the refined cameras see the true
base to where this reads it sum to 7.8 mm; the outline alone, 9.5; the edges
alone, 10.8.

A base end that the frames do not see alike (hidden in a mount, out of view) or
that is farther from ``base_mm`` than a calibration's error can put it leaves
the rig where the poses hold it, and the report says why.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import Camera
from ..geometry.polyline import polyline_arclength
from ..reconstruct.radius_profile import RadiusProfile
from ..reconstruct.side_readings import read_sides
from ..reconstruct.tip_bend import refine_tip_to_pixels
from ..reconstruct.tube_tip import refit_tip
from .adjust import SPACING_MM, Similarity, Tube

FloatArray = NDArray[np.float64]

# The base ends of the frames refined on may lie this far (mm, median) from their
# median: a few tenths of a mm where the end is seen (the sessions of docs/calibration.md).
_MAX_SPREAD_MM = 1.5
# A base seen farther than this (mm) from base_mm is not the calibration's error but a
# mount placed elsewhere: with cameras kept as given (the silhouettes agree with them) ...
_MAX_SHIFT_MM = 6.0
# ... and with cameras the silhouettes showed off and refined. Three cameras 0.15 deg off
# put the base up to 4 mm away, 0.3 deg off 2.0-7.8 mm (`accuracy_table --frames 90
# --no-polyfit --calib-error 0.3 --cases helix ninety-s_curve-r9 ninety-three_segments-r5
# oblique-bend-r4-bright oblique-straight-r8`, and `synth --shape random --seed 103
# --calib-error 0.3 --frames 30`; 2026-12-06). Moved there, a straight r 8 tube seen 6.3
# mm off came 1.07 mm from the truth (mean) and the random shape seen 7.8 mm off 0.94 mm,
# against 5.14 and 4.87 mm held where the poses put them (every frame then bent to start
# at base_mm). On a fresh draw (`accuracy_table --draw 811 --cases 8 --frames 60
# --no-polyfit --calib-error 0.3`, same day), its four three-camera rigs saw the base
# 2.6-6.4 mm off, and the one past 6 mm, a stepped random shape, came 0.60 mm from the
# truth (mean) instead of 5.49; the other seven cases as they were. Exact cameras kept, a
# base_mm 8.6 mm off is better left to the frames' fit: on `synth --shape random --seed 55
# --frames 40` with base_mm moved by (+5, -7, 0) mm, the rig moved to it put the curves
# 6.28 mm from the truth in mean, against 0.41 mm held where its poses put it, every frame
# bent to start at base_mm (same day).
_MAX_SHIFT_REFINED_MM = 12.0
# Fewer frames than this give no median to trust.
_MIN_FRAMES = 3
# The base's radius is read as a tip's (the side readings' end radius: their lower quartile
# over the last few samples), and only where that reads none, the median of the radius
# profile over the tube's first samples (~4 mm apart). That median is a spacer disk's more
# than the tube's where disks are seen at an angle: on `synth --profile disks --shape
# s_curve --frames 40` (r 6 mm, exact cameras; 2026-12-06) it read 7.1-7.3 mm, the base end
# 1.34 mm along the tube from the mount (the rig was moved there, and the mean error came
# out 0.48 mm against 0.15 kept), read as a tip's 0.15 mm; the uniform tube's 0.08 mm ->
# -0.01 mm. `process`, then `evaluate`, on that session and on seven 60-frame renders of the
# named shapes and a random one with calibrations 0-0.15 deg off (same day), against the
# profile's median: means 0.479 -> 0.147 mm (the disks), 0.250 -> 0.245, 0.420 -> 0.398,
# 0.237 -> 0.234, 0.202 -> 0.173, 0.136 -> 0.125 mm, two unchanged; frames more than 2 mm
# off 0 -> 3 on a loop and 0 -> 1 on the random shape.
_BASE_SAMPLES = 3
# The part of the axis (radii back from the end) bent to the grey levels.
_BEND_RADII = (1.0,)
# What the note ends with when base_mm itself seems wrong.
CHECK_BASE = "check base_mm"


def base_ends(cameras: Sequence[Camera], tubes: Sequence[Tube]) -> FloatArray:
    """(F, 3) where ``cameras`` see each tube's base end, mm (its flat end, read on the
    axis run backwards, see the module)."""
    ends = []
    for tube in tubes:
        # The tube's own radius at its base (a tapered tube's is its widest), read as a tip's
        # is, on the axis run backwards (see _BASE_SAMPLES).
        axis, radii = tube.points_mm[::-1], tube.radii_mm[::-1]
        disks = None if tube.disks is None else tube.disks.from_tip(float(polyline_arclength(axis)[-1]))
        radius = read_sides(
            axis, cameras, tube.contrasts, radii, SPACING_MM, session_radii=RadiusProfile.of_disks(disks)
        ).end_radius_mm
        if not np.isfinite(radius):
            radius = float(np.median(tube.radii_mm[:_BASE_SAMPLES]))
        backwards = refit_tip(axis, cameras, tube.contrasts, radius, cap="flat")
        fitted = refine_tip_to_pixels(
            backwards, cameras, tube.masks, tube.contrasts, radius, spans_radii=_BEND_RADII, cap="flat"
        )
        # Across the tube, the end stays where its sides put it; along it, the outline says.
        along = backwards[-1] - backwards[-3]
        along /= np.linalg.norm(along)
        ends.append(backwards[-1] + along * float((fitted[-1] - backwards[-1]) @ along))
    return np.array(ends, dtype=np.float64).reshape(-1, 3)


def mount_shift(
    cameras: Sequence[Camera], tubes: Sequence[Tube], base_mm: FloatArray, *, refined: bool = False
) -> tuple[FloatArray | None, str]:
    """(3,) how far (mm) ``cameras`` see the tubes' base from ``base_mm``, or None and
    why the rig is better left where it is; ``refined``: the cameras were refined from
    silhouettes that showed them off (a farther base is then still their error, see
    ``_MAX_SHIFT_REFINED_MM``)."""
    ends = base_ends(cameras, tubes)
    if len(ends) < _MIN_FRAMES:
        return None, f"the tube's base was seen in {len(ends)} frames, too few"
    off = ends - np.asarray(base_mm, dtype=np.float64)
    shift = np.median(off, axis=0)
    spread = float(np.median(np.linalg.norm(off - shift, axis=1)))
    if spread > _MAX_SPREAD_MM:
        return None, f"the tube's base end is not seen alike from frame to frame ({spread:.1f} mm apart)"
    distance = float(np.linalg.norm(shift))
    if distance > (_MAX_SHIFT_REFINED_MM if refined else _MAX_SHIFT_MM):
        return None, (
            f"the tube's base is seen {distance:.1f} mm from [manipulator] base_mm, more than "
            f"a calibration's error; {CHECK_BASE}"
        )
    return shift, ""


def moved_to_mount(cameras: Sequence[Camera], shift_mm: FloatArray) -> list[Camera]:
    """``cameras`` in a world moved by ``shift_mm`` (3,): what they saw at base_mm +
    shift is at base_mm."""
    return Similarity(np.eye(3), 1.0, np.asarray(shift_mm, dtype=np.float64)).cameras(cameras)
