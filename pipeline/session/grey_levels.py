"""Grey images of any stored depth as the videos' 8-bit levels.

One rule for every image read beside the videos (a session's backgrounds, a calibration's
board images): a level is scaled from the full range of the depth it is stored at, never
stretched to the image's brightest pixel, so one scene reads at one level whatever else is
in view. A background is subtracted from the videos' frames at their levels; a board's
detector takes any of them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

# The depths a camera stores grey levels at (bits), shallowest first: 8-bit values, and a
# 10-, 12- or 14-bit sensor's, are saved in 16-bit files by some tools.
STORED_DEPTHS_BITS = (8, 10, 12, 14, 16)


def full_scale_level(image: NDArray[np.generic]) -> float:
    """The level that stands for white in ``image`` (any shape): 1.0 for floating-point
    levels up to 1; else 2**bits - 1 for the shallowest of STORED_DEPTHS_BITS that holds
    its brightest pixel (65535 beyond them)."""
    top = float(np.nanmax(image)) if image.size else 0.0
    if np.issubdtype(image.dtype, np.floating) and top <= 1.0:
        return 1.0
    for bits in STORED_DEPTHS_BITS:
        if top <= 2**bits - 1:
            return float(2**bits - 1)
    return float(2 ** STORED_DEPTHS_BITS[-1] - 1)


def grey_8bit(image: NDArray[np.generic], full_scale: float | None = None) -> NDArray[np.uint8]:
    """(H, W) grey levels of any depth (uint8, uint16, float) as (H, W) uint8 levels.

    uint8 is returned as it is. Other levels are scaled from ``full_scale`` (default
    :func:`full_scale_level` of ``image``: a video's frames share their first's) to
    255 and rounded: a 16-bit file holding 8-bit values reads as those values, one holding
    a 12-bit sensor's as its levels x 255 / 4095, one using the full 16-bit range as its
    levels / 257, and floating-point levels up to 1 as their levels x 255. Levels beyond
    the range (negative, or above 65535) are clipped, and a NaN reads as 0.
    """
    if image.dtype == np.uint8:
        return np.asarray(image, dtype=np.uint8)
    white = full_scale_level(image) if full_scale is None else full_scale
    levels = np.asarray(image, dtype=np.float64) * (255.0 / white)
    return np.clip(np.round(np.nan_to_num(levels)), 0, 255).astype(np.uint8)
