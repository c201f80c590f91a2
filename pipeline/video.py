"""Video files: probing, and reading a contiguous range of frames.

Kept apart from the array code: everything downstream receives (H, W) uint8 grey
images and never a path.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from .errors import VideoError

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mkv", ".mov", ".m4v")

# A damaged or half-copied video is reported by us, once, naming the file; OpenCV's and
# FFmpeg's own lines ("moov atom not found", "overread 8") would bury that message and
# repeat for every bad frame. FFmpeg reads its level when first used, so this also holds
# in worker processes; set OPENCV_FFMPEG_LOGLEVEL yourself (e.g. 24) to see them again.
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET
cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


@dataclass(frozen=True)
class VideoInfo:
    path: Path
    width: int
    height: int
    fps: float
    frame_count: int


def probe_video(path: Path) -> VideoInfo:
    """Open ``path`` and read its size, fps and frame count; VideoError if it is not a video."""
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    try:
        if not cap.isOpened():
            raise VideoError(
                f"{path}: cannot be opened as a video (empty, unreadable, copied half-way "
                "or not a video); re-copy or re-export it"
            )
        width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        ok, _ = cap.read()
        if not ok or width <= 0 or height <= 0:
            raise VideoError(f"{path}: holds no decodable frame; re-copy or re-export it")
        if not fps > 0:
            raise VideoError(f"{path}: has no frame rate; re-export it with a fixed fps")
    finally:
        cap.release()
    return VideoInfo(path=Path(path), width=width, height=height, fps=fps, frame_count=max(count, 1))


def read_frames(path: Path, start: int, stop: int) -> Iterator[tuple[int, NDArray[np.uint8] | None]]:
    """Yield ``(index, grey image or None)`` for frames ``start <= index < stop``.

    None marks a frame that could not be decoded (a truncated or damaged file);
    frames are positioned exactly (decoded from the start or a seek verified by
    the reported position), so frame ``i`` is the i-th frame of the file.
    """
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    try:
        if not cap.isOpened():
            for i in range(start, stop):
                yield i, None
            return
        _seek(cap, start)
        for i in range(start, stop):
            ok, frame = cap.read()
            if not ok or frame is None:
                yield i, None
                continue
            if frame.ndim == 3:
                frame = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
            yield i, np.asarray(frame, dtype=np.uint8)  # no copy: already uint8 (typed for mypy)
    finally:
        cap.release()


def _seek(cap: cv2.VideoCapture, start: int) -> None:
    """Place ``cap`` so that the next read returns frame ``start``."""
    if start <= 0:
        return
    cap.set(cv2.CAP_PROP_POS_FRAMES, start)
    if int(cap.get(cv2.CAP_PROP_POS_FRAMES)) == start:
        return
    # The container could not seek exactly: decode from the beginning instead.
    cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
    for _ in range(start):
        if not cap.grab():
            return
