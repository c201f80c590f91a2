"""Exact ray casting of a tube along a polyline, as seen by a true (distorted) camera.

The tube is the union of balls swept along a polyline with a radius varying linearly
between its vertices (a tapered capsule per segment: a cone frustum between two balls;
a plain capsule where the radius is constant), cut flat at the base (the mount) and,
for a flat tip, at the tip, by the planes perpendicular to the end segments; a round
tip keeps its end ball. Spacer disks are short closed cylinders added to the union.
Each pixel's ray goes through its *distorted* position: the pixel is undistorted with
our own fixed-point inverse of the OpenCV model, so the renderer shares no projection
code with the reconstruction.

Culling: the segments are grouped in chunks of CHUNK_SEGMENTS; a KD-tree over the
unit ray directions of the pixel centres returns, per chunk, only the rays inside
the cone that the chunk's bounding ball subtends at the camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from .names import TIPS
from .radius_profiles import Disks
from .ray_pieces import Hits, ball_hits, cone_hits, disc_hits, nearest, short_cylinder_hits
from .rig import SynthCamera

CHUNK_SEGMENTS = 10
# Capsules within this many radii (arc length) of an end are clipped by its end plane:
# farther ones cannot reach it, and clipping them could wrongly cut a looping tube.
END_CLIP_RADII = 2.0


def distort_normalized(camera: SynthCamera, xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """OpenCV (k1, k2, p1, p2, k3) distortion of normalised image coordinates, (Q, 2) -> (Q, 2)."""
    k1, k2, p1, p2, k3 = camera.dist[:5]
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def project_points(camera: SynthCamera, points_mm: NDArray[np.float64]) -> NDArray[np.float64]:
    """Pixel positions of world points, (..., 3) mm -> (..., 2) px (points in front of the camera)."""
    x_cam = points_mm @ camera.R.T + camera.t
    xy = x_cam[..., :2] / x_cam[..., 2:3]
    d = distort_normalized(camera, xy.reshape(-1, 2)).reshape(xy.shape)
    K = camera.K
    return np.stack(
        [K[0, 0] * d[..., 0] + K[0, 1] * d[..., 1] + K[0, 2], K[1, 1] * d[..., 1] + K[1, 2]], axis=-1
    )


def undistort_pixels(
    camera: SynthCamera, uv_px: NDArray[np.float64], *, max_iterations: int = 100
) -> NDArray[np.float64]:
    """Normalised, undistorted coordinates of pixel positions, (Q, 2) px -> (Q, 2).

    Fixed-point inversion of :func:`distort_normalized`; with the rig's mild
    distortion it converges to ~1e-13 (about 1e-10 px) in a few dozen iterations.
    """
    K = camera.K
    yd = (uv_px[:, 1] - K[1, 2]) / K[1, 1]
    xd = (uv_px[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    target = np.stack([xd, yd], axis=1)
    xy = target.copy()
    for _ in range(max_iterations):
        step = target - distort_normalized(camera, xy)
        xy = xy + step
        if len(step) == 0 or np.abs(step).max() < 1e-13:
            break
    return xy


def ray_directions(camera: SynthCamera, uv_px: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit world-frame directions of the rays through pixel positions, (Q, 2) -> (Q, 3)."""
    xy = undistort_pixels(camera, uv_px)
    d_cam = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    d_world = d_cam @ camera.R  # R.T @ d for each row: world from camera
    return d_world / np.linalg.norm(d_world, axis=1, keepdims=True)


@dataclass(frozen=True, eq=False)
class CameraRays:
    """A camera's pixel-centre rays, computed once per session.

    origin_mm : (3,) camera centre, world frame; dirs : (H*W, 3) unit, row-major pixels;
    tree : KD-tree over ``dirs`` for cone queries.
    """

    camera: SynthCamera
    origin_mm: NDArray[np.float64]
    dirs: NDArray[np.float64]
    tree: cKDTree


_RAYS_CACHE: dict[bytes, CameraRays] = {}


def camera_rays(camera: SynthCamera) -> CameraRays:
    """Pixel-centre rays of ``camera``, cached by the camera's parameters (not its
    identity, so that worker processes reuse them across tasks)."""
    key = b"".join(
        np.asarray(a, dtype=np.float64).tobytes()
        for a in (camera.K, camera.dist, camera.R, camera.t, [camera.width, camera.height])
    )
    if key not in _RAYS_CACHE:
        v, u = np.mgrid[0 : camera.height, 0 : camera.width]
        uv = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
        dirs = ray_directions(camera, uv)
        if len(_RAYS_CACHE) >= 16:
            _RAYS_CACHE.clear()
        _RAYS_CACHE[key] = CameraRays(camera, camera.center, dirs, cKDTree(dirs))
    return _RAYS_CACHE[key]


@dataclass(frozen=True)
class Tube:
    """Tapered-capsule-chain geometry of a tube, precomputed from its centreline (mm, world frame).

    The tube is the union of the balls centred on the polyline whose radius varies
    linearly between the vertices' radii (each segment the convex hull of its two end
    balls: a cone frustum tangent to both, plus the balls), cut flat at the base and,
    for ``tip == "flat"``, at the tip; a "round" tip keeps its end ball (a hemispherical
    cap centred on the backbone's end). Spacer disks are closed cylinders added to it.

    start : (S, 3) segment starts; axis : (S, 3) unit directions; length : (S,);
    radii : (S+1,) radius at each vertex;
    cone_c0, cone_c1, cone_lo, cone_hi : (S,) each segment's frustum, radius c0 + c1 h
    for lo <= h <= hi along the segment (see :func:`ray_pieces.cone_hits`);
    joints : (J, 3) ball centres (interior vertices, and the tip for a round end),
    joint_radii : (J,); base_cap_mm, tip_cap_mm : radii of the flat end faces;
    disk_center : (D, 3), disk_axis : (D, 3) unit, disk_radius_mm, disk_thickness_mm;
    chunk_center : (M, 3), chunk_radius : (M,) bounding balls of CHUNK_SEGMENTS segments,
    then of each disk.
    """

    start: NDArray[np.float64]
    axis: NDArray[np.float64]
    length: NDArray[np.float64]
    radii: NDArray[np.float64]
    cone_c0: NDArray[np.float64]
    cone_c1: NDArray[np.float64]
    cone_lo: NDArray[np.float64]
    cone_hi: NDArray[np.float64]
    joints: NDArray[np.float64]
    joint_radii: NDArray[np.float64]
    tip: str
    base_cap_mm: float
    tip_cap_mm: float
    disk_center: NDArray[np.float64]
    disk_axis: NDArray[np.float64]
    disk_radius_mm: float
    disk_thickness_mm: float
    arc_mm: NDArray[np.float64]  # (S+1,) arc length at each polyline vertex
    chunk_center: NDArray[np.float64]
    chunk_radius: NDArray[np.float64]

    @classmethod
    def from_centerline(
        cls,
        centerline_mm: NDArray[np.float64],
        radius_mm: float | NDArray[np.float64],
        *,
        tip: str = "flat",
        disks: Disks | None = None,
    ) -> Tube:
        """The tube around ``centerline_mm`` (N, 3); ``radius_mm`` is one radius or (N,) per vertex."""
        if tip not in TIPS:
            raise ValueError(f"unknown tip {tip!r}; use one of {TIPS}")
        pts = np.asarray(centerline_mm, dtype=np.float64)
        radii = np.broadcast_to(np.asarray(radius_mm, dtype=np.float64), (len(pts),)).copy()
        seg = np.diff(pts, axis=0)
        length = np.linalg.norm(seg, axis=1)
        if np.any(length <= 0):
            raise ValueError("centreline has repeated points")
        axis = seg / length[:, None]
        arc = np.concatenate([[0.0], np.cumsum(length)])
        c0, c1, lo, hi = _frustums(radii, length)
        centers, bounds = [], []
        for first in range(0, len(seg), CHUNK_SEGMENTS):
            chunk_pts = pts[first : first + CHUNK_SEGMENTS + 1]
            c = 0.5 * (chunk_pts.min(axis=0) + chunk_pts.max(axis=0))
            centers.append(c)
            bounds.append(
                np.linalg.norm(chunk_pts - c, axis=1).max() + radii[first : first + CHUNK_SEGMENTS + 1].max()
            )
        disk_center, disk_axis = _disk_poses(pts, axis, arc, disks)
        disk_radius = 0.0 if disks is None else disks.radius_mm
        disk_thickness = 0.0 if disks is None else disks.thickness_mm
        centers.extend(disk_center)
        bounds.extend([float(np.hypot(disk_radius, 0.5 * disk_thickness))] * len(disk_center))
        last = len(pts) if tip == "round" else len(pts) - 1
        return cls(
            start=pts[:-1],
            axis=axis,
            length=length,
            radii=radii,
            cone_c0=c0,
            cone_c1=c1,
            cone_lo=lo,
            cone_hi=hi,
            joints=pts[1:last],
            joint_radii=radii[1:last],
            tip=tip,
            base_cap_mm=_end_face_radius(radii[0], c0[0], c1[0], lo[0], hi[0], 0.0),
            tip_cap_mm=_end_face_radius(radii[-1], c0[-1], c1[-1], lo[-1], hi[-1], length[-1]),
            disk_center=disk_center,
            disk_axis=disk_axis,
            disk_radius_mm=float(disk_radius),
            disk_thickness_mm=float(disk_thickness),
            arc_mm=arc,
            chunk_center=np.array(centers),
            chunk_radius=np.array(bounds),
        )

    @property
    def n_chunks(self) -> int:
        return len(self.chunk_center)

    @property
    def n_segment_chunks(self) -> int:
        return -(-len(self.length) // CHUNK_SEGMENTS)

    def chunk_slice(self, m: int) -> slice:
        return slice(m * CHUNK_SEGMENTS, min((m + 1) * CHUNK_SEGMENTS, len(self.length)))


def _frustums(
    radii: NDArray[np.float64], length: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Each segment's cone frustum tangent to its two end balls: (c0, c1, lo, hi), each (S,).

    With slope m = (r_b - r_a) / L the tangent cone's radius is (r_a + m h) / sqrt(1 - m^2)
    and it touches the balls at h = -r_a m and h = L - r_b m. Where |m| >= 1 one ball holds
    the other and the segment has no cone (an empty range).
    """
    ra, rb = radii[:-1], radii[1:]
    m = (rb - ra) / length
    has_cone = np.abs(m) < 1.0
    cos_a = np.sqrt(np.where(has_cone, 1.0 - m * m, 1.0))
    # For equal radii m = 0 and these are exactly (r, 0, 0, L): the plain cylinder.
    lo = np.where(has_cone, -ra * m, np.inf)
    hi = np.where(has_cone, length - rb * m, -np.inf)
    return ra / cos_a, m / cos_a, lo, hi


def _end_face_radius(r_end: float, c0: float, c1: float, lo: float, hi: float, h_face: float) -> float:
    """Radius of the tube's section by an end plane at axial coordinate ``h_face`` of the end
    segment: the frustum's radius there where the frustum reaches the plane, else the end ball's."""
    return float(c0 + c1 * h_face) if lo <= h_face <= hi else float(r_end)


def _disk_poses(
    pts: NDArray[np.float64], axis: NDArray[np.float64], arc: NDArray[np.float64], disks: Disks | None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Centres (D, 3) and unit axes (D, 3) of the disks: on the polyline at their arc
    positions, perpendicular to the segment they sit on."""
    if disks is None or len(disks.arc_mm) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    s = np.clip(np.asarray(disks.arc_mm, dtype=np.float64), 0.0, arc[-1])
    seg = np.clip(np.searchsorted(arc, s, side="right") - 1, 0, len(axis) - 1)
    return pts[seg] + (s - arc[seg])[:, None] * axis[seg], axis[seg]


def _chunk_hits(tube: Tube, m: int, o: NDArray[np.float64], d: NDArray[np.float64]) -> Hits:
    """Nearest hit of rays ``d`` (P, 3) with chunk ``m`` of the tube (and its end faces)."""
    if m >= tube.n_segment_chunks:
        disk = m - tube.n_segment_chunks
        return short_cylinder_hits(
            o, d, tube.disk_center[disk], tube.disk_axis[disk], tube.disk_radius_mm, tube.disk_thickness_mm
        )
    sl = tube.chunk_slice(m)
    base_pt, base_n = tube.start[0], -tube.axis[0]
    tip_pt = tube.start[-1] + tube.axis[-1] * tube.length[-1]
    tip_n = tube.axis[-1]
    near_base = tube.arc_mm[sl.start] < END_CLIP_RADII * tube.radii[0]
    flat_tip = tube.tip == "flat"
    near_tip = flat_tip and tube.arc_mm[sl.stop] > tube.arc_mm[-1] - END_CLIP_RADII * tube.radii[-1]

    def keep(points: NDArray[np.float64]) -> NDArray[np.bool_]:
        # Near a flat end, an entry point beyond the end plane is not on the tube;
        # rays that cross the plane inside the tube hit the end face instead.
        ok = np.ones(points.shape[:-1], bool)
        if near_base:
            ok &= (points - base_pt) @ base_n <= 1e-9
        if near_tip:
            ok &= (points - tip_pt) @ tip_n <= 1e-9
        return ok

    # Joint j (the end of segment j) is a ball for j < S - 1, and for j = S - 1 at a round tip.
    joints = slice(sl.start, min(sl.stop, len(tube.joints)))
    pieces = [
        cone_hits(
            o,
            d,
            tube.start[sl],
            tube.axis[sl],
            tube.cone_c0[sl],
            tube.cone_c1[sl],
            tube.cone_lo[sl],
            tube.cone_hi[sl],
            keep,
        ),
        ball_hits(o, d, tube.joints[joints], tube.joint_radii[joints], keep),
    ]
    if near_base:
        pieces.append(disc_hits(o, d, base_pt, base_n, tube.base_cap_mm))
    if near_tip:
        pieces.append(disc_hits(o, d, tip_pt, tip_n, tube.tip_cap_mm))
    k, t = nearest(np.stack([p[0] for p in pieces], axis=1))
    normal = np.stack([p[1] for p in pieces], axis=1)[np.arange(len(d)), k]
    return t, normal


def intersect(
    tube: Tube, origin_mm: NDArray[np.float64], dirs: NDArray[np.float64], candidates: list[NDArray[np.intp]]
) -> Hits:
    """First hit of rays with the tube.

    Parameters
    ----------
    tube : the tube geometry.
    origin_mm : (3,) common ray origin (the camera centre), world frame.
    dirs : (Q, 3) unit ray directions, world frame.
    candidates : per chunk, indices into ``dirs`` of the rays that may hit it.

    Returns
    -------
    t_mm : (Q,) distance to the first hit (inf: miss).
    normal : (Q, 3) unit outward surface normal at the hit (zeros: miss).
    """
    t_best = np.full(len(dirs), np.inf)
    normal = np.zeros((len(dirs), 3))
    o = np.asarray(origin_mm, dtype=np.float64)
    for m, idx in enumerate(candidates):
        if len(idx) == 0:
            continue
        t, n = _chunk_hits(tube, m, o, dirs[idx])
        better = t < t_best[idx]
        t_best[idx[better]] = t[better]
        normal[idx[better]] = n[better]
    return t_best, normal


def cone_candidates(tube: Tube, rays: CameraRays) -> list[NDArray[np.intp]]:
    """Per chunk, the pixel-centre rays inside the cone of its bounding ball."""
    rel = tube.chunk_center - rays.origin_mm
    dist = np.linalg.norm(rel, axis=1)
    half = np.arcsin(np.clip(tube.chunk_radius / dist, 0.0, 1.0))
    chord = 2.0 * np.sin(half / 2.0)  # unit-sphere distance for that cone angle
    found = rays.tree.query_ball_point(rel / dist[:, None], chord)
    return [np.asarray(f, dtype=np.intp) for f in found]


def cone_candidates_brute(
    tube: Tube, origin_mm: NDArray[np.float64], dirs: NDArray[np.float64]
) -> list[NDArray[np.intp]]:
    """Like :func:`cone_candidates` for an arbitrary (small) set of rays, without a tree."""
    rel = tube.chunk_center - origin_mm
    dist = np.linalg.norm(rel, axis=1)
    cos_half = np.cos(np.arcsin(np.clip(tube.chunk_radius / dist, 0.0, 1.0)))
    inside = dirs @ (rel / dist[:, None]).T >= cos_half - 1e-12
    return [np.flatnonzero(inside[:, m]) for m in range(tube.n_chunks)]
