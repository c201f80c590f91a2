"""Videos in other cameras' places are named before any work: the hull tells them apart."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.calibrate.background_order import check_background_order, scene_correlations
from pipeline.calibrate.video_order import check_video_order
from pipeline.errors import SessionError
from pipeline.reconstruct.frame import build_model
from pipeline.reconstruct.frame_task import decode_frames
from pipeline.session.folder import load_session
from pipeline.synth import render_session
from pipeline.synth.session_render import SceneOptions


@pytest.fixture(scope="module", params=[(1, "oblique"), (2, "ninety")], ids=["seed1-oblique", "seed2-ninety"])
def session(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    seed, arrangement = request.param
    directory = tmp_path_factory.mktemp("order") / "take"
    options = SceneOptions(distractor=False)
    render_session(
        directory,
        shape="random",
        frames=6,
        seed=seed,
        arrangement=arrangement,
        options=options,
        progress=False,
        jobs=1,
    )
    return directory


def _check(directory: Path) -> None:
    session = load_session(directory)
    frames = decode_frames(session.video_paths, range(session.frame_count))
    check_video_order(build_model(session), frames, session.video_paths)


def test_videos_as_their_cameras_pass(session: Path) -> None:
    _check(session)


def test_two_videos_swapped_are_named(session: Path, tmp_path: Path) -> None:
    swapped = tmp_path / "take"
    swapped.mkdir()
    for item in session.iterdir():
        name = {"cam1.mp4": "cam2.mp4", "cam2.mp4": "cam1.mp4"}.get(item.name, item.name)
        (swapped / name).symlink_to(item)
    with pytest.raises(SessionError) as info:
        _check(swapped)
    message = str(info.value)
    assert "the videos do not match their cameras in calibration.toml" in message
    assert "cam2.mp4 looks like cam1's view" in message and "cam1.mp4 looks like cam2's view" in message
    assert "cam0.mp4" not in message


def test_cameras_of_other_sizes_are_not_taken_for_each_other(session: Path) -> None:
    # cam2 films at twice the size (its images and its calibration both): no order may give
    # its video to another camera, while the other two are still checked against each other.
    import dataclasses

    import cv2

    loaded = load_session(session)
    big = loaded.cameras[2]
    big = dataclasses.replace(
        big, size_px=(2 * big.width, 2 * big.height), matrix=big.matrix * [[2], [2], [1]]
    )
    model = build_model(dataclasses.replace(loaded, cameras=(*loaded.cameras[:2], big)))
    frames = [
        (i, [images[0], images[1], cv2.resize(images[2], big.size_px, interpolation=cv2.INTER_LINEAR)])
        for i, images in decode_frames(loaded.video_paths, range(loaded.frame_count))
    ]
    check_video_order(model, frames, loaded.video_paths)  # as named: passes
    swapped = [(i, [images[1], images[0], images[2]]) for i, images in frames]
    with pytest.raises(SessionError, match=r"cam1\.mp4 looks like cam0's view"):
        check_video_order(model, swapped, loaded.video_paths)


def test_frames_with_a_view_that_is_mostly_silhouette_are_not_carved(
    session: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A threshold on the wrong side of the scene makes a view nearly all silhouette: such
    # frames fail on their own, named, and their hull (the whole workspace) is not carved
    # here for every order of the videos.
    import dataclasses

    from pipeline.calibrate import video_order

    loaded = load_session(session)
    silhouette = dataclasses.replace(loaded.settings.silhouette, polarity="bright")
    model = build_model(
        dataclasses.replace(loaded, settings=dataclasses.replace(loaded.settings, silhouette=silhouette))
    )
    carved: list[int] = []
    monkeypatch.setattr(video_order, "explained_share", lambda *args: carved.append(1) or 0.0)
    frames = decode_frames(loaded.video_paths, range(loaded.frame_count))
    check_video_order(model, frames, loaded.video_paths)
    assert carved == []
    # Frames that show a tube are still compared (the check is not switched off).
    check_video_order(build_model(loaded), frames, loaded.video_paths)
    assert carved


# --- background images (pipeline.calibrate.background_order) -----------------------------


def _background_take(session: Path, target: Path, renamed: dict[str, str] | None = None) -> Path:
    """``session`` linked into ``target`` with its silhouettes by background subtraction (the
    only method its backgrounds are read for), each background under ``renamed``'s name."""
    (target / "background").mkdir(parents=True)
    for item in session.iterdir():
        if item.name not in ("background", "session.toml"):
            (target / item.name).symlink_to(item)
    settings = (session / "session.toml").read_text()
    (target / "session.toml").write_text(settings.replace('method = "threshold"', 'method = "background"'))
    for item in (session / "background").iterdir():
        (target / "background" / (renamed or {}).get(item.name, item.name)).symlink_to(item)
    return target


def _check_backgrounds(directory: Path) -> None:
    session = load_session(directory)
    frames = decode_frames(session.video_paths, range(session.frame_count))
    names = [c.name for c in session.cameras]
    check_background_order(session.backgrounds, frames, names, directory / "background")


def test_backgrounds_as_their_cameras_pass_and_match_their_own_scene_alone(
    session: Path, tmp_path: Path
) -> None:
    take = _background_take(session, tmp_path / "take")
    _check_backgrounds(take)
    loaded = load_session(take)
    frames = decode_frames(loaded.video_paths, range(loaded.frame_count))
    correlation = scene_correlations([b for b in loaded.backgrounds if b is not None], frames)
    own = np.diag(correlation)
    assert own.min() > 0.7  # the scene, with the moving tube left out by the median
    assert np.abs(correlation[~np.eye(len(own), dtype=bool)]).max() < 0.35


def test_two_backgrounds_swapped_are_named(session: Path, tmp_path: Path) -> None:
    swapped = _background_take(session, tmp_path / "take", {"cam0.png": "cam2.png", "cam2.png": "cam0.png"})
    with pytest.raises(SessionError) as info:
        _check_backgrounds(swapped)
    message = str(info.value)
    assert message.startswith(f"{swapped / 'background'}: the background images do not match their cameras: ")
    assert "cam0.png looks like cam2's scene" in message and "cam2.png looks like cam0's scene" in message
    assert "cam1.png" not in message and message.endswith("take each camera's background again")
