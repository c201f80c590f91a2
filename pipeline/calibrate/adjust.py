"""Cameras refined from the silhouettes of a session's own frames.

A calibration is never exact, and half a pixel of error over the workspace
costs more accuracy than the whole centreline fit. A session holds far more
evidence about its cameras than a few board images: in every frame the same tube
must project onto every view's silhouette at once. Here the tubes of a few
frames spread over the session and the cameras are adjusted together, by
Gauss-Newton on the side readings of the tube fit (:func:`pipeline.reconstruct.tube_fit.read_sides`):
each reading says where the tube's axis projects across the tube in one view,
and moves either the tube's sample or the camera.

Each camera has nine parameters: a turn about its optical centre (3, radians,
camera axes), a shift of that centre (3, mm, world axes), a relative change of
its focal length and a shift of its principal point (2, px). Lens distortion is
kept. The tubes' corrections are those of the tube fit (smooth along the tube,
none along it; the base held at the mount if asked). The normal equations are solved
with the tubes eliminated frame by frame (a Schur complement: each frame's
block is banded), so the cost is linear in the number of frames.

Where the silhouettes say little (a camera orbiting the workspace, its focal
length against its distance), a prior keeps each camera near the given one
(:data:`PRIOR_SIGMA`). What they cannot tell at all (the whole rig turned, moved
or scaled with the tubes it sees) is then set by the given rig: the adjusted one
is moved, as a whole, to where its cameras' poses best match the given ones
(:func:`nearest_to_given`). The world frame stays the user's.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.linalg import solveh_banded
from scipy.optimize import least_squares

from ..geometry.camera import Camera
from ..geometry.polyline import by_fraction, polyline_arclength, resample_polyline
from ..reconstruct.disks import Disks
from ..reconstruct.placement import normal_equations
from ..reconstruct.radius_profile import RadiusProfile
from ..reconstruct.side_readings import SideReadings, consistent_readings, read_sides

FloatArray = NDArray[np.float64]

N_PARAMS = 9
# The prior's spread of each parameter: how far a calibrated camera may be from
# its calibration before the silhouettes alone decide (0.3 deg, 3 mm, 1 %, 3 px).
PRIOR_SIGMA = np.array([np.deg2rad(0.3)] * 3 + [3.0] * 3 + [0.01] + [3.0] * 2)
# Sample spacing along the tubes (mm), the tube fit's; smoothness of their corrections.
SPACING_MM = 4.0
_SMOOTHNESS = 0.5
# The prior is weighed against the readings as if each were this uncertain (mm):
# neighbouring readings along a tube are far from independent (they share the
# blur, the video's compression blocks and the tube's own errors of shape), and
# weighed as independent they let the cameras drift along what they barely
# tell (a camera orbiting the workspace, its focal length against its distance).
_READING_SIGMA_MM = 1.0
# The tube fit's crowding margin for tracked tubes (px): the tubes are on the tube.
_CROWD_MARGIN_PX = 4.0


def moved_camera(camera: Camera, params: FloatArray) -> Camera:
    """``camera`` changed by the nine ``params`` (see the module)."""
    turn = cv2.Rodrigues(np.asarray(params[:3], dtype=np.float64))[0]
    rotation = turn @ camera.camera_from_world
    centre = camera.center_mm + params[3:6]
    matrix = np.array(camera.matrix, dtype=np.float64)
    matrix[0, 0] *= 1.0 + params[6]
    matrix[1, 1] *= 1.0 + params[6]
    matrix[0, 2] += params[7]
    matrix[1, 2] += params[8]
    return Camera(
        name=camera.name,
        size_px=camera.size_px,
        matrix=matrix,
        distortions=camera.distortions,
        rotation=np.asarray(cv2.Rodrigues(rotation)[0], dtype=np.float64).ravel(),
        translation_mm=-rotation @ centre,
    )


def parameter_jacobian(camera: Camera, points_mm: FloatArray) -> FloatArray:
    """(N, 2, 9) d(pixel) / d(params) of ``points_mm`` (N, 3) in ``camera``, at params 0.

    Analytic: a turn w and a shift dC of the centre move a camera-frame point to
    x + w x x - R dC, whose pixel's derivatives OpenCV gives (the projection's
    Jacobian with respect to its translation, at the point itself in the camera
    frame); the focal length's relative change scales fx and fy together.
    """
    in_camera = camera.to_camera(points_mm)
    n = len(in_camera)
    _, jac = cv2.projectPoints(in_camera, np.zeros(3), np.zeros(3), camera.matrix, camera.distortions)
    jac = np.asarray(jac, dtype=np.float64).reshape(n, 2, -1)
    by_point = jac[:, :, 3:6]  # (N, 2, 3): d(pixel) / d(camera-frame point)
    x, y, z = in_camera.T
    zero = np.zeros(n)
    # d(w x p) / dw = -[p]x, row by row.
    minus_cross = -np.stack(
        [np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1), np.stack([-y, x, zero], -1)], 1
    )
    out = np.empty((n, 2, N_PARAMS))
    out[:, :, 0:3] = by_point @ minus_cross
    out[:, :, 3:6] = -by_point @ camera.camera_from_world
    out[:, :, 6] = jac[:, :, 6] * camera.matrix[0, 0] + jac[:, :, 7] * camera.matrix[1, 1]
    out[:, :, 7:9] = jac[:, :, 8:10]
    return out


@dataclass(frozen=True, eq=False)
class Tube:
    """One frame's evidence: its tube and the views' images.

    points_mm : (K, 3) axis samples base -> tip, mm; radii_mm : (K,) radius along it, mm;
    contrasts : per camera (H, W) float32 (:func:`pipeline.reconstruct.tube_fit.foreground_contrast`);
    masks : per camera (H, W) bool, the silhouettes; disks : the tube's spacer disks, if
    it has any (drawn into the outline its sides are read against).
    """

    points_mm: FloatArray
    radii_mm: FloatArray
    contrasts: tuple[NDArray[np.float32], ...]
    masks: tuple[NDArray[np.bool_], ...]
    disks: Disks | None = None

    def outline(self) -> RadiusProfile | None:
        """The tube's disks as :func:`~pipeline.reconstruct.side_readings.read_sides` draws
        them (None without)."""
        return RadiusProfile.of_disks(self.disks)


def resampled_tube(
    points_mm: FloatArray,
    radii_mm: FloatArray | None,
    radius_mm: float,
    contrasts: Sequence[NDArray[np.float32]],
    masks: Sequence[NDArray[np.bool_]],
) -> Tube:
    """A frame's centreline (M, 3) with its radii (M,) (or one ``radius_mm``) and its
    views' ``contrasts`` and ``masks`` as a :class:`Tube` sampled every ~``SPACING_MM``."""
    arc = polyline_arclength(points_mm)
    k = max(round(float(arc[-1]) / SPACING_MM) + 1, 4)
    pts = resample_polyline(points_mm, k, arclength_mm=arc)
    radii = (
        np.full(k, radius_mm) if radii_mm is None else by_fraction(np.asarray(radii_mm, dtype=np.float64), k)
    )
    return Tube(pts, radii, tuple(contrasts), tuple(masks))


@dataclass(frozen=True)
class Adjustment:
    """The result of :func:`adjust_cameras`.

    cameras : the adjusted cameras, in the given order.
    params : (C, 9) each camera's change from the given one (see the module).
    tubes : the frames' tubes as adjusted with them, in the adjusted cameras' world.
    before_px, after_px : RMS distance (px) between where the silhouettes put the
        tubes' axes and where the tubes fitted to them project, with the given and
        with the adjusted cameras: the views' (in)consistency.
    readings : side readings used in the last round.
    rounds : the Gauss-Newton rounds taken.
    """

    cameras: tuple[Camera, ...]
    params: FloatArray
    tubes: tuple[Tube, ...]
    before_px: float
    after_px: float
    readings: int
    rounds: int


@dataclass(frozen=True, eq=False)
class _FrameSystem:
    """One frame's part of the normal equations, its tube eliminated (a Schur complement).

    solved : (3K, 1 + P) the tube's block solved against [its right-hand side, its
        coupling to the P = 9 C camera parameters]; schur : (P, P) and rhs : (P,) the
        frame's contribution to the cameras' reduced system; residual_px : the readings'
        distances across the tube after a tube-only solve; obs : the readings used.
    """

    solved: FloatArray
    schur: FloatArray
    rhs: FloatArray
    residual_px: FloatArray
    obs: SideReadings

    def tube_step(self, camera_step: FloatArray) -> FloatArray:
        """(K, 3) the tube's correction (mm) given the cameras' (P,)."""
        return (self.solved[:, 0] - self.solved[:, 1:] @ camera_step).reshape(-1, 3)


def _frame_system(
    tube: Tube, cameras: Sequence[Camera], base_fixed: bool, held: Sequence[int] = ()
) -> _FrameSystem | None:
    """The frame's part of the normal equations (the cameras ``held`` given no part: their
    parameters stay); None without enough readings."""
    obs = read_sides(
        tube.points_mm,
        cameras,
        tube.contrasts,
        tube.radii_mm,
        SPACING_MM,
        crowd_margin_px=_CROWD_MARGIN_PX,
        session_radii=tube.outline(),
    )
    across = obs.across
    if obs.readings < 6 or across is None:
        return None
    k, c = obs.rows.shape[:2]
    band, g = normal_equations(tube.points_mm, obs, base_fixed=base_fixed, smoothness=_SMOOTHNESS)
    # Drop the readings a tube-only solve disagrees with (another part of the tube
    # beside this one, that the tube does not know of), as the tube fit does.
    tube_only = solveh_banded(band, g).reshape(k, 3)
    kept = consistent_readings(obs, tube_only)
    if kept is not obs:
        obs = kept
        band, g = normal_equations(tube.points_mm, obs, base_fixed=base_fixed, smoothness=_SMOOTHNESS)
        tube_only = solveh_banded(band, g).reshape(k, 3)
    centre, w = obs.centres()
    scale = 1.0 / np.maximum(np.linalg.norm(across, axis=-1), 1e-12)  # px per mm across
    residual_px = ((centre - np.einsum("kci,ki->kc", obs.rows, tube_only)) * scale)[w > 0]
    jac = np.zeros((c, k, 2, N_PARAMS))  # (C, K, 2, 9); a held camera's parameters move nothing
    for view, cam in enumerate(cameras):
        if view not in held:
            jac[view] = parameter_jacobian(cam, tube.points_mm)
    d: FloatArray = np.einsum("kci,ckij->kcj", across, jac)  # (K, C, 9): mm across per parameter
    coupling = np.einsum("kc,kci,kcj->kicj", w, obs.rows, d).reshape(3 * k, c * N_PARAMS)
    if base_fixed:
        coupling[:3] = 0.0  # the base sample is held
    solved = solveh_banded(band, np.column_stack([g, coupling]))
    cameras_block = np.zeros((c, N_PARAMS, c, N_PARAMS))
    for j in range(c):
        cameras_block[j, :, j, :] = np.einsum("k,ki,kl->il", w[:, j], d[:, j], d[:, j])
    h = np.einsum("kc,kcj,kc->cj", w, d, centre).ravel()
    schur = cameras_block.reshape(c * N_PARAMS, -1) - coupling.T @ solved[:, 1:]
    rhs = h - coupling.T @ solved[:, 0]
    return _FrameSystem(solved, schur, rhs, residual_px, obs)


def adjust_cameras(
    cameras: Sequence[Camera],
    tubes: Sequence[Tube],
    *,
    base_mm: FloatArray | None = None,
    rounds: int = 6,
    prior_sigma: FloatArray = PRIOR_SIGMA,
    held: Sequence[int] = (),
    settled_px: float = 0.0,
    max_rounds: int = 0,
) -> Adjustment:
    """Adjust ``cameras`` and the frames' ``tubes`` together so that the tubes project
    onto every silhouette (see the module); ``rounds`` Gauss-Newton rounds, each
    reading the images again; or ``max_rounds`` where after ``rounds`` the views are left
    more than ``settled_px`` apart. ``base_mm`` (3,): the mount, each tube's first sample,
    or None if unknown. The cameras ``held`` (indices) are kept as given, and the world
    frame is then theirs (else the given rig's, :func:`nearest_to_given`)."""
    base_fixed = base_mm is not None
    c = len(cameras)
    params = np.zeros((c, N_PARAMS))
    free = np.repeat([k not in held for k in range(c)], N_PARAMS)
    tubes = list(tubes)
    prior = np.tile(1.0 / np.asarray(prior_sigma) ** 2, c)
    before = after = float("nan")
    readings = 0
    for round_ in range(max(rounds, max_rounds) + 1):
        current = [moved_camera(cam, p) for cam, p in zip(cameras, params, strict=True)]
        systems = [_frame_system(t, current, base_fixed, held) for t in tubes]
        found = [s for s in systems if s is not None]
        residuals = np.concatenate([s.residual_px for s in found] or [np.zeros(0)])
        rms = float(np.sqrt(np.mean(residuals**2))) if residuals.size else float("nan")
        if round_ == 0:
            before = rms
        after = rms
        readings = sum(s.obs.readings for s in found)
        if round_ >= max(rounds, max_rounds) or not readings:
            break
        if round_ == rounds and rms <= settled_px:
            break  # settled: no more rounds
        schur = np.diag(prior * _READING_SIGMA_MM**2) + sum(s.schur for s in found)
        rhs = -prior * _READING_SIGMA_MM**2 * params.ravel() + sum(s.rhs for s in found)
        step = np.zeros(c * N_PARAMS)
        step[free] = np.linalg.solve(schur[np.ix_(free, free)], rhs[free])
        params = params + step.reshape(c, N_PARAMS)
        for i, s in enumerate(systems):
            if s is not None:
                moved = tubes[i].points_mm + s.tube_step(step)
                tubes[i] = replace(tubes[i], points_mm=moved, radii_mm=s.obs.radii_mm)
    adjusted = [moved_camera(cam, p) for cam, p in zip(cameras, params, strict=True)]
    if held:
        return Adjustment(tuple(adjusted), params, tuple(tubes), before, after, readings, round_)
    world = nearest_to_given(adjusted, cameras, prior_sigma)
    tubes = [replace(t, points_mm=world.points(t.points_mm)) for t in tubes]
    return Adjustment(tuple(world.cameras(adjusted)), params, tuple(tubes), before, after, readings, round_)


def similar_camera(camera: Camera, rotation: FloatArray, scale: float, shift_mm: FloatArray) -> Camera:
    """``camera`` seeing the world through the similarity X -> scale R X + shift (R the
    (3, 3) ``rotation``): the camera whose image of X is ``camera``'s image of that point."""
    r_cam = camera.camera_from_world
    return replace(
        camera,
        rotation=np.asarray(cv2.Rodrigues(r_cam @ rotation)[0], dtype=np.float64).ravel(),
        translation_mm=(r_cam @ shift_mm + camera.translation_mm) / scale,
    )


def aligned_by_images(
    cameras: Sequence[Camera], reference: Sequence[Camera], points_mm: FloatArray
) -> list[Camera]:
    """``cameras`` moved, as a rig, by the similarity (rotation, scale and shift of the
    world) that best maps their images of ``points_mm`` (N, 3) onto the ``reference``
    cameras' images, least squares: what is left between the two rigs is what the
    silhouettes can tell (each camera's own correction), not where the world is."""
    target = np.concatenate([cam.project(points_mm).ravel() for cam in reference])
    centre = points_mm.mean(axis=0)

    def rig_through(q: FloatArray) -> list[Camera]:
        # X -> s R (X - centre) + centre + shift: about the points' centre.
        rotation = np.asarray(cv2.Rodrigues(q[:3])[0], dtype=np.float64)
        scale = float(np.exp(q[3]))
        shift = centre - scale * rotation @ centre + q[4:7]
        return [similar_camera(cam, rotation, scale, shift) for cam in cameras]

    def residual(q: FloatArray) -> FloatArray:
        return np.concatenate([cam.project(points_mm).ravel() for cam in rig_through(q)]) - target

    solution = least_squares(residual, np.zeros(7), x_scale=np.array([1e-3] * 4 + [0.1] * 3))
    return rig_through(solution.x)


@dataclass(frozen=True)
class Similarity:
    """The world seen through X -> scale R X + shift: ``rotation`` (3, 3) R, ``scale``,
    ``shift_mm`` (3,)."""

    rotation: FloatArray
    scale: float
    shift_mm: FloatArray

    def cameras(self, cameras: Sequence[Camera]) -> list[Camera]:
        """The cameras whose image of X is that of ``cameras`` of scale R X + shift."""
        return [similar_camera(cam, self.rotation, self.scale, self.shift_mm) for cam in cameras]

    def points(self, points_mm: FloatArray) -> FloatArray:
        """(N, 3) points of the cameras' world, in the world of :meth:`cameras`."""
        return np.asarray((points_mm - self.shift_mm) @ self.rotation / self.scale, dtype=np.float64)


def nearest_to_given(
    adjusted: Sequence[Camera], given: Sequence[Camera], prior_sigma: FloatArray = PRIOR_SIGMA
) -> Similarity:
    """The similarity (rotation, scale and shift of the world) that brings the poses of
    the ``adjusted`` cameras, moved by it as a rig, nearest the ``given`` cameras': the
    turns and centre shifts between them, weighed by the prior's spreads (the first six
    of ``prior_sigma``), least squares.

    The silhouettes cannot tell a rig from the same rig turned, moved or scaled with
    the tubes it sees: that is for the calibration to say, and it says it through
    its cameras' poses, each off by its own error. Matched pose by pose, those
    errors average out over the cameras. Matched by the images instead
    (:func:`aligned_by_images`), the rig's seven degrees of freedom take up most of
    them: their leading part is a shift of each image, 2 numbers a camera, 6 for
    three (tests/calibrate/test_refine.py holds the difference on seeded rigs).
    """
    origin = np.mean([cam.center_mm for cam in given], axis=0)
    turn_sigma, shift_sigma = float(prior_sigma[0]), float(prior_sigma[3])

    def similarity(q: FloatArray) -> tuple[FloatArray, float, FloatArray]:
        # X -> s R (X - origin) + origin + q[4:]: about the rig's centre.
        rotation = np.asarray(cv2.Rodrigues(q[:3])[0], dtype=np.float64)
        scale = float(np.exp(q[3]))
        return rotation, scale, origin - scale * rotation @ origin + q[4:7]

    def residual(q: FloatArray) -> FloatArray:
        rotation, scale, shift = similarity(q)
        out = []
        for cam, ref in zip(adjusted, given, strict=True):
            # The camera seeing X as ``cam`` sees s R X + shift (see similar_camera).
            centre = rotation.T @ (cam.center_mm - shift) / scale
            turn = cam.camera_from_world @ rotation @ ref.camera_from_world.T
            out.append(np.asarray(cv2.Rodrigues(turn)[0], dtype=np.float64).ravel() / turn_sigma)
            out.append((centre - ref.center_mm) / shift_sigma)
        return np.concatenate(out)

    solution = least_squares(residual, np.zeros(7))
    return Similarity(*similarity(solution.x))
