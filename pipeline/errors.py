"""The user's mistakes, as one exception family.

Every error a user can fix (a missing file, a bad calibration, a setting out of
range) is a :class:`PipelineError` whose message names the file, camera or frame
and says what to do. The CLI prints it as one line and exits with status 2.
"""

from __future__ import annotations

import os
from pathlib import Path

# The file a synthetic render (``pipeline synth``, ``synth-calib``) keeps in its folder
# while it writes there, and leaves behind if it stops part-way: a folder holding it is
# neither the earlier render nor the new one, and no reader takes it for a whole one.
UNFINISHED_RENDER = "UNFINISHED-RENDER.txt"


class PipelineError(Exception):
    """Base class for every error the user can fix; the message is shown as is."""


class SessionError(PipelineError):
    """The session directory, its videos or its session.toml are unusable."""


class CalibrationError(PipelineError):
    """calibration.toml (or calibration images) cannot be used."""


class SettingsError(PipelineError):
    """A setting in session.toml is unknown or out of range."""


class VideoError(PipelineError):
    """A video cannot be opened or disagrees with the calibration."""


class OutputError(PipelineError):
    """An output cannot be written (exists, not writable, disk full)."""


class WorkersError(PipelineError):
    """The workers could reconstruct no frame at all (every one killed, or the scheduler's gone)."""


class EvaluationError(PipelineError):
    """A recording or ground truth cannot be evaluated (missing, unreadable, mismatched)."""


class RecordingError(PipelineError):
    """A recording (MCAP) cannot be read."""


class Interrupted(KeyboardInterrupt):
    """A run stopped by Ctrl-C or a signal, after cleaning up; the message says what is left."""


def refuse_unfinished_render(folder: Path, error: type[PipelineError]) -> None:
    """Raise ``error`` naming ``folder`` where a synthetic render stopped part-way there
    (it holds :data:`UNFINISHED_RENDER`)."""
    if (folder / UNFINISHED_RENDER).is_file():
        raise error(
            f"{folder}: a synthetic render stopped part-way here ({UNFINISHED_RENDER}); render it again"
        )


def home_meant(path: Path) -> Path | None:
    """The path a ``path`` starting with a ``~`` that no shell expanded means (zsh in
    ``make process VIDEO_DIR=~/s``, ``--out=~/x``, a quoted path, Python's own string):
    ``path`` with the home folder in its place; None where it starts with no ``~``, is
    there as it is, or names no user of this machine."""
    if not path.parts or not path.parts[0].startswith("~") or path.exists():
        return None
    try:
        meant = path.expanduser()
    except RuntimeError:  # ~name of no user on this machine
        return None
    return meant if meant != path else None


def refuse_unexpanded_home(path: Path, option: str) -> None:
    """Raise OutputError where the output ``path`` starts with a ``~`` no shell expanded
    (:func:`home_meant`): written as it is, it would make a folder named ``~`` here, which
    a later ``rm -rf ~`` would take for home. ``option``: what gives the path ("-o", "--out")."""
    meant = home_meant(path)
    if meant is not None:
        raise OutputError(
            f"{path}: ~ is not expanded here (it would make a folder named ~); give {option} {meant}"
        )


def refuse_link_to_nothing(path: Path, option: str) -> None:
    """Raise OutputError where the output ``path``, or a folder above it, is a symbolic link
    to nothing (a drive not mounted, a folder moved): making it would fail with "File exists",
    which says nothing of the link. ``option``: what gives the path ("--out")."""
    for folder in (path, *path.parents):
        if folder.is_symlink() and not folder.exists():
            raise OutputError(
                f"{folder}: is a symbolic link to {os.readlink(folder)}, which does not exist; fix the "
                f"link (mount the drive), or give {option} another folder"
            )
