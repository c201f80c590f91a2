"""The Rerun writer and its layout: checked with Rerun's own tools (`rerun rrd verify`,
RrdReader, the blueprint read back from the file)."""

from __future__ import annotations

import itertools
import os
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import pytest
import rerun as rr
from conftest import rig_cameras
from rerun.chunk import RrdReader

from pipeline.geometry.camera import Camera
from pipeline.reconstruct.frame_result import FrameResult
from pipeline.record.rerun_layout import HULL_PATH, LEGEND_3D, default_blueprint, framing_eye, series_colors
from pipeline.record.rerun_log import CENTERLINE_RGB, SMOOTHED_RGB, TIP_RGB, RerunRecorder
from pipeline.session.settings import Workspace

T0_NS = 1_700_000_000_000_000_000
DT_NS = 33_333_333
N_FRAMES = 8
FPS = 30.0
# A frame found suspect after the last one (pipeline.run.outputs: far from its smoothed curve).
FLAGGED_LATE = 2
EMPTY = 3


def _curve(i: int) -> np.ndarray:
    s = np.linspace(0.0, 1.0, 9)
    return np.column_stack([128 + 30 * s * np.sin(0.3 * i), np.full(9, 128.0), 150 * s])


def _result(i: int) -> FrameResult:
    if i == EMPTY:
        return FrameResult(index=i, status="empty", reason="nothing seen")
    return FrameResult(
        index=i,
        status="ok",
        points_mm=np.array([[128.0, 128.0, 10.0 * i]], np.float32),
        centerline_mm=_curve(i),
        curvature_per_mm=np.full(9, 0.01 * i),
        length_mm=150.0 + i,
        iou=(0.9, 0.8, 0.7),
    )


@pytest.fixture(scope="module")
def rrd(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rerun") / "s.rrd"
    cams = rig_cameras()
    stream = rr.RecordingStream(application_id="pipeline", recording_id=uuid.uuid4())
    stream.set_log_time_enabled(False)
    stream.save(path, default_blueprint=default_blueprint(cams, Workspace(), fps=FPS))
    recorder = RerunRecorder(stream, cams, Workspace())
    jpeg = cv2.imencode(".jpg", np.full((240, 320), 90, np.uint8))[1].tobytes()
    png = cv2.imencode(".png", np.zeros((240, 320, 4), np.uint8))[1].tobytes()
    for i in range(N_FRAMES):
        silhouettes = None if i == EMPTY else [png] * 3  # as when a frame has no silhouettes
        recorder.write_frame(_result(i), T0_NS + i * DT_NS, jpegs=[jpeg] * 3, silhouettes_png=silhouettes)
    smoothed = np.stack([_curve(i) + 1.0 for i in range(N_FRAMES)])
    smoothed[EMPTY] = np.nan
    recorder.write_smoothed(smoothed, list(range(N_FRAMES)), [T0_NS + i * DT_NS for i in range(N_FRAMES)])
    recorder.mark_suspect(FLAGGED_LATE, T0_NS + FLAGGED_LATE * DT_NS)  # as beside the smoothed curves
    recorder.finish()
    stream.flush()
    stream.disconnect()
    return path


def _table(path: Path, entity: str, index: str | None = "frame") -> Any:
    store = RrdReader(path).stream().collect()
    return store.reader(index=index, contents=entity).to_arrow_table()


def _column(table: Any, suffix: str) -> list[Any]:
    (name,) = [n for n in table.column_names if n.endswith(suffix)]
    return table.column(name).to_pylist()


def test_rerun_verifies_the_file(rrd: Path) -> None:
    rerun = Path(sys.executable).parent / "rerun"  # the CLI installed with rerun-sdk
    env = {**os.environ, "RERUN_ANALYTICS": "off"}
    verify = subprocess.run([str(rerun), "rrd", "verify", str(rrd)], env=env, capture_output=True, text=True)
    assert verify.returncode == 0, verify.stderr


def test_the_blueprint_is_saved_with_the_recording(rrd: Path) -> None:
    reader = RrdReader(rrd)
    assert len(reader.blueprints()) == 1 and len(reader.recordings()) == 1


def test_rerun_reads_back_the_logged_centreline(rrd: Path) -> None:
    table = _table(rrd, "/world/centerline")
    frames = _column(table, "frame")
    strips = _column(table, "LineStrips3D:strips")
    got = {f: s for f, s in zip(frames, strips, strict=True) if s}
    assert sorted(got) == [i for i in range(N_FRAMES) if i != EMPTY]
    for i, (strip,) in got.items():
        # Rerun stores float32 positions: 150 mm to ~1e-5 mm.
        np.testing.assert_allclose(np.array(strip), _curve(i), atol=1e-4)
    (time_name,) = [n for n in table.column_names if n == "time"]
    times_ns = table.column(time_name).cast(pa.int64()).to_pylist()
    assert dict(zip(frames, times_ns, strict=True))[2] == T0_NS + 2 * DT_NS


def test_the_reprojected_centreline_uses_the_camera_model(rrd: Path) -> None:
    cam = rig_cameras()[1]
    table = _table(rrd, f"/world/cameras/{cam.name}/image/centerline")
    rows = dict(zip(_column(table, "frame"), _column(table, "LineStrips2D:strips"), strict=True))
    (strip,) = rows[5]
    # Distortion included: Camera.project's pixels, moved from OpenCV's pixel-centre origin
    # to Rerun's pixel-corner origin, to float32 precision.
    np.testing.assert_allclose(np.array(strip), cam.project(_curve(5)) + 0.5, atol=1e-3)


def test_cameras_are_logged_once_as_world_from_camera(rrd: Path) -> None:
    for cam in rig_cameras():
        pose = _table(rrd, f"/world/cameras/{cam.name}", index=None)
        (translation,) = _column(pose, "Transform3D:translation")
        (mat,) = _column(pose, "Transform3D:mat3x3")
        np.testing.assert_allclose(np.ravel(translation), cam.center_mm, rtol=1e-6)  # float32
        # Rerun stores 3x3 matrices column-major.
        np.testing.assert_allclose(np.reshape(mat, (3, 3)).T, cam.camera_from_world.T, atol=1e-6)
        pinhole = _table(rrd, f"/world/cameras/{cam.name}/image", index=None)
        (k,) = _column(pinhole, "Pinhole:image_from_camera")
        expected_k = cam.matrix + np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])  # principal point moved
        np.testing.assert_allclose(np.reshape(k, (3, 3)).T, expected_k, rtol=1e-6)
        assert _column(pinhole, "Pinhole:resolution") == [[[320.0, 240.0]]]  # one row, one instance


def test_time_series_are_sent_as_columns(rrd: Path) -> None:
    table = _table(rrd, "/plots/tip/z")
    frames, values = _column(table, "frame"), _column(table, "Scalars:scalars")
    assert frames == [i for i in range(N_FRAMES) if i != EMPTY]  # no value, no point
    assert [v[0] for v in values] == pytest.approx([150.0] * len(frames))
    table = _table(rrd, "/plots/voxels")
    assert [v[0] for v in _column(table, "Scalars:scalars")] == [
        0.0 if i == EMPTY else 1.0 for i in range(N_FRAMES)
    ]


def test_a_frame_flagged_after_the_last_has_its_suspect_plot_set_once(rrd: Path) -> None:
    table = _table(rrd, "/plots/suspect")
    frames, values = _column(table, "frame"), _column(table, "Scalars:scalars")
    assert frames == list(range(N_FRAMES))  # one value a frame, the flagged one's replaced
    assert [v[0] for v in values] == [1.0 if i == FLAGGED_LATE else 0.0 for i in range(N_FRAMES)]


def test_smoothed_centreline_has_its_own_entity(rrd: Path) -> None:
    table = _table(rrd, "/world/centerline_smoothed")
    rows = dict(zip(_column(table, "frame"), _column(table, "Points3D:positions"), strict=True))
    np.testing.assert_allclose(np.array(rows[0]), _curve(0) + 1.0, atol=1e-4)  # its samples, base first
    assert not rows.get(EMPTY)


def test_a_frame_without_silhouettes_clears_the_previous_ones(rrd: Path) -> None:
    table = _table(rrd, "/world/cameras/cam2/image/silhouette")
    blobs = dict(zip(_column(table, "frame"), _column(table, "EncodedImage:blob"), strict=True))
    # A Clear reads back as a row with no instance: nothing shown at that frame.
    assert len(blobs[EMPTY - 1]) == 1 and len(blobs[EMPTY]) == 0 and len(blobs[EMPTY + 1]) == 1


# --- the layout -------------------------------------------------------------------------


def _blueprint(path: Path) -> dict[str, dict[str, Any]]:
    """The blueprint saved in ``path``: entity path -> component -> its last value logged
    (the one instance, or the list of them where there are several)."""
    reader = RrdReader(path)
    (entry,) = reader.blueprints()
    table = reader.stream(store=entry).collect().reader(index="blueprint", contents="/**").to_arrow_table()
    out: dict[str, dict[str, Any]] = {}
    for name in table.column_names:
        if ":" not in name:
            continue  # an index column
        entity, component = name.split(":", 1)
        values = [v for v in table.column(name).to_pylist() if v is not None]
        if values:
            last = values[-1]
            out.setdefault(entity, {})[component] = last[0] if len(last) == 1 else last
    return out


def _views(blueprint: dict[str, dict[str, Any]]) -> dict[str, str]:
    """View display name -> its blueprint entity path."""
    return {
        parts["ViewBlueprint:display_name"]: entity
        for entity, parts in blueprint.items()
        if "ViewBlueprint:display_name" in parts
    }


def test_the_layout_opens_on_the_frame_timeline(rrd: Path) -> None:
    panel = _blueprint(rrd)["/time_panel"]
    assert panel["TimePanelBlueprint:timeline"] == "frame"
    assert panel["TimePanelBlueprint:fps"] == FPS


def test_the_hull_is_hidden_in_the_default_3d_view_and_shown_in_the_other(rrd: Path) -> None:
    blueprint = _blueprint(rrd)
    views = _views(blueprint)
    spatial = [name for name in views if blueprint[views[name]]["ViewBlueprint:class_identifier"] == "3D"]
    assert len(spatial) == 2
    tabs = [parts for parts in blueprint.values() if "ContainerBlueprint:active_tab" in parts]
    (tab,) = tabs
    first, second = (c.removeprefix("view/") for c in tab["ContainerBlueprint:contents"])
    assert tab["ContainerBlueprint:active_tab"] == f"view/{first}"  # the one shown on opening
    hidden = f"/view/{first}/ViewContents/overrides/{HULL_PATH}/visualizers"
    assert blueprint[hidden]["EntityBehavior:visible"] is False
    assert f"/view/{second}/ViewContents/overrides/{HULL_PATH}/visualizers" not in blueprint
    # The default view's title is the 3-D legend, naming each curve by its colour.
    title = blueprint[f"/view/{first}"]["ViewBlueprint:display_name"]
    assert all(word in title for word in ("orange", "per frame", "blue", "smoothed", "red", "tip"))


def test_both_3d_views_open_on_the_framing_eye(rrd: Path) -> None:
    blueprint = _blueprint(rrd)
    eye_mm, target_mm = framing_eye(rig_cameras(), Workspace())
    eyes = [parts for entity, parts in blueprint.items() if entity.endswith("/EyeControls3D")]
    assert len(eyes) == 2
    for eye in eyes:
        np.testing.assert_allclose(eye["EyeControls3D:position"], eye_mm, rtol=1e-6)  # float32
        np.testing.assert_allclose(eye["EyeControls3D:look_target"], target_mm, rtol=1e-6)
        assert eye["EyeControls3D:eye_up"] == [0.0, 0.0, 1.0]


def _image_corners_mm(cam: Camera, depth_mm: float) -> np.ndarray:
    """(4, 3) world points of the image's outer corners at ``depth_mm`` in front of ``cam``
    (OpenCV pixel centres, so the corners are half a pixel outside the first and last)."""
    w, h = cam.width, cam.height
    px = np.array([[-0.5, -0.5, 1], [w - 0.5, -0.5, 1], [-0.5, h - 0.5, 1], [w - 0.5, h - 0.5, 1]])
    in_camera = depth_mm * px @ np.linalg.inv(cam.matrix).T
    return (in_camera - np.ravel(cam.translation_mm)) @ cam.camera_from_world  # R^T (x - t)


@pytest.mark.parametrize("arrangement", ["oblique", "ninety"])
def test_the_framing_eye_sees_the_workspace_and_every_camera_whole(arrangement: str) -> None:
    cams = rig_cameras(arrangement)
    ws = Workspace(origin_mm=(-50.0, 0.0, 0.0), size_mm=(300.0, 256.0, 200.0))
    eye, target = framing_eye(cams, ws)
    lo, hi = np.array(ws.origin_mm), np.array(ws.origin_mm) + np.array(ws.size_mm)
    box = np.array(list(itertools.product(*zip(lo, hi, strict=True))))
    frusta = [np.vstack([c.center_mm, _image_corners_mm(c, 60.0)]) for c in cams]  # the Pinhole's 60 mm
    points = np.vstack([box, *frusta])
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    rel = points - eye
    depth = rel @ forward
    assert (depth > 0).all()  # nothing behind the eye
    # Rerun's 3-D view: 55 degrees high; a view 0.9 times as wide as tall is the
    # narrowest the layout is expected in.
    tan_y = np.tan(np.radians(55.0) / 2)
    tan_x = 0.9 * tan_y
    fill = np.maximum(np.abs(rel @ right) / depth / tan_x, np.abs(rel @ up) / depth / tan_y)
    assert fill.max() <= 1.0  # all in view
    assert fill.max() >= 0.85  # and not a speck in the middle: fitted to within 10 % of an edge


def test_the_framing_eye_looks_down_between_the_cameras() -> None:
    cams = rig_cameras()
    eye, target = framing_eye(cams, Workspace())
    assert eye[2] > target[2]
    toward_eye = np.arctan2(*(eye - target)[1::-1])
    for cam in cams:
        toward_cam = np.arctan2(*(cam.center_mm - target)[1::-1])
        apart_rad = abs((toward_eye - toward_cam + np.pi) % (2 * np.pi) - np.pi)
        # Three cameras leave a gap of at least 120 degrees; its middle is 60 from each side.
        assert apart_rad > np.radians(45.0), cam.name


@pytest.mark.parametrize("n_cameras", [2, 3, 8])
def test_every_plot_series_has_its_own_colour(n_cameras: int) -> None:
    colors = series_colors([f"cam{i}" for i in range(n_cameras)])
    assert len(colors) == 7 + n_cameras
    rgb = np.array(list(colors.values()), dtype=float)
    # 80 of 255 in RGB: far enough apart to be told apart as thin lines on a dark plot.
    closest = min(np.linalg.norm(a - b) for a, b in itertools.combinations(rgb, 2))
    assert closest >= 80.0


def test_plot_colours_and_names_are_logged_with_the_series(rrd: Path) -> None:
    expected = series_colors([c.name for c in rig_cameras()])
    for path in ("plots/tip/x", "plots/tip/z", "plots/iou/cam0", "plots/iou/cam2", "plots/length"):
        table = _table(rrd, f"/{path}", index=None)
        (color,) = _column(table, "SeriesLines:colors")
        (name,) = _column(table, "SeriesLines:names")
        r, g, b = expected[path]
        assert color == [(r << 24) | (g << 16) | (b << 8) | 0xFF]  # packed RGBA
        assert name == [path.rsplit("/", 1)[-1]]
    tip_x = _column(_table(rrd, "/plots/tip/x", index=None), "SeriesLines:colors")
    tip_z = _column(_table(rrd, "/plots/tip/z", index=None), "SeriesLines:colors")
    assert tip_x != tip_z


# --- the layout as the viewer draws it ---------------------------------------------------

_VULKAN_ICDS = Path("/usr/share/vulkan/icd.d")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def viewer(rrd: Path) -> Iterator[Any]:
    """Rerun's headless viewer (software Vulkan: `make test` installs Mesa's) showing ``rrd``."""
    if not any(_VULKAN_ICDS.glob("*.json")) and not os.environ.get("VK_ICD_FILENAMES"):
        message = "no Vulkan driver for Rerun's headless viewer (apt-get install mesa-vulkan-drivers)"
        if os.environ.get("CI"):
            pytest.fail(message)  # `make test` installs it: CI must run this test
        pytest.skip(message)
    from rerun.experimental import ViewerClient

    os.environ.setdefault("RERUN_ANALYTICS", "off")  # inherited by the spawned viewer
    client = ViewerClient.spawn(
        headless=True,
        port=_free_port(),
        executable_path=str(Path(sys.executable).parent / "rerun"),
        hide_welcome_screen=True,
    )
    try:
        client.open(str(rrd))
        deadline = time.monotonic() + 60.0
        while client.get_state().loading and time.monotonic() < deadline:
            time.sleep(0.2)
        yield client
    finally:
        client.quit()


def _pixels_of_hue(png: bytes, rgb: tuple[int, int, int]) -> int:
    """How many strongly coloured pixels of ``png`` have the hue of ``rgb`` (within 17
    degrees): spheres are shaded and edges blended, so the hue survives, not the RGB."""
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    hsv = cv2.cvtColor(image, cv2.COLOR_BGR2HSV_FULL).astype(int)  # hue 0-255
    (target,) = cv2.cvtColor(np.uint8([[rgb[::-1]]]), cv2.COLOR_BGR2HSV_FULL)[0].astype(int)
    hue_apart = np.abs((hsv[..., 0] - target[0] + 128) % 256 - 128)
    return int(((hue_apart < 12) & (hsv[..., 1] > 128) & (hsv[..., 2] > 80)).sum())


def test_the_viewer_opens_on_the_frame_timeline(viewer: Any) -> None:
    (recording,) = viewer.get_state().recordings
    assert recording.current_timeline == "frame"


def test_the_viewer_draws_the_curves_and_tip_in_the_default_3d_view(viewer: Any, tmp_path: Path) -> None:
    # Nothing fails to draw once the viewer has taken in the whole file: a view may report
    # for a moment after loading ends (images taken in before their cameras' pinholes), and
    # a report that lasts 10 s is the layout's.
    deadline = time.monotonic() + 10.0
    while True:
        default_3d = {v.name: v for v in viewer.get_state().views}[LEGEND_3D]
        if not default_3d.reports or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    assert not default_3d.reports, default_3d.reports
    viewer.set_time("frame", sequence=2, play_state="paused")
    png = viewer.take_screenshot(default_3d.view_id)
    (tmp_path / "3d.png").write_bytes(png)  # to look at when this fails
    # The curve is about 100 px long at this zoom: the per-frame line (7 px wide) covers
    # hundreds of pixels, the tip (10 px) and the smoothed samples (3.6 px) tens; a curve
    # hidden (as the hull hid them) leaves none.
    assert _pixels_of_hue(png, CENTERLINE_RGB) > 100
    assert _pixels_of_hue(png, TIP_RGB) > 30
    assert _pixels_of_hue(png, SMOOTHED_RGB) > 30


def test_the_viewer_draws_the_tip_axes_in_their_colours(viewer: Any) -> None:
    views = {v.name: v for v in viewer.get_state().views}
    png = viewer.take_screenshot(views["tip (mm)"].view_id)
    colors = series_colors([c.name for c in rig_cameras()])
    for axis in "xyz":
        assert _pixels_of_hue(png, colors[f"plots/tip/{axis}"]) > 30, axis


def test_plots_go_out_in_batches_and_a_frame_flagged_after_its_batch_reads_back_once(tmp_path: Path) -> None:
    # A run's plots are sent with the other rows, 100 frames at a time (so that a long
    # live run's memory stays flat); a frame flagged after its batch went out gets a row
    # of its own, which a reader takes over the first.
    n_frames, late = 150, 10
    path = tmp_path / "long.rrd"
    cams = rig_cameras()
    stream = rr.RecordingStream(application_id="pipeline", recording_id=uuid.uuid4())
    stream.set_log_time_enabled(False)
    stream.save(path, default_blueprint=default_blueprint(cams, Workspace(), fps=FPS))
    recorder = RerunRecorder(stream, cams, Workspace())
    for i in range(n_frames):
        recorder.write_frame(_result(i), T0_NS + i * DT_NS, jpegs=None, silhouettes_png=None)
        assert recorder.frames_waiting == (i + 1) % 100  # sent with each batch of rows
    recorder.mark_suspect(late, T0_NS + late * DT_NS)
    recorder.finish()
    stream.flush()
    stream.disconnect()
    table = _table(path, "/plots/suspect")
    frames, values = _column(table, "frame"), _column(table, "Scalars:scalars")
    assert frames == list(range(n_frames))
    assert [v[0] for v in values] == [1.0 if i == late else 0.0 for i in range(n_frames)]
