"""The synthetic three-camera renderer: our demo and the independent test oracle.

It shares no projection or carving code with the reconstruction modules.
"""

from __future__ import annotations

from typing import Any

__all__ = ["render_calibration_views", "render_session"]


def __getattr__(name: str) -> Any:
    if name == "render_session":
        from .session_render import render_session

        return render_session
    if name == "render_calibration_views":
        from .boards import render_calibration_views

        return render_calibration_views
    raise AttributeError(name)
