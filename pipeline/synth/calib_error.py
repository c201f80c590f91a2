"""A calibration that is slightly off, as every real one is: the rig as a user's
calibration.toml would give it, while the videos are filmed with the true cameras.

One number sets the size of the error, ``error_deg``: each camera is turned by
that angle about its optical centre (a random axis), its centre moved by
``MM_PER_DEG * error_deg`` mm, its focal length scaled by ``FOCAL_PERCENT_PER_DEG *
error_deg`` percent and its principal point moved by ``PX_PER_DEG * error_deg``
pixels, each in a random direction. At 0.05 deg that is about 0.3-0.6 px over
the workspace of the synthetic rigs, a good lab calibration; at 0.15 deg
0.8-1.9 px, a camera nudged after it was calibrated. With ``bumped``, that camera alone
is off, turned by ``error_deg`` about its centre (a random axis) and nothing else: a rig
calibrated exactly whose one camera was knocked since.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import cv2
import numpy as np

from .rig import SynthCamera

MM_PER_DEG = 20.0 / 3.0
# The largest error drawn (degrees): a camera 13 mm and 13 px off, past which a rig's views
# need not meet in its workspace at all.
MAX_ERROR_DEG = 2.0
FOCAL_PERCENT_PER_DEG = 2.0
PX_PER_DEG = 20.0 / 3.0


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=n)
    return v / np.linalg.norm(v)


def perturbed_rig(
    cameras: Sequence[SynthCamera], error_deg: float, *, seed: int, bumped: int | None = None
) -> list[SynthCamera]:
    """``cameras`` each moved by an error of size ``error_deg`` (see the module), drawn from
    ``seed``; or, with ``bumped`` (an index), that camera alone turned by it.

    ``error_deg`` 0 returns the cameras unchanged.
    """
    if error_deg == 0.0:
        return list(cameras)
    rng = np.random.default_rng([seed, 0xCA11B])
    if bumped is not None:
        cam = cameras[bumped]
        rotation = cv2.Rodrigues(_unit(rng, 3) * np.deg2rad(error_deg))[0] @ cam.R
        turned = replace(cam, R=rotation, t=-rotation @ cam.center)
        return [turned if k == bumped else c for k, c in enumerate(cameras)]
    out = []
    for cam in cameras:
        turn, _ = cv2.Rodrigues(_unit(rng, 3) * np.deg2rad(error_deg))
        rotation = turn @ cam.R
        centre = cam.center + _unit(rng, 3) * MM_PER_DEG * error_deg
        k = cam.K.copy()
        k[:2, :2] *= 1.0 + rng.choice((-1.0, 1.0)) * FOCAL_PERCENT_PER_DEG * error_deg / 100.0
        k[:2, 2] += _unit(rng, 2) * PX_PER_DEG * error_deg
        out.append(replace(cam, K=k, R=rotation, t=-rotation @ centre))
    return out
