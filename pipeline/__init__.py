"""3-D shape of a continuum manipulator from three calibrated cameras.

Public API::

    session = pipeline.load_session("path/to/session")
    summary = pipeline.process_session(session, out_dir="recordings")
    rec = pipeline.load_recording("recordings/session.mcap")
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .errors import PipelineError

if TYPE_CHECKING:
    from .session.folder import Session, load_session

__all__ = ["PipelineError", "Session", "load_recording", "load_session", "process_session"]


def __getattr__(name: str) -> Any:
    # Lazy: importing pipeline must not pull in rerun, mcap and joblib, nor OpenCV
    # (``pipeline process`` starts its workers before it imports anything heavy).
    if name in ("Session", "load_session"):
        from .session import folder as session

        return getattr(session, name)
    if name == "process_session":
        from .run.runner import process_session

        return process_session
    if name == "load_recording":
        from .record.load import load_recording

        return load_recording
    raise AttributeError(f"module 'pipeline' has no attribute {name!r}")


def __dir__() -> list[str]:
    """The public API beside the module's own names: what tab completion and help() show."""
    return sorted({*globals(), *__all__})
