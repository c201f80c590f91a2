"""VIDEO_DIR -> Session: what a valid directory gives, and the checks across files."""

from __future__ import annotations

import errno
import logging
import shutil
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import build_session, remux_with_creation_time
from numpy.typing import NDArray

from pipeline.errors import SessionError
from pipeline.session.folder import load_session


@pytest.fixture(scope="module")
def good_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_session(tmp_path_factory.mktemp("good") / "take_01", frames=3, fps=25.0)


@pytest.fixture
def session(good_session: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(good_session, tmp_path / "take_01"))


def test_valid_session(good_session: Path) -> None:
    s = load_session(good_session)
    assert s.name == "take_01"
    assert [c.name for c in s.cameras] == ["cam0", "cam1", "cam2"]
    assert [p.name for p in s.video_paths] == ["cam0.avi", "cam1.avi", "cam2.avi"]
    assert s.fps == 25.0
    assert (s.frame_count, s.frame_counts) == (3, (3, 3, 3))
    assert s.backgrounds == (None, None, None)


def test_timestamps_follow_start_time_and_fps(tmp_path: Path) -> None:
    session = build_session(
        tmp_path / "s", frames=2, fps=25.0, settings={"session": {"start_time": "2024-01-01T00:00:00Z"}}
    )
    s = load_session(session)
    start_ns = 1_704_067_200 * 10**9  # 2024-01-01T00:00:00Z in Unix time
    assert s.timestamp_ns(0) == start_ns
    assert s.timestamp_ns(1) == start_ns + 40_000_000  # 1/25 s
    assert s.timestamp_ns(250) == start_ns + 10 * 10**9


def _stamped_session(directory: Path, settings: dict[str, object] | None = None) -> Path:
    """A session whose MP4s were created at 12:00:05, 12:00:03 (the earliest) and 12:00:04."""
    session = build_session(directory, frames=2, fps=25.0, ext=".mp4", settings=settings)
    for name, second in (("cam0", 5), ("cam1", 3), ("cam2", 4)):
        path = session / f"{name}.mp4"
        when = f"2024-05-01T12:00:0{second}Z"
        remux_with_creation_time(path, path.with_suffix(".part.mp4"), when).replace(path)
    return session


def test_session_time_is_the_videos_creation_time(tmp_path: Path) -> None:
    s = load_session(_stamped_session(tmp_path / "s"))
    start_ns = int(datetime(2024, 5, 1, 12, 0, 3, tzinfo=UTC).timestamp()) * 10**9
    assert s.settings.session.start_time == datetime(2024, 5, 1, 12, 0, 3, tzinfo=UTC)
    assert s.timestamp_ns(0) == start_ns  # the first camera to start
    assert s.timestamp_ns(25) == start_ns + 10**9


@pytest.mark.parametrize(
    ("start_time", "expected"),
    [
        ("2023-02-03T04:05:06Z", datetime(2023, 2, 3, 4, 5, 6, tzinfo=UTC)),
        # Given explicitly, even the default's value is kept over the videos'.
        ("1970-01-01T00:00:00Z", datetime(1970, 1, 1, tzinfo=UTC)),
    ],
)
def test_start_time_in_session_toml_overrides_the_creation_time(
    tmp_path: Path, start_time: str, expected: datetime
) -> None:
    session = _stamped_session(tmp_path / "s", settings={"session": {"start_time": start_time}})
    s = load_session(session)
    assert s.settings.session.start_time == expected
    assert s.timestamp_ns(0) == round(expected.timestamp()) * 10**9


def test_without_creation_time_or_start_time_the_epoch(session: Path) -> None:
    s = load_session(session)  # OpenCV's AVIs carry no creation time
    assert s.timestamp_ns(0) == 0


def test_mp4_and_avi_mixed(session: Path) -> None:
    cap = cv2.VideoCapture(str(session / "cam1.avi"))
    frames = [cap.read()[1] for _ in range(3)]
    cap.release()
    (session / "cam1.avi").unlink()
    writer = cv2.VideoWriter(str(session / "cam1.mp4"), cv2.VideoWriter.fourcc(*"mp4v"), 25.0, (320, 240))
    for frame in frames:
        writer.write(frame)
    writer.release()
    s = load_session(session)
    assert s.video_paths[1].name == "cam1.mp4" and s.frame_count == 3


def test_videos_of_different_lengths_warn_with_each_count(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    session = build_session(tmp_path / "s", frame_counts={"cam0": 5, "cam1": 3, "cam2": 4})
    with caplog.at_level(logging.WARNING, logger="pipeline.session.folder"):
        s = load_session(session)
    assert (s.frame_count, s.frame_counts) == (3, (5, 3, 4))
    assert "cam0: 5, cam1: 3, cam2: 4" in caplog.text and "3 common frames" in caplog.text


def test_a_video_much_shorter_than_the_others_is_a_problem_naming_it(tmp_path: Path) -> None:
    # 2 frames short of 20 is within what cameras started by hand leave; 8 short is not.
    session = build_session(tmp_path / "s", frame_counts={"cam0": 20, "cam1": 12, "cam2": 18}, frames=2)
    s = load_session(session)
    assert s.frame_count == 12
    assert s.problems == (
        f"{session / 'cam1.avi'} has 12 frames, the others 18-20: only the first 12 frames were "
        "processed; check the recording",
    )


def test_other_files_are_ignored(session: Path) -> None:
    (session / "notes.txt").write_text("camera 1 was bumped")
    (session / "ground_truth.npz").write_bytes(b"")
    (session / "cam0.avi.part").write_bytes(b"")
    (session / "._cam0.mp4").write_bytes(b"\x00\x05\x16\x07")  # macOS's metadata beside a copied video
    assert len(load_session(session).cameras) == 3


def test_background_method_needs_every_background(session: Path) -> None:
    (session / "session.toml").write_text('[silhouette]\nmethod = "background"\n')
    (session / "background").mkdir()
    cv2.imwrite(str(session / "background" / "cam0.png"), np.full((240, 320), 150, np.uint8))
    with pytest.raises(SessionError, match=r"background/cam1\.png \(missing for camera 'cam1'\)"):
        load_session(session)
    # A JPEG under the camera's name is named, with what to do.
    cv2.imwrite(str(session / "background" / "cam1.jpg"), np.full((240, 320), 150, np.uint8))
    with pytest.raises(SessionError, match=r"\(missing for camera 'cam1'; background/cam1\.jpg is there"):
        load_session(session)
    (session / "background" / "cam1.jpg").unlink()
    for name in ("cam1", "cam2"):
        cv2.imwrite(str(session / "background" / f"{name}.png"), np.full((240, 320), 150, np.uint8))
    s = load_session(session)
    assert all(b is not None and b.shape == (240, 320) and b.dtype == np.uint8 for b in s.backgrounds)


def _backgrounds(session: Path, **images: NDArray[np.uint8] | bytes) -> None:
    """Every camera's background, a plain one where ``images`` gives none (PNG bytes as they are)."""
    (session / "background").mkdir(exist_ok=True)
    for name in ("cam0", "cam1", "cam2"):
        image = images.get(name, np.full((240, 320), 150, np.uint8))
        path = session / "background" / f"{name}.png"
        if isinstance(image, bytes):
            path.write_bytes(image)
        else:
            cv2.imwrite(str(path), image)


def test_background_of_wrong_size(session: Path) -> None:
    (session / "session.toml").write_text('[silhouette]\nmethod = "background"\n')
    _backgrounds(session, cam2=np.zeros((100, 100), np.uint8))
    with pytest.raises(SessionError, match=r"cam2\.png: is 100x100 but camera 'cam2' is 320x240"):
        load_session(session)


def test_background_not_an_image_or_cut_short(session: Path) -> None:
    (session / "session.toml").write_text('[silhouette]\nmethod = "background"\n')
    _backgrounds(session, cam1=b"not a png")
    with pytest.raises(SessionError, match=r"cam1\.png: cannot be read as an image"):
        load_session(session)
    whole = cv2.imencode(".png", np.random.default_rng(0).integers(0, 256, (240, 320), np.uint8))[1].tobytes()
    _backgrounds(session, cam1=whole[: len(whole) // 2])  # decoded, it gave libpng's own line too
    with pytest.raises(
        SessionError, match=r"cam1\.png: the image is cut short \(\d+ bytes, copied half-way\?\)"
    ):
        load_session(session)


def test_backgrounds_are_not_read_where_the_silhouettes_are_thresholded(session: Path) -> None:
    # A session filmed again at another size (calibrated again), its old backgrounds left
    # in place, or one of them damaged: the threshold has no use for them.
    _backgrounds(session, cam1=b"not a png", cam2=np.zeros((100, 100), np.uint8))
    assert load_session(session).backgrounds == (None, None, None)


def test_workspace_partly_seen_is_accepted(session: Path) -> None:
    # A box reaching far beyond the images is fine as long as each camera sees some of it.
    (session / "session.toml").write_text(
        "[workspace]\norigin_mm = [-1000.0, -1000.0, 0.0]\n"
        "size_mm = [2256.0, 2256.0, 256.0]\nvoxel_mm = 8.0\n"
    )
    assert load_session(session).settings.workspace.voxel_mm == 8.0


def test_workspace_behind_a_camera_is_refused(session: Path) -> None:
    # A small box placed just behind cam0's optical centre: cam0 cannot see it at all.
    cam0 = load_session(session).cameras[0]
    behind = cam0.center_mm + 50.0 * (cam0.center_mm - np.array([128.0, 128.0, 128.0])) / np.linalg.norm(
        cam0.center_mm - 128.0
    )
    origin = ", ".join(f"{v:.1f}" for v in behind - 5.0)
    base = ", ".join(f"{v:.1f}" for v in behind)  # the base goes with the box
    (session / "session.toml").write_text(
        f"[workspace]\norigin_mm = [{origin}]\nsize_mm = [10.0, 10.0, 10.0]\nvoxel_mm = 1.0\n"
        f"[manipulator]\nbase_mm = [{base}]\n"
    )
    with pytest.raises(SessionError, match="camera 'cam0' does not see the workspace"):
        load_session(session)


@pytest.mark.parametrize("unit_mm", [10.0, 25.4], ids=["cm", "inches"])
def test_a_calibration_in_another_unit_is_named_by_a_camera_inside_the_box(
    session: Path, unit_mm: float, caplog: pytest.LogCaptureFixture
) -> None:
    # The translations in cm or inches put every camera as many times nearer the world's origin.
    import tomllib

    import tomli_w

    doc = tomllib.loads((session / "calibration.toml").read_text())
    for table in doc.values():
        if isinstance(table, dict) and "translation" in table:
            table["translation"] = [v / unit_mm for v in table["translation"]]
    (session / "calibration.toml").write_text(tomli_w.dumps(doc))
    with caplog.at_level(logging.WARNING):
        load_session(session)
    assert "sits inside the workspace box" in caplog.text
    assert "is calibration.toml's translation in another unit than mm (cm, inches)?" in caplog.text


def test_a_folder_or_file_this_user_may_not_read_is_named(
    session: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Permissions are simulated: a test run as root reads every file.
    import os

    def denied(path: Path) -> PermissionError:
        return PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))

    real_iterdir = Path.iterdir

    def iterdir(self: Path) -> Iterator[Path]:
        if self == session:
            raise denied(self)
        return real_iterdir(self)

    with monkeypatch.context() as m:
        m.setattr(Path, "iterdir", iterdir)
        with pytest.raises(
            SessionError, match=r"take_01: cannot be read \(permission denied\); give this user"
        ):
            load_session(session)
    (session / "session.toml").write_text('[silhouette]\nmethod = "background"\n')
    _backgrounds(session)
    real_read = Path.read_bytes

    def read_bytes(path: Path) -> bytes:
        if path.name == "cam1.png":
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
        return real_read(path)

    monkeypatch.setattr(Path, "read_bytes", read_bytes)
    with pytest.raises(SessionError, match=r"background/cam1\.png: cannot be read \(permission denied\)"):
        load_session(session)


def test_missing_session_toml_is_a_note_naming_the_folder_and_the_defaults(
    session: Path, caplog: pytest.LogCaptureFixture
) -> None:
    (session / "session.toml").unlink()
    with caplog.at_level(logging.WARNING, logger="pipeline.session.folder"):
        s = load_session(session)
    assert s.settings.manipulator.radius_mm == 6.0  # the defaults, and the run goes on
    [note] = [r.getMessage() for r in caplog.records]
    assert note.startswith(f"session.toml not found in {session}: using the default settings (")
    assert "2 mm voxels" in note and "threshold 60" in note and "radius 6 mm" in note


@pytest.mark.parametrize("name", ["session.toml", "calibration.toml"])
def test_a_settings_file_named_in_other_capitals_is_named_not_passed_over(session: Path, name: str) -> None:
    spelt = session / name.capitalize()
    (session / name).rename(spelt)
    with pytest.raises(SessionError, match=rf"{spelt.name}: the file must be named {name}, in lower case"):
        load_session(session)


def test_a_session_toml_given_brings_no_note(session: Path, caplog: pytest.LogCaptureFixture) -> None:
    (session / "session.toml").write_text("[silhouette]\nthreshold = 92\n")
    with caplog.at_level(logging.WARNING, logger="pipeline.session.folder"):
        load_session(session)
    assert not caplog.records


def test_a_video_with_a_rotation_tag_is_read_as_stored_and_named(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    import av

    session = build_session(tmp_path / "s", frames=3, ext=".mp4", settings={})
    stored = session / "cam0.mp4"
    tagged = tmp_path / "tagged.mp4"
    with av.open(str(stored)) as src, av.open(str(tagged), "w") as out:
        stream = out.add_stream_from_template(src.streams.video[0])
        stream.set_display_rotation(90)  # as a phone held upright writes it
        for packet in src.demux(src.streams.video[0]):
            if packet.dts is not None:
                packet.stream = stream
                out.mux(packet)
    tagged.replace(stored)
    with caplog.at_level(logging.WARNING, logger="pipeline.session.folder"):
        s = load_session(session)
    # The size check and the reader see the frames as stored: the calibration's 320x240.
    assert s.frame_count == 3
    assert [r.getMessage() for r in caplog.records] == [
        f"{stored}: carries a 270-degree rotation tag that is not applied; the calibration must be "
        "of the frames as stored (320x240)"
    ]


def test_a_video_whose_first_stream_is_not_the_cameras_says_so(tmp_path: Path) -> None:
    # A thumbnail or preview stream muxed first: its size is the one read, and the message
    # says why it is not the camera's.
    import av

    from pipeline.errors import VideoError

    directory = build_session(tmp_path / "take", frames=4)
    session = load_session(directory)
    width, height = session.cameras[1].size_px
    target = directory / session.video_paths[1].with_suffix(".mp4").name
    session.video_paths[1].unlink()
    with av.open(str(target), "w") as out:
        streams = []
        for w, h in [(width // 2, height // 2), (width, height)]:
            stream = out.add_stream("mpeg4", rate=30)
            stream.width, stream.height, stream.pix_fmt = w, h, "yuv420p"
            streams.append(stream)
        for i in range(4):
            for stream in streams:
                frame = av.VideoFrame.from_ndarray(
                    np.full((stream.height, stream.width, 3), 20 * i, np.uint8), "bgr24"
                )
                out.mux(stream.encode(frame))
        for stream in streams:
            out.mux(stream.encode())
    with pytest.raises(
        VideoError, match=rf"frames are {width // 2}x{height // 2} \(the first of its 2 video streams"
    ):
        load_session(directory)


def test_a_variable_rate_video_whose_average_rate_is_not_the_others_is_named_against_them() -> None:
    from pipeline.errors import VideoError
    from pipeline.session.folder import _common_fps
    from pipeline.session.video import VideoInfo

    steady = VideoInfo(Path("s/cam0.mp4"), 320, 240, 30.0, 90)
    uneven = VideoInfo(Path("s/cam1.mp4"), 320, 240, 24.1963, 73, variable_rate="frames 33.3-66.7 ms apart")
    for infos in ([steady, uneven], [uneven, steady]):
        with pytest.raises(VideoError) as raised:
            _common_fps(infos)
        assert str(raised.value) == (
            "s/cam1.mp4: has a variable frame rate (frames 33.3-66.7 ms apart; 24.2 fps on average, "
            "against 30 fps of cam0.mp4); re-export it at a constant rate"
        )


def test_rates_within_the_tolerance_are_named_where_they_part_the_frames(
    caplog: pytest.LogCaptureFixture,
) -> None:
    from pipeline.session.folder import _common_fps, _note_rates_apart
    from pipeline.session.video import VideoInfo

    ntsc = VideoInfo(Path("s/cam1.mp4"), 320, 240, 30000 / 1001, 1800)
    whole = VideoInfo(Path("s/cam0.mp4"), 320, 240, 30.0, 1800)
    assert _common_fps([whole, ntsc]) == 30.0  # one rate, within the tolerance
    with caplog.at_level("WARNING"):
        _note_rates_apart([whole, ntsc], 300)  # 0.3 frames apart by the end: not said
        assert caplog.text == ""
        _note_rates_apart([whole, ntsc], 1800)
    assert "s/cam1.mp4 runs at 29.97 fps and cam0.mp4 at 30 fps" in caplog.text
    assert "by the last frame they are 1.8 frames apart" in caplog.text


def test_a_session_loaded_by_a_relative_path_keeps_its_videos_after_a_chdir(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    build_session(tmp_path / "take", frames=2)
    monkeypatch.chdir(tmp_path)
    session = load_session("take")
    monkeypatch.chdir("/")  # as a notebook does before processing
    assert all(path.is_absolute() and path.is_file() for path in session.video_paths)
    assert session.video_paths[0] == tmp_path / "take" / session.video_paths[0].name
