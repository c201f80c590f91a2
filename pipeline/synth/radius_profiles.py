"""Radius profiles of the synthetic tube along its backbone: uniform, tapered, a step, spacer disks.

A profile turns the nominal radius (the radius at the base) into a radius at each
centreline sample, and, for "disks", the arc positions of short wider cylinders
(the spacer disks of tendon-driven robots).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .names import PROFILES


@dataclass(frozen=True)
class Disks:
    """Spacer disks: closed cylinders centred on the backbone, perpendicular to it.

    arc_mm : (D,) arc length of each disk's centre from the base; radius_mm, thickness_mm : each disk's size.
    """

    arc_mm: NDArray[np.float64]
    radius_mm: float
    thickness_mm: float


@dataclass(frozen=True)
class RadiusProfile:
    """How the tube's radius varies along its backbone.

    kind : one of PROFILES. radius_mm : nominal radius (at the base).
    tip_ratio : "tapered", the radius at the tip over the nominal one (linear in between).
    step_at : "step", where the radius changes, as a fraction of the length;
    step_ratio : the radius after the step over the nominal one; step_ramp_mm : the
    length of the conical shoulder between the two.
    disk_spacing_mm, disk_ratio, disk_thickness_mm : "disks", one every spacing (the
    first a spacing from the base, none closer than a spacing / 2 to the tip), of
    radius disk_ratio x nominal.
    """

    kind: str = "uniform"
    radius_mm: float = 6.0
    tip_ratio: float = 0.6
    step_at: float = 0.5
    step_ratio: float = 0.7
    step_ramp_mm: float = 2.0
    disk_spacing_mm: float = 20.0
    disk_ratio: float = 1.5
    disk_thickness_mm: float = 2.0

    def __post_init__(self) -> None:
        if self.kind not in PROFILES:
            raise ValueError(f"unknown radius profile {self.kind!r}; use one of {PROFILES}")
        if self.radius_mm <= 0:
            raise ValueError(f"radius_mm must be positive, got {self.radius_mm}")


def radius_along(profile: RadiusProfile, arc_mm: NDArray[np.float64]) -> NDArray[np.float64]:
    """The tube's radius at arc positions ``arc_mm`` (N,) from the base (last = the length): (N,) mm.

    Disks are not included (see :func:`disks_of`); between disks the tube is uniform.
    """
    arc = np.asarray(arc_mm, dtype=np.float64)
    r = profile.radius_mm
    if profile.kind == "tapered":
        return r * (1.0 + (profile.tip_ratio - 1.0) * arc / arc[-1])
    if profile.kind == "step":
        ramp = np.clip((arc - profile.step_at * arc[-1]) / profile.step_ramp_mm, 0.0, 1.0)
        return r * (1.0 + (profile.step_ratio - 1.0) * ramp)
    return np.full(arc.shape, r)


def disks_of(profile: RadiusProfile, length_mm: float) -> Disks | None:
    """The spacer disks of a tube of ``length_mm``, or None for profiles without disks."""
    if profile.kind != "disks":
        return None
    spacing = profile.disk_spacing_mm
    arcs = np.arange(spacing, length_mm - 0.5 * spacing + 1e-9, spacing)
    return Disks(arcs, profile.disk_ratio * profile.radius_mm, profile.disk_thickness_mm)


def max_radius(profile: RadiusProfile) -> float:
    """The widest part of the tube (disks included), mm: what clearances must allow for."""
    ratios = {"uniform": 1.0, "tapered": max(1.0, profile.tip_ratio), "step": max(1.0, profile.step_ratio)}
    return profile.radius_mm * ratios.get(profile.kind, max(1.0, profile.disk_ratio))
