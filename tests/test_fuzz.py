"""Fuzz the loaders: any session.toml or calibration.toml is accepted or a PipelineError.

Nothing else may escape (a TypeError, an OverflowError, a numpy warning turned error):
the CLI shows a PipelineError as one line, anything else as a traceback.
"""

from __future__ import annotations

from datetime import UTC, date, datetime, time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import rig_cameras
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.errors import PipelineError
from pipeline.session.calibration_io import calibration_dict, cameras_from_dict, read_calibration
from pipeline.session.settings import _SECTIONS, Settings, load_settings, settings_from_dict

# Bounded so the whole module stays within a few seconds; derandomized so that CI
# runs the same examples every time (a fixed seed, like every other test).
FUZZ = settings(
    max_examples=200,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)

# Every value TOML can hold, with the awkward ones over-represented: huge integers
# (beyond float range), tiny and non-finite floats, dates and times, nesting.
scalars = st.one_of(
    st.booleans(),
    st.integers(),
    st.sampled_from([0, -1, 10**400, -(10**400), 2**63]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e-320, 5e-324, 1e308, float("nan"), float("inf")]),
    st.text(max_size=8),
    st.sampled_from(["auto", "threshold", "otsu", "background", "dark", "bright", "fit", "polyfit"]),
    st.datetimes(timezones=st.just(UTC) | st.none()),
    st.dates(),
    st.times(),
)
values = st.recursive(
    scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=12,
)
numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(),
    st.sampled_from([10**400, 1e-320, 0]),
)


def assert_one_readable_line(exc: PipelineError) -> None:
    """The CLI prints the message as one line: no newlines, no 300-digit echo of a value."""
    message = str(exc)
    assert "\n" not in message and len(message) < 400, message


def _section_values(cls: type) -> st.SearchStrategy[dict[str, Any]]:
    """Dicts over a section's real keys (plus a typo now and then) with plausible or wild values."""
    keys = [*cls.__dataclass_fields__, "typo"]
    plausible = st.one_of(numbers, st.lists(numbers, min_size=3, max_size=3), values)
    return st.dictionaries(st.sampled_from(keys), plausible, max_size=4)


session_docs = st.fixed_dictionaries(
    {},
    optional={name: _section_values(cls) | values for name, cls in _SECTIONS.items()},
) | st.dictionaries(st.text(max_size=10), values, max_size=3)


@FUZZ
@given(doc=session_docs)
def test_settings_from_dict_accepts_or_raises_pipeline_error(doc: dict[str, Any]) -> None:
    try:
        result = settings_from_dict(doc)
    except PipelineError as exc:
        assert_one_readable_line(exc)
        return
    assert isinstance(result, Settings)
    assert result.workspace.voxel_mm > 0


def _camera_table(i: int = 0) -> dict[str, Any]:
    return calibration_dict(rig_cameras()[i : i + 1])["cam_0"]


CAMERA_KEYS = list(_camera_table())


@st.composite
def calibration_docs(draw: st.DrawFn) -> dict[str, Any]:
    """A valid three-camera calibration with a few keys replaced, removed or retyped."""
    doc: dict[str, Any] = {f"cam_{i}": _camera_table(i) for i in range(3)}
    for _ in range(draw(st.integers(1, 3))):
        table = doc[f"cam_{draw(st.integers(0, 2))}"]
        key = draw(st.sampled_from(CAMERA_KEYS))
        action = draw(st.sampled_from(["replace", "delete", "perturb"]))
        if action == "delete":
            table.pop(key, None)
        elif action == "replace":
            table[key] = draw(values | numbers | st.lists(numbers, max_size=4))
        elif isinstance(table.get(key), list):
            flat = np.asarray(table[key], dtype=object).ravel()
            if flat.size:  # an earlier "replace" may have left an empty list
                flat[draw(st.integers(0, flat.size - 1))] = draw(numbers | scalars)
                table[key] = flat.reshape(np.shape(table[key])).tolist()
    if draw(st.booleans()):
        doc[draw(st.text(max_size=6))] = draw(values)
    return doc


@FUZZ
@given(doc=calibration_docs() | st.dictionaries(st.text(max_size=6), values, max_size=3))
def test_cameras_from_dict_accepts_or_raises_pipeline_error(doc: dict[str, Any]) -> None:
    try:
        cameras = cameras_from_dict(doc)
    except PipelineError as exc:
        assert_one_readable_line(exc)
        return
    for cam in cameras:
        assert np.isfinite(cam.matrix).all() and np.isfinite(cam.rotation).all()
        assert cam.matrix.shape == (3, 3) and cam.translation_mm.shape == (3,)


# Random TOML-ish bytes (not always UTF-8): fragments of real documents glued with noise, so the parser's
# error paths and the loaders' type checks are both reached.
_FRAGMENTS = [
    "[workspace]\n",
    "[silhouette]\n",
    "[cam_0]\n",
    "[metadata]\n",
    'name = "cam0"\n',
    "size = [320, 240]\n",
    "voxel_mm = ",
    "origin_mm = [",
    "1e999",
    "nan",
    "-inf",
    "99999999999999999999999",
    "1979-05-27T07:32:00Z",
    "]",
    "\n",
    '"',
    "= ",
    ",",
    "{a = 1}",
]
toml_bytes = st.lists(
    st.sampled_from([f.encode() for f in _FRAGMENTS]) | st.binary(max_size=6), max_size=14
).map(b"".join)


@FUZZ
@given(content=toml_bytes)
def test_loaders_accept_or_raise_pipeline_error_on_random_bytes(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "doc.toml"
    path.write_bytes(content)
    for load in (load_settings, read_calibration):
        try:
            load(path)
        except PipelineError as exc:
            assert str(path) in str(exc)  # every message names the file
            assert_one_readable_line(exc)


@pytest.mark.parametrize(
    "value",
    [10**400, 1e-320, datetime(2024, 1, 1, tzinfo=UTC), date(2024, 1, 1), time(12, 0), {"a": 1}],
    ids=repr,
)
def test_voxel_mm_edge_values_are_pipeline_errors(value: Any) -> None:
    # The examples hypothesis found first, kept as plain regression tests.
    with pytest.raises(PipelineError, match="voxel_mm"):
        settings_from_dict({"workspace": {"voxel_mm": value}})


@pytest.mark.parametrize("value", [10**400, -(10**400)], ids=["huge", "-huge"])
def test_huge_integer_in_calibration_is_a_calibration_error(value: int) -> None:
    table = _camera_table()
    table["translation"] = [value, 0, 0]
    with pytest.raises(PipelineError, match="translation"):
        cameras_from_dict({"cam_0": table})


def test_utf16_file_is_named_as_not_utf8(tmp_path: Path) -> None:
    # What some Windows editors save: found by the byte fuzzer as a UnicodeDecodeError.
    path = tmp_path / "calibration.toml"
    path.write_text("[cam_0]\n", encoding="utf-16")
    for load in (load_settings, read_calibration):
        with pytest.raises(PipelineError, match=r"calibration\.toml: is not UTF-8 text; save it as UTF-8"):
            load(path)
