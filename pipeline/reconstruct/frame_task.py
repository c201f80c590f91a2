"""One task of a run: decode a contiguous range of frames and reconstruct them.

Runs in the worker processes. A task opens the videos itself, decodes only its
frames and returns, per frame, the small :class:`~pipeline.reconstruct.frame_result.FrameResult`
plus compressed media (JPEG images, 1-bit PNG silhouettes): no full-resolution
frame crosses a process boundary.
"""

from __future__ import annotations

import dataclasses
import struct
import time
import zlib
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from ..session.video import read_frames
from .frame_result import FrameResult
from .tracking import LENGTH_FRAMES, WARMUP_FRAMES, segment_start, starts_next_track, track_start

JPEG_QUALITY = 85
# Silhouettes are drawn over the camera image in Rerun: a translucent tint (RGBA).
SILHOUETTE_RGBA = (0, 200, 255, 110)

Mask = NDArray[np.bool_]
Image = NDArray[np.uint8]
# (frame index, grey images in camera order, model[, the track's last results]) ->
# (result, silhouettes or None); the last argument only for a tracked process_range.
FrameFunction = Callable[..., tuple[FrameResult, Sequence[Mask] | None]]
# A session's sample frames, (index, data) each: the frame's grey images, or what was read
# of them; a function of one of them and the model; and what runs it on each of the frames
# and returns the results in order: map_here in this process, or a run's workers
# (pipeline.run.workers.local_frame_map), for which the function must be a module-level one.
Frames = Sequence[tuple[int, Any]]
PerFrame = Callable[[int, Any, Any], Any]
FrameMap = Callable[[PerFrame, Frames, Any], list[Any]]


def map_here(fn: PerFrame, frames: Frames, model: Any) -> list[Any]:
    """``fn(index, images, model)`` for each of ``frames``, in order, in this process."""
    return [fn(index, images, model) for index, images in frames]


@dataclass(frozen=True, eq=False)
class FrameOutput:
    """What a task returns per frame: the result and small, compressed media.

    jpegs : per camera JPEG bytes of the grey frame (b"" when not decoded), or None
        when images are disabled.
    silhouettes_png : per camera RGBA PNG bytes of the tinted silhouette, or None.
    """

    result: FrameResult
    jpegs: tuple[bytes, ...] | None
    silhouettes_png: tuple[bytes, ...] | None


def _png_chunk(tag: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))


def encode_silhouette(mask: Mask) -> bytes:
    """(H, W) bool silhouette -> PNG bytes: 1 bit per pixel, transparent / tinted.

    Written by hand as a 1-bit palette PNG with a transparency chunk: ~0.1 ms and
    ~200 bytes per mask, where tinting an RGBA image and encoding it with OpenCV
    takes ~5 ms (three masks a frame would cost more than decoding the frame).
    """
    height, width = mask.shape
    rows = np.packbits(np.asarray(mask, dtype=bool), axis=1)  # MSB first, as PNG wants
    raw = np.hstack([np.zeros((height, 1), np.uint8), rows]).tobytes()  # filter 0 per row
    r, g, b, a = SILHOUETTE_RGBA
    return b"".join(
        [
            b"\x89PNG\r\n\x1a\n",
            _png_chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 1, 3, 0, 0, 0)),
            _png_chunk(b"PLTE", bytes([0, 0, 0, r, g, b])),
            _png_chunk(b"tRNS", bytes([0, a])),  # palette entry 0 fully transparent
            _png_chunk(b"IDAT", zlib.compress(raw, 6)),
            _png_chunk(b"IEND", b""),
        ]
    )


def _encode_jpeg(image: Image | None) -> bytes:
    if image is None:
        return b""
    ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    return jpeg.tobytes() if ok else b""


def decode_frames(paths: Sequence[Path], indices: Sequence[int]) -> list[tuple[int, list[Image]]]:
    """(index, per camera grey image) of each frame of ``indices`` that every video provides."""
    out = []
    for index in indices:
        images = [image for k in range(len(paths)) for image in camera_frames(paths, k, index, index + 1)]
        if len(images) == len(paths) and all(image is not None for image in images):
            out.append((index, [image for image in images if image is not None]))
    return out


def camera_frames(paths: Sequence[Path], camera: int, first: int, stop: int) -> list[Image | None]:
    """Camera number ``camera``'s grey images of frames ``first <= i < stop`` (its video,
    ``paths[camera]``), None where the video provides none."""
    reader = read_frames(Path(paths[camera]), first, stop, problems={})
    try:
        return [image for _, image in reader]
    finally:
        close = getattr(reader, "close", None)  # release the decoder now, not at GC
        if close is not None:
            close()


def one_frame(
    index: int,
    images: Sequence[Image | None],
    model: Any,
    camera_names: Sequence[str],
    fit: Callable[[int, Sequence[Image]], tuple[FrameResult, Sequence[Mask] | None]],
    problems: Sequence[dict[int, str]],
) -> tuple[FrameResult, Sequence[Mask] | None]:
    """One frame's result and silhouettes; ``problems``: per camera, frame index -> why
    its image is None (read_frames')."""
    missing = [k for k, im in enumerate(images) if im is None]
    if missing:
        by_reason: dict[str, list[str]] = {}
        for k in missing:
            why = problems[k].get(index, "frame could not be decoded")
            by_reason.setdefault(why, []).append(camera_names[k])
        reason = "; ".join(
            f"camera{'s' * (len(names) > 1)} {', '.join(names)}: {why}" for why, names in by_reason.items()
        )
        return FrameResult.failed(index, reason), None
    try:
        return fit(index, [im for im in images if im is not None])
    except Exception as exc:  # a frame's failure is data, never the end of the run
        return FrameResult.failed(index, f"{type(exc).__name__}: {exc}"), None


def frame_output(
    result: FrameResult,
    masks: Sequence[Mask] | None,
    images: Sequence[Image | None],
    encode_images: bool,
    decode_s: float | None,
) -> FrameOutput:
    """The frame's output, its media compressed; ``decode_s`` None: decoded elsewhere (live
    cameras, in their reader threads), so not timed here."""
    t0 = time.perf_counter()
    jpegs = tuple(_encode_jpeg(im) for im in images) if encode_images else None
    pngs = None if masks is None else tuple(encode_silhouette(m) for m in masks)
    decoded = {} if decode_s is None else {"decode": decode_s}
    timings = {**decoded, **result.timings_s, "encode": time.perf_counter() - t0}
    return FrameOutput(dataclasses.replace(result, timings_s=timings), jpegs, pngs)


# A live frame whose track is lost keeps the lost fit (flagged) where its start from the
# hull cannot be waited for; after this many lost fits running, the next lost frame waits
# for it however long that takes. Replaying the loop of `synth --shape loop --seed 7
# --arrangement ninety --radius-mm 7 --tip round` on this 2-core machine (2026-12-04,
# frame-sets dropped of 900; mean error against the truth, `process` 0.267 mm):
# - every lost-again frame waiting: 116 and 129 dropped (two replays);
# - 2 lost fits kept: 50-87 dropped, mean 0.258-0.273 mm (three replays);
# - lost fits kept without limit: 8-54 dropped (seven replays, five of them with the
#   restart worker at a lower priority), but mean up to 0.440 mm, p95 2.1 mm, where a run
#   of lost fits went astray; and where the tube moves 5-10 mm a frame (tests/live's UDP
#   session, on a loaded machine) almost every frame kept one.
LOST_FITS_KEPT = 2


def _lost_run(track: Sequence[FrameResult]) -> int:
    """How many of ``track``'s last results, running, kept a lost track's fit."""
    run = 0
    for result in reversed(track):
        if not result.lost:
            break
        run += 1
    return run


class Restarts(Protocol):
    """Where a :class:`Tracker` starts tracks (from the hull) and follows them until they
    catch up, away from its own thread (a live run's
    :class:`pipeline.live.restarts.RestartWorker`)."""

    @property
    def available(self) -> bool:
        """Whether it can take starts (False once it has failed)."""
        ...

    @property
    def under_way(self) -> bool:
        """Whether a started track has yet to catch up."""
        ...

    @property
    def nearly_caught_up(self) -> bool:
        """Whether the started track has only its last frame given to it left to fit, and
        that one tracked (its start from the hull done)."""
        ...

    def start(self, index: int, images: Sequence[Image], previous: Sequence[FrameResult]) -> bool:
        """Start a track at frame ``index``, computed as ``process`` computes it (from its
        per camera (H, W) uint8 grey ``images`` and the track's results before it,
        ``previous``: from the hull where there are none or the track is lost); False
        where one is under way."""
        ...

    def follow(self, index: int, images: Sequence[Image]) -> None:
        """The started track goes on through frame ``index`` (the frame after its last)."""
        ...

    def caught_up(self, may_wait: Callable[[], bool]) -> list[FrameResult] | None:
        """The started track's last results, oldest first, once it has every frame given to
        it, waiting for that as long as ``may_wait()`` says the caller can; else None."""
        ...


class Tracker:
    """Frames reconstructed one after another, each fitted from the track's last results.

    A live run's core: the same per-frame computation as :func:`process_range`'s, frame
    after frame (:mod:`pipeline.reconstruct.tracking`).

    ``restarts``: where to start tracks from the hull. Without, one track goes on across
    every frame and starts again only where it is lost, the frame waiting for its start
    (150-350 ms on a loop). With, starts run there: where the track is lost, the frame
    waits for its start only as long as ``may_wait()`` says it can (a live run: while no
    frame-set would be dropped for it), and a start that comes in time gives the frame
    ``process``'s result. Otherwise the frame keeps the lost track's fit, flagged
    suspect, the frames go on from it, and the started track follows them there until it
    has caught up, when it takes over. A frame lost again from the lost track's fit waits
    for the started track as long as the first did, and after ``LOST_FITS_KEPT`` lost
    fits running, as long as it takes. A track also starts where ``process`` starts each
    segment's.
    """

    def __init__(
        self,
        model: Any,
        camera_names: Sequence[str],
        *,
        images: bool,
        restarts: Restarts | None = None,
        may_wait: Callable[[], bool] = lambda: False,
    ) -> None:
        from .frame import reconstruct_with_silhouettes

        self._compute = reconstruct_with_silhouettes
        self._model, self._names, self._images = model, tuple(camera_names), images
        self._restarts, self._may_wait = restarts, may_wait
        self._track: list[FrameResult] = []
        self._problems: list[dict[int, str]] = [{} for _ in self._names]

    def step(self, index: int, images: Sequence[Image]) -> FrameOutput:
        """Frame ``index`` from its per camera (H, W) uint8 grey images."""
        restarts = self._restarts if self._restarts is not None and self._restarts.available else None
        if restarts is not None and restarts.under_way:
            # A started track with only its last tracked frame left is worth waiting for while
            # a frame-set can still wait: it fits a frame about as fast as this thread, so
            # without the wait it could stay a frame behind for good.
            patience = self._may_wait if restarts.nearly_caught_up else lambda: False
            self._take_over(restarts.caught_up(patience))

        def fitted(restart_here: bool) -> tuple[FrameResult, Sequence[Mask] | None]:
            def fit(i: int, grey: Sequence[Image]) -> tuple[FrameResult, Sequence[Mask] | None]:
                return self._compute(i, grey, self._model, self._track, restart_here=restart_here)

            return one_frame(index, list(images), self._model, self._names, fit, self._problems)

        result, masks = fitted(restart_here=restarts is None)
        lost_before = _lost_run(self._track) if restarts is not None and result.lost else 0
        if restarts is not None and lost_before:
            # Lost again from a lost track's fit, which is a poor guide: this frame waits for
            # the started track, and is fitted from it as process fits it (started again here
            # if lost from it too). The wait is held to the queue's room while the lost fits
            # are few (a frame that waits out a start from the hull, 150-500 ms, drops 5-15
            # frame-sets), and a frame it does not give keeps its own fit; beyond, the frame
            # waits as long as it takes, started again here if no started track is left, and
            # sets are dropped (a tube too fast for its track gives dropped frames, not a run
            # of wrong ones).
            waits_out = lost_before >= LOST_FITS_KEPT
            taken = self._take_over(restarts.caught_up((lambda: True) if waits_out else self._may_wait))
            if taken or waits_out:
                result, masks = fitted(restart_here=True)
        if restarts is not None:
            if restarts.under_way:
                restarts.follow(index, images)
            elif result.lost and restarts.start(index, images, self._track):
                started = restarts.caught_up(self._may_wait)
                if started is not None:  # the frame as process has it (its silhouettes are these)
                    self._track, result = started[:-1], started[-1]
            elif starts_next_track(index):
                # Where process starts its next segment's track (from the hull, WARMUP_FRAMES
                # before the segment), one starts here too, and takes over once caught up: a
                # wrong course that no lost-track test catches is forgotten as in process,
                # and from the take-over on the frames are process's.
                restarts.start(index, images, ())
        self._track = [*self._track, result][-LENGTH_FRAMES:]
        return frame_output(result, masks, list(images), self._images, None)

    def _take_over(self, started: list[FrameResult] | None) -> bool:
        """The started track, where it has caught up, replaces the run's."""
        if started is not None:
            self._track = started
        return started is not None


def process_range(
    model: Any,
    video_paths: Sequence[Path],
    camera_names: Sequence[str],
    start: int,
    stop: int,
    *,
    images: bool = True,
    frame_fn: FrameFunction | None = None,
    tracked: bool | None = None,
    tally: str | None = None,
) -> list[FrameOutput]:
    """Decode frames ``start <= i < stop`` of every video and process them (one task).

    The default computation tracks the tube from frame to frame
    (:mod:`pipeline.reconstruct.tracking`): the task decodes from the start of its first
    frame's track, and restarts the track, from the frames before, at each
    segment it enters, so that every frame's curve is the one any other split
    of the work would give. A replacement ``frame_fn`` sees each frame alone,
    unless ``tracked``: it is then called with the track's last results too,
    as ``frame_fn(index, images, model, previous)``. ``tally``: a file that gets a
    byte appended for each frame done (the parent's progress bar reads its size).
    """
    tracked = frame_fn is None if tracked is None else tracked
    compute: Callable[..., tuple[FrameResult, Sequence[Mask] | None]]
    if frame_fn is None:
        from .frame import reconstruct_with_silhouettes as compute
    else:
        compute = frame_fn
    first = track_start(start) if tracked else start
    # Why a camera has no image for a frame goes into that frame's reason, and so into the
    # run's summary (merged over frames, in order), not into each worker's log.
    problems: list[dict[int, str]] = [{} for _ in video_paths]
    readers = [
        read_frames(Path(p), first, stop, problems=found)
        for p, found in zip(video_paths, problems, strict=True)
    ]
    track: list[FrameResult] = []
    segment: int | None = None  # the segment whose track is running
    recent: deque[tuple[int, list[Image | None]]] = deque(maxlen=WARMUP_FRAMES)

    def fit(index: int, grey: Sequence[Image]) -> tuple[FrameResult, Sequence[Mask] | None]:
        return compute(index, grey, model, track) if tracked else compute(index, grey, model)

    def step(index: int, images_: list[Image | None]) -> tuple[FrameResult, Sequence[Mask] | None]:
        result, masks = one_frame(index, images_, model, camera_names, fit, problems)
        track.append(result)
        return result, masks

    outputs = []
    frames = zip(*readers, strict=True)
    counter = open(tally, "ab", buffering=0) if tally else None  # closed in the finally below
    try:
        while True:
            t0 = time.perf_counter()
            decoded = next(frames, None)
            if decoded is None:
                break
            index = decoded[0][0]
            images_ = [image for _, image in decoded]
            decode_s = time.perf_counter() - t0
            # The frames before ``start`` are the first segment's warm-up.
            if tracked and segment_start(max(index, start)) != segment:
                if segment is not None:
                    # A new segment: its track starts again from the frames before it.
                    track.clear()
                    for before, grey in recent:
                        if before >= track_start(index):
                            step(before, grey)
                segment = segment_start(max(index, start))
            result, masks = step(index, images_)
            del track[:-LENGTH_FRAMES]  # what the next frame looks back at (see predict_length)
            recent.append((index, images_))
            if index >= start:
                outputs.append(frame_output(result, masks, images_, images, decode_s))
                if counter is not None:
                    counter.write(b".")
    finally:
        if counter is not None:
            counter.close()
        for reader in readers:
            close = getattr(reader, "close", None)  # release the decoders now, not at GC
            if close is not None:
                close()
    return outputs
