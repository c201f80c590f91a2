"""What a board calibration found: the cameras and each image's re-projection error."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..geometry.camera import Camera
from .boards import Board


@dataclass(frozen=True)
class ImageError:
    """Mean re-projection error of one image, px."""

    camera: str
    key: str
    source: str
    mean_px: float


@dataclass
class CalibrationResult:
    """What :func:`calibrate_directory` found; ``cameras`` are in calibration.toml's world frame."""

    cameras: list[Camera]
    image_errors: list[ImageError]
    board: Board
    rms_px: float
    dropped: list[str] = field(default_factory=list)
    outliers: list[ImageError] = field(default_factory=list)
    report_files: list[Path] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)  # one line each: why the cameras are unfit for use

    def camera_mean_px(self) -> dict[str, float]:
        """Per camera, the mean over its images of their mean re-projection error, px."""
        return {
            cam.name: float(np.mean([e.mean_px for e in self.image_errors if e.camera == cam.name]))
            for cam in self.cameras
        }
