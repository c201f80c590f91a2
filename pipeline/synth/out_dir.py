"""The folder a synthetic render writes into: new, empty, or an earlier render of the same command."""

from __future__ import annotations

from pathlib import Path

from ..errors import PipelineError


def check_out_dir(out_dir: Path, *, command: str, contents: str, marker: str, kind: str) -> None:
    """Refuse ``out_dir`` unless it is new, empty, or an earlier render of ``command`` (it
    holds ``marker``, a file only that render writes): never a folder of the user's own files.

    contents : what the render writes, for the message ("the session").
    kind : what an earlier render is called, for the message ("a synthetic session").
    """
    if out_dir.exists() and not out_dir.is_dir():
        raise PipelineError(f"{out_dir}: is a file; give {command} a directory to write {contents} in")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not (out_dir / marker).is_file():
        raise PipelineError(
            f"{out_dir}: holds files and is not {kind} (no {marker}); give {command} a new or empty directory"
        )
