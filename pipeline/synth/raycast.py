"""Exact ray casting of a tube along a polyline, as seen by a true (distorted) camera.

The tube is the union of capsules (a cylinder per polyline segment plus a ball at
every joint: the exact swept tube of the polyline), cut flat at both ends by the
planes perpendicular to the end segments (a flat tip cap; the base is cut at the
mount). Each pixel's ray goes through its *distorted* position: the pixel is
undistorted with our own fixed-point inverse of the OpenCV model, so the renderer
shares no projection code with the reconstruction.

Culling: the capsules are grouped in chunks of CHUNK_SEGMENTS; a KD-tree over the
unit ray directions of the pixel centres returns, per chunk, only the rays inside
the cone that the chunk's bounding ball subtends at the camera.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

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
    """Capsule-chain geometry of a tube, precomputed from its centreline (mm, world frame).

    start : (S, 3) segment starts; axis : (S, 3) unit directions; length : (S,);
    joints : (S-1, 3) interior joint centres (ball of ``radius`` each);
    chunk_center : (M, 3), chunk_radius : (M,) bounding balls of CHUNK_SEGMENTS segments.
    """

    start: NDArray[np.float64]
    axis: NDArray[np.float64]
    length: NDArray[np.float64]
    joints: NDArray[np.float64]
    radius: float
    arc_mm: NDArray[np.float64]  # (S+1,) arc length at each polyline vertex
    chunk_center: NDArray[np.float64]
    chunk_radius: NDArray[np.float64]

    @classmethod
    def from_centerline(cls, centerline_mm: NDArray[np.float64], radius_mm: float) -> Tube:
        pts = np.asarray(centerline_mm, dtype=np.float64)
        seg = np.diff(pts, axis=0)
        length = np.linalg.norm(seg, axis=1)
        if np.any(length <= 0):
            raise ValueError("centreline has repeated points")
        arc = np.concatenate([[0.0], np.cumsum(length)])
        centers, radii = [], []
        for lo in range(0, len(seg), CHUNK_SEGMENTS):
            chunk_pts = pts[lo : lo + CHUNK_SEGMENTS + 1]
            c = 0.5 * (chunk_pts.min(axis=0) + chunk_pts.max(axis=0))
            centers.append(c)
            radii.append(np.linalg.norm(chunk_pts - c, axis=1).max() + radius_mm)
        return cls(
            start=pts[:-1],
            axis=seg / length[:, None],
            length=length,
            joints=pts[1:-1],
            radius=float(radius_mm),
            arc_mm=arc,
            chunk_center=np.array(centers),
            chunk_radius=np.array(radii),
        )

    @property
    def n_chunks(self) -> int:
        return len(self.chunk_center)

    def chunk_slice(self, m: int) -> slice:
        return slice(m * CHUNK_SEGMENTS, min((m + 1) * CHUNK_SEGMENTS, len(self.length)))


Hits = tuple[NDArray[np.float64], NDArray[np.float64]]  # distance (P,) (inf: miss), unit normal (P, 3)
# Which candidate surface points (..., 3) lie on the flat-ended tube.
Keep = Callable[[NDArray[np.float64]], NDArray[np.bool_]]


def _nearest(t: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Per ray (row), the index and distance of the nearest of several pieces (columns)."""
    if t.shape[1] == 0:
        return np.zeros(len(t), np.intp), np.full(len(t), np.inf)
    k = np.argmin(t, axis=1)
    return k, t[np.arange(len(t)), k]


def _unit(v: NDArray[np.float64]) -> NDArray[np.float64]:
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _cylinder_hits(o: NDArray[np.float64], d: NDArray[np.float64], tube: Tube, sl: slice, keep: Keep) -> Hits:
    """Nearest entry into the finite cylinders of segments ``sl``; ``keep(points)``
    (P, S, 3) -> bool says which entry points lie on the tube."""
    a, u, L, r = tube.start[sl], tube.axis[sl], tube.length[sl], tube.radius
    w = o - a  # (S, 3): every ray starts at the camera centre
    du = d @ u.T  # (P, S)
    wu = np.einsum("ij,ij->i", w, u)  # (S,)
    # |w_perp + t d_perp|^2 = r^2, with the half-b form of the quadratic.
    A = 1.0 - du * du
    B = d @ w.T - du * wu
    C = np.einsum("ij,ij->i", w, w) - wu * wu - r * r
    disc = B * B - A * C
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-B - np.sqrt(disc)) / A
        h = wu + t * du  # axial coordinate of the entry point
        ok = (disc >= 0) & (A > 1e-12) & (t > 0) & (h >= 0) & (h <= L)
        ok &= keep(o + t[..., None] * d[:, None, :])
    k, t_min = _nearest(np.where(ok, t, np.inf))
    rows = np.arange(len(d))
    hit = o + t_min[:, None] * d
    axis_pt = a[k] + h[rows, k][:, None] * u[k]
    return t_min, _unit(hit - axis_pt)


def _ball_hits(
    o: NDArray[np.float64], d: NDArray[np.float64], centers: NDArray[np.float64], r: float, keep: Keep
) -> Hits:
    """Nearest entry into balls of radius ``r`` at ``centers`` (J, 3)."""
    w = o - centers  # (J, 3)
    b = d @ w.T  # (P, J)
    disc = b * b - (np.einsum("ij,ij->i", w, w) - r * r)
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
        ok = (disc >= 0) & (t > 0) & keep(o + t[..., None] * d[:, None, :])
    k, t_min = _nearest(np.where(ok, t, np.inf))
    hit = o + t_min[:, None] * d
    return t_min, _unit(hit - centers[k]) if len(centers) else np.zeros_like(hit)


def _cap_hits(
    o: NDArray[np.float64],
    d: NDArray[np.float64],
    center: NDArray[np.float64],
    normal: NDArray[np.float64],
    r: float,
) -> Hits:
    """Hits on a flat disc of radius ``r`` (an end cap) whose outward normal is ``normal``."""
    dn = d @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((center - o) @ normal) / dn
        hit = o + t[:, None] * d
        ok = (np.abs(dn) > 1e-12) & (t > 0) & (np.linalg.norm(hit - center, axis=1) <= r)
    return np.where(ok, t, np.inf), np.broadcast_to(normal, d.shape)


def _chunk_hits(tube: Tube, m: int, o: NDArray[np.float64], d: NDArray[np.float64]) -> Hits:
    """Nearest hit of rays ``d`` (P, 3) with chunk ``m`` of the tube (and its end caps)."""
    sl = tube.chunk_slice(m)
    r = tube.radius
    clip = END_CLIP_RADII * r
    base_pt, base_n = tube.start[0], -tube.axis[0]
    tip_pt = tube.start[-1] + tube.axis[-1] * tube.length[-1]
    tip_n = tube.axis[-1]
    near_base = tube.arc_mm[sl.start] < clip
    near_tip = tube.arc_mm[sl.stop] > tube.arc_mm[-1] - clip

    def keep(points: NDArray[np.float64]) -> NDArray[np.bool_]:
        # Near an end, an entry point beyond the end plane is not on the (flat-ended)
        # tube; rays that cross the plane inside the tube hit the cap instead.
        ok = np.ones(points.shape[:-1], bool)
        if near_base:
            ok &= (points - base_pt) @ base_n <= 1e-9
        if near_tip:
            ok &= (points - tip_pt) @ tip_n <= 1e-9
        return ok

    # Joint j (the end of segment j) is an interior joint for j < S - 1.
    joints = tube.joints[sl.start : min(sl.stop, len(tube.joints))]
    pieces = [_cylinder_hits(o, d, tube, sl, keep), _ball_hits(o, d, joints, r, keep)]
    if near_base:
        pieces.append(_cap_hits(o, d, base_pt, base_n, r))
    if near_tip:
        pieces.append(_cap_hits(o, d, tip_pt, tip_n, r))
    k, t = _nearest(np.stack([p[0] for p in pieces], axis=1))
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
