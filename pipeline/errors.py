"""The user's mistakes, as one exception family.

Every error a user can fix (a missing file, a bad calibration, a setting out of
range) is a :class:`PipelineError` whose message names the file, camera or frame
and says what to do. The CLI prints it as one line and exits with status 2.
"""

from __future__ import annotations


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


class EvaluationError(PipelineError):
    """A recording or ground truth cannot be evaluated (missing, unreadable, mismatched)."""


class RecordingError(PipelineError):
    """A recording (MCAP) cannot be read."""


class Interrupted(KeyboardInterrupt):
    """A run stopped by Ctrl-C or a signal, after cleaning up; the message says what is left."""
