"""The per-session model: what every frame of a session shares, built once.

Cameras, settings, the voxel grid with its per-camera lookup tables and the
background images never change over a session: the parent builds them once and
sends them to every worker. Kept apart from the per-frame path
(:mod:`pipeline.reconstruct.frame`): building it needs the cameras and the grid, not
the centreline's modules.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..carve.hull import HullGrid, build_grid
from ..geometry.camera import Camera
from ..session.folder import Session
from ..session.settings import Settings
from .disks import Disks
from .radius_profile import RadiusProfile


@dataclass(frozen=True, eq=False)
class SessionModel:
    """What every frame of a session shares; built once, pickled to workers."""

    cameras: tuple[Camera, ...]
    settings: Settings
    grid: HullGrid
    backgrounds: tuple[NDArray[np.uint8] | None, ...]
    # The tube's end the fit assumes, "flat" or "round": the settings' choice, or
    # what pipeline.reconstruct.tip_shape chose from the session's frames for "auto".
    tip: str = "flat"
    # The radius along the tube read on the session's sample frames, for the stretches a
    # frame's own views do not read (pipeline.reconstruct.radius_profile); None: each
    # frame's own profile alone.
    radius_profile: RadiusProfile | None = None

    @property
    def disks(self) -> Disks | None:
        """The tube's spacer disks, drawn with it (in ``radius_profile``), or None."""
        return None if self.radius_profile is None else self.radius_profile.disks


def build_model(session: Session) -> SessionModel:
    """The per-session model: cameras, settings, voxel grid with its lookup tables."""
    return SessionModel(
        cameras=session.cameras,
        settings=session.settings,
        grid=build_grid(session.cameras, session.settings.workspace),
        backgrounds=session.backgrounds,
        tip=session.settings.manipulator.tip if session.settings.manipulator.tip != "auto" else "flat",
    )
