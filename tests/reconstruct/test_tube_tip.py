"""The tip model of pipeline.reconstruct.tube_tip: the drawn tube against exact coverage, the
grey levels read as coverage, and the bend started from the true curve.

The exact coverage comes from the synthetic renderer (pipeline.synth, which shares
no drawing or projection code with the pipeline): every pixel's covered fraction
of a flat-ended tube, by ray casting with 3 x 3 rays on its rim.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from pipeline.geometry.camera import Camera
from pipeline.geometry.polyline import cut_polyline, polyline_arclength
from pipeline.reconstruct.tip_bend import bend_tip_to_pixels, continue_on_circle
from pipeline.reconstruct.tube_drawing import (
    SUPERSAMPLE,
    _coverage,
    _end_tangents,
    _shrink_convex,
    canvas_levels,
    coverage_mismatch,
    draw_tube,
    normals,
    tube_points,
)
from pipeline.reconstruct.tube_tip import back_along

FloatArray = NDArray[np.float64]
CENTRE = np.array([128.0, 128.0, 80.0])


def _drawn(cam: Camera, axis_mm: FloatArray, radius_mm: float) -> FloatArray:
    """(H, W) coverage of the flat-ended tube as the bend draws it."""
    w, h = cam.size_px
    canvas = np.zeros((h * SUPERSAMPLE, w * SUPERSAMPLE), np.uint8)
    discs, outline = tube_points(axis_mm, radius_mm, flat_end=True)
    draw_tube(canvas, cam, discs, outline, radius_mm, (0, 0))
    return cv2.resize(canvas, (w, h), interpolation=cv2.INTER_AREA).astype(np.float64) / 255.0


def _exact(arrangement: str, curve_mm: FloatArray, radius_mm: float) -> list[FloatArray]:
    """Per camera of the rig, the renderer's exact (H, W) coverage of the tube."""
    from pipeline.synth.images import tube_coverage
    from pipeline.synth.raycast import Tube
    from pipeline.synth.rig import make_rig

    tube = Tube.from_centerline(curve_mm, radius_mm)
    return [tube_coverage(c, tube)[0] for c in make_rig(arrangement)]


def _arc(bend_radius_mm: float, plane: tuple[FloatArray, FloatArray], length_mm: float = 100.0) -> FloatArray:
    """(400, 3) arc of a circle in the plane of the unit vectors ``plane``, ending near CENTRE."""
    a, b = plane
    s = np.linspace(0.0, length_mm, 400)
    r = bend_radius_mm
    return CENTRE + (r * np.sin(s / r))[:, None] * a + (r * (1 - np.cos(s / r)))[:, None] * b


def _plane(seed: int) -> tuple[FloatArray, FloatArray]:
    rng = np.random.default_rng(seed)
    a = rng.standard_normal(3)
    a /= np.linalg.norm(a)
    b = rng.standard_normal(3)
    b -= (b @ a) * a
    return a, b / np.linalg.norm(b)


def _pinhole(depth_mm: float, focal_px: float = 400.0) -> Camera:
    """A distortion-free camera at the origin looking along +z, 160 x 120 px."""
    return Camera(
        "top", (160, 120), np.array([[focal_px, 0, 80.0], [0, focal_px, 60.0], [0, 0, 1]]),
        np.zeros(5), np.zeros(3), np.array([0.0, 0.0, depth_mm]),
    )  # fmt: skip


def test_shrink_convex_moves_every_edge_in_by_the_amount() -> None:
    # A regular 30-gon of circumradius 100: its inradius 100 cos(pi / 30) drops
    # by exactly 8, its vertices stay on a circle; either orientation.
    angle = np.linspace(0.0, 2 * np.pi, 30, endpoint=False)
    polygon = 100.0 * np.column_stack([np.cos(angle), np.sin(angle)])
    inradius = 100.0 * np.cos(np.pi / 30) - 8.0
    for p in (polygon, polygon[::-1]):
        shrunk = _shrink_convex(p, 8.0)
        np.testing.assert_allclose(np.linalg.norm(shrunk, axis=1), inradius / np.cos(np.pi / 30), rtol=1e-12)
    # Repeated vertices (a degenerate hull) are dropped, not divided by zero.
    square = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    np.testing.assert_allclose(_shrink_convex(square, 1.0), [[1, 1], [9, 1], [9, 9], [1, 9]], atol=1e-12)


def test_drawn_discs_cover_their_true_area() -> None:
    # A short tube seen end-on down the optical axis projects to a disc (its
    # end face) of radius f r / z: here 400 x 6 / 300 = 8 px. Drawn at random
    # sub-pixel places, its mean area is pi 8^2 within 1 % (cv2's fill made it
    # ~5 % larger: 0.42 fine pixel on an 32-fine-pixel radius, twice).
    cam = _pinhole(300.0)
    rng = np.random.default_rng(4)
    areas = []
    for _ in range(20):
        x, y = rng.uniform(-3.0, 3.0, 2)
        axis = np.array([[x, y, 0.0], [x, y, 2.0]])  # running away from the camera
        areas.append(_drawn(cam, axis, 6.0).sum())
    assert np.mean(areas) == pytest.approx(np.pi * 8.0**2, rel=0.01)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_drawn_tube_matches_exact_coverage_at_its_end(seed: int) -> None:
    # An arc (bend radius 40 mm: a loop's tip turns ~13 degrees over its last
    # radius) with a flat end, r 9 mm, in each view of the "ninety" rig: the
    # coverage drawn near the end against the renderer's. The excess over the
    # end zone, per pixel of the tube's width there, is how far the drawn end
    # overshoots: measured -0.12 to +0.01 px (up to +0.39 px before the fill
    # bias was taken off and the end face made square to the tangent); the
    # bound allows that and a pixel of area (the width is counted in pixels).
    from conftest import rig_cameras

    radius = 9.0
    curve = _arc(40.0, _plane(seed))
    axis = curve[::8] if len(curve) % 8 == 1 else np.vstack([curve[::8], curve[-1]])
    for cam, exact in zip(rig_cameras("ninety"), _exact("ninety", curve, radius), strict=True):
        drawn = _drawn(cam, axis, radius)
        tip, back = cam.project(curve[[-1, -40]])
        along = (tip - back) / np.linalg.norm(tip - back)
        h, w = exact.shape
        yy, xx = np.mgrid[0:h, 0:w]
        ahead = (xx - tip[0]) * along[0] + (yy - tip[1]) * along[1]
        across = np.abs((xx - tip[0]) * along[1] - (yy - tip[1]) * along[0])
        r_px = cam.matrix[0, 0] * radius / cam.to_camera(curve[-1:])[0, 2]
        # The end and its cap: up to 3 px back from the axis' end, ahead as far
        # as a radius reaches, and no farther across than the tube.
        zone = (ahead > -3.0) & (ahead < r_px + 3.0) & (across < r_px + 3.0)
        width = float(np.count_nonzero(exact[(np.abs(ahead + 5.0) < 0.5) & (across < r_px + 3.0)] > 0.5))
        if width < 4:  # seen end-on: no end edge to speak of
            continue
        assert abs((drawn - exact)[zone].sum()) / width < 0.1 + 1.0 / width


def test_end_tangents_of_an_arc() -> None:
    # On a circle of radius 30 mm sampled every 4 mm (as the fit samples its
    # axis), the tangents at the end and a radius (6 mm) before it, from the
    # parabola over the last two radii: within 0.2 degrees of the circle's.
    s = np.append(np.arange(0.0, 90.0, 4.0), 90.0)
    axis = np.column_stack([30 * np.sin(s / 30), 30 * (1 - np.cos(s / 30)), 0 * s])
    back, end = _end_tangents(axis, polyline_arclength(axis), 6.0)
    for got, at in ((back, 84.0), (end, 90.0)):
        want = np.array([np.cos(at / 30), np.sin(at / 30), 0.0])
        assert np.degrees(np.arccos(got @ want / np.linalg.norm(got))) < 0.2


def test_coverage_reads_local_levels_on_a_textured_scene() -> None:
    # A bar (true coverage 1 inside, 0.5 on its edge columns) on a scene whose
    # left half is much darker than its right (contrast 90 against 30): each
    # half reads 0 away from the bar, the bar 1, its edge pixels ~0.5. With one
    # median for the whole background, the dark half read 0.3 covered.
    h, w = 60, 80
    background = np.where(np.arange(w)[None, :] < 40, 90.0, 30.0) * np.ones((h, 1))
    cover = np.zeros((h, w))
    cover[10:50, 30:50] = 1.0
    cover[10:50, [29, 50]] = 0.5
    tube = 220.0
    contrast = (background * (1 - cover) + tube * cover).astype(np.float32)
    mask = cover >= 0.5
    got = _coverage(contrast, mask)
    # Away from the bar by more than the level's reach (a few sigma): exact.
    assert np.abs(got[:, :15]).max() < 1e-3 and np.abs(got[:, 65:]).max() < 1e-3
    np.testing.assert_allclose(got[12:48, 31:49], 1.0, atol=1e-3)
    # The edges' levels are averaged over a few pixels of a background that
    # steps at column 40: within 0.1 of a half.
    np.testing.assert_allclose(got[15:45, [29, 50]], 0.5, atol=0.1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bend_leaves_a_true_free_tip_where_it_is(seed: int) -> None:
    # Against exact coverage (given as the contrast: its local levels are 0 and
    # 100), the bend started from the true curve keeps its tip within one step
    # of its search (0.25 mm), across and along: the drawn tube is unbiased.
    # Measured: 0.00-0.25 mm here; it moved such tips 0.25-0.5 mm shorter with
    # cv2's fill bias and its end face square to the chord.
    from conftest import rig_cameras

    radius = 6.0
    curve = _arc(60.0, _plane(10 + seed))
    exact = _exact("ninety", curve, radius)
    contrasts = [(100.0 * c).astype(np.float32) for c in exact]
    masks = [c >= 0.5 for c in exact]
    axis = np.vstack([curve[::8], curve[-1]])
    bent = bend_tip_to_pixels(axis, rig_cameras("ninety"), masks, contrasts, radius)
    assert np.linalg.norm(bent[-1] - curve[-1]) <= 0.26


class _TipAside(NamedTuple):
    radius_mm: float
    curve_mm: FloatArray  # (P, 3) the true centreline
    axis_mm: FloatArray  # (M, 3) its coarse axis
    moved_mm: FloatArray  # (M, 3) the axis, its last 30 mm moved a radius sideways
    masks: list[NDArray[np.bool_]]  # (H, W) per view
    contrasts: list[NDArray[np.float32]]  # (H, W) per view


def _tip_moved_aside() -> _TipAside:
    """A 60 mm arc of a 6 mm tube seen exactly on the "ninety" rig, and its axis
    with the tip moved aside (growing as the square of the arc length)."""
    radius = 6.0
    curve = _arc(60.0, _plane(4))
    exact = _exact("ninety", curve, radius)
    contrasts = [(100.0 * c).astype(np.float32) for c in exact]
    masks = [c >= 0.5 for c in exact]
    axis = np.vstack([curve[::8], curve[-1]])
    arc = polyline_arclength(axis)
    normal = np.cross(axis[-1] - axis[-2], [0.0, 0.0, 1.0])
    moved = axis + (np.clip((arc - (arc[-1] - 30.0)) / 30.0, 0.0, None) ** 2)[:, None] * (
        radius * normal / np.linalg.norm(normal)
    )
    return _TipAside(radius, curve, axis, moved, masks, contrasts)


def test_coverage_mismatch_ranks_the_true_tube_first() -> None:
    # Against exact coverage, the true tube's mismatch is what drawing at 4x
    # supersampling leaves along all its edges, in three views; a tube whose
    # last 30 mm is moved sideways by a radius (the tip beside where it is),
    # or cut 6 mm short, adds whole pixels near its end. Measured: 20 / 55 /
    # 59; asserted with room: more than twice.
    from conftest import rig_cameras

    radius, _, axis, moved, masks, contrasts = _tip_moved_aside()
    short = cut_polyline(axis, float(polyline_arclength(axis)[-1]) - 6.0)
    costs = coverage_mismatch([axis, moved, short], rig_cameras("ninety"), masks, contrasts, radius)
    assert costs[0] > 0.0
    assert costs[1] > 2.0 * costs[0] and costs[2] > 2.0 * costs[0]
    # A tube's cost does not depend on the others given with it: their shared
    # window only adds background pixels, read and drawn as 0 here.
    alone = coverage_mismatch([axis], rig_cameras("ninety"), masks, contrasts, radius)
    assert alone[0] == pytest.approx(costs[0], rel=0.05)


@pytest.mark.parametrize("seed", [0, 1])
def test_continue_on_circle_follows_an_arc_and_a_straight_line(seed: int) -> None:
    # An arc of radius 30 mm in a random plane, its last 40 mm gone straight
    # along its tangent: the continuation puts them back on the circle the part
    # before follows, to the same length. Exact but for the polyline's chords (0.2 mm apart on
    # the arc, sagitta ~2e-4 mm) and lstsq's rounding: 1e-3 mm.
    rng = np.random.default_rng(seed)
    rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    angle = np.linspace(0.0, 4.0, 600)
    circle = np.column_stack([30.0 * np.cos(angle), 30.0 * np.sin(angle), np.zeros_like(angle)])
    axis = circle @ rotation.T + rng.normal(size=3) * 50.0
    arc = polyline_arclength(axis)
    stem = cut_polyline(axis, float(arc[-1]) - 40.0)
    tangent = (stem[-1] - stem[-2]) / np.linalg.norm(stem[-1] - stem[-2])
    bent = np.vstack([stem, stem[-1] + np.outer(np.arange(1.0, 41.0), tangent)])
    out = continue_on_circle(bent, redo_mm=40.0, fit_mm=50.0)
    local = (out - (axis[0] - circle[0] @ rotation.T)) @ rotation
    np.testing.assert_allclose(np.hypot(local[:, 0], local[:, 1]), 30.0, atol=1e-3)
    np.testing.assert_allclose(local[:, 2], 0.0, atol=1e-3)
    assert polyline_arclength(out)[-1] == pytest.approx(arc[-1], abs=0.05)  # chords of 2 mm steps
    np.testing.assert_allclose(out[-1], axis[-1], atol=0.05)
    # A straight line has no circle: it is continued straight, to the same end.
    line = np.outer(np.linspace(0.0, 100.0, 51), rotation[:, 0])
    np.testing.assert_allclose(continue_on_circle(line, redo_mm=20.0, fit_mm=40.0)[-1], line[-1], atol=1e-9)


def test_bend_search_that_stops_early_finds_the_same_bend(monkeypatch: pytest.MonkeyPatch) -> None:
    # A bend that cannot win is left after the views that already show it
    # (their partial cost reaches the best one): the search must end on the
    # same axis, bit for bit, as when every view of every bend is drawn, and
    # draw fewer views. The start: the true tube with its last 30 mm moved a
    # radius sideways, so the search has a way to go.
    from conftest import rig_cameras

    import pipeline.reconstruct.tip_bend as tip_bend

    radius, curve, _, moved, masks, contrasts = _tip_moved_aside()
    drawn = {"views": 0}
    level_difference = tip_bend.level_difference

    def counted(levels: NDArray[np.uint8], seen: NDArray[np.float32]) -> float:
        drawn["views"] += 1
        return level_difference(levels, seen)

    monkeypatch.setattr(tip_bend, "level_difference", counted)
    cameras = rig_cameras("ninety")
    early = bend_tip_to_pixels(moved, cameras, masks, contrasts, radius)
    views_early = drawn["views"]
    drawn["views"] = 0
    monkeypatch.setattr(tip_bend, "_PARTIAL_MARGIN", np.inf)
    every = bend_tip_to_pixels(moved, cameras, masks, contrasts, radius)
    assert np.array_equal(early, every)
    assert views_early < drawn["views"]
    # ... and the bend did move the tip back towards the truth.
    assert np.linalg.norm(early[-1] - curve[-1]) < 0.5 * np.linalg.norm(moved[-1] - curve[-1])


def test_levels_of_a_part_of_the_canvas_are_those_of_the_whole() -> None:
    # Each pixel's level averages its own s x s block only: the levels of any
    # block-aligned part (what a bend redraws) equal that part of the whole's.
    rng = np.random.default_rng(3)
    canvas = np.zeros((120 * SUPERSAMPLE, 160 * SUPERSAMPLE), np.uint8)
    for _ in range(30):
        centre = tuple(int(v) for v in rng.integers(0, 160 * SUPERSAMPLE * 16, 2))
        cv2.circle(canvas, centre, int(rng.integers(16, 40 * 16)), 255, -1, cv2.LINE_8, 4)
    whole = canvas_levels(canvas)
    assert whole.shape == (120, 160) and 0 < whole.mean() < 255
    for _ in range(20):
        x0, y0 = rng.integers(0, 150), rng.integers(0, 110)
        x1, y1 = x0 + rng.integers(1, 160 - x0 + 1), y0 + rng.integers(1, 120 - y0 + 1)
        s = SUPERSAMPLE
        part = canvas_levels(canvas[y0 * s : y1 * s, x0 * s : x1 * s])
        assert np.array_equal(part, whole[y0:y1, x0:x1])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_draw_tube_box_holds_every_pixel_it_draws(seed: int) -> None:
    # Random tube ends seen by a pinhole camera: nothing drawn outside the
    # returned box, which is far smaller than the canvas (else it saves nothing).
    cam = _pinhole(300.0)
    rng = np.random.default_rng(seed)
    axis = _arc(40.0 + 20.0 * seed, _plane(seed), length_mm=30.0) - CENTRE + rng.normal(0.0, 5.0, 3)
    canvas = np.zeros((120 * SUPERSAMPLE, 160 * SUPERSAMPLE), np.uint8)
    x0, y0, x1, y1 = draw_tube(canvas, cam, *tube_points(axis, 4.0, flat_end=True), 4.0, (0, 0))
    inside = np.zeros_like(canvas, dtype=bool)
    inside[y0:y1, x0:x1] = True
    assert canvas[inside].any() and not canvas[~inside].any()
    assert (x1 - x0) * (y1 - y0) < 0.5 * canvas.size


def test_a_tube_thinner_than_the_drawings_bias_is_drawn_as_points() -> None:
    # 0.002 mm seen from ~500 mm is a hundredth of a canvas pixel, less than the bias the
    # discs are drawn smaller by: no negative radius reaches OpenCV.
    cam = _pinhole(300.0)
    axis = _arc(60.0, _plane(1), length_mm=30.0) - CENTRE
    canvas = np.zeros((120 * SUPERSAMPLE, 160 * SUPERSAMPLE), np.uint8)
    x0, y0, x1, y1 = draw_tube(canvas, cam, *tube_points(axis, 0.002, flat_end=False), 0.002, (0, 0))
    assert x0 < x1 and y0 < y1
    assert 0 < np.count_nonzero(canvas) < 0.01 * canvas.size


def test_normals_are_orthonormal_to_the_direction() -> None:
    # Random directions and the axes themselves (where two components are 0).
    rng = np.random.default_rng(5)
    for direction in [*rng.standard_normal((20, 3)), *np.eye(3), -np.eye(3)[1]]:
        n1, n2 = normals(direction)
        t = direction / np.linalg.norm(direction)
        frame = np.stack([t, n1, n2])
        # Unit vectors built from unit vectors: a few ulps of rounding.
        np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=1e-12)


@pytest.mark.parametrize("seed", range(4))
def test_coverage_read_in_windows_is_the_whole_images_there(seed: int) -> None:
    from pipeline.reconstruct.tube_drawing import pixel_coverages

    rng = np.random.default_rng(seed)
    # Squares of 8-12 px in a checkerboard over noise, in 320x240 views: every pixel has
    # certain tube and background pixels near it, as along a tube's edges.
    contrasts, masks = [], []
    ys, xs = np.mgrid[0:240, 0:320]
    for _ in range(3):
        size, (dx, dy) = int(rng.integers(8, 13)), rng.integers(0, 8, 2)
        mask = ((xs + dx) // size + (ys + dy) // size) % 2 == 0
        contrasts.append((mask * 80.0 + rng.normal(10.0, 5.0, mask.shape)).astype(np.float32))
        masks.append(mask)
    windows = []
    for _ in range(3):
        x0, y0 = int(rng.integers(-20, 280)), int(rng.integers(-20, 200))
        w, h = (int(v) for v in rng.integers(20, 120, 2))
        windows.append(((max(x0, 0), max(y0, 0)), (min(x0 + w, 320), min(y0 + h, 240))))
    windows[int(rng.integers(3))] = None  # a view that does not see the tip
    whole = pixel_coverages(contrasts, masks)
    read = pixel_coverages(contrasts, masks, windows)
    for full, part, window in zip(whole, read, windows, strict=True):
        inside = np.zeros(full.shape, bool)
        if window is not None:
            (x0, y0), (x1, y1) = window
            inside[y0:y1, x0:x1] = True
        np.testing.assert_array_equal(part[inside], full[inside])
        assert not part[~inside].any()


@pytest.mark.parametrize("seed", range(4))
def test_the_cap_is_taken_off_along_the_line_as_the_image_shows_it(seed: int) -> None:
    rng = np.random.default_rng(seed)
    u = np.arange(-10.0, 10.0, 0.25)
    # A straight line at k px per unit: the reach comes off at that rate.
    k = rng.uniform(0.3, 2.0)
    direction = rng.normal(size=2)
    straight = np.outer(u, k * direction / np.linalg.norm(direction)) + rng.uniform(0, 300, 2)
    at, reach = rng.uniform(-2.0, 5.0), rng.uniform(0.5, 4.0)
    assert back_along(straight, u, at, reach) == pytest.approx(at - reach / k, abs=1e-9)
    # An arc (a curved end's projection): the point found lies at that distance in the
    # image from the edge's, sooner along the line than the arc's length would put it.
    radius_px, speed = rng.uniform(8.0, 20.0), rng.uniform(0.5, 1.5)
    arc = radius_px * np.column_stack([np.cos(speed * u / radius_px), np.sin(speed * u / radius_px)])
    found = back_along(arc, u, at, reach)
    point = radius_px * np.array([np.cos(speed * found / radius_px), np.sin(speed * found / radius_px)])
    edge = radius_px * np.array([np.cos(speed * at / radius_px), np.sin(speed * at / radius_px)])
    assert np.linalg.norm(point - edge) == pytest.approx(reach, abs=0.01)
    assert found < at - reach / speed
    # No reach: the edge itself; a reach beyond the samples: the first of them.
    assert back_along(straight, u, at, 0.0) == at
    assert back_along(straight, u, at, 1e6) == u[0]
