"""What one frame's reconstruction produces: small arrays and a status.

This is the only thing that crosses from a worker back to the parent process,
so it holds no images, only the hull points and the curve.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

STATUSES = ("ok", "empty", "failed")


# The reason of an "empty" frame whose every view saw something: the silhouettes' cones do
# not meet inside the workspace box (a box that misses the tube, another rig's calibration).
NO_SHARED_VOXEL = "the silhouettes share no voxel of the workspace"


def nothing_seen(names: Sequence[str]) -> str:
    """The reason of an "empty" frame in which the cameras ``names`` see no silhouette at
    all, naming each (the user mends them all at once)."""
    if len(names) == 1:
        return f"nothing seen by camera {names[0]!r}"
    quoted = [repr(name) for name in names]
    return f"nothing seen by cameras {', '.join(quoted[:-1])} and {quoted[-1]}"


@dataclass(frozen=True, eq=False)
class FrameResult:
    """One frame's reconstruction.

    Attributes
    ----------
    index : frame index in the session (0-based).
    status : "ok", "empty" (nothing to reconstruct) or "failed" (see ``reason``).
    reason : why the frame is empty or failed; "" when ok.
    unseen_by : the cameras whose views hold no silhouette, for an "empty" frame
        (:func:`nothing_seen`); () otherwise.
    points_mm : (P, 3) float32 occupied voxel centres, world frame, mm.
    centerline_mm : (N, 3) float64 curve ordered base -> tip, uniform in arc
        length, world frame, mm; None unless status is "ok".
    tangents : (N, 3) float64 unit tangents along the curve, or None.
    curvature_per_mm : (N,) float64 curvature (1/mm), or None.
    length_mm : curve length, NaN when there is no curve.
    radius_mm : tube radius estimated from the silhouettes, NaN when unknown.
    radii_mm : (N,) float64 the radius at each centreline point (a tapered or stepped
        tube), mm, or None.
    fit_residual_mm : RMS residual of the curve fit, NaN when unknown.
    tube_width_px : (C,) how many pixels across each camera sees the tube at the frame's
        radius (:func:`pipeline.reconstruct.quality.tube_width_px`); empty where the frame
        has no curve, NaN where it has no radius.
    iou : per-camera IoU of the re-projected tube with the silhouette (camera order).
    misfits : per camera, the share of its silhouette the re-projected tube leaves
        unexplained (:func:`pipeline.reconstruct.quality.misfit_fractions`).
    tracked : the curve was fitted from the previous frames' (:mod:`pipeline.reconstruct.tracking`),
        not initialised from the hull.
    lost : why the track was lost at this frame, where the frame kept the lost track's
        fit instead of starting again from the hull (a live run starts it again on
        another core, :mod:`pipeline.live.restarts`); "" otherwise.
    jump_mm : how far the curve lies from its track's prediction at the track's velocity
        (:func:`pipeline.geometry.polyline.axis_gap_mm`; see
        :func:`pipeline.reconstruct.tracking.velocity_pair`), mm; NaN where the prediction
        carried no velocity.
    suspect_reason : why the curve may be wrong, judged without ground truth
        (:func:`pipeline.reconstruct.quality.suspect_reason`); "" when nothing says so.
    doubt_reason : why the curve may be off where the track has no better one, as suspect
        reasons: the views barely fix its course across a stretch
        (:meth:`pipeline.reconstruct.placement.Placement.loose_reason`), its edges lie off its
        tube (:func:`pipeline.reconstruct.quality.unexplained_reason`); "" where neither.
        Written with ``suspect_reason``, but not one the track treats as a wrong curve: the
        course is the one the track carried, and its velocity holds.
    timings_s : stage name -> seconds spent on this frame.
    """

    index: int
    status: str
    reason: str = ""
    unseen_by: tuple[str, ...] = ()
    points_mm: NDArray[np.float32] = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    centerline_mm: NDArray[np.float64] | None = None
    tangents: NDArray[np.float64] | None = None
    curvature_per_mm: NDArray[np.float64] | None = None
    length_mm: float = float("nan")
    radius_mm: float = float("nan")
    radii_mm: NDArray[np.float64] | None = None
    fit_residual_mm: float = float("nan")
    tube_width_px: tuple[float, ...] = ()
    iou: tuple[float, ...] = ()
    misfits: tuple[float, ...] = ()
    tracked: bool = False
    lost: str = ""
    jump_mm: float = float("nan")
    suspect_reason: str = ""
    doubt_reason: str = ""
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def voxel_count(self) -> int:
        return len(self.points_mm)

    @property
    def suspect(self) -> bool:
        return bool(self.suspect_reason)

    @property
    def tip_mm(self) -> NDArray[np.float64] | None:
        return None if self.centerline_mm is None else self.centerline_mm[-1]

    @classmethod
    def failed(cls, index: int, reason: str, **kwargs: object) -> FrameResult:
        return cls(index=index, status="failed", reason=reason, **kwargs)  # type: ignore[arg-type]
