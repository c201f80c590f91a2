"""Where the side readings put a tube's samples, and how firmly.

Each side reading fixes its sample across the tube in one direction: along the view's
image normal of the tube. :func:`normal_equations` gathers them, with the smoothness of
the corrections, into the least-squares step the fit takes
(:mod:`pipeline.reconstruct.tube_fit`). Where the views that read a stretch look along
one plane with it (two cameras whose common, epipolar, plane holds the tube's course),
or other parts of the tube hide it, no reading fixes it in the other direction, and the
fit carries it there from the curve around it and from the frame before. Such a curve
re-projects onto every silhouette as well as the right one does, so neither the IoU nor
the misfit can tell; the inverse of the normal equations, the step's covariance in units
of one two-edge reading's, can (:func:`spread_across`): where it is large over a
stretch, the frame is suspect there (:meth:`Placement.loose_reason`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import cho_solve_banded, cholesky_banded

from ..geometry.polyline import polyline_arclength, unit_tangents
from .side_readings import SideReadings

FloatArray = NDArray[np.float64]

# A sample is placed loosely where its posterior spread across the tube (the standard
# deviation of its place in the direction the readings fix least, in units of one
# two-edge reading's) exceeds this. Samples fixed by every view spread 0.6-0.9; on
# three cameras a stretch lost in one view's crossing reaches 2-5; a stretch that no
# reading fixes in one direction across reaches it at its middle from about 56 mm long
# on (40 mm: 4.5, 80 mm: 7.9; tests/reconstruct/test_placement.py's straight tube).
# Chosen on the curves `process` wrote for the 72 sessions of `accuracy_table` draws
# 191-223 (8 cases, 90 frames; every third frame, read again at the curve; 2026-12-05):
# on the 22 two-camera ones without disks, frames more than 2 mm off flagged 84 -> 98 of
# 112, good ones 30 -> 51 of 548 (bars of 5 and 7: 108 and 92 off, 65 and 40 good); on
# the three-camera ones, one more good frame of 770. Measured as built on four other
# draws (2, 227, 229 and 231, 8 cases, 90 frames, same day; the curves are the same with
# and without it): two cameras without disks, off flagged 134 -> 146 of 297, good
# 87 -> 106 of 603; three cameras without disks, 32 -> 33 of 36 off and 64 -> 65 of 1,224
# good; with disks, no change. Of the frames it adds to the flagged, 13 of 33 are more
# than 2 mm off.
LOOSE_SPREAD = 6.0
# The samples judged lie this many radii from the base and from the tip: the tip's
# course is the tip's own fit (pipeline.reconstruct.tip_bend), and near a base that
# is not held the spread only says the base is free. Judged up to 2 radii from the tip
# instead, on 83 rendered sessions without disks (those of `accuracy_table` draws 2, 191,
# 193, 197-203, 211, 223 and 227-231, and the bench's three shapes; 90 tracked frames
# each, the true tube end; 2026-12-05), the frame's own reasons and this one flag 11
# more of the 88 three-camera frames more than 2 mm off and 39 more of the 4,142 good
# ones (two cameras: 31 more of 507, 36 more of 2,733). Nor does the longest run of
# samples that no view reads on both sides separate them: on those frames, three-camera
# runs of 20 mm or more are 36 of the 70 unflagged frames off and 510 of the good ones
# (crossings the fit follows rightly).
_FROM_BASE_RADII = 2.0
_FROM_TIP_RADII = 3.0


@dataclass(frozen=True, eq=False)
class Placement:
    """The side readings ``sides`` a fit's last round read at its (K, 3) ``points_mm``,
    whether its base was held there (``base_fixed``) and the smoothness of its steps:
    what :func:`spread_across` needs."""

    points_mm: FloatArray
    sides: SideReadings
    base_fixed: bool
    smoothness: float

    def spread(self, judged: NDArray[np.bool_] | None = None) -> FloatArray:
        """(K,) each sample's spread across the tube (see ``LOOSE_SPREAD`` and
        :func:`spread_across`, whose ``judged`` this is)."""
        return spread_across(
            self.points_mm, self.sides, base_fixed=self.base_fixed, smoothness=self.smoothness, judged=judged
        )

    def loose_stretch(self, radius_mm: float) -> tuple[float, float] | None:
        """(from, to) mm from the base of the longest run of samples placed loosely
        (``LOOSE_SPREAD``), at least ``_FROM_BASE_RADII`` and ``_FROM_TIP_RADII`` tube
        radii ``radius_mm`` from the ends; None where there is none."""
        arc = polyline_arclength(self.points_mm)
        judged = (arc > _FROM_BASE_RADII * radius_mm) & (arc < arc[-1] - _FROM_TIP_RADII * radius_mm)
        loose = judged & (self.spread(judged) > LOOSE_SPREAD)
        if not loose.any():
            return None
        # Runs of loose samples: their starts and ends (exclusive) in sample order.
        edges = np.diff(np.concatenate(([0], loose.view(np.int8), [0])))
        starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
        longest = int(np.argmax(arc[ends - 1] - arc[starts]))
        return float(arc[starts[longest]]), float(arc[ends[longest] - 1])

    def loose_end_mm(self, spread: float, within_mm: float) -> float:
        """How far (mm along the curve) back from the tip the samples are placed more
        loosely than ``spread`` (:func:`spread_across`), judging the last ``within_mm``:
        the stretch before the tip that the side readings leave to the grey levels (the
        tip's zone, which no side reading reads, and where the tube lies along another
        part of itself in the views); all of them where every sample judged is loose."""
        arc = polyline_arclength(self.points_mm)
        judged = arc >= arc[-1] - within_mm
        firm = np.flatnonzero(judged & (self.spread(judged) <= spread))
        last_firm = arc[firm[-1]] if len(firm) else arc[judged][0]
        return float(arc[-1] - last_firm)

    def loose_reason(self, radius_mm: float) -> str:
        """Why the curve may be wrong where the views place it loosely (a suspect reason,
        naming the stretch), or "" where they place it firmly throughout."""
        stretch = self.loose_stretch(radius_mm)
        if stretch is None:
            return ""
        start, end = stretch
        where = f"{start:.0f}-{end:.0f}" if round(start) != round(end) else f"near {start:.0f}"
        return f"its course {where} mm from the base is barely seen across (the views look along it)"


def spread_across(
    points_mm: FloatArray,
    sides: SideReadings,
    *,
    base_fixed: bool,
    smoothness: float,
    judged: NDArray[np.bool_] | None = None,
) -> FloatArray:
    """(K,) for each of the K samples ``points_mm`` (mm), the standard deviation of its place
    across the tube, in the direction the readings ``sides`` fix least, in units of one
    two-edge reading's: the square root of the largest eigenvalue of the across-tube
    block of the inverse of :func:`normal_equations`. The motion along the tube, which no
    side reading sees and the fit holds, is left out.

    Exact where it may exceed ``LOOSE_SPREAD``; elsewhere the bound a sample's own
    readings set (the readings of the other samples and the smoothness only narrow it):
    only samples that their own views barely fix in some direction across are solved for,
    and of those only the ``judged`` (K,) ones (default all; the others keep the bound:
    the tip's zone, which no side reading reads, would otherwise be solved every frame).
    """
    pts = np.asarray(points_mm, dtype=np.float64)
    k = len(pts)
    tangents = unit_tangents(pts)
    across = np.eye(3) - tangents[:, :, None] * tangents[:, None, :]  # (K, 3, 3) projectors
    _, weights = sides.centres()
    own = np.einsum("kc,kci,kcj->kij", weights, np.nan_to_num(sides.rows), np.nan_to_num(sides.rows))
    # The weaker direction across of each sample's own information: the smallest
    # eigenvalue of the across block (the tangent's, 0, set to 1: where both directions
    # across hold more, the bound says 1, still above their spread and far below the bar).
    weakest = np.linalg.eigvalsh(across @ own @ across + tangents[:, :, None] * tangents[:, None, :])[:, 0]
    spread = 1.0 / np.sqrt(np.maximum(weakest, 1e-12))
    if base_fixed:
        spread[0] = 0.0  # held: its rows of the equations are the identity's, not readings
    solve = np.flatnonzero((spread > LOOSE_SPREAD) & (True if judged is None else judged))
    if len(solve):
        band, _ = normal_equations(pts, sides, base_fixed=base_fixed, smoothness=smoothness)
        # Those samples' 3 x 3 blocks of the inverse: solved for their columns of the identity.
        columns = (3 * solve[:, None] + np.arange(3)).ravel()
        unit = np.zeros((3 * k, len(columns)))
        unit[columns, np.arange(len(columns))] = 1.0
        solved = cho_solve_banded((cholesky_banded(band), False), unit)
        blocks = solved[columns].reshape(len(solve), 3, len(solve), 3)[
            np.arange(len(solve)), :, np.arange(len(solve)), :
        ]
        largest = np.linalg.eigvalsh(across[solve] @ blocks @ across[solve])[:, -1]
        spread[solve] = np.sqrt(np.maximum(largest, 0.0))
    return spread


@lru_cache(maxsize=256)
def _second_difference_gram(k: int) -> FloatArray:
    """(3, k) diagonals 0, 1, 2 of D^T D, D the (k-2, k) second difference;
    entry [d, j] is (D^T D)[j - d, j]. Cached per k (read-only): curves keep their
    sample count from frame to frame."""
    stencil = np.array([1.0, -2.0, 1.0])
    out = np.zeros((3, k))
    rows = np.arange(k - 2)
    for p in range(3):
        for q in range(p, 3):
            np.add.at(out[q - p], rows + q, stencil[p] * stencil[q])
    out.flags.writeable = False
    return out


# The normal equations' upper bandwidth: a sample couples with the two either side
# of it through the second difference, 3 * 2 + 2 entries above the diagonal.
BAND_UPPER = 8


def normal_equations(
    pts: FloatArray,
    obs: SideReadings,
    *,
    base_fixed: bool,
    smoothness: float,
    held: NDArray[np.bool_] | None = None,
) -> tuple[FloatArray, FloatArray]:
    """The normal equations of :func:`_solve_corrections`: LAPACK's upper band
    (BAND_UPPER + 1, 3K) of the (3K, 3K) matrix and the (3K,) right-hand side, for the
    corrections of the K samples ``pts`` (mm) from the readings ``obs``. A held sample's
    rows and columns are the identity's and its right-hand side 0."""
    k = len(pts)
    tangents = unit_tangents(pts)
    centre, w = obs.centres()
    # Normal equations, block-diagonal data part: sum_j w a a^T and sum_j w a b.
    blocks = np.einsum("kc,kci,kcj->kij", w, obs.rows, obs.rows)
    rhs = np.einsum("kc,kci,kc->ki", w, obs.rows, centre)
    # Motion along the tangent is not observed by the sides: hold it (weight 1),
    # plus a tiny damping so that a sample with no reading stays solvable. Holding each
    # sample across the tube towards the track's prediction as well (weight 0.05 against
    # 1 for a two-edge reading), so that a direction no view reads stays where it was
    # expected, was measured on three drawn three-camera sessions, stepped and with spacer
    # disks (pipeline.synth.variety.draw_cases, seeds 7000-7010, 90 tracked frames,
    # 2026-12-04): frames more than 2 mm off 96 -> 124; it holds a wrong course as firmly
    # as a right one. Left out.
    blocks += tangents[:, :, None] * tangents[:, None, :] + 1e-3 * np.eye(3)
    # The system is banded: store it as LAPACK's upper band and solve it in O(K)
    # instead of densely.
    n, upper = 3 * k, BAND_UPPER
    band = np.zeros((upper + 1, n))
    for a in range(3):
        for b in range(a, 3):
            band[upper + a - b, b::3] += blocks[:, a, b]  # columns 3 i + b
    if k >= 3:
        # Second-difference penalty D^T D on each coordinate: the pentadiagonal
        # stencil (1, -4, 6, -4, 1) inside, trimmed at the ends.
        d2tdd = _second_difference_gram(k)  # diagonals 0, 1, 2 of D^T D
        for off in range(3):
            # Columns 3 i + a (i >= off) of that band row, all three coordinates at once.
            band[upper - 3 * off].reshape(k, 3)[off:] += smoothness * d2tdd[off, off:, None]
    g = rhs.reshape(-1)
    pinned = np.zeros(k, dtype=bool) if held is None else np.array(held, dtype=bool)
    pinned[0] |= base_fixed
    for i in np.flatnonzero(pinned):
        # Pin sample i: its rows and columns become the identity.
        for row in range(3 * i, 3 * i + 3):
            for d in range(1, min(upper, n - 1 - row) + 1):
                band[upper - d, row + d] = 0.0  # row, right of the diagonal
            for d in range(1, min(upper, row) + 1):
                band[upper - d, row] = 0.0  # column, above the diagonal
            band[upper, row] = 1.0
        g[3 * i : 3 * i + 3] = 0.0
    return band, g
