"""The Makefile's process target: the session folder reaches the pipeline as given."""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Mapping
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="needs GNU make")


def _process_words(tmp_path: Path, *assignments: str, env: dict[str, str] | None = None) -> list[str]:
    """The words ``make process ASSIGNMENTS`` (with ``env`` added to the environment) passes
    to the virtualenv's Python, caught by a stand-in for it (no virtualenv is made: the
    install stamp is newer than pyproject.toml)."""
    stand_in = tmp_path / "python"
    stand_in.write_text('#!/bin/sh\nprintf \'%s\\0\' "$@" > "$CAUGHT_WORDS"\n')
    stand_in.chmod(0o755)
    stamp = tmp_path / "installed"
    stamp.touch()
    caught = tmp_path / "words"
    subprocess.run(
        ["make", "-s", "-C", str(ROOT), "process", f"PY={stand_in}", f"STAMP={stamp}", *assignments],
        env={**_without_outer_make(os.environ), **(env or {}), "CAUGHT_WORDS": str(caught)},
        check=True,
        capture_output=True,
        timeout=60,
    )
    return caught.read_text().split("\0")[:-1]


def _without_outer_make(environ: Mapping[str, str]) -> dict[str, str]:
    """``environ`` without what a make running these tests (``make test ARGS=...``) hands
    down to the make under test, and without a VIDEO_DIR of its own."""
    return {k: v for k, v in environ.items() if k not in ("MAKEFLAGS", "MFLAGS", "MAKELEVEL", "VIDEO_DIR")}


def test_process_gives_the_folder_after_a_double_dash(tmp_path: Path) -> None:
    words = _process_words(tmp_path, "VIDEO_DIR=-x", "ARGS=--force --jobs 2")
    assert words == ["-m", "pipeline", "process", "--out", "recordings", "--force", "--jobs", "2", "--", "-x"]


@pytest.mark.parametrize(
    "video_dir",
    ["s$x", "s$$x", 's "1"', "s$(x", "it's", "s #1", "s\\1 2"],
    ids=["dollar", "two-dollars", "quotes", "open-reference", "apostrophe", "hash", "backslash-space"],
)
def test_process_gives_the_folder_as_written(tmp_path: Path, video_dir: str) -> None:
    assert _process_words(tmp_path, f"VIDEO_DIR={video_dir}")[-1] == video_dir


def test_process_reads_the_folder_from_the_environment_as_written(tmp_path: Path) -> None:
    assert _process_words(tmp_path, env={"VIDEO_DIR": 'a$x"b'})[-1] == 'a$x"b'
