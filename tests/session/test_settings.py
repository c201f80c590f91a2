"""session.toml -> Settings: defaults, conversions, and a named error for every bad value."""

from __future__ import annotations

import logging
from datetime import UTC, date, datetime, timedelta, timezone
from pathlib import Path
from typing import Any

import pytest

from pipeline.errors import SettingsError
from pipeline.session.settings import MAX_GRID_BYTES, Settings, Workspace, load_settings, settings_from_dict


def test_no_file_gives_the_defaults(tmp_path: Path) -> None:
    assert load_settings(None) == Settings()
    assert load_settings(tmp_path / "session.toml") == Settings()
    ws = Settings().workspace
    assert ws.shape == (128, 128, 128)  # the original rig: 256 mm at 2 mm


def test_values_are_read_and_converted(tmp_path: Path) -> None:
    path = tmp_path / "session.toml"
    path.write_text(
        "[workspace]\norigin_mm = [-10, 0, 5]\nsize_mm = [100, 50, 20]\nvoxel_mm = 5\n"
        '[silhouette]\nmethod = "otsu"\npolarity = "bright"\nthreshold = 30\n'
        '[manipulator]\nbase_mm = "auto"\nradius_mm = "auto"\n'
        "[session]\nstart_time = 2024-03-01T12:00:00+01:00\n"
    )
    s = load_settings(path)
    assert s.workspace == Workspace(origin_mm=(-10.0, 0.0, 5.0), size_mm=(100.0, 50.0, 20.0), voxel_mm=5.0)
    assert s.workspace.shape == (20, 10, 4)
    assert (s.silhouette.method, s.silhouette.polarity, s.silhouette.threshold) == ("otsu", "bright", 30)
    assert s.manipulator.base_mm is None and s.manipulator.radius_mm is None
    assert s.session.start_time == datetime(2024, 3, 1, 11, 0, tzinfo=UTC)


@pytest.mark.parametrize(
    "value", ["2024-03-01T12:00:00", datetime(2024, 3, 1, 12)], ids=["text", "toml-local-datetime"]
)
def test_start_time_without_zone_is_utc_and_says_so(value: Any, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        s = settings_from_dict({"session": {"start_time": value}})
    assert s.session.start_time == datetime(2024, 3, 1, 12, tzinfo=UTC)
    assert "start_time 2024-03-01T12:00:00 has no UTC offset; taken as UTC (add Z" in caplog.text


@pytest.mark.parametrize(
    ("value", "shown"),
    [(True, "got true"), (date(2026, 1, 1), "got 2026-01-01"), ({"x": 0}, "got a table {x = 0}")],
    ids=["bool", "date", "table"],
)
def test_a_setting_of_the_wrong_type_is_shown_as_toml_writes_it(value: Any, shown: str) -> None:
    with pytest.raises(SettingsError, match=rf"threshold must be .*, {shown}$"):
        settings_from_dict({"silhouette": {"threshold": value}})


def test_start_time_keeps_its_zone() -> None:
    zone = timezone(timedelta(hours=-5))
    s = settings_from_dict({"session": {"start_time": datetime(2024, 3, 1, 7, tzinfo=zone)}})
    assert s.session.start_time == datetime(2024, 3, 1, 12, tzinfo=UTC)


def test_memory_estimate_is_exact() -> None:
    ws = Workspace(size_mm=(10.0, 20.0, 30.0), voxel_mm=1.0)
    # 6000 voxels x (int32 index per camera x 3 + float32 centre x 3 + 1 mask byte).
    assert ws.estimated_bytes(3) == 6000 * (12 + 12 + 1)


def test_a_fine_grid_under_the_limit_is_accepted() -> None:
    # 1.5 mm over 256 mm: 171^3 voxels, about 0.12 GiB, far below the limit.
    s = settings_from_dict({"workspace": {"voxel_mm": 1.5}})
    assert s.workspace.estimated_bytes(3) < MAX_GRID_BYTES


@pytest.mark.parametrize("base_mm", [[128, 128, 0], [0, 256, 100], [128, 128, -17]])
def test_a_base_in_the_box_or_just_below_its_floor_is_accepted(base_mm: list[float]) -> None:
    # Three tube radii (18 mm) of slack: a mount under a box that leaves the mount out.
    doc = {"manipulator": {"base_mm": base_mm, "radius_mm": 6.0}}
    assert settings_from_dict(doc).manipulator.base_mm == tuple(base_mm)


@pytest.mark.parametrize(
    ("doc", "needles"),
    [
        ({"workspace": {"voxel_mm": 0}}, ("voxel_mm", "> 0")),
        ({"workspace": {"voxel_mm": -2.0}}, ("voxel_mm", "> 0")),
        ({"workspace": {"voxel_mm": 1e-320}}, ("grid needs about inf GiB", "raise voxel_mm")),
        ({"workspace": {"voxel_mm": 0.2}}, ("1280x1280x1280", "48.8 GiB", "limit 4 GiB")),
        # 7.6 GiB estimated, and a run of it took 17 GB.
        ({"workspace": {"voxel_mm": 0.38}}, ("674x674x674", "limit 4 GiB")),
        ({"workspace": {"size_mm": [1, 0, 1]}}, ("size_mm", "> 0")),
        ({"workspace": {"origin_mm": [1, 2]}}, ("origin_mm", "list of 3 numbers")),
        ({"workspace": {"origin_mm": [1, 2, "x"]}}, ("origin_mm", "finite number")),
        ({"workspace": {"voxel_mm": float("nan")}}, ("voxel_mm", "finite number")),
        ({"workspace": {"voxel_mm": True}}, ("voxel_mm", "finite number")),
        ({"workspace": 3}, ("[workspace]", "table")),
        ({"silhouette": {"method": "magic"}}, ("'magic'", "threshold", "otsu", "background")),
        ({"silhouette": {"polarity": "grey"}}, ("'grey'", "dark", "bright")),
        ({"silhouette": {"threshold": 256}}, ("threshold", "1-254", "256")),
        ({"silhouette": {"threshold": 255}}, ("threshold", "1-254", "255")),
        ({"silhouette": {"threshold": 0}}, ("threshold", "1-254", "got 0")),
        ({"silhouette": {"threshold": 60.5}}, ("threshold", "integer")),
        ({"silhouette": {"min_area_px": -1}}, ("min_area_px", ">= 0")),
        ({"manipulator": {"radius_mm": 0}}, ("radius_mm", "0.1-100", "millimetres")),
        ({"manipulator": {"radius_mm": 0.005}}, ("radius_mm", "0.1-100", "got 0.005")),
        ({"manipulator": {"radius_mm": 6000}}, ("radius_mm", "0.1-100", "got 6000")),
        (
            {"workspace": {"voxel_mm": 60}, "manipulator": {"radius_mm": 6}},
            ("voxel_mm 60 is more than 2 times", "radius_mm 6", "at most 12, or correct radius_mm"),
        ),
        (
            {"workspace": {"voxel_mm": 100}, "manipulator": {"radius_mm": "auto"}},
            ("voxel_mm 100", "fewer than 4 voxels", "256 mm", "at most 64"),
        ),
        ({"session": {"start_time": "1969-12-31T23:59:59Z"}}, ("1969-12-31", "1970-01-01..2262")),
        ({"session": {"start_time": "2300-01-01T00:00:00Z"}}, ("start_time", "2300-01-01", "give a date")),
        ({"manipulator": {"base_mm": "middle"}}, ("base_mm", "list of 3 numbers", '"auto"')),
        ({"manipulator": {"radius_mm": "Auto"}}, ("radius_mm", 'a number (mm) or "auto"', '"Auto"')),
        ({"manipulator": {"base_mm": [128, 128, -50]}}, ("base_mm [128.0, 128.0, -50.0]", "0..256 x")),
        ({"workspace": {"origin_mm": [0, 0, 40]}}, ("base_mm", "outside the workspace box", "40..296")),
        ({"centerline": {"method": "spline"}}, ("'spline'", "fit", "polyfit")),
        ({"centerline": {"points": 3}}, ("points", "32-1024", "slow every frame")),
        ({"centerline": {"points": 16}}, ("points", "32-1024")),
        ({"centerline": {"points": 10000}}, ("points", "32-1024")),
        ({"session": {"start_time": "yesterday"}}, ("start_time", "RFC 3339")),
        ({"workspace": {"voxel": 2}}, ("unknown key [workspace] 'voxel'", "origin_mm, size_mm, voxel_mm")),
        (
            {"silhouete": {}},
            ("unknown key 'silhouete'", "centerline, live, manipulator, session, silhouette"),
        ),
        ({"manipulator": {"radius": 6.0}}, ("[manipulator] 'radius' (did you mean 'radius_mm'?)",)),
        ({"manipulater": {}}, ("unknown key 'manipulater' (did you mean 'manipulator'?)",)),
        ({"threshold": 92}, ("unknown key 'threshold' (a key of [silhouette]: put it under [silhouette])",)),
        ({"workspace": {"radius_mm": 6.0}}, ("[workspace] 'radius_mm' (a key of [manipulator]: put it",)),
        ({"workspace": {"xyz": 1}}, ("unknown key [workspace] 'xyz'; allowed: origin_mm",)),
        (
            {"method": "otsu"},
            ("'method' (a key of [silhouette] and [centerline]: put it under one of them)",),
        ),
    ],
    ids=lambda v: "-".join(f"{k}:{v[k]}" for k in v) if isinstance(v, dict) else "",
)
def test_bad_values_name_the_key(doc: dict[str, Any], needles: tuple[str, ...]) -> None:
    with pytest.raises(SettingsError) as info:
        settings_from_dict(doc, source="s/session.toml")
    message = str(info.value)
    assert message.startswith("s/session.toml: ")
    for needle in needles:
        assert needle in message


def test_unreadable_file_is_a_settings_error(tmp_path: Path) -> None:
    (tmp_path / "session.toml").mkdir()  # a directory where a file should be
    with pytest.raises(SettingsError, match=r"session\.toml: cannot read"):
        load_settings(tmp_path / "session.toml")
