"""Seeded random smooth shapes of the synthetic manipulator, moving smoothly over time.

The backbone is integrated from its body frame's angular velocity along the arc,
omega(s) = (twist, k_y, k_z) in the (tangent, normal, binormal) frame: (k_y, k_z) is
the curvature vector and the twist turns the frame about the tangent (a helix has
constant omega, its torsion being the twist). Each component is a few cosines in
arc length whose coefficients are sinusoids of time, so the shape is smooth along
the arc and the motion smooth and periodic (PERIOD_FRAMES). Some draws add a loop:
a flat-topped curvature bump that turns by more than a full circle, with a twist
that lifts its second turn off its first.

A smooth clamp keeps the curvature below 1 / (BEND_LIMIT_RADII r); draws whose tube
leaves the workspace, passes through itself or moves too fast are redrawn. The motion
repeats every period, so checking one period checks a session of any length.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import PipelineError
from .poses import outside_box, self_contact
from .radius_profiles import RadiusProfile, disks_of, max_radius, radius_along
from .shapes import rotation

PERIOD_FRAMES = 300  # 10 s at 30 fps
BEND_LIMIT_RADII = 3.0  # a tube cannot bend tighter than this many radii
# Self-contact: parts of the backbone more than CONTACT_ARC_RADII radii apart along it
# must stay CONTACT_GAP_RADII radii apart (the widest radius, disks included).
CONTACT_ARC_RADII = 4.0
CONTACT_GAP_RADII = 2.5
MAX_TIP_STEP_MM = 6.0  # per frame: 180 mm/s, a brisk manipulator
LENGTH_RANGE_MM = (180.0, 250.0)
MAX_ATTEMPTS = 400
_ARC_TERMS = 4  # cosines cos(pi j s / L), j < _ARC_TERMS
_CLAMP_POWER = 16.0  # sharpness of the curvature clamp: 0.8 of the limit passes nearly unchanged
_LOOP_RAMP_MM = 15.0  # length of the loop bump's raised-cosine flanks
_LOOP_PEAK = 0.8  # loop curvature over the bending limit


@dataclass(frozen=True)
class Loop:
    """A curvature bump along arc [start_mm, start_mm + span_mm] turning by ``turns`` (+ ``swing``
    sin(2 pi t / period + phase)) full circles towards body angle ``angle``; ``twist`` (1/mm)
    sets the pitch between its turns."""

    start_mm: float
    span_mm: float
    turns: float
    swing: float
    phase: float
    angle: float
    twist: float


@dataclass(frozen=True)
class RandomShape:
    """A drawn shape and its motion.

    length_mm : backbone length. coef : (3, J, 3) per component (twist, k_y, k_z) and
    arc term j: mean, first- and second-harmonic amplitude (1/mm); phase : (3, J, 2) rad.
    yaw_turns : whole turns of the whole shape about the vertical per period;
    yaw0 : its starting angle (rad). loop : the loop, or None.
    bend_limit : the curvature limit (1/mm).
    """

    length_mm: float
    coef: NDArray[np.float64]
    phase: NDArray[np.float64]
    yaw0: float
    yaw_turns: int
    loop: Loop | None
    bend_limit: float


def _draw(rng: np.random.Generator, profile: RadiusProfile) -> RandomShape:
    """One candidate shape (not yet checked)."""
    r = profile.radius_mm
    bend_limit = 1.0 / (BEND_LIMIT_RADII * r)
    loop = None
    length = rng.uniform(*LENGTH_RANGE_MM)
    if rng.random() < 0.5:
        loop_radius_min = 1.0 / (_LOOP_PEAK * bend_limit)
        turns = rng.uniform(1.08, 1.25)
        # Radius from the tightest allowed to what the length leaves room for (a 30 mm stem at least).
        room = (LENGTH_RANGE_MM[1] - 30.0 - _LOOP_RAMP_MM) / (2.0 * math.pi * (turns + 0.05))
        if room > loop_radius_min:
            radius = rng.uniform(loop_radius_min, min(room, 45.0))
            span = 2.0 * math.pi * (turns + 0.05) * radius + _LOOP_RAMP_MM
            length = rng.uniform(max(LENGTH_RANGE_MM[0], span + 30.0), LENGTH_RANGE_MM[1])
            start = rng.uniform(30.0, length - span)
            gap = 1.3 * CONTACT_GAP_RADII * max_radius(profile)
            kappa = 1.0 / radius
            loop = Loop(
                start_mm=start,
                span_mm=span,
                turns=turns,
                swing=rng.uniform(0.0, 0.05),
                phase=rng.uniform(0.0, 2.0 * math.pi),
                angle=rng.uniform(0.0, 2.0 * math.pi),
                # Pitch of a helix: 2 pi tau / (kappa^2 + tau^2) ~ 2 pi tau / kappa^2 for small tau.
                twist=float(rng.choice([-1.0, 1.0])) * gap * kappa**2 / (2.0 * math.pi),
            )
    # Coefficient sizes: the mean bend of the whole tube ~1 rad, smaller in finer terms
    # and in the loop's presence; the twist turns the bending plane by ~1.5 rad.
    j = np.arange(_ARC_TERMS)
    bend = (0.6 if loop else 1.8) / length / (1.0 + j)
    scale = np.stack([1.5 / length / (1.0 + j), bend, bend])  # (3, J)
    coef = rng.standard_normal((3, _ARC_TERMS, 3)) * scale[..., None] * np.array([1.0, 0.6, 0.3])
    return RandomShape(
        length_mm=float(length),
        coef=coef,
        phase=rng.uniform(0.0, 2.0 * math.pi, (3, _ARC_TERMS, 2)),
        yaw0=float(rng.uniform(0.0, 2.0 * math.pi)),
        yaw_turns=int(rng.integers(-1, 2)),
        loop=loop,
        bend_limit=bend_limit,
    )


def _loop_window(loop: Loop, s_mm: NDArray[np.float64]) -> NDArray[np.float64]:
    """The loop's flat-topped window along the arc (S,), 0..1, raised-cosine flanks."""
    up = np.clip((s_mm - loop.start_mm) / _LOOP_RAMP_MM, 0.0, 1.0)
    down = np.clip((loop.start_mm + loop.span_mm - s_mm) / _LOOP_RAMP_MM, 0.0, 1.0)
    return 0.5 * (1.0 - np.cos(np.pi * np.minimum(up, down)))


def body_rates(
    shape: RandomShape, frame_t: NDArray[np.float64], s_mm: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Body angular velocity (twist, k_y, k_z) (1/mm) at times ``frame_t`` (F,) frames and
    arc positions ``s_mm`` (S,): (F, S, 3)."""
    wt = 2.0 * np.pi * np.asarray(frame_t, dtype=np.float64)[:, None, None] / PERIOD_FRAMES  # (F, 1, 1)
    mean, a1, a2 = shape.coef[..., 0], shape.coef[..., 1], shape.coef[..., 2]  # (3, J)
    # (F, 3, J) coefficients at each time
    c = mean + a1 * np.sin(wt + shape.phase[..., 0]) + a2 * np.sin(2.0 * wt + shape.phase[..., 1])
    basis = np.cos(np.pi * np.arange(_ARC_TERMS)[:, None] * s_mm[None] / shape.length_mm)  # (J, S)
    rates = np.einsum("fcj,js->fsc", c, basis)
    if shape.loop is not None:
        loop = shape.loop
        window = _loop_window(loop, s_mm)
        turns = loop.turns + loop.swing * np.sin(wt[:, 0] + loop.phase)  # (F, 1)
        # Peak curvature such that the window turns by `turns` circles.
        kappa = 2.0 * np.pi * turns / (loop.span_mm - _LOOP_RAMP_MM)
        rates[..., 1] += kappa * window * math.cos(loop.angle)
        rates[..., 2] += kappa * window * math.sin(loop.angle)
        rates[..., 0] += loop.twist * window
    # Smooth clamp of the curvature's magnitude: k / (1 + (k / limit)^p)^(1/p) < limit.
    k = np.linalg.norm(rates[..., 1:], axis=-1, keepdims=True)
    factor = 1.0 / (1.0 + (k / shape.bend_limit) ** _CLAMP_POWER) ** (1.0 / _CLAMP_POWER)
    rates[..., 1:] *= factor
    return rates


def _step_displacement(omega: NDArray[np.float64], h: float) -> NDArray[np.float64]:
    """Displacement (F, 3), in the step's start frame, along an arc of length h turning at
    constant body rate omega (F, 3): the integral of R(u omega) e1 for u in [0, h]."""
    w = np.linalg.norm(omega, axis=1, keepdims=True)
    e1 = np.array([1.0, 0.0, 0.0])
    safe = np.where(w > 1e-12, w, 1.0)
    a = omega / safe
    along = a[:, :1]  # a . e1
    perp = e1 - along * a
    wh = w * h
    out = h * along * a + (np.sin(wh) / safe) * perp + ((1.0 - np.cos(wh)) / safe) * np.cross(a, perp)
    return np.where(w > 1e-12, out, h * e1)


def shape_at(
    shape: RandomShape, frame_t: NDArray[np.float64], *, base_mm: NDArray[np.float64], points: int = 200
) -> NDArray[np.float64]:
    """Centrelines at times ``frame_t`` (F,) frames: (F, points, 3) mm, base -> tip, uniform in arc length.

    Each step between samples is an exact arc (constant rate, taken at the step's middle),
    so the samples are exactly ``length / (points - 1)`` apart along the curve.
    """
    h = shape.length_mm / (points - 1)
    s_mid = (np.arange(points - 1, dtype=np.float64) + 0.5) * h
    rates = body_rates(shape, frame_t, s_mid)  # (F, S, 3)
    n = len(frame_t)
    # World-from-body frame at the base: tangent +z, first normal +x, binormal +y.
    frame = np.broadcast_to(np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), (n, 3, 3)).copy()
    out = np.zeros((n, points, 3))
    turn = rotation(h * rates)  # (F, S, 3, 3)
    for i in range(points - 1):
        step = _step_displacement(rates[:, i], h)
        out[:, i + 1] = out[:, i] + np.einsum("fij,fj->fi", frame, step)
        frame = frame @ turn[:, i]
    yaw = shape.yaw0 + 2.0 * np.pi * shape.yaw_turns * np.asarray(frame_t, dtype=np.float64) / PERIOD_FRAMES
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.zeros((n, 3, 3))
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = c, -s, s, c, 1.0
    return np.asarray(base_mm, dtype=np.float64) + np.einsum("fij,fpj->fpi", rot, out)


def _acceptable(
    shape: RandomShape,
    lines: NDArray[np.float64],
    profile: RadiusProfile,
    tip: str,
    box_lo_mm: NDArray[np.float64],
    box_hi_mm: NDArray[np.float64],
) -> bool:
    """Whether a period of poses (P, N, 3) stays in the box, off itself, and moves gently."""
    arc = np.linspace(0.0, shape.length_mm, lines.shape[1])
    radii = radius_along(profile, arc)
    widest = max_radius(profile)
    tip_steps = np.linalg.norm(np.diff(lines[:, -1], axis=0, append=lines[:1, -1]), axis=1)
    return bool(
        tip_steps.max() <= MAX_TIP_STEP_MM
        and not outside_box(
            lines, radii, box_lo_mm, box_hi_mm, tip=tip, disks=disks_of(profile, shape.length_mm)
        ).any()
        and not self_contact(
            lines, min_gap_mm=CONTACT_GAP_RADII * widest, min_arc_mm=CONTACT_ARC_RADII * widest, step=2
        ).any()
    )


def draw_shape(
    seed: int,
    *,
    profile: RadiusProfile,
    tip: str,
    base_mm: NDArray[np.float64],
    box_lo_mm: NDArray[np.float64],
    box_hi_mm: NDArray[np.float64],
    points: int = 200,
) -> RandomShape:
    """The first random shape drawn from ``seed`` whose whole motion period fits.

    Raises PipelineError if none of MAX_ATTEMPTS draws fits (a tube too thick for the box).
    """
    rng = np.random.default_rng([seed, 0x5A9E])
    period = np.arange(PERIOD_FRAMES, dtype=np.float64)
    for _ in range(MAX_ATTEMPTS):
        shape = _draw(rng, profile)
        lines = shape_at(shape, period, base_mm=base_mm, points=points)
        if _acceptable(shape, lines, profile, tip, box_lo_mm, box_hi_mm):
            return shape
    raise PipelineError(
        f"no random shape of a {profile.radius_mm:g} mm tube fits the workspace after "
        f"{MAX_ATTEMPTS} draws (seed {seed}); use a thinner tube"
    )
