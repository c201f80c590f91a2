"""The Makefile's process target: the session folder reaches the pipeline as given."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="needs GNU make")


def _process_words(tmp_path: Path, *assignments: str) -> list[str]:
    """The words ``make process ASSIGNMENTS`` passes to the virtualenv's Python, caught by a
    stand-in for it (no virtualenv is made: the install stamp is newer than pyproject.toml)."""
    stand_in = tmp_path / "python"
    stand_in.write_text('#!/bin/sh\nprintf \'%s\\0\' "$@" > "$CAUGHT_WORDS"\n')
    stand_in.chmod(0o755)
    stamp = tmp_path / "installed"
    stamp.touch()
    caught = tmp_path / "words"
    subprocess.run(
        ["make", "-s", "-C", str(ROOT), "process", f"PY={stand_in}", f"STAMP={stamp}", *assignments],
        env={**os.environ, "CAUGHT_WORDS": str(caught)},
        check=True,
        capture_output=True,
        timeout=60,
    )
    return caught.read_text().split("\0")[:-1]


def test_process_gives_the_folder_after_a_double_dash(tmp_path: Path) -> None:
    words = _process_words(tmp_path, "VIDEO_DIR=-x", "ARGS=--force --jobs 2")
    assert words == ["-m", "pipeline", "process", "--out", "recordings", "--force", "--jobs", "2", "--", "-x"]
