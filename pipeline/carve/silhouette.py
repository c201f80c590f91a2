"""Silhouettes: one grey image -> a boolean foreground mask, cleaned of specks.

Methods (``[silhouette] method`` in session.toml):

- ``"threshold"``, the original: a fixed grey level. With polarity ``"dark"`` the
  foreground is ``image < threshold``; with ``"bright"`` it is ``image > threshold``.
- ``"otsu"``: the level is chosen per image by Otsu's method, applied recursively
  (Cheriet et al. 1998): a thin manipulator covers about 1 % of a view, and on a
  textured scene one Otsu split falls inside the background's own spread of grey levels
  (marking a third to two thirds of the image; every frame then went tens of mm wrong).
  So while the split is not a clean one (Otsu's separability below
  ``_OTSU_SEPARATED``) and the manipulator's side of it still holds more than
  ``_OTSU_MAX_FOREGROUND`` of the image, Otsu is applied again to that side alone. On a
  plain backdrop the first split is clean and is kept, as plain Otsu would. Otsu always
  splits an image in two, even one showing only background; a split whose two classes
  differ by less than ``otsu_min_contrast`` grey levels is treated as "nothing here".
- ``"background"``: ``|image - background| > threshold`` against an empty-scene frame.
  Polarity plays no part: the manipulator differs from the scene whatever its shade.

Clean-up: a small morphological opening (drops isolated pixels and one-pixel spurs)
and closing (fills pinholes), then removal of connected blobs smaller than
``min_area_px``, which cannot be the manipulator.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from ..session.settings import SilhouetteSettings

# A 3x3 cross is the gentlest structuring element: it removes one-pixel noise but,
# unlike a square, leaves the staircase edges of a thin tube's silhouette intact.
_KERNEL = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
# ... unless it takes more than this share of the tube's pixels (see _cuts_thin_parts).
_THIN_SHARE = 0.5
# Recursive Otsu: a split is clean when the between-class variance is this share of the
# total (Otsu's eta: ~0.64 for one Gaussian mode, 0.75 for a flat one, -> 1 for two
# well-separated modes; 0.95 for a tube on a plain backdrop).
_OTSU_SEPARATED = 0.85
# ... and a manipulator's side of a split holding more than this share of the image
# is split again (the synthetic tubes cover 0.5-1.3 % of a 320x240 view).
_OTSU_MAX_FOREGROUND = 0.05
# Enough splits to reach any class: each leaves fewer grey levels.
_OTSU_MAX_SPLITS = 8


def extract_silhouette(
    image: NDArray[np.uint8],
    settings: SilhouetteSettings,
    *,
    background: NDArray[np.uint8] | None = None,
    morphology: bool = True,
    otsu_min_contrast: float = 20.0,
) -> NDArray[np.bool_]:
    """Foreground mask of one camera image.

    Parameters
    ----------
    image : (H, W) uint8 grey image.
    settings : method, threshold (grey level, or difference level for "background"),
        polarity and min_area_px.
    background : (H, W) uint8 empty-scene image; required by method "background".
    morphology : apply the 3x3 opening and closing (off: threshold and speck removal only).
    otsu_min_contrast : grey levels; an Otsu split whose class means differ by less
        than this is taken as an empty scene.

    Returns
    -------
    (H, W) bool, True on the manipulator. An image with nothing in it gives all False.
    """
    img = np.ascontiguousarray(image, dtype=np.uint8)
    if img.ndim != 2:
        raise ValueError(f"extract_silhouette needs an (H, W) grey image, got shape {img.shape}")
    if img.size == 0:  # cv2 refuses 0-pixel images; nothing in it is nothing seen
        return np.zeros(img.shape, dtype=np.bool_)
    fg = _threshold(img, settings, background, otsu_min_contrast)
    if morphology:
        opened = _u8(cv2.morphologyEx(fg, cv2.MORPH_OPEN, _KERNEL))
        if not _cuts_thin_parts(fg, opened, settings.min_area_px):
            fg = opened
        fg = _u8(cv2.morphologyEx(fg, cv2.MORPH_CLOSE, _KERNEL))
    if settings.min_area_px > 0:
        fg = remove_small_blobs(fg, settings.min_area_px)
    return fg.view(np.bool_)


def _cuts_thin_parts(fg: NDArray[np.uint8], opened: NDArray[np.uint8], min_area_px: int) -> bool:
    """Whether the opening of the (H, W) uint8 0/1 foreground ``fg`` (``opened``) would cut
    the tube, not only its specks and spurs: a tube about two pixels wide (thin, or far from
    the camera) is all spur to the cross, and one about three wide narrows to spurs where
    its edges step. Counting blobs of ``min_area_px`` pixels or more (what the speck removal
    keeps), it does where the opening leaves them in more pieces, keeps less than
    ``_THIN_SHARE`` of their pixels, or shatters ``min_area_px`` of them into specks. (A
    tube of 1.5 mm radius at 320x240, two pixels wide, went whole; of one of 2.5 mm, the
    opening left the upper part whole and the lower in specks: 24 of 30 frames ok against 0.)

    On the 124 rendered sessions of the accuracy draws and the bench (every third of 90
    frames; 2026-12-05), 137 of 8,694 silhouettes keep their opening off, in 11 stepped and
    tapered sessions: processed again (90 frames), a tapered loop's tip median 1.63 ->
    0.39 mm and its frames more than 2 mm off 30 -> 1, a two-camera tapered shape's mean
    0.31 -> 0.37 mm, the other nine within 0.006 mm."""
    n, labels = cv2.connectedComponents(opened, connectivity=8, ltype=cv2.CV_32S)
    if n <= 2 and cv2.countNonZero(opened) >= max(_THIN_SHARE * cv2.countNonZero(fg), min_area_px):
        return False  # the usual tube, in one piece: the foreground is not labelled
    pieces, sizeable = _sizeable(np.asarray(labels, np.int32), n, min_area_px)
    fg_n, fg_labels = cv2.connectedComponents(fg, connectivity=8, ltype=cv2.CV_32S)
    fg_pieces, fg_sizeable = _sizeable(np.asarray(fg_labels, np.int32), fg_n, min_area_px)
    shattered = np.count_nonzero(opened.view(np.bool_) & fg_sizeable & ~sizeable)
    kept, whole = np.count_nonzero(sizeable), np.count_nonzero(fg_sizeable)
    return bool(pieces > fg_pieces or kept < _THIN_SHARE * whole or shattered >= max(min_area_px, 1))


def _sizeable(labels: NDArray[np.int32], n: int, min_area_px: int) -> tuple[int, NDArray[np.bool_]]:
    """How many of the ``n - 1`` blobs of ``labels`` (0: the background) have at least
    ``min_area_px`` pixels (1 at least), and (H, W) bool, their pixels."""
    keep = np.bincount(labels.ravel(), minlength=n) >= max(min_area_px, 1)
    keep[0] = False
    return int(np.count_nonzero(keep)), keep[labels]


def remove_small_blobs(mask: NDArray[np.uint8], min_area_px: int) -> NDArray[np.uint8]:
    """(H, W) uint8 0/1 mask without its 8-connected blobs of fewer than ``min_area_px`` pixels."""
    # cv2.connectedComponentsWithStats costs ~0.4 ms at 320x240, labelling alone ~25 us:
    # label, and count areas only when there is more than one blob (rare after the opening).
    n, labels = cv2.connectedComponents(mask, connectivity=8, ltype=cv2.CV_32S)
    if n <= 2:
        keep_all = n == 2 and cv2.countNonZero(mask) >= min_area_px
        return mask if keep_all else np.zeros_like(mask)
    keep = np.bincount(labels.ravel(), minlength=n) >= min_area_px
    keep[0] = False  # label 0 is the background
    if keep[1:].all():
        return mask
    return keep.view(np.uint8)[labels]


def _threshold(
    img: NDArray[np.uint8],
    settings: SilhouetteSettings,
    background: NDArray[np.uint8] | None,
    otsu_min_contrast: float,
) -> NDArray[np.uint8]:
    """(H, W) uint8 0/1 raw foreground."""
    dark = settings.polarity == "dark"
    if settings.method == "threshold":
        # cv2 compares with ">" (BINARY) and "<=" (BINARY_INV); "< t" is "<= t - 1".
        if dark:
            if settings.threshold <= 0:
                return np.zeros_like(img)
            _, fg = cv2.threshold(img, settings.threshold - 1, 1, cv2.THRESH_BINARY_INV)
        else:
            _, fg = cv2.threshold(img, settings.threshold, 1, cv2.THRESH_BINARY)
        return _u8(fg)
    if settings.method == "otsu":
        hist = np.bincount(img.ravel(), minlength=256).astype(np.float64)
        level = _recursive_otsu(hist, dark)
        if not _otsu_contrast_ok(hist, level, otsu_min_contrast):
            return np.zeros_like(img)
        mode = cv2.THRESH_BINARY_INV if dark else cv2.THRESH_BINARY
        _, fg = cv2.threshold(img, level, 1, mode)
        return _u8(fg)
    if settings.method == "background":
        if background is None:
            raise ValueError("silhouette method 'background' needs a background image")
        if background.shape != img.shape:
            raise ValueError(f"background shape {background.shape} differs from the image's {img.shape}")
        diff = cv2.absdiff(img, np.ascontiguousarray(background, dtype=np.uint8))
        _, fg = cv2.threshold(diff, settings.threshold, 1, cv2.THRESH_BINARY)
        return _u8(fg)
    raise ValueError(f"unknown silhouette method {settings.method!r}")


def _recursive_otsu(hist: NDArray[np.float64], dark: bool) -> int:
    """The grey level splitting off the manipulator: foreground <= level (dark) or > level.

    hist : (256,) pixel count per grey level.
    """
    lo, hi = 0, 255  # the grey levels still in play
    total = hist.sum()
    level = 0
    for _ in range(_OTSU_MAX_SPLITS):
        level, separability = _otsu(hist, lo, hi)
        side = hist[lo : level + 1] if dark else hist[level + 1 : hi + 1]
        if separability >= _OTSU_SEPARATED or side.sum() <= _OTSU_MAX_FOREGROUND * total:
            break
        lo, hi = (lo, level) if dark else (level + 1, hi)
        if lo >= hi:
            break
    return level


def _otsu(hist: NDArray[np.float64], lo: int, hi: int) -> tuple[int, float]:
    """Otsu's split of grey levels ``lo..hi``: (level, separability), the classes being
    ``<= level`` and ``> level``; separability = between-class / total variance, 0-1."""
    h = hist[lo : hi + 1]
    grey = np.arange(lo, hi + 1, dtype=np.float64)
    n = h.sum()
    if n == 0 or hi <= lo:
        return lo, 0.0
    w0 = np.cumsum(h)[:-1]
    s0 = np.cumsum(h * grey)[:-1]
    mean = (h @ grey) / n
    with np.errstate(divide="ignore", invalid="ignore"):
        # The between-class variance w0 w1 (mu0 - mu1)^2 / n^2, as (mean w0 - s0)^2 / (w0 (n - w0)).
        between = np.where((w0 > 0) & (w0 < n), (mean * w0 - s0) ** 2 / (w0 * (n - w0)), 0.0)
    k = int(np.argmax(between))
    total_var = (h @ (grey - mean) ** 2) / n
    return lo + k, float(between[k] / total_var) if total_var > 0 else 0.0


def _otsu_contrast_ok(hist: NDArray[np.float64], level: float, min_contrast: float) -> bool:
    """Whether the whole image's two classes (<= level, > level) differ in mean by at
    least ``min_contrast``. hist : (256,) pixel count per grey level."""
    grey = np.arange(256, dtype=np.float64)
    split = int(level) + 1
    lo_n, hi_n = hist[:split].sum(), hist[split:].sum()
    if lo_n == 0 or hi_n == 0:
        return False
    lo_mean = (hist[:split] @ grey[:split]) / lo_n
    hi_mean = (hist[split:] @ grey[split:]) / hi_n
    return bool(hi_mean - lo_mean >= min_contrast)


def _u8(array: object) -> NDArray[np.uint8]:
    """cv2's result as a typed uint8 array (no copy)."""
    return np.asarray(array, dtype=np.uint8)
