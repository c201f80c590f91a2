"""Reading frames: exact positions, OpenCV's grey levels, and damage that fails the right frames.

Every video here shows a texture moving by a few pixels a frame, so that each frame
differs from its neighbours: a frame read one position late cannot pass for the
right one. Damage is made by overwriting bytes where the container's index says a
frame is stored, then compared frame by frame with the undamaged file.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

import av
import cv2
import numpy as np
import pytest
from conftest import grey16_video, remux_with_creation_time, write_video
from numpy.typing import NDArray

from pipeline.session import video
from pipeline.session.video import read_frames

N_FRAMES = 30
KEYFRAME_INTERVAL = 12  # OpenCV's mp4v writer: frames 0, 12, 24 are keyframes
AVI_CHUNK_HEADER = 8  # fourcc and size, before an AVI chunk's data

Frames = list[NDArray[np.uint8] | None]


def _moving_texture(n: int = N_FRAMES) -> list[NDArray[np.uint8]]:
    """(64, 96) uint8 frames: a smooth random texture shifted 3 px right per frame."""
    noise = np.random.default_rng(0).integers(0, 256, (64, 96)).astype(np.uint8)
    texture = cv2.GaussianBlur(noise, (0, 0), 1.5)
    return [np.roll(texture, 3 * i, axis=1) for i in range(n)]


def _read_all(path: Path, n: int = N_FRAMES) -> Frames:
    got = list(read_frames(path, 0, n))
    assert [i for i, _ in got] == list(range(n))
    return [image for _, image in got]


def _stored_at(path: Path, frame: int) -> tuple[int, int]:
    """(byte offset, size) where the container's index stores ``frame`` (AVI: its chunk header)."""
    with av.open(str(path)) as container:
        entries = sorted(container.streams.video[0].index_entries, key=lambda e: e.timestamp)
        return entries[frame].pos, entries[frame].size


def _overwrite(source: Path, target: Path, start: int, length: int) -> Path:
    """Copy ``source`` to ``target`` with ``length`` bytes from ``start`` replaced by noise."""
    data = bytearray(source.read_bytes())
    data[start : start + length] = np.random.default_rng(1).bytes(length)
    target.write_bytes(bytes(data))
    return target


def _same(a: NDArray[np.uint8] | None, b: NDArray[np.uint8] | None) -> bool:
    return a is not None and b is not None and np.array_equal(a, b)


@pytest.fixture(scope="module")
def videos(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The moving texture as MJPG in AVI (every frame a keyframe) and mp4v in MP4 and AVI."""
    directory = tmp_path_factory.mktemp("video")
    images = _moving_texture()
    return {
        "mjpg.avi": write_video(directory / "mjpg.avi", images, fourcc="MJPG"),
        "mp4v.mp4": write_video(directory / "mp4v.mp4", images, fourcc="mp4v"),
        "mp4v.avi": write_video(directory / "mp4v.avi", images, fourcc="mp4v"),
    }


@pytest.fixture(scope="module")
def originals(videos: dict[str, Path]) -> dict[str, Frames]:
    return {name: _read_all(path) for name, path in videos.items()}


# --- undamaged files ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["mjpg.avi", "mp4v.mp4", "mp4v.avi"])
def test_grey_levels_are_opencvs_to_the_bit(
    videos: dict[str, Path], originals: dict[str, Frames], name: str
) -> None:
    capture = cv2.VideoCapture(str(videos[name]), cv2.CAP_FFMPEG)
    for i, image in enumerate(originals[name]):
        ok, bgr = capture.read()
        assert ok, f"{name}: OpenCV could not read frame {i}"
        assert _same(image, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)), f"{name}: frame {i}"
    capture.release()


def test_frames_follow_the_texture(originals: dict[str, Frames]) -> None:
    """MJPG keeps the texture within a few grey levels; a neighbouring frame is far off."""
    truth = _moving_texture()
    images = originals["mjpg.avi"]
    for i in range(N_FRAMES):
        image = images[i]
        assert image is not None
        err = np.abs(image.astype(int) - truth[i]).mean()
        # JPEG at OpenCV's default quality: ~1-2 levels mean error; a 3 px shift of
        # this texture (blurred at sigma 1.5 px) gives ~20.
        assert err < 4, f"frame {i}: mean error {err:.1f}"
        if i > 0:
            assert np.abs(image.astype(int) - truth[i - 1]).mean() > 10


# Starts on and between keyframes, the last frame, and a range past the end.
RANGES = [(0, 5), (1, 4), (11, 14), (12, 13), (13, 20), (23, 30), (29, 30), (27, 33)]


@pytest.mark.parametrize("name", ["mjpg.avi", "mp4v.mp4", "mp4v.avi"])
def test_ranges_read_with_seeking_equal_the_full_read(
    videos: dict[str, Path], originals: dict[str, Frames], name: str
) -> None:
    full = originals[name]
    for start, stop in RANGES:
        got = list(read_frames(videos[name], start, stop))
        assert [i for i, _ in got] == list(range(start, stop))
        for i, image in got:
            if i < N_FRAMES:
                assert _same(image, full[i]), f"{name}: frame {i} read from {start}"
            else:
                assert image is None, f"{name}: frame {i} is past the end"


def test_a_file_that_does_not_open_gives_none_for_every_frame(tmp_path: Path) -> None:
    path = tmp_path / "junk.avi"
    path.write_bytes(b"not a video at all")
    assert list(read_frames(path, 2, 5)) == [(2, None), (3, None), (4, None)]


# --- damaged files -----------------------------------------------------------------------------


def _check_damage(damaged: Frames, original: Frames, failed: set[int]) -> None:
    """Frames in ``failed`` are None; every other frame equals the original of the same index."""
    for i, (got, want) in enumerate(zip(damaged, original, strict=True)):
        if i in failed:
            assert got is None, f"frame {i} should have failed"
        else:
            assert _same(got, want), f"frame {i} differs from the undamaged file's frame {i}"


def test_mjpg_chunk_lost_in_damaged_bytes_fails_that_frame_only(
    videos: dict[str, Path], originals: dict[str, Frames], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # Frame 9's chunk header and half its data become noise: the AVI demuxer loses the
    # chunk, resynchronises on frame 10's, and numbers it 9 (the shift this guards against).
    pos, size = _stored_at(videos["mjpg.avi"], 9)
    damaged = _overwrite(videos["mjpg.avi"], tmp_path / "lost.avi", pos, AVI_CHUNK_HEADER + size // 2)
    with caplog.at_level(logging.WARNING, logger="pipeline.session.video"):
        frames = _read_all(damaged)
    _check_damage(frames, originals["mjpg.avi"], {9})
    assert "lost.avi: frame(s) 9 failed: lost in damaged bytes" in caplog.text


def test_mjpg_picture_data_damaged_fails_that_frame_only(
    videos: dict[str, Path], originals: dict[str, Frames], tmp_path: Path
) -> None:
    # The chunk's header survives, 40 bytes of its JPEG data do not: the decoder rejects it.
    pos, size = _stored_at(videos["mjpg.avi"], 9)
    damaged = _overwrite(videos["mjpg.avi"], tmp_path / "data.avi", pos + AVI_CHUNK_HEADER + size // 3, 40)
    _check_damage(_read_all(damaged), originals["mjpg.avi"], {9})


@pytest.mark.parametrize("name", ["mp4v.avi", "mp4v.mp4"])
def test_damaged_p_frame_fails_the_frames_up_to_the_next_keyframe(
    videos: dict[str, Path], originals: dict[str, Frames], tmp_path: Path, name: str
) -> None:
    # Frame 5 is a P-frame; 6-11 are predicted from it, so they would decode to a
    # damaged picture too. From keyframe 12 on, every frame is exact again.
    pos, size = _stored_at(videos[name], 5)
    damaged = _overwrite(videos[name], tmp_path / name, pos, size // 2)
    _check_damage(_read_all(damaged), originals[name], set(range(5, KEYFRAME_INTERVAL)))


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("name", ["mp4v.avi", "mp4v.mp4"])
def test_a_keyframe_damaged_into_no_picture_fails_the_frames_built_on_it(
    videos: dict[str, Path], originals: dict[str, Frames], tmp_path: Path, name: str, seed: int
) -> None:
    # Noise from frame 10's data into the first bytes of keyframe 12's: the decoder may take
    # what is left of the keyframe without a word and give no picture of it, and frames 13-23
    # then decode from frame 9's picture (each of them wrong, none flagged corrupt).
    rng = np.random.default_rng(seed)
    pos_10, size_10 = _stored_at(videos[name], 10)
    pos_12, size_12 = _stored_at(videos[name], 12)
    start = pos_10 + size_10 // 2
    end = pos_12 + AVI_CHUNK_HEADER + int(rng.integers(8, max(9, size_12 // 2)))
    data = bytearray(videos[name].read_bytes())
    data[start:end] = rng.bytes(end - start)
    damaged = tmp_path / name
    damaged.write_bytes(bytes(data))
    frames = _read_all(damaged)
    failed = {i for i, image in enumerate(frames) if image is None}
    assert failed and min(failed) >= 10 and max(failed) < 2 * KEYFRAME_INTERVAL
    _check_damage(frames, originals[name], failed)


def test_damaged_file_read_in_ranges_equals_its_full_read(videos: dict[str, Path], tmp_path: Path) -> None:
    """Seeking near, onto and past the damage finds the same frames as reading from the start."""
    pos, size = _stored_at(videos["mp4v.avi"], 14)
    damaged = _overwrite(videos["mp4v.avi"], tmp_path / "ranges.avi", pos, AVI_CHUNK_HEADER + size // 2)
    full = _read_all(damaged)
    assert [i for i, image in enumerate(full) if image is None] == list(range(14, 2 * KEYFRAME_INTERVAL))
    for start, stop in [(12, 16), (13, 15), (14, 20), (15, 26), (23, 25), (24, 30)]:
        for i, image in read_frames(damaged, start, stop):
            assert (image is None and full[i] is None) or _same(image, full[i]), f"frame {i} from {start}"


# --- H.264 with B-frames (decode order differs from display order) -----------------------------


@pytest.fixture(scope="module")
def h264(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The moving texture as H.264 with B-frames in MP4, a keyframe every 12 frames."""
    if "libx264" not in av.codecs_available:
        pytest.skip("this PyAV build has no libx264 encoder")
    path = tmp_path_factory.mktemp("h264") / "h264.mp4"
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=30, options={"g": "12", "sc_threshold": "0"})
        stream.width, stream.height, stream.pix_fmt = 96, 64, "yuv420p"
        for image in _moving_texture():
            frame = av.VideoFrame.from_ndarray(np.dstack([image] * 3), format="bgr24")
            container.mux(stream.encode(frame))
        container.mux(stream.encode(None))
    return path


def test_h264_ranges_read_with_seeking_equal_the_full_read(h264: Path) -> None:
    full = _read_all(h264)
    assert all(image is not None for image in full)
    for start, stop in RANGES:
        for i, image in read_frames(h264, start, stop):
            assert image is None if i >= N_FRAMES else _same(image, full[i]), f"frame {i} read from {start}"


def test_h264_damaged_frame_fails_and_no_frame_is_wrong(h264: Path, tmp_path: Path) -> None:
    """A damaged P-frame fails, and so may frames that refer to it (B-frames on either side
    of it); every frame that is returned is exact, and all are from the next keyframe on."""
    original = _read_all(h264)
    with av.open(str(h264)) as container:
        stream = container.streams.video[0]
        # A P-frame with enough bytes to damage, before keyframe 12 (index in decode order).
        k = next(k for k, e in enumerate(stream.index_entries) if not e.is_keyframe and e.size > 60)
        pos, size = stream.index_entries[k].pos, stream.index_entries[k].size
    damaged = _overwrite(h264, tmp_path / "h264.mp4", pos + size // 3, 20)
    frames = _read_all(damaged)
    failed = [i for i, image in enumerate(frames) if image is None]
    assert failed and max(failed) < KEYFRAME_INTERVAL
    _check_damage(frames, original, set(failed))


# --- FFmpeg's own messages -------------------------------------------------------------------------


def test_ffmpeg_messages_are_quiet_until_debug_asks(monkeypatch: pytest.MonkeyPatch) -> None:
    # A fresh interpreter: earlier tests here may have run the CLI with --debug.
    env = {k: v for k, v in os.environ.items() if k != "OPENCV_FFMPEG_LOGLEVEL"}
    code = (
        "import av.logging, pipeline.session.video, os; "
        "print(av.logging.get_level(), os.environ['OPENCV_FFMPEG_LOGLEVEL'])"
    )
    fresh = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert fresh.stdout.split() == ["None", "-8"]  # PyAV passes nothing on; OpenCV's FFmpeg quiet
    monkeypatch.setattr(video, "_USER_FFMPEG_LEVEL", None)
    monkeypatch.setenv("OPENCV_FFMPEG_LOGLEVEL", "-8")  # restored after the test
    try:
        video.show_ffmpeg_messages()
        assert os.environ["OPENCV_FFMPEG_LOGLEVEL"] == "24"  # for OpenCV, and workers started later
        assert av.logging.get_level() == av.logging.WARNING
    finally:
        av.logging.set_level(None)


def test_a_matroska_stream_that_starts_late_counts_its_own_frames(tmp_path: Path) -> None:
    # Matroska keeps no frame count, and its duration runs from time 0: OpenCV's
    # estimate (duration x fps) counted the 2 s before the first frame as 60 more.
    path = tmp_path / "late.mkv"
    with av.open(str(path), "w") as container:
        stream = container.add_stream("mpeg4", rate=30)
        stream.width, stream.height, stream.pix_fmt = 96, 64, "yuv420p"
        for i, image in enumerate(_moving_texture()):
            frame = av.VideoFrame.from_ndarray(np.dstack([image] * 3), format="bgr24")
            frame.pts = 60 + i  # time base 1/30 s: the first frame at 2 s
            container.mux(stream.encode(frame))
        container.mux(stream.encode(None))
    assert video.probe_video(path).frame_count == N_FRAMES
    frames = [image for _, image in read_frames(path, 0, N_FRAMES)]
    assert len(frames) == N_FRAMES and all(image is not None for image in frames)


@pytest.mark.parametrize("fps", [120, 240])
def test_a_matroska_video_at_a_constant_high_rate_is_not_variable(tmp_path: Path, fps: int) -> None:
    # Matroska stores whole milliseconds: a constant 120 fps reads 8, 8, 9 ms apart.
    path = tmp_path / "fast.mkv"
    with av.open(str(path), "w") as container:
        stream = container.add_stream("mpeg4", rate=fps)
        stream.width, stream.height, stream.pix_fmt = 96, 64, "yuv420p"
        for i, image in enumerate(_moving_texture()):
            frame = av.VideoFrame.from_ndarray(np.dstack([image] * 3), format="bgr24")
            frame.pts = i
            container.mux(stream.encode(frame))
        container.mux(stream.encode(None))
    info = video.probe_video(path)
    assert info.variable_rate == "" and not info.notes
    assert info.fps == pytest.approx(fps, rel=0.01)


@pytest.mark.parametrize(
    ("suffix", "when", "expected"),
    [
        # MP4 keeps whole seconds; Matroska keeps microseconds.
        (".mp4", "2024-05-01T12:34:56.000000Z", datetime(2024, 5, 1, 12, 34, 56, tzinfo=UTC)),
        (".mkv", "2024-05-01T12:34:56.250000Z", datetime(2024, 5, 1, 12, 34, 56, 250000, tzinfo=UTC)),
        (".mkv", "2024-05-01T14:34:56+02:00", datetime(2024, 5, 1, 12, 34, 56, tzinfo=UTC)),
    ],
)
def test_creation_time_is_read_from_the_container(
    tmp_path: Path, suffix: str, when: str, expected: datetime
) -> None:
    plain = write_video(tmp_path / "plain.mp4", _moving_texture(5))
    stamped = remux_with_creation_time(plain, tmp_path / f"stamped{suffix}", when)
    got = video.probe_video(stamped).creation_time
    assert got == expected and got is not None and got.tzinfo is not None


def test_a_video_without_creation_time_has_none(tmp_path: Path) -> None:
    plain = write_video(tmp_path / "plain.mp4", _moving_texture(5))  # OpenCV writes none
    assert video.probe_video(plain).creation_time is None
    unstamped = remux_with_creation_time(plain, tmp_path / "copy.mkv", None)
    assert video.probe_video(unstamped).creation_time is None


def test_a_creation_time_that_is_no_date_is_ignored(tmp_path: Path) -> None:
    plain = write_video(tmp_path / "plain.mp4", _moving_texture(5))
    # NUT keeps the text as it is given (MP4 and Matroska drop what they cannot parse).
    odd = remux_with_creation_time(plain, tmp_path / "odd.nut", "last tuesday")
    with av.open(str(odd)) as container:
        assert container.metadata["creation_time"] == "last tuesday"
    assert video.probe_video(odd).creation_time is None


# --- what the reader does not follow: rotation tags, second streams, variable rates ----------


def _encode(
    path: Path,
    *,
    rotation: int | None = None,
    second_stream: bool = False,
    intervals: tuple[int, ...] = (1,),
    frames: int = 12,
) -> Path:
    """An MPEG-4 video of ``frames`` 64x48 frames whose intervals cycle through
    ``intervals`` (in 1/30 s, the encoder's time base), with a display rotation and a
    second (32x24) video stream if asked."""
    from fractions import Fraction

    with av.open(str(path), "w") as out:
        streams = []
        for width, height in [(64, 48), (32, 24)][: 2 if second_stream else 1]:
            stream = out.add_stream("mpeg4", rate=30)
            stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
            streams.append(stream)
        if rotation is not None:
            streams[0].set_display_rotation(rotation)
        t = 0
        for i in range(frames):
            for stream in streams:
                frame = av.VideoFrame.from_ndarray(
                    np.full((stream.height, stream.width, 3), 10 * i, np.uint8), format="bgr24"
                )
                frame.pts, frame.time_base = t, Fraction(1, 30)
                out.mux(stream.encode(frame))
            t += intervals[i % len(intervals)]
        for stream in streams:
            out.mux(stream.encode())
    return path


def test_a_rotation_tag_is_named_and_the_frames_are_sized_as_stored(tmp_path: Path) -> None:
    info = video.probe_video(_encode(tmp_path / "cam0.mp4", rotation=90))
    # The frames are read as stored (64x48), not turned as a player would show them.
    assert (info.width, info.height) == (64, 48)
    # 90 degrees counter-clockwise is the "rotate" tag's 270 (clockwise, as phones write it).
    assert info.notes == (
        f"{tmp_path / 'cam0.mp4'}: carries a 270-degree rotation tag that is not applied; the "
        "calibration must be of the frames as stored (64x48)",
    )
    assert video.probe_video(_encode(tmp_path / "plain.mp4")).notes == ()


def test_a_second_video_stream_is_named_and_the_first_is_read(tmp_path: Path) -> None:
    info = video.probe_video(_encode(tmp_path / "cam1.mp4", second_stream=True))
    assert info.notes == (f"{tmp_path / 'cam1.mp4'}: holds 2 video streams; the first (64x48) is read",)
    assert (info.width, info.height) == (64, 48)


@pytest.mark.parametrize("seed", range(3))
def test_a_container_whose_header_is_overwritten_is_named_damaged(tmp_path: Path, seed: int) -> None:
    # FFmpeg then finds only the bare MPEG-4 stream, and guesses its rate (25 fps): the run
    # would blame the camera's frame rate. Its first 8-200 bytes overwritten, at random.
    rng = np.random.default_rng(seed)
    path = _encode(tmp_path / "cam1.mp4")
    data = bytearray(path.read_bytes())
    count = int(rng.integers(8, 200))
    data[:count] = rng.integers(0, 256, count, dtype=np.uint8).tobytes()
    path.write_bytes(bytes(data))
    damaged = r"cam1\.mp4: its \.mp4 header is damaged or missing \(only a bare"
    with pytest.raises(video.VideoError, match=damaged):
        video.probe_video(path)
    # The same stream under its own name (a bare stream's file) is a bare stream's matter,
    # not a damaged container's.
    bare = tmp_path / "cam1.m4v"
    bare.write_bytes(bytes(data))
    try:
        video.probe_video(bare)
    except video.VideoError as exc:
        assert "header is damaged" not in str(exc)


def test_a_variable_frame_rate_is_named_with_its_intervals_and_the_rate_used(tmp_path: Path) -> None:
    # A frame now and then twice as long after the last: a camera that drops frames, or a phone's.
    info = video.probe_video(_encode(tmp_path / "cam2.mp4", intervals=(1, 1, 2)))
    (note,) = info.notes
    assert note.startswith(
        f"{tmp_path / 'cam2.mp4'}: has a variable frame rate (frames 33.3-66.7 ms apart, median 33.3 ms)"
    )
    assert f"i / {info.fps:g} s, its average rate" in note and info.variable_rate


def test_describe_variable_rate_against_the_median_interval() -> None:
    steady = np.arange(10) / 30.0
    assert video.describe_variable_rate(steady) == ""
    assert video.describe_variable_rate(steady[:2]) == ""  # one interval: nothing to compare
    # A camera's own jitter (a millisecond in 33) is a constant rate.
    assert video.describe_variable_rate(steady + np.tile([0.0, 0.001], 5)) == ""
    # One interval 20 % long: more than VFR_TOLERANCE (10 %) of the median.
    stretched = np.concatenate([steady[:5], steady[5:] + 0.2 / 30.0])
    assert video.describe_variable_rate(stretched) == "frames 33.3-40.0 ms apart, median 33.3 ms"
    # Stamps in whole ms (a Matroska clock): a tick's rounding is no variation, more is.
    fast = np.round(np.arange(20) / 120.0, 3)
    assert video.describe_variable_rate(fast, tick_s=0.001) == ""
    assert video.describe_variable_rate(fast, tick_s=0.0) != ""
    assert video.describe_variable_rate(np.round(stretched, 3), tick_s=0.001) != ""


# --- one probe per file ----------------------------------------------------------------------


def test_a_probe_opens_the_file_once_per_library_and_an_unchanged_file_not_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = write_video(tmp_path / "cam0.mkv", _moving_texture(5), fourcc="MJPG")
    opened: list[str] = []
    real_av_open, real_capture = av.open, cv2.VideoCapture

    def av_open(*args: object, **kwargs: object) -> object:
        opened.append("PyAV")
        return real_av_open(*args, **kwargs)  # type: ignore[call-overload]

    def capture(*args: object) -> object:
        opened.append("OpenCV")
        return real_capture(*args)  # type: ignore[call-overload]

    monkeypatch.setattr(video.av, "open", av_open)
    monkeypatch.setattr(video.cv2, "VideoCapture", capture)
    first = video.probe_video(path)
    assert sorted(opened) == ["OpenCV", "PyAV"] and first.frame_count == 5
    assert video.probe_video(path) == first and len(opened) == 2  # the same file: no opening
    write_video(path, _moving_texture(7), fourcc="MJPG")  # rewritten where it is
    assert video.probe_video(path).frame_count == 7 and len(opened) == 4


def _edit_listed_mp4(path: Path, shown: list[NDArray[np.uint8]], hidden: int) -> Path:
    """An MP4 storing ``hidden`` frames before ``shown`` that its edit list hides (what a trim
    without re-encoding writes): stored with negative timestamps."""
    from fractions import Fraction

    tick = Fraction(1, 15360)
    step = 512  # ticks a frame at 30 fps
    with av.open(str(path), "w") as out:
        stream = out.add_stream("mpeg4", rate=30)
        stream.width, stream.height, stream.pix_fmt = shown[0].shape[1], shown[0].shape[0], "yuv420p"
        stream.codec_context.time_base = tick
        stream.time_base = tick
        stream.codec_context.gop_size = 1

        def mux(packets: list[av.Packet]) -> None:
            for packet in packets:
                packet.pts -= hidden * step
                packet.dts -= hidden * step
                out.mux(packet)

        frames = [np.full_like(shown[0], 255)] * hidden + list(shown)
        for i, image in enumerate(frames):
            frame = av.VideoFrame.from_ndarray(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR), format="bgr24")
            frame.pts, frame.time_base = i * step, tick
            mux(stream.encode(frame))
        mux(stream.encode())
    return path


def test_frames_an_edit_list_hides_are_not_counted(tmp_path: Path) -> None:
    # The container stores 23 frames and shows 20 (its duration's): the session is 20 long,
    # as its reader and every player show it; counted as 23, the other cameras' videos
    # were called short.
    rng = np.random.default_rng(0)
    shown = [rng.integers(0, 200, (48, 64), dtype=np.uint8) for _ in range(20)]
    path = _edit_listed_mp4(tmp_path / "trimmed.mp4", shown, hidden=3)
    with av.open(str(path)) as container:
        assert container.streams.video[0].frames == 23  # what the container keeps
    info = video.probe_video(path)
    assert info.frame_count == 20
    read = [image for _, image in read_frames(path, 0, info.frame_count)]
    assert len(read) == 20 and all(image is not None for image in read)
    assert np.abs(read[0].astype(int) - shown[0]).mean() < 12  # the first shown, not a hidden one


@pytest.mark.parametrize("bits", [8, 10, 12, 16])
def test_a_16_bit_grey_video_reads_at_its_first_frames_depth_in_any_range(tmp_path: Path, bits: int) -> None:
    rng = np.random.default_rng(bits)
    scene = rng.integers(0, 256, (48, 64), dtype=np.uint16)
    white = 2**bits - 1
    # The first frame's values fill ``bits``; the third is twice as bright (it clips).
    deep = [np.round(scene * (white / 255)).astype(np.uint16), scene * 0, scene * 0]
    deep[2] = np.minimum(deep[0].astype(np.int64) * 2, 65535).astype(np.uint16)
    path = grey16_video(tmp_path / "deep.mkv", deep)
    info = video.probe_video(path)
    assert info.grey_full_scale == white
    assert bool(info.notes) == (bits < 16)
    frames = [image for _, image in read_frames(path, 0, 3)]
    assert frames[0] is not None and np.abs(frames[0].astype(int) - scene).max() <= 1
    assert frames[1] is not None and not frames[1].any()
    # A range that starts at the bright frame reads it at the first frame's depth too:
    # the levels do not depend on how a run splits the video.
    ((_, alone),) = read_frames(path, 2, 3)
    np.testing.assert_array_equal(alone, frames[2])
    if bits < 16:
        assert alone is not None and (alone[scene >= 128] == 255).all()


def test_a_live_greyer_takes_its_first_deep_frames_depth() -> None:
    scene = np.arange(64 * 48, dtype=np.uint16).reshape(48, 64) % 256
    greyer = video.Greyer()
    first = greyer(av.VideoFrame.from_ndarray(scene << 2, format="gray16le"))  # 10-bit values
    brighter = greyer(av.VideoFrame.from_ndarray(scene << 4, format="gray16le"))
    assert np.abs(first.astype(int) - scene).max() <= 1
    assert (brighter[scene >= 64] == 255).all()
