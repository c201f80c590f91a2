"""The folder a synthetic render writes into: new, empty, or an earlier render of the same command."""

from __future__ import annotations

import contextlib
import errno
import shutil
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from ..errors import UNFINISHED_RENDER, PipelineError, refuse_link_to_nothing, refuse_unexpanded_home


def check_out_dir(out_dir: Path, *, command: str, contents: str, marker: str, kind: str) -> None:
    """Refuse ``out_dir`` unless it is new, empty, or an earlier render of ``command`` (it
    holds ``marker``, a file only that render writes, or the mark of a render stopped
    part-way, see :func:`unfinished`): never a folder of the user's own files.

    contents : what the render writes, for the message ("the session").
    kind : what an earlier render is called, for the message ("a synthetic session").
    """
    refuse_unexpanded_home(out_dir, command)
    refuse_link_to_nothing(out_dir, command)
    if out_dir.exists() and not out_dir.is_dir():
        raise PipelineError(f"{out_dir}: is a file; give {command} a directory to write {contents} in")
    earlier = (out_dir / marker).is_file() or (out_dir / UNFINISHED_RENDER).is_file()
    if out_dir.is_dir() and any(out_dir.iterdir()) and not earlier:
        raise PipelineError(
            f"{out_dir}: holds files and is not {kind} (no {marker}); give {command} a new or empty directory"
        )


def write_image(path: Path, image: NDArray[np.uint8]) -> None:
    """Write ``image`` ((H, W) uint8 grey levels) to ``path``; OSError where OpenCV does not
    (it only returns False: a full disk, a folder in the file's place)."""
    if not cv2.imwrite(str(path), image):
        raise OSError(errno.EIO, "OpenCV wrote no image: a full disk, or a folder in its place?", str(path))


def left_behind(out_dir: Path, created: bool, incomplete: str) -> str:
    """What a render into ``out_dir`` that stopped part-way leaves, for its message: "nothing
    written" where the render made the folder (it is removed here); the earlier render
    unchanged where the render stopped before marking it (:func:`unfinished`: a folder
    that takes no file); else ``incomplete`` (the earlier render it partly replaced, and
    what to do)."""
    if created:
        shutil.rmtree(out_dir, ignore_errors=True)
        return "nothing written"
    if not (out_dir / UNFINISHED_RENDER).exists():
        return f"the earlier render in {out_dir} is unchanged"
    return incomplete


def write_advice(exc: OSError) -> str:
    """What to do where ``exc`` stopped a render's writing: a folder that takes no file
    (read-only, not this user's) wants another; anything else may be a full disk."""
    if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
        return "give a directory you can write to"
    return "free space, or give another directory"


@contextlib.contextmanager
def unfinished(out_dir: Path) -> Iterator[None]:
    """Mark ``out_dir`` (which exists) as a render in progress for the block: the mark
    (``UNFINISHED_RENDER``) is removed only when the block finishes, so that a render
    stopped part-way (an error, Ctrl-C, a kill) leaves a folder that every reader refuses."""
    (out_dir / UNFINISHED_RENDER).write_text(
        "A synthetic render is writing this folder, or stopped before it finished.\n"
        "Its files are not a whole render: render it again.\n"
    )
    yield
    (out_dir / UNFINISHED_RENDER).unlink()
