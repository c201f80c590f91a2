"""The calibration report: error table, outliers, bar chart and world axes drawn on world.*."""

from __future__ import annotations

import errno
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    from .result import CalibrationResult, ImageError
    from .views import View

log = logging.getLogger(__name__)

# An image stands out when its error exceeds the camera's median by 3 robust
# standard deviations (1.4826 MAD), by half the median AND by 0.1 px: on clean
# images the MAD is tiny and the first test alone would flag ordinary views, while
# a tenth of a pixel is below what matters for the reconstruction.
MAD_FACTOR, MIN_EXCESS, MIN_EXCESS_PX = 3.0, 0.5, 0.1


def find_outliers(errors: Sequence[ImageError]) -> list[ImageError]:
    """Images whose mean error stands out among their camera's (see MAD_FACTOR)."""
    out = []
    for cam in sorted({e.camera for e in errors}):
        mine = [e for e in errors if e.camera == cam]
        values = np.array([e.mean_px for e in mine])
        median = float(np.median(values))
        mad = 1.4826 * float(np.median(np.abs(values - median)))
        limit = median + max(MAD_FACTOR * mad, MIN_EXCESS * median, MIN_EXCESS_PX)
        out += [e for e in mine if e.mean_px > limit]
    return out


def format_table(result: CalibrationResult) -> str:
    """Per camera and per image mean re-projection error, as text."""
    lines = [f"{'camera':<10} {'image':<28} {'mean error (px)':>15}"]
    flagged = {(e.camera, e.key) for e in result.outliers}
    for cam, mean in result.camera_mean_px().items():
        for e in (e for e in result.image_errors if e.camera == cam):
            mark = "  <- stands out" if (e.camera, e.key) in flagged else ""
            lines.append(f"{cam:<10} {e.key:<28} {e.mean_px:>15.3f}{mark}")
        lines.append(f"{cam:<10} {'(mean)':<28} {mean:>15.3f}")
    lines.append(f"overall RMS {result.rms_px:.3f} px")
    if result.dropped:
        lines.append("dropped: " + ", ".join(result.dropped))
    return "\n".join(lines)


def write_report(result: CalibrationResult, views: Sequence[View], out_dir: Path) -> list[Path]:
    """Write the bar chart and one world-axes picture per camera into ``out_dir``; return the paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    files = [_bar_chart(result, out_dir / "reprojection_errors.png")]
    for cam in result.cameras:
        world = next((v for v in views if v.camera == cam.name and v.key == "world"), None)
        if world is None:
            log.info("camera %s has no world image: no world-axes picture", cam.name)
            continue
        image = cv2.imread(world.source, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
        if image is None:  # read once already for detection; only a file removed since gets here
            continue
        length = 3 * result.board.square_mm
        # Camera from world straight from calibration.toml: the axes land on the board
        # only if the world frame is where the user meant it.
        cv2.drawFrameAxes(image, cam.matrix, cam.distortions, cam.rotation, cam.translation_mm, length, 2)
        path = out_dir / f"world_axes_{cam.name}.png"
        if not cv2.imwrite(str(path), image):  # OpenCV returns False (a full disk), raises nothing
            raise OSError(errno.EIO, f"{path.name} could not be written")
        files.append(path)
    for e in result.outliers:
        log.warning("%s: mean re-projection error %.3f px stands out (--drop-outliers)", e.source, e.mean_px)
    return files


def _bar_chart(result: CalibrationResult, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cams = [c.name for c in result.cameras]
    fig, axes = plt.subplots(len(cams), 1, figsize=(9, 2.2 * len(cams)), squeeze=False)
    flagged = {(e.camera, e.key) for e in result.outliers}
    for ax, cam in zip(axes[:, 0], cams, strict=True):
        mine = [e for e in result.image_errors if e.camera == cam]
        colours = ["tab:red" if (e.camera, e.key) in flagged else "tab:blue" for e in mine]
        ax.bar(range(len(mine)), [e.mean_px for e in mine], color=colours)
        mean = result.camera_mean_px()[cam]
        ax.axhline(mean, color="k", linestyle="--", linewidth=1, label=f"mean {mean:.3f} px")
        ax.set_ylabel(f"{cam}\npx")
        # "i03" = intrinsics/03.png, "s03" = shared/03, "world"
        labels = [e.key.replace("intrinsics/", "i").replace("shared/", "s").rsplit(".", 1)[0] for e in mine]
        ax.set_xticks(range(len(mine)), labels, rotation=90, fontsize=6)
        ax.legend(loc="upper right", fontsize=7)
    axes[0, 0].set_title("Mean re-projection error per image")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
