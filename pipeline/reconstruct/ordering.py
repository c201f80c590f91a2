"""Base -> tip ordering of a visual hull by tracking along the tube.

A visual hull of a curled tube is not a tube: where two parts of the tube overlap
in one view, the hull grows false bridges between them, and an ordering by
geodesic distance from the base short-cuts across them. Tracking does not: it
marches from the base in steps, and at each step takes the centroid of the hull's
cross-section just ahead, found by a mean shift restricted to a thin slab across
the current direction and started on the straight-ahead prediction. A bridge
leaving the tube sideways pulls that centroid by at most a fraction of the
radius, and the march keeps its heading through the crossing (the continuation
with the smallest turn wins). Where the cross-section swells (crowded), the
march reports it, so that the caller can try the other hypotheses: coasting on
the curve's own course through the crowd, or resuming from a known curve.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

FloatArray = NDArray[np.float64]

# Mean-shift iterations per step: the centroid moves < 0.2 voxel after two, and
# the tube fit, not the march, sets the final position.
_MEAN_SHIFT_ITERATIONS = 2
# The usual cross-section size is the median over the last 2 x _BASELINE_STEPS
# clear steps (at least _BASELINE_STEPS); a slab holding more than _CROWDED
# times it is crowded.
# Measured on a rendered loop: a clear tube gives 54-60 points at 2 mm voxels,
# the junction of a tip with its stem 70-290.
_BASELINE_STEPS = 4
_CROWDED = 1.3
# Clear steps whose turns are averaged into the course a coasting march keeps.
_TURN_STEPS = 3
# Across a gap in the hull the march looks ahead, straight on, at least this
# many steps beyond the next and this far (mm) before it stops. A thin or dim
# part of the tube drops out of one view's silhouette for a few pixels (a step
# to a thinner tube, flicker): at 320x240 and the rigs' ~0.4 px/mm, 6 px of
# silhouette lost cut a 250 mm straight tube's hull for 15 mm, 120 mm before
# its tip.
_LOOK_AHEAD_STEPS = 2
_GAP_MM = 24.0


def infer_base(
    points_mm: FloatArray, origin_mm: FloatArray, size_mm: FloatArray, *, radius_mm: float
) -> FloatArray:
    """Where the tube enters the workspace, when the session does not say.

    The manipulator is mounted outside or on the boundary of the carving box (the
    floor, for the original rig), so its base is the hull's end nearest a face of
    the box: the hull point closest to any face is found, and the base is the
    centroid of the hull points within ``radius_mm`` of that face near that
    point, moved onto the face.

    Parameters
    ----------
    points_mm : (P, 3) hull voxel centres, world frame, mm.
    origin_mm, size_mm : (3,) the workspace box (min corner and size), mm.
    radius_mm : tube radius, mm (sets the neighbourhood size).

    Returns
    -------
    (3,) float64 base point, world frame, mm.
    """
    pts = np.asarray(points_mm, dtype=np.float64)
    lo = np.asarray(origin_mm, dtype=np.float64)
    hi = lo + np.asarray(size_mm, dtype=np.float64)
    gaps = np.concatenate([pts - lo, hi - pts], axis=1)  # (P, 6): distance to each face
    nearest = int(np.argmin(gaps.min(axis=1)))
    face = int(np.argmin(gaps[nearest]))
    axis = face % 3
    near_face = gaps[:, face] <= gaps[nearest, face] + radius_mm
    near_point = np.linalg.norm(pts - pts[nearest], axis=1) <= 3.0 * radius_mm
    base = pts[near_face & near_point].mean(axis=0)
    base[axis] = lo[axis] if face < 3 else hi[axis]
    return base


@dataclass(frozen=True, eq=False)
class March:
    """Result of :func:`march_hull`.

    Attributes
    ----------
    points_mm : (M, 3) float64 polyline ordered base -> tip, world frame, mm.
    crowded : (M,) bool, whether the hull's cross-section was crowded (swollen
        past its usual size) at each point: where the march had to choose.
    """

    points_mm: FloatArray
    crowded: NDArray[np.bool_]


def march_hull(
    points_mm: FloatArray,
    base_mm: FloatArray,
    *,
    radius_mm: float,
    voxel_mm: float,
    step_mm: float | None = None,
    max_length_mm: float = 2000.0,
    refine: Callable[[FloatArray, FloatArray], FloatArray | None] | None = None,
    coast: bool = False,
    resume_mm: FloatArray | None = None,
    heading: FloatArray | None = None,
) -> March:
    """March through the hull from the base to the tip.

    Parameters
    ----------
    points_mm : (P, 3) occupied voxel centres, world frame, mm.
    base_mm : (3,) where the tube starts, world frame, mm.
    radius_mm : tube radius, mm: the cross-section searched at each step.
    voxel_mm : voxel edge, mm: the slab thickness.
    step_mm : march step (default: the larger of one voxel and half the radius).
    max_length_mm : stop after this much curve whatever happens (a guard).
    refine : ``refine(point, direction) -> point or None``: where the hull is
        crowded (its cross-section swells: another part of the tube or a false
        bridge joins it), the march asks this for the axis near the predicted
        point (from the images, see :func:`pipeline.reconstruct.tube_fit.centre_across`)
        instead of trusting the hull's centroid (used when it returns None).
    coast : where the hull is crowded, keep going on the curve's own course (the
        last step's turn repeated) instead of asking ``refine`` or the hull: the
        other hypothesis at a crossing, where whatever the hull offers may belong
        to another part of the tube.
    resume_mm : (R, 3) a curve already known from ``base_mm`` on (a fit that
        stopped short): the march carries on from its end, in its direction,
        and never comes back onto it; the usual cross-section is taken from the
        hull along it.
    heading : (3,) the direction to resume in (default: ``resume_mm``'s own at
        its end).

    Returns
    -------
    :class:`March`; its polyline starts at ``base_mm`` (with ``resume_mm`` as
    its first points), and has one point when the hull holds nothing near the base.
    """
    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    base = np.asarray(base_mm, dtype=np.float64)
    if len(pts) == 0:
        return March(base[None].copy(), np.zeros(1, dtype=bool))
    step = step_mm if step_mm is not None else max(voxel_mm, 0.75 * radius_mm)
    index = _HullIndex.build(pts, voxel_mm)
    # The cross-section sought: the tube's own radius plus a voxel of hull overshoot.
    reach = radius_mm + voxel_mm
    half_slab = max(voxel_mm, 0.5 * step)

    known = base[None] if resume_mm is None else np.asarray(resume_mm, dtype=np.float64).reshape(-1, 3)
    counts: list[int] = []  # cross-section sizes of the last clear steps
    if len(known) > 1:
        direction = _end_direction(known, step) if heading is None else _unit(heading)
        counts = _usual_sections(index, known, reach, half_slab)
    else:
        direction = _initial_direction(index, base, reach)
    if direction is None:
        return March(known.copy(), np.zeros(len(known), dtype=bool))
    limit = int(max_length_mm / step)
    track = np.empty((limit + len(known), 3))
    track[: len(known)] = known
    crowded_at = np.zeros(len(track), dtype=bool)
    turn: FloatArray | None = None  # the change of heading per step, recently
    turns: list[FloatArray] = []
    if coast and len(known) > 1 and direction is not None:
        # Coasting on from a known curve: its own turn per step at its end.
        before = _end_direction(known[: _index_back(known, step) + 1], step)
        if before is not None:
            turn = direction - before
    n = len(known)
    # Revisiting means the march turned into a part of the tube already walked
    # (a tip touching the body): the axes of two touching parts are 2 r apart.
    revisit_sq = (1.5 * radius_mm) ** 2
    skip_recent = int(np.ceil(4.0 * radius_mm / step)) + 1
    look_ahead = max(_LOOK_AHEAD_STEPS, math.ceil(_GAP_MM / step) - 1)
    for _ in range(limit):
        here = track[n - 1]
        found = _step(index, here, direction, step, reach, half_slab, counts, refine)
        course = None
        if coast and found is not None and found[1] and turn is not None:
            # On course: the heading turned by the last clear steps' turn, one step on.
            course = direction + turn
            course /= math.sqrt(course @ course)
            found = (here + step * course, True, found[2])
        if found is None:
            # A gap in the hull (a thin view, a crossing) or a bad heading: look a
            # few steps further straight ahead before calling it the tip. Running
            # on too far is harmless: trim_unexplained_tail cuts what explains no
            # silhouette pixel.
            for ahead in range(2, look_ahead + 2):
                found = _step(index, here, direction, ahead * step, reach, half_slab, counts, refine)
                if found is not None:
                    break
        if found is None:
            break
        centre, crowded, size = found
        if n > skip_recent:
            gap = track[: n - skip_recent] - centre
            if np.einsum("ij,ij->i", gap, gap).min() < revisit_sq:
                break
        if not crowded:
            # A running baseline: an inclined tube fills more voxels per slab
            # than one along a grid axis (measured 65-75 against 56).
            counts = [*counts[-2 * _BASELINE_STEPS + 1 :], size]
        track[n] = centre
        crowded_at[n] = crowded
        n += 1
        blended = _blend(centre.tolist(), here.tolist(), direction.tolist())
        if course is not None:
            blended = course
        elif coast and not crowded:
            turns = [*turns[-_TURN_STEPS + 1 :], blended - direction]
            turn = np.add.reduce(turns) / len(turns)
        direction = blended
    return March(track[:n].copy(), crowded_at[:n].copy())


def _blend(centre: list[float], here: list[float], direction: list[float]) -> FloatArray:
    """The next heading (3,): a blend of the old one and the measured move from
    ``here`` to ``centre``, which damps the voxel noise without lagging behind a
    bend of radius >> step.

    Scalar arithmetic on the three components: the operations, in the order,
    that (3,) arrays would do (numpy's three-term dot sums left to right), at a
    fraction of the cost of numpy's calls.
    """
    mx, my, mz = centre[0] - here[0], centre[1] - here[1], centre[2] - here[2]
    norm = math.sqrt(mx * mx + my * my + mz * mz)
    bx = mx / norm + 0.5 * direction[0]
    by = my / norm + 0.5 * direction[1]
    bz = mz / norm + 0.5 * direction[2]
    norm = math.sqrt(bx * bx + by * by + bz * bz)
    return np.array([bx / norm, by / norm, bz / norm])


def _step(
    index: _HullIndex,
    here: FloatArray,
    direction: FloatArray,
    step: float,
    reach: float,
    half_slab: float,
    counts: list[int],
    refine: Callable[[FloatArray, FloatArray], FloatArray | None] | None,
) -> tuple[FloatArray, bool, int] | None:
    """The axis ``step`` mm ahead: (centre, crowded, cross-section size), or None
    when the hull has no cross-section there or it lies behind ``here``."""
    predicted = here + step * direction
    radius = _slab_radius(reach, half_slab)
    section, dist_sq = index.slab_with_distances(predicted, direction, radius, half_slab)
    if len(section) == 0:
        return None
    # Where the hull swells past its usual cross-section, another part of the
    # tube or a false bridge joins it and a centroid would be dragged sideways:
    # the images say where the axis is, if ``refine`` can read them.
    crowded = len(counts) >= _BASELINE_STEPS and len(section) > _CROWDED * statistics.median(counts)
    centre = refine(predicted, direction) if crowded and refine is not None else None
    if centre is None:
        centre = _mean_shift(section, predicted, reach, dist_sq=dist_sq)
    if centre is None or (centre - here) @ direction <= 0.25 * step:
        return None
    return centre, crowded, len(section)


def _unit(v: FloatArray) -> FloatArray | None:
    norm = float(np.linalg.norm(v))
    return np.asarray(v, dtype=np.float64) / norm if norm > 1e-9 else None


def _index_back(known: FloatArray, step: float) -> int:
    """Index of the last point of an (R, 3) polyline at least ``step`` (mm) from its end."""
    back = np.nonzero(np.linalg.norm(known[-1] - known, axis=1) >= step)[0]
    return int(back[-1]) if len(back) else 0


def _end_direction(known: FloatArray, step: float) -> FloatArray | None:
    """Unit direction at the end of an (R, 3) polyline, over its last ~2 steps."""
    gaps = np.linalg.norm(known[-1] - known, axis=1)
    back = np.nonzero(gaps >= 2.0 * step)[0]
    ahead = known[-1] - known[back[-1] if len(back) else 0]
    norm = float(np.linalg.norm(ahead))
    return ahead / norm if norm > 1e-9 else None


def _usual_sections(index: _HullIndex, known: FloatArray, reach: float, half_slab: float) -> list[int]:
    """Hull cross-section sizes (point counts) across an (R, 3) polyline at up to
    2 x _BASELINE_STEPS places along it: the march's baseline when it resumes."""
    picks = np.unique(np.linspace(1, len(known) - 1, 2 * _BASELINE_STEPS).round().astype(int))
    out = []
    for i in picks:
        d = known[i] - known[i - 1]
        norm = float(np.linalg.norm(d))
        if norm > 1e-9:
            out.append(len(_slab(index, known[i], d / norm, reach, half_slab)))
    return out


def _initial_direction(index: _HullIndex, base: FloatArray, reach: float) -> FloatArray | None:
    """Unit direction from the base into the hull, or None if no hull is near the base.

    The hull around the base itself, not around its nearest voxel: a base on a
    grid corner is equidistant from four voxel centres, and the course must not
    hang on which one a tie-break picks.
    """
    near = index.ball(base, 3.0 * reach)
    if len(near) == 0:  # the hull starts farther off (an inferred or misplaced base)
        near = index.ball(index.pts[index.nearest(base)], 3.0 * reach)
    ahead = near.mean(axis=0) - base
    norm = float(np.linalg.norm(ahead))
    if norm < 1e-9:
        return None
    return ahead / norm


def _slab(
    index: _HullIndex,
    predicted: FloatArray,
    direction: FloatArray,
    reach: float,
    half_slab: float,
) -> FloatArray:
    """(Q, 3) hull points in the slab |(x - predicted) . direction| <= half_slab,
    within 2 * reach of ``predicted``."""
    return index.slab(predicted, direction, _slab_radius(reach, half_slab), half_slab)


@lru_cache(maxsize=64)
def _slab_radius(reach: float, half_slab: float) -> float:
    """How far from its centre (mm) a slab reaches: the same for every step of a march."""
    return float(np.hypot(2.0 * reach, half_slab))


def _mean_shift(
    section: FloatArray, start: FloatArray, reach: float, *, dist_sq: FloatArray | None = None
) -> FloatArray | None:
    """Centroid of a slab's points near ``start``: a mean shift limited to ``reach``
    around its current estimate, so that hull material more than a tube radius
    away (a false bridge, another part of the tube) is ignored. ``dist_sq`` (Q,):
    the points' squared distances from ``start``, if known (the slab's own)."""
    centre = start
    reach_sq = reach * reach
    for i in range(_MEAN_SHIFT_ITERATIONS):
        if i == 0 and dist_sq is not None:
            close = dist_sq <= reach_sq
        else:
            gap = section - centre
            close = np.einsum("ij,ij->i", gap, gap) <= reach_sq
        count = np.count_nonzero(close)
        if count == 0:
            return None
        # A 0/1 weighted sum: one matrix product instead of gathering the rows.
        centre = (close @ section) / count
    return np.asarray(centre)


# A voxel grid over the hull's bounding box larger than this (cells) is not
# worth allocating per march: a k-d tree answers instead.
_MAX_GRID_CELLS = 4_000_000


@dataclass(frozen=True, eq=False)
class _HullIndex:
    """The hull's points, indexed for "points within r of p" queries.

    Hull points are voxel centres on one grid, so the points near p are a block
    of a grid of row numbers: a slice, a few array calls, and no k-d tree to
    build (its build alone was a sixth of the march). Points not on one grid
    (or a huge one) fall back to a k-d tree; both give the same points.

    Attributes
    ----------
    pts : (P, 3) float64 points, world frame, mm.
    origin : (3,) float64 the point of cell (0, 0, 0): the points' minimum, mm.
    voxel : grid spacing, mm.
    rows : (X, Y, Z) int32 row of ``pts`` in each cell, -1 where empty (empty
        array with a tree).
    tree : the k-d tree when the points are not on one grid, else None.
    """

    pts: FloatArray
    origin: FloatArray
    voxel: float
    rows: NDArray[np.int32]
    tree: cKDTree | None

    @classmethod
    def build(cls, pts: FloatArray, voxel_mm: float) -> _HullIndex:
        """Index (P, 3) points (P > 0) expected on a grid of ``voxel_mm`` spacing."""
        origin = pts.min(axis=0)
        cell = (pts - origin) / voxel_mm
        ijk = np.rint(cell).astype(np.intp)
        shape = ijk.max(axis=0) + 1
        # 1e-3 voxel: float32 voxel centres round-tripped to float64 are off by ~1e-7.
        if voxel_mm > 0 and np.abs(cell - ijk).max() < 1e-3 and int(np.prod(shape)) <= _MAX_GRID_CELLS:
            rows = np.full(tuple(shape), -1, dtype=np.int32)
            rows[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = np.arange(len(pts), dtype=np.int32)
            if np.count_nonzero(rows >= 0) == len(pts):  # no two points share a cell
                return cls(pts, origin, float(voxel_mm), rows, None)
        return cls(pts, origin, float(voxel_mm), np.zeros((0, 0, 0), dtype=np.int32), cKDTree(pts))

    def ball(self, centre: FloatArray, radius: float) -> FloatArray:
        """(Q, 3) points within ``radius`` (mm) of ``centre`` (3,), in no particular order."""
        return self.slab(centre, None, radius, 0.0)

    def slab(self, centre: FloatArray, normal: FloatArray | None, radius: float, half: float) -> FloatArray:
        """(Q, 3) points within ``radius`` (mm) of ``centre`` (3,) and within ``half``
        (mm) of the plane through it across unit ``normal`` (3,) (None: no plane)."""
        return self.slab_with_distances(centre, normal, radius, half)[0]

    def slab_with_distances(
        self, centre: FloatArray, normal: FloatArray | None, radius: float, half: float
    ) -> tuple[FloatArray, FloatArray]:
        """:meth:`slab`'s (Q, 3) points and their (Q,) squared distances from ``centre`` (mm^2)."""
        if self.tree is not None:
            idx = self.tree.query_ball_point(centre, radius)
            cand = np.take(self.pts, idx, axis=0) if idx else np.zeros((0, 3))
            if normal is not None:
                cand = cand[np.abs((cand - centre) @ normal) <= half]
            gap = cand - centre
            return np.asarray(cand), np.einsum("ij,ij->i", gap, gap)
        # Only the cells of the box around the slab's disk can hold such points:
        # along axis i it reaches radius * sin(angle to the normal) + half * |cos|
        # (one cell of margin against rounding), then the exact tests.
        # Scalar arithmetic on the three axes: a tenth of the cost of numpy's
        # per-call overhead on (3,) arrays.
        at = [(c - o) / self.voxel for c, o in zip(centre.tolist(), self.origin.tolist(), strict=True)]
        cos = [0.0, 0.0, 0.0] if normal is None else normal.tolist()
        lo, hi = [], []
        for i in range(3):
            reach = (radius * math.sqrt(max(1.0 - cos[i] * cos[i], 0.0)) + half * abs(cos[i])) / self.voxel
            lo.append(max(math.floor(at[i] - reach) - 1, 0))
            hi.append(math.ceil(at[i] + reach) + 2)
        a, b, c = lo
        x, y, z = hi
        if x <= 0 or y <= 0 or z <= 0:
            return np.zeros((0, 3)), np.zeros(0)
        block = self.rows[a:x, b:y, c:z].ravel()
        cand = np.take(self.pts, block[block >= 0], axis=0)
        gap = cand - centre
        dist_sq = np.einsum("ij,ij->i", gap, gap)
        keep = dist_sq <= radius * radius
        if normal is not None:
            keep &= np.abs(gap @ normal) <= half
        return np.asarray(cand[keep]), dist_sq[keep]

    def nearest(self, point: FloatArray) -> int:
        """Row of the point nearest ``point`` (3,) (the first such row on a tie)."""
        if self.tree is not None:
            return int(self.tree.query(point)[1])
        gap = self.pts - point
        return int(np.argmin(np.einsum("ij,ij->i", gap, gap)))
