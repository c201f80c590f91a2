"""Seeded random draws of synthetic sessions covering the variety of real robots.

A :class:`Case` holds every option of a session: shape (random or named), tube end,
radius profile (with spacer disks: their spacing, size and thickness), rig, camera count,
image size, distractor, flicker, polarity, radius and seed. :func:`draw_cases` draws them
so that every option value comes up within a few draws (each option cycles through its
values in shuffled rounds), and :func:`render_case` renders one.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..errors import PipelineError
from .names import PROFILES, RANDOM_SHAPE, SHAPES, TIPS
from .poses import outside_box, self_contact
from .radius_profiles import RadiusProfile, disks_of, radius_along
from .rig import ARRANGEMENTS
from .session_render import (
    BASE_MM,
    CENTERLINE_POINTS,
    WORKSPACE_ORIGIN_MM,
    WORKSPACE_SIZE_MM,
    SceneOptions,
    render_session,
)
from .shapes import PERIOD_FRAMES, shape_centerlines

RADIUS_RANGE_MM = (4.0, 8.0)
# Spacer disks: one every so many mm, of so many times the tube's radius, so thick (mm).
DISK_SPACING_RANGE_MM = (12.0, 36.0)
DISK_RATIO_RANGE = (1.3, 2.0)
DISK_THICKNESS_RANGE_MM = (1.0, 4.0)
# Half of the draws are random shapes, the other half the named ones in turn.
_SHAPE_ROUND = (RANDOM_SHAPE,) * len(SHAPES) + SHAPES


@dataclass(frozen=True)
class Case:
    """Every option of one synthetic session (see :func:`render_session`)."""

    shape: str
    tip: str
    profile: str
    arrangement: str
    cameras: int
    distractor: bool
    flicker: bool
    polarity: str
    radius_mm: float
    seed: int
    size: tuple[int, int] = (320, 240)
    # The calibration.toml's error (pipeline.synth.calib_error); the videos use the true cameras.
    calib_error_deg: float = 0.0
    # Profile "disks": their spacing (mm), radius over the tube's, and thickness (mm).
    disk_spacing_mm: float = 20.0
    disk_ratio: float = 1.5
    disk_thickness_mm: float = 2.0

    @property
    def profile_text(self) -> str:
        """The profile's name, with the disks' spacing, radius ratio and thickness."""
        if self.profile != "disks":
            return self.profile
        return f"disks{self.disk_spacing_mm:g}x{self.disk_ratio:g}t{self.disk_thickness_mm:g}"

    def radius_profile(self) -> RadiusProfile:
        """The tube's :class:`RadiusProfile`."""
        return RadiusProfile(
            self.profile,
            self.radius_mm,
            disk_spacing_mm=self.disk_spacing_mm,
            disk_ratio=self.disk_ratio,
            disk_thickness_mm=self.disk_thickness_mm,
        )

    @property
    def scene(self) -> list[str]:
        """The scene's extras: "distractor", "flicker"."""
        return [f for f, on in (("distractor", self.distractor), ("flicker", self.flicker)) if on]

    @property
    def name(self) -> str:
        """A directory-safe name that tells the options apart."""
        flags = "".join(f"-{f}" for f in self.scene)
        bright = "-bright" if self.polarity == "bright" else ""
        return (
            f"{self.shape}-{self.tip}-{self.profile_text}-{self.arrangement}-{self.cameras}cam-"
            f"r{self.radius_mm:g}-{self.size[0]}x{self.size[1]}{bright}{flags}-s{self.seed}"
            + (f"-calib{self.calib_error_deg:g}" if self.calib_error_deg else "")
        )

    def describe(self) -> str:
        """One line for a table: shape, end, profile, rig and scene."""
        return (
            f"{self.shape} (seed {self.seed}), {self.tip} tip, {self._profile_words()}, "
            f"r {self.radius_mm:g} mm, "
            f"{self.arrangement} {self.cameras} cameras, {self.size[0]}x{self.size[1]}, {self.polarity}"
            + "".join(f", {f}" for f in self.scene)
            + (f", calibration {self.calib_error_deg:g} deg off" if self.calib_error_deg else "")
        )

    def _profile_words(self) -> str:
        if self.profile != "disks":
            return self.profile
        return (
            f"disks (every {self.disk_spacing_mm:g} mm, {self.disk_ratio:g}x, "
            f"{self.disk_thickness_mm:g} mm thick)"
        )

    def options(self) -> SceneOptions:
        return SceneOptions(
            tip=self.tip,
            profile=self.radius_profile(),
            cameras=self.cameras,
            size=self.size,
            distractor=self.distractor,
            flicker=self.flicker,
            calib_error_deg=self.calib_error_deg,
        )


def _rounds(rng: np.random.Generator, values: tuple, n: int) -> list:
    """n values: shuffled rounds of ``values``, so each appears once per len(values) draws."""
    out: list = []
    while len(out) < n:
        out.extend(values[i] for i in rng.permutation(len(values)))
    return out[:n]


@functools.cache
def _cycle(shape: str) -> NDArray[np.float64]:
    """Every other pose of a named shape's motion cycle, (PERIOD_FRAMES / 2, N, 3) mm."""
    lines = shape_centerlines(shape, PERIOD_FRAMES, base_mm=BASE_MM, points=CENTERLINE_POINTS)[::2]
    lines.flags.writeable = False
    return lines


def _named_shape_fits(case: Case) -> bool:
    """Whether a named shape's motion cycle keeps the case's tube inside the workspace and
    off itself (random shapes are drawn to fit). Poses 1/150 of a cycle apart are checked;
    the renderer checks every frame it renders, and the views too (the workspace lies
    inside every view)."""
    lines = _cycle(case.shape)
    profile = case.radius_profile()
    radii = radius_along(profile, np.linspace(0.0, 250.0, CENTERLINE_POINTS))
    disks = disks_of(profile, 250.0)
    widest = max(float(radii.max()), 0.0 if disks is None else disks.radius_mm)
    lo, hi = WORKSPACE_ORIGIN_MM, WORKSPACE_ORIGIN_MM + WORKSPACE_SIZE_MM
    return not (
        outside_box(lines, radii, lo, hi, tip=case.tip, disks=disks).any()
        or self_contact(lines, min_gap_mm=2.0 * widest, min_arc_mm=4.0 * widest).any()
    )


def draw_cases(seed: int, n: int, *, size: tuple[int, int] = (320, 240)) -> list[Case]:
    """``n`` cases drawn from ``seed``: the same seed gives the same cases.

    Each option cycles through its values in shuffled rounds (shapes: random half the
    time, else the named ones in turn), so 14 draws cover every value of every option.
    A named shape whose motion would not fit with the drawn tube gets a thinner tube.
    ``size`` is the image size of every case (1280x960 only when asked for).
    """
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    rng = np.random.default_rng([seed, 0xCA5E])
    columns = {
        "shape": _rounds(rng, _SHAPE_ROUND, n),
        "tip": _rounds(rng, TIPS, n),
        "profile": _rounds(rng, PROFILES, n),
        "arrangement": _rounds(rng, tuple(ARRANGEMENTS), n),
        "cameras": _rounds(rng, (3, 2), n),
        "distractor": _rounds(rng, (False, True), n),
        "flicker": _rounds(rng, (False, True), n),
        "polarity": _rounds(rng, ("dark", "bright"), n),
    }
    cases = []
    for i in range(n):
        radius = float(np.round(rng.uniform(*RADIUS_RANGE_MM) * 2.0) / 2.0)  # 0.5 mm steps
        case_seed = int(rng.integers(1_000_000))
        options = {key: values[i] for key, values in columns.items()}
        if options["profile"] == "disks":
            options.update(_disks(seed, i))
        case = Case(**options, radius_mm=radius, seed=case_seed, size=size)
        while case.shape != RANDOM_SHAPE and not _named_shape_fits(case):
            if case.radius_mm <= RADIUS_RANGE_MM[0]:
                raise PipelineError(f"{case.name}: the shape does not fit even with a {radius:g} mm tube")
            case = Case(**{**options, "radius_mm": case.radius_mm - 0.5, "seed": case_seed, "size": size})
        cases.append(case)
    return cases


def _disks(seed: int, index: int) -> dict[str, float]:
    """Case ``index`` of draw ``seed``'s spacer disks, from a generator of their own (the
    draw's other options do not depend on them)."""
    rng = np.random.default_rng([seed, 0xD15C, index])
    return {
        "disk_spacing_mm": float(np.round(rng.uniform(*DISK_SPACING_RANGE_MM) * 2.0) / 2.0),
        "disk_ratio": float(np.round(rng.uniform(*DISK_RATIO_RANGE), 2)),
        "disk_thickness_mm": float(np.round(rng.uniform(*DISK_THICKNESS_RANGE_MM) * 2.0) / 2.0),
    }


def render_case(case: Case, out_dir: Path, frames: int, *, progress: bool = False, jobs: int = -1) -> Path:
    """Render ``case`` as a session directory ``out_dir`` of ``frames`` frames; returns ``out_dir``."""
    render_session(
        out_dir,
        shape=case.shape,
        frames=frames,
        seed=case.seed,
        polarity=case.polarity,
        radius_mm=case.radius_mm,
        arrangement=case.arrangement,
        options=case.options(),
        progress=progress,
        jobs=jobs,
    )
    return Path(out_dir)
