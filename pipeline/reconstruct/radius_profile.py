"""The tube's radius along it, pooled over the session's frames.

One frame reads the tube's width only where a view sees both of its edges clear of
the rest of the tube; where another part crowds a stretch in every view, that frame's
profile is a line across the gap (:mod:`pipeline.reconstruct.side_readings`), and a
step in the radius within the gap is smeared over all of it. The frames of a session
show the tube in other poses, crowded elsewhere: their readings, pooled by arc length
from the base, give the radius there. A one-edge reading is moved in by the radius
(:meth:`~pipeline.reconstruct.side_readings.SideReadings.centres`), so a radius a
millimetre off in a gap puts the axis a millimetre off: on a stepped random shape (r 5
to 3.5 mm half way along, three cameras, 90 frames tracked) whose frames read both edges
nowhere over 30-40 mm around the step, the true radius given there took the mean error
from 0.34 to 0.22 mm.

The session's profile is pooled over the sample frames the cameras are checked on
(:func:`pipeline.calibrate.refine.refined_cameras`, rigs of three cameras or more).
Measured on `accuracy_table --draw 2`, 409, 433, 439 and 443 (8 cases of 90 frames each,
40 sessions; 2026-12-06), against each frame's own profile alone: three-camera sessions
without disks, frames more than 2 mm off 30 -> 20, their means summed 2.97 -> 2.79 mm
(stepped random shapes 0.337 -> 0.262, 0.408 -> 0.350 and 0.261 -> 0.246 mm; a tapered
loop 0.197 -> 0.173 mm and 9 -> 4 frames off, another 4 -> 6); with spacer disks 261 ->
243 (a random shape 0.730 -> 0.676 mm); median tips closer by 0.03 mm or more on four
sessions, farther on none. Pooled on two cameras as well (16 frames fitted alone, the 14
two-camera sessions without disks of those draws, same day), frames off went 74 -> 111.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .disks import Disks
from .width_bins import binned_medians

FloatArray = NDArray[np.float64]

# Readings are pooled in bins of this length along the tube (mm) ...
BIN_MM = 2.0
# ... and a bin is kept where at least this many frames read it: one frame's stray
# readings (another part's outline taken for an edge) do not make a bin.
MIN_FRAMES = 3
# The pooled profile is the median over this many bins either side (a window moved in from
# the profile's ends, so that it is never cut short): spacer disks (a few mm thick, 13 mm
# apart or more) stay a minority of the window, a step is kept where it is (as a running
# median keeps a monotone step). The window counts bins read, so across a stretch that no
# frame reads it reaches the far side. The bins beside such a stretch read narrow (another
# part a few pixels beyond an edge raises the background the edge is read against: 3.9-4.4
# mm of 4.5 at the true axes of a stepped random shape), and the far side's bins pull them
# back up. Read 4 px clear of other parts instead, those bins are left out, and a step
# inside a 60 mm gap becomes a ramp across it: on the two stepped random shapes of
# `accuracy_table --draw 439` (90 frames, 2026-12-07) 0.262 -> 0.299 and 0.350 -> 0.318 mm
# mean (three-camera means over draws 2, 409, 433, 439 and 443 summed 4.58 -> 4.56 mm);
# with a window of arc as well, 0.311 and 0.344 mm (4.62 mm); a window of arc alone, 0.266
# and 0.397 mm. Left as it is.
HALF_WINDOW_BINS = 3
# Disks seen at an angle widen the outline over as much of the tube as they reach along it
# in the view, often over most of a window, and the median reads them. A tube with disks
# has them drawn (pipeline.reconstruct.disks): the readings their outline reaches are left
# out of its radius, and the profile is the tube's own between them. Leaving out instead
# every bin more than 12 % above the bins' grey opening over 16 mm (a step or a taper kept,
# any shorter bump taken away), with the disks not drawn, read the tubes' radius but fitted
# worse curves (2026-12-06, `accuracy_table --draw 2`, 409, 433, 439 and 443: frames more
# than 2 mm off 679 -> 696).


@dataclass(frozen=True)
class RadiusProfile:
    """The tube's radius (B,) mm at arc lengths (B,) mm from its base, increasing (B may be
    0: none read), and its spacer disks, if it has any (:mod:`pipeline.reconstruct.disks`)."""

    arc_mm: FloatArray
    radius_mm: FloatArray
    disks: Disks | None = None

    def at(self, arc_mm: FloatArray) -> FloatArray:
        """(K,) the radius at arc lengths ``arc_mm`` (K,), interpolated; NaN outside the
        stretch the frames read."""
        arc = np.asarray(arc_mm, dtype=np.float64)
        if len(self.arc_mm) == 0:
            return np.full(arc.shape, np.nan)
        inside = (arc >= self.arc_mm[0]) & (arc <= self.arc_mm[-1])
        return np.where(inside, np.interp(arc, self.arc_mm, self.radius_mm), np.nan)

    @classmethod
    def of_disks(cls, disks: Disks | None) -> RadiusProfile | None:
        """A profile of spacer ``disks`` alone, no radius read (the frames read their own),
        as :func:`pipeline.reconstruct.side_readings.read_sides` draws them; None without."""
        return None if disks is None else cls(np.zeros(0), np.zeros(0), disks)

    def disks_alone(self) -> RadiusProfile | None:
        """This profile's disks without its radius (:meth:`of_disks`)."""
        return RadiusProfile.of_disks(self.disks)

    def describe(self) -> str:
        """One line for the summary: the radius's range and the stretch of the tube read, and
        its disks."""
        disks = "" if self.disks is None else self.disks.describe()
        if len(self.arc_mm) == 0:
            return disks
        low, high = float(self.radius_mm.min()), float(self.radius_mm.max())
        radius = f"{low:.2f} mm" if f"{low:.2f}" == f"{high:.2f}" else f"{low:.2f}-{high:.2f} mm"
        read = (
            f"{radius}, read {self.arc_mm[0] - BIN_MM / 2:.0f}-{self.arc_mm[-1] + BIN_MM / 2:.0f} mm "
            "from the base on the session's sample frames"
        )
        return f"{read}; {disks}" if disks else read

    def to_json(self) -> str:
        """The profile as JSON (``{"arc_mm": [...], "radius_mm": [...]}``, to 0.001 mm, and
        ``"disks"`` where it has them): the recordings' metadata."""
        data: dict[str, object] = {
            "arc_mm": np.round(self.arc_mm, 3).tolist(),
            "radius_mm": np.round(self.radius_mm, 3).tolist(),
        }
        if self.disks is not None:
            data["disks"] = self.disks.to_dict()
        return json.dumps(data)

    @classmethod
    def from_json(cls, text: str) -> RadiusProfile | None:
        """The profile :meth:`to_json` wrote; None where ``text`` is not one (empty, or
        another program's)."""
        try:
            data = json.loads(text)
            arc = np.asarray(data["arc_mm"], dtype=np.float64)
            radius = np.asarray(data["radius_mm"], dtype=np.float64)
        except (ValueError, TypeError, KeyError):
            return None
        disks = Disks.from_dict(data["disks"]) if "disks" in data else None
        ordered = arc.ndim == 1 and (len(arc) > 0 or disks is not None) and bool(np.all(np.diff(arc) > 0))
        if not ordered or radius.shape != arc.shape or not np.all(np.isfinite(radius)):
            return None
        return cls(arc, radius, disks)

    @classmethod
    def pooled(cls, readings: Sequence[tuple[FloatArray, FloatArray]]) -> RadiusProfile | None:
        """The profile of the frames' ``readings``, each (arc lengths (R,) mm, half-widths
        (R,) mm) of the two-edge readings of one frame; None where no bin is read by
        ``MIN_FRAMES`` frames."""
        profile = binned_medians(readings, BIN_MM, MIN_FRAMES)
        if profile is None or not np.isfinite(profile).any():
            return None
        read = np.flatnonzero(np.isfinite(profile))
        values = profile[read]
        span = min(2 * HALF_WINDOW_BINS + 1, len(values))
        first = np.clip(np.arange(len(values)) - HALF_WINDOW_BINS, 0, len(values) - span)
        smoothed = np.array([np.median(values[f : f + span]) for f in first])
        return cls((read + 0.5).astype(np.float64) * BIN_MM, smoothed)
