"""Shared test helpers: a tiny, valid session directory built on demand.

``make_session(tmp_path, **overrides)`` writes calibration.toml (the synthetic rig's
true cameras), one short video per camera showing a dark vertical rod on grey, and
optionally session.toml; tests then break one thing at a time.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Collection, Iterator, Sequence
from pathlib import Path
from typing import Any

import av
import cv2
import numpy as np
import pytest
import tomli_w
from numpy.typing import NDArray

from pipeline.geometry.camera import Camera
from pipeline.session.calibration_io import read_calibration, write_calibration
from pipeline.session.settings import Workspace
from pipeline.synth.rig import make_rig

# A rod standing on the default manipulator base (128, 128, 0) mm, 160 mm tall: inside
# the default workspace and seen whole by every camera of the oblique rig.
ROD_MM = np.array([[128.0, 128.0, 0.0], [128.0, 128.0, 160.0]])
ROD_WIDTH_PX = 7
GREY, DARK = 150, 30

# The accuracy targets: mean and p95 of the symmetric centreline distance (mm),
# median tip error (mm), mean length error (%), failed frames.
MEAN_MM, P95_MM, TIP_MM, LENGTH_PCT = 0.4, 1.0, 1.0, 1.0


def rig_cameras(arrangement: str = "oblique") -> list[Camera]:
    """The synthetic rig's true cameras as :class:`Camera` (Rodrigues rotation)."""
    return [
        Camera(
            c.name,
            (c.width, c.height),
            c.K,
            c.dist,
            cv2.Rodrigues(c.R)[0].ravel(),
            c.t,
        )
        for c in make_rig(arrangement)
    ]


def rod_image(cam: Camera, *, visible: bool = True) -> NDArray[np.uint8]:
    """(H, W) uint8 grey image of the rod seen by ``cam`` (plain grey if not ``visible``)."""
    image = np.full((cam.height, cam.width), GREY, np.uint8)
    if visible:
        a, b = np.round(cam.project(ROD_MM)).astype(int)
        cv2.line(image, tuple(a.tolist()), tuple(b.tolist()), DARK, ROD_WIDTH_PX)
    return image


def write_video(
    path: Path,
    images: Sequence[NDArray[np.uint8]],
    *,
    fps: float = 30.0,
    fourcc: str | None = None,
    size: tuple[int, int] | None = None,
) -> Path:
    """Write grey ``images`` to ``path``: MJPG for .avi, mp4v otherwise (unless ``fourcc``).

    ``size`` (width, height) is needed only when ``images`` is empty.
    """
    code = fourcc or ("MJPG" if path.suffix == ".avi" else "mp4v")
    w, h = size if size is not None else (images[0].shape[1], images[0].shape[0])
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*code), fps, (w, h), isColor=False)
    assert writer.isOpened(), f"cannot write {path} with {code}"
    for image in images:
        writer.write(image)
    writer.release()
    return path


def grey16_video(path: Path, frames: Sequence[NDArray[np.uint16]]) -> Path:
    """An FFV1 video of 16-bit grey (H, W) uint16 ``frames``, as a machine-vision camera's."""
    with av.open(str(path), "w") as container:
        stream = container.add_stream("ffv1", rate=30)
        stream.width, stream.height, stream.pix_fmt = frames[0].shape[1], frames[0].shape[0], "gray16le"
        for image in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="gray16le")))
        container.mux(stream.encode())
    return path


def build_session(
    directory: Path,
    *,
    frames: int = 4,
    fps: float | dict[str, float] = 30.0,
    ext: str = ".avi",
    cameras: list[Camera] | None = None,
    frame_counts: dict[str, int] | None = None,
    empty_frames: Collection[int] = (),
    settings: dict[str, Any] | None = None,
) -> Path:
    """Write a valid session into ``directory`` (created) and return it.

    Parameters
    ----------
    frames : frames per video (unless ``frame_counts`` names the camera).
    fps : one rate for all videos, or camera name -> rate.
    ext : video container, ".avi" (MJPG) or ".mp4" (mp4v).
    cameras : calibration to write and render with; the oblique synthetic rig by default.
    empty_frames : frame indices where the rod is out of view (plain grey images).
    settings : session.toml contents; None writes an empty one (the default settings,
        without the note a session missing its session.toml gets).
    """
    directory.mkdir(parents=True, exist_ok=True)
    cams = cameras if cameras is not None else rig_cameras()
    write_calibration(directory / "calibration.toml", cams)
    for cam in cams:
        n = (frame_counts or {}).get(cam.name, frames)
        rate = fps[cam.name] if isinstance(fps, dict) else fps
        images = [rod_image(cam, visible=i not in empty_frames) for i in range(n)]
        write_video(directory / f"{cam.name}{ext}", images, fps=rate)
    (directory / "session.toml").write_text(tomli_w.dumps(settings or {}))
    return directory


@pytest.fixture(autouse=True)
def _quiet_ffmpeg_after_each_test() -> Iterator[None]:
    """A test that runs the CLI with --debug lets FFmpeg's messages through, in this
    process and in every process it starts later (OPENCV_FFMPEG_LOGLEVEL, PyAV's
    levels): put them back, so that later tests' runs keep the quiet of a real one."""
    import pipeline.session.video as video

    before = os.environ.get("OPENCV_FFMPEG_LOGLEVEL")
    yield
    if before is None:
        os.environ.pop("OPENCV_FFMPEG_LOGLEVEL", None)
    else:
        os.environ["OPENCV_FFMPEG_LOGLEVEL"] = before
    video._set_pyav_level(os.environ.get("OPENCV_FFMPEG_LOGLEVEL", "-8"))


@pytest.fixture(scope="session", autouse=True)
def _board_detections_remembered() -> Iterator[None]:
    """A calibration run in a test takes the board detection (pipeline.calibrate.views.detect)
    of an image whose bytes an earlier run in this process already detected a board of the same
    kind in: detection answers alike every time (find_chessboard seeds OpenCV's generator;
    tests/calibrate/test_solve.py::test_the_board_detector_answers_alike_every_time), and the
    suite calibrates the same rendered views again and again (1,126 detections of 568 images
    over the calibration tests, 2026-12-06). Every image is still detected once, and a
    test that replaces the detection replaces this."""
    import hashlib
    import threading

    import pipeline.calibrate.views as views

    detect = views.detect
    seen: dict[tuple[str, tuple[int, ...], str], Any] = {}
    lock = threading.Lock()  # the detections run on threads

    def remembered(image: NDArray[np.uint8], board: Any) -> Any:
        key = (hashlib.sha1(image.tobytes()).hexdigest(), image.shape, repr(board))
        with lock:
            if key in seen:
                found = seen[key]
                return None if found is None else tuple(part.copy() for part in found)
        found = detect(image, board)
        with lock:
            seen[key] = None if found is None else tuple(part.copy() for part in found)
        return found

    views.detect = remembered
    yield
    views.detect = detect


@pytest.fixture(scope="session")
def make_session() -> Callable[..., Path]:
    """Factory: ``make_session(tmp_path / "s", **overrides)``; see :func:`build_session`."""
    return build_session


def rotation_angle_deg(R_a: NDArray[np.float64], R_b: NDArray[np.float64]) -> float:
    """Angle (degrees) of the rotation between two (3, 3) rotation matrices."""
    rvec, _ = cv2.Rodrigues(R_a @ R_b.T)
    return float(np.degrees(np.linalg.norm(rvec)))


def assert_meets_calibration_targets(
    cameras: Sequence[Camera], mean_px: dict[str, float], truth: Path
) -> None:
    """The calibration targets for every calibrated camera against truth_calibration.toml:
    0.2 px mean re-projection error (the original's figure), focal length within
    0.5 %, optical centre within 2 mm, orientation within 0.2 degrees."""
    true_cams = {c.name: c for c in read_calibration(truth)}
    for cam in cameras:
        true = true_cams[cam.name]
        assert mean_px[cam.name] <= 0.2, cam.name
        assert abs(cam.matrix[0, 0] / true.matrix[0, 0] - 1) <= 0.005, cam.name
        assert abs(cam.matrix[1, 1] / true.matrix[1, 1] - 1) <= 0.005, cam.name
        assert np.linalg.norm(cam.center_mm - true.center_mm) <= 2.0, cam.name
        assert rotation_angle_deg(cam.camera_from_world, true.camera_from_world) <= 0.2, cam.name


def remux_with_creation_time(source: Path, target: Path, when: str | None) -> Path:
    """``source``'s video packets remuxed into ``target`` (container from its suffix),
    with the container metadata creation_time ``when`` (none if None)."""
    with av.open(str(source)) as src, av.open(str(target), "w") as out:
        if when is not None:
            out.metadata["creation_time"] = when
        stream = out.add_stream_from_template(src.streams.video[0])
        for packet in src.demux(src.streams.video[0]):
            if packet.dts is not None:  # the demuxer's empty flush packet
                packet.stream = stream
                out.mux(packet)
    return target


def rewrite_mcap(
    source: Path,
    target: Path,
    *,
    chunk_size: int | None = None,
    data: Callable[[str, int, bytes], bytes] | None = None,
) -> Path:
    """``source``'s schemas, channels and messages written again, in file order, into the
    MCAP ``target``: with chunks of ``chunk_size`` bytes (the writer's default if None), and
    each message's bytes replaced by ``data(topic, log_time_ns, bytes)`` where given."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with source.open("rb") as f, target.open("wb") as out:
        writer = Writer(out) if chunk_size is None else Writer(out, chunk_size=chunk_size)
        writer.start()
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id] if schema else 0
                )
            payload = message.data if data is None else data(channel.topic, message.log_time, message.data)
            writer.add_message(channels[channel.id], message.log_time, payload, message.publish_time)
        writer.finish()
    return target


COARSE_WS = Workspace((0.0, 0.0, 0.0), (256.0, 256.0, 256.0), 8.0)  # 32^3: brute force in ~0.1 s


def random_masks(cameras: list[Camera], seed: int, *, blobs: int = 6) -> list[NDArray[np.bool_]]:
    """One mask per camera: a few random filled ellipses (large and thin ones)."""
    rng = np.random.default_rng(seed)
    masks = []
    for cam in cameras:
        m = np.zeros((cam.height, cam.width), np.uint8)
        for _ in range(blobs):
            centre = (int(rng.integers(0, cam.width)), int(rng.integers(0, cam.height)))
            axes = (int(rng.integers(1, cam.width // 4)), int(rng.integers(1, cam.height // 4)))
            cv2.ellipse(m, centre, axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
        masks.append(m.astype(bool))
    return masks
