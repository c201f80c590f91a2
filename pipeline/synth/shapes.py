"""Centrelines of the synthetic manipulator: piecewise constant curvature (and torsion).

A pose is a chain of 1-3 segments. Each segment has a length, a curvature
``kappa`` (1/mm), a torsion ``tau`` (1/mm) and a bending-plane angle ``phi``
(rad, measured in the segment's own start frame). Within a segment the body
frame turns at a constant rate, so both the frame and the position have closed
forms (Rodrigues' formula and its integral): the curve is exact, not integrated
step by step, and samples are exactly uniform in arc length.

The manipulator is mounted at ``base_mm`` pointing up +z. Motion over a session
is a smooth function of the phase ``p`` (in cycles): bending comes and goes while
the bending plane rotates, like the original robot.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .names import SHAPES

# The motion repeats every PERIOD_FRAMES frames (10 s at 30 fps) so that a 900-frame
# session shows three bending cycles; shorter sessions fit one whole cycle instead,
# so that even 10 frames show varied poses.
PERIOD_FRAMES = 300

# Out-of-plane shift of the loop per turn (mm): the tube diameter plus a gap.
LOOP_OFFSET_MM = 20.0


@dataclass(frozen=True)
class Segment:
    """One constant-curvature-and-torsion piece of the centreline.

    length_mm : arc length (mm); kappa : curvature (1/mm); tau : torsion (1/mm);
    phi : direction of bending in the segment's start frame (rad, 0 = frame's first normal).
    The frame turns with the bend, so phi + pi in the next segment bends back (an S).
    """

    length_mm: float
    kappa: float
    tau: float = 0.0
    phi: float = 0.0


def rotation(axis_angle: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation matrices from axis-angle vectors, (..., 3) -> (..., 3, 3) (Rodrigues)."""
    theta = np.linalg.norm(axis_angle, axis=-1)[..., None, None]
    safe = np.where(theta > 0, theta, 1.0)
    k = axis_angle / safe[..., 0]
    kx = np.zeros((*axis_angle.shape[:-1], 3, 3))
    kx[..., 0, 1], kx[..., 0, 2] = -k[..., 2], k[..., 1]
    kx[..., 1, 0], kx[..., 1, 2] = k[..., 2], -k[..., 0]
    kx[..., 2, 0], kx[..., 2, 1] = -k[..., 1], k[..., 0]
    eye = np.broadcast_to(np.eye(3), kx.shape)
    return eye + np.sin(theta) * kx + (1.0 - np.cos(theta)) * (kx @ kx)


def _segment_points(
    segment: Segment, s_mm: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Positions and frames along one segment, in the segment's start frame.

    The body frame's columns are (tangent, normal, binormal); the tangent starts
    along the first axis. Returns ``points`` (S, 3) and ``frames`` (S, 3, 3).
    """
    # Body angular velocity: bending towards d = (0, cos phi, sin phi) turns about
    # tangent x d = (0, -sin phi, cos phi); torsion turns about the tangent.
    omega = np.array(
        [segment.tau, -segment.kappa * math.sin(segment.phi), segment.kappa * math.cos(segment.phi)]
    )
    w = float(np.linalg.norm(omega))
    frames = rotation(s_mm[:, None] * omega)
    e1 = np.array([1.0, 0.0, 0.0])
    if w < 1e-12:
        return s_mm[:, None] * e1, frames
    a = omega / w
    along = a @ e1
    perp = e1 - along * a
    # Integral of R(u w a) e1 du from 0 to s: the axial part advances linearly, the
    # perpendicular part turns on a circle of radius 1/w.
    ws = w * s_mm[:, None]
    points = (
        s_mm[:, None] * along * a + (np.sin(ws) / w) * perp + ((1.0 - np.cos(ws)) / w) * np.cross(a, perp)
    )
    return points, frames


def centerline(
    segments: list[Segment], *, base_mm: NDArray[np.float64], points: int = 200
) -> NDArray[np.float64]:
    """Sample a segment chain uniformly in arc length, from the base to the tip.

    Parameters
    ----------
    segments : the chain, base first.
    base_mm : (3,) float64, world frame; the chain starts here pointing up +z.
    points : number of samples N (both ends included).

    Returns
    -------
    (N, 3) float64, mm, world frame.
    """
    total = sum(seg.length_mm for seg in segments)
    s_all = np.linspace(0.0, total, points)
    # World-from-body frame at the base: tangent +z, first normal +x, binormal +y.
    frame = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    origin = np.asarray(base_mm, dtype=np.float64).copy()
    out = np.empty((points, 3))
    start = 0.0
    for i, seg in enumerate(segments):
        last = i == len(segments) - 1
        end = start + seg.length_mm
        sel = (s_all >= start) & ((s_all <= end) if last else (s_all < end))
        local = np.concatenate([s_all[sel] - start, [seg.length_mm]])
        pts, frames = _segment_points(seg, local)
        out[sel] = origin + pts[:-1] @ frame.T
        origin = origin + frame @ pts[-1]
        frame = frame @ frames[-1]
        start = end
    return out


def _smooth(p: float, lo: float, hi: float, *, rate: float = 1.0, phase: float = 0.0) -> float:
    """A value oscillating smoothly between lo and hi, ``rate`` cycles per motion cycle."""
    return lo + (hi - lo) * 0.5 * (1.0 - math.cos(2.0 * math.pi * (rate * p + phase)))


def _bend_rotate(p: float, length: float) -> list[Segment]:
    theta = _smooth(p, 0.25, 1.0)  # total bend (rad): ~115 mm sideways at the most
    phi = 2.0 * math.pi * 0.7 * p
    return [Segment(length, theta / length, 0.0, phi)]


def _s_curve(p: float, length: float) -> list[Segment]:
    theta = _smooth(p, 0.3, 0.95, phase=0.1)  # the tip ends up to ~115 mm sideways
    phi = 2.0 * math.pi * 0.6 * p + 0.5
    half = length / 2
    return [Segment(half, theta / half, 0.0, phi), Segment(half, theta / half, 0.0, phi + math.pi)]


def _loop(p: float, length: float) -> list[Segment]:
    # A short, gently bent stem lifts the loop off the floor; the loop turns by
    # 0.85-1.05 of a full circle so its tip comes back past the stem, and views see
    # the tube cross itself. A slight torsion shifts the loop out of its plane by
    # about LOOP_OFFSET_MM per turn, so the tip passes beside the stem instead of
    # through it.
    stem = 0.28 * length
    loop = length - stem
    turn = 2.0 * math.pi * _smooth(p, 0.85, 1.05, phase=0.25)
    kappa = turn / loop
    tau = LOOP_OFFSET_MM / (2.0 * math.pi) * kappa**2  # pitch = 2 pi tau / (kappa^2 + tau^2)
    lean = _smooth(p, 0.0, 0.25, rate=2.0)
    phi = 2.0 * math.pi * 0.5 * p
    return [Segment(stem, lean / stem, 0.0, phi), Segment(loop, kappa, tau, phi + math.pi)]


def _straight(p: float, length: float) -> list[Segment]:
    theta = _smooth(p, 0.0, 0.08)  # sway: at most ~10 mm at the tip
    return [Segment(length, theta / length, 0.0, 2.0 * math.pi * 0.3 * p)]


def _three_segments(p: float, length: float) -> list[Segment]:
    third = length / 3
    t1 = _smooth(p, 0.1, 0.6)
    t2 = _smooth(p, 0.2, 0.9, rate=2.0, phase=0.3)
    t3 = _smooth(p, 0.2, 1.1, rate=3.0, phase=0.6)
    phi = 2.0 * math.pi * 0.5 * p
    return [
        Segment(third, t1 / third, 0.0, phi),
        Segment(third, t2 / third, 0.0, phi + 2.4),
        Segment(third, t3 / third, 0.0, phi - 2.0),
    ]


def _helix(p: float, length: float) -> list[Segment]:
    # A coil spring standing upright: a short lead-in arc tilts the tangent by the
    # helix angle alpha, then a constant-curvature-and-torsion segment winds
    # 1.2-1.6 turns of 14-20 mm radius around a vertical axis. A helix of turning
    # rate w = |(tau, kappa)| and radius rho has sin(alpha) = rho * w, and its axis is
    # vertical when its bending plane is a quarter turn from the lead-in's.
    lead = 0.12 * length
    coil = length - lead
    turns = _smooth(p, 1.2, 1.6, phase=0.2)
    rho = _smooth(p, 14.0, 20.0, rate=2.0) * length / 250.0
    w = 2.0 * math.pi * turns / coil
    alpha = math.asin(min(rho * w, 0.95))
    phi = 2.0 * math.pi * 0.5 * p
    return [
        Segment(lead, alpha / lead, 0.0, phi),
        Segment(coil, w * math.sin(alpha), w * math.cos(alpha), phi + math.pi / 2),
    ]


_SHAPES: dict[str, Callable[[float, float], list[Segment]]] = {
    "bend_rotate": _bend_rotate,
    "s_curve": _s_curve,
    "loop": _loop,
    "straight": _straight,
    "three_segments": _three_segments,
    "helix": _helix,
}
assert tuple(_SHAPES) == SHAPES


def pose_segments(shape: str, phase: float, *, length_mm: float = 250.0) -> list[Segment]:
    """The segment chain of ``shape`` at ``phase`` (cycles of its motion)."""
    if shape not in _SHAPES:
        raise ValueError(f"unknown shape {shape!r}; use one of {SHAPES}")
    return _SHAPES[shape](phase, length_mm)


def motion_phases(frames: int) -> NDArray[np.float64]:
    """Phase (cycles) of each frame: one cycle per PERIOD_FRAMES, or the whole cycle
    spread over a shorter session. (F,) float64."""
    period = min(PERIOD_FRAMES, max(frames, 1))
    return np.arange(frames) / period


def shape_centerlines(
    shape: str,
    frames: int,
    *,
    base_mm: NDArray[np.float64],
    length_mm: float = 250.0,
    points: int = 200,
) -> NDArray[np.float64]:
    """Centrelines of every frame of a session. (F, N, 3) float64 mm, base -> tip."""
    return np.stack(
        [
            centerline(pose_segments(shape, p, length_mm=length_mm), base_mm=base_mm, points=points)
            for p in motion_phases(frames)
        ]
    )
