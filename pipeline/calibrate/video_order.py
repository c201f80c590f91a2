"""Whether each video is its camera's: the silhouettes' cones meet in one tube only so.

Two videos swapped (or two names swapped in calibration.toml) give each camera another
camera's view. The cones of such silhouettes still meet here and there, and a run of
them would take every camera for one that moved since its calibration. Told apart by the hull:
with each view where it belongs, the voxels every view sees re-project onto the whole of
each silhouette; a view in another camera's place leaves much of its silhouette (and
the others') unexplained. On a rendered three-camera session (`pipeline synth`, ten
frames; 2026-12-04) the videos as named explained all of every silhouette (median over
the frames of the least explained view's share: 1.00), the five other orders 0.58-0.88;
with two videos swapped, the order that undoes the swap explained 1.00. On the 56
sessions of `accuracy_table` draws 127, 131, 137, 139, 149, 151 and 157 (two and three
cameras, dark objects, spacer disks; 2026-12-04) no order beat the named one by the margin
below: a dark object leaves as much unexplained in every order (named 0.19-1.00), and
where the named order explained all, others reached up to 0.99 (a straight tube).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from ..carve.hull import carve, voxel_centers_mm
from ..errors import SessionError
from ..geometry.camera import project_in_views
from ..reconstruct.frame import MAX_SILHOUETTE_SHARE, frame_silhouettes
from ..reconstruct.model import SessionModel

# Below this share (median over the frames) the videos as named leave too much of a
# silhouette unexplained to be taken as they are, and the other orders are tried ...
EXPLAINED_AS_NAMED = 0.95
# ... and an order that explains this much more, and at least SWAPPED_EXPLAINS, is the
# videos' own: the run stops and names it. A view with a dark object in its background
# leaves that object unexplained in every order alike.
SWAP_MARGIN = 0.1
SWAPPED_EXPLAINS = 0.9
# Orders are tried for rigs of up to this many cameras (4! = 24 orders).
MAX_CAMERAS = 4


def explained_share(model: SessionModel, masks: Sequence[NDArray[np.bool_]]) -> float:
    """The least share, over the views, of a view's silhouette pixels (``masks``, per
    camera (H, W) bool) onto which a voxel of their hull projects (within a pixel); 0 where a
    view has no silhouette or the views' cones share no voxel."""
    if not all(mask.any() for mask in masks):
        return 0.0
    points = voxel_centers_mm(model.settings.workspace, carve(model.grid, masks)).astype(np.float64)
    if not len(points):
        return 0.0
    pixels = np.round(project_in_views(model.cameras, points)).astype(np.int64)  # (C, P, 2)
    least = 1.0
    for mask, px in zip(masks, pixels, strict=True):
        h, w = mask.shape
        inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        marks = np.zeros(mask.shape, np.uint8)
        marks[px[inside, 1], px[inside, 0]] = 1
        hit = cv2.dilate(marks, np.ones((3, 3), np.uint8)) > 0
        least = min(least, float(np.count_nonzero(mask & hit)) / float(np.count_nonzero(mask)))
    return least


def check_video_order(
    model: SessionModel,
    frames: Sequence[tuple[int, Sequence[NDArray[np.uint8]]]],
    video_paths: Sequence[Path],
) -> None:
    """SessionError naming the videos where another order of them (``frames``: (index, per
    camera grey image), in calibration order; ``video_paths`` in the same order) explains
    the silhouettes clearly better than the order they are named in; nothing otherwise."""
    cameras = len(model.cameras)
    if not frames or not 2 <= cameras <= MAX_CAMERAS:
        return
    masks = [frame_silhouettes(images, model) for _, images in frames]
    # Frames with a view that is mostly silhouette fail on their own, named (their hull, the
    # whole workspace, would take minutes to carve and project in every order here).
    masks = [frame for frame in masks if all(m.mean() <= MAX_SILHOUETTE_SHARE for m in frame)]
    if not any(all(m.any() for m in frame) for frame in masks):
        return  # no frame in which every view sees something: nothing to tell orders by

    def share(order: tuple[int, ...]) -> float:
        return float(np.median([explained_share(model, [frame[k] for k in order]) for frame in masks]))

    named = tuple(range(cameras))
    as_named = share(named)
    # A video can only be the view of a camera whose images are its size.
    sizes = [mask.shape for mask in masks[0]]
    orders = [
        order
        for order in itertools.permutations(named)
        if order != named and all(sizes[k] == sizes[i] for i, k in enumerate(order))
    ]
    if as_named >= EXPLAINED_AS_NAMED or not orders:
        return
    best, best_share = max(((order, share(order)) for order in orders), key=lambda item: item[1])
    if best_share < max(SWAPPED_EXPLAINS, as_named + SWAP_MARGIN):
        return
    moves = ", ".join(
        f"{video_paths[k].name} looks like {model.cameras[i].name}'s view"
        for i, k in enumerate(best)
        if k != i
    )
    raise SessionError(
        f"{video_paths[0].parent}: the videos do not match their cameras in calibration.toml: {moves} "
        f"(their silhouettes meet in one tube so: {100 * best_share:.0f} % of them explained, against "
        f"{100 * as_named:.0f} % as named); rename the videos, or the cameras in calibration.toml"
    )
