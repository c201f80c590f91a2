"""The marker a run leaves beside its outputs while it renames the pair into place.

``.<session>.<run>.commit`` exists only between a run's two renames (the .mcap, then the
.rrd; :meth:`pipeline.run.output_target.OutputTarget.commit`): one still there means that run was
killed between them, and the folder may hold its new .mcap beside an earlier .rrd until the
next run of the session there puts the rest in place. Kept apart from
:mod:`pipeline.run.outputs` so that the loader can look for it without the writers' imports.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

_SUFFIX = ".commit"


def marker_path(out_dir: Path, name: str, run: str) -> Path:
    """The marker of run ``run`` (no dots in it) of session ``name`` in ``out_dir``."""
    return out_dir / f".{name}.{run}{_SUFFIX}"


def marker_run(marker: Path, name: str) -> str:
    """The run a marker of session ``name`` names."""
    return marker.name[len(f".{name}.") : -len(_SUFFIX)]


def killed_commits(out_dir: Path, name: str) -> list[Path]:
    """The markers of runs of ``name`` killed while putting their pair in place in ``out_dir``."""
    prefix = f".{name}."
    with contextlib.suppress(OSError):
        return sorted(
            Path(entry.path)
            for entry in os.scandir(out_dir)
            if entry.name.startswith(prefix)
            and entry.name.endswith(_SUFFIX)
            # not another session's whose name is this one's and a dot and more
            and "." not in entry.name[len(prefix) : -len(_SUFFIX)]
        )
    return []
