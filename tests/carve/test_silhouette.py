"""Silhouettes on synthetic images whose foreground is known pixel for pixel."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from pipeline.carve.silhouette import extract_silhouette, remove_small_blobs
from pipeline.session.settings import SilhouetteSettings

H, W = 60, 80
BG, FG = 180, 40


def _scene(*, seed: int = 0, noise: float = 3.0) -> tuple[NDArray[np.uint8], NDArray[np.bool_]]:
    """A dark bar and a dark disc on a bright, slightly noisy background, and the truth."""
    truth = np.zeros((H, W), bool)
    truth[10:50, 20:27] = True
    yy, xx = np.mgrid[:H, :W]
    truth |= (yy - 30) ** 2 + (xx - 55) ** 2 <= 8**2
    rng = np.random.default_rng(seed)
    image = np.where(truth, FG, BG) + rng.normal(0, noise, (H, W))
    return np.clip(np.round(image), 0, 255).astype(np.uint8), truth


@pytest.mark.parametrize("method", ["threshold", "otsu"])
@pytest.mark.parametrize("polarity", ["dark", "bright"])
def test_methods_find_the_shapes_in_both_polarities(method: str, polarity: str) -> None:
    image, truth = _scene()
    if polarity == "bright":
        image = 255 - image
        threshold = 255 - 110
    else:
        threshold = 110
    settings = SilhouetteSettings(method=method, threshold=threshold, polarity=polarity)
    # Noise of 3 grey levels never crosses a level 70 away: the mask is exact.
    np.testing.assert_array_equal(extract_silhouette(image, settings, morphology=False), truth)


@pytest.mark.parametrize("polarity", ["dark", "bright"])
def test_otsu_finds_a_thin_tube_on_a_textured_scene(polarity: str) -> None:
    # A 6-pixel tube (0.6 % of the image, as in the synthetic views) on clouds spanning
    # grey levels 110-220: one Otsu split falls inside the clouds and marks about half
    # the image; the recursive split must find the tube, and only the tube.
    rng = np.random.default_rng(3)
    clouds = cv2.GaussianBlur(rng.normal(0.0, 1.0, (240, 320)), (0, 0), 12)
    clouds = 110 + 110 * (clouds - clouds.min()) / np.ptp(clouds)
    truth = np.zeros((240, 320), bool)
    truth[60:140, 150:156] = True
    image = np.clip(np.where(truth, 50 + rng.normal(0, 4, truth.shape), clouds), 0, 255).astype(np.uint8)
    if polarity == "bright":
        image = 255 - image
    one_split, _ = cv2.threshold(image, 0, 1, cv2.THRESH_OTSU | cv2.THRESH_BINARY)
    assert 0.2 < np.mean(image <= one_split) < 0.8  # the case that defeats plain Otsu
    settings = SilhouetteSettings(method="otsu", polarity=polarity, min_area_px=0)
    np.testing.assert_array_equal(extract_silhouette(image, settings, morphology=False), truth)


def test_threshold_is_strict() -> None:
    image = np.array([[59, 60, 61]], np.uint8).repeat(3, axis=0)
    dark = extract_silhouette(image, SilhouetteSettings(threshold=60, min_area_px=0), morphology=False)
    bright = extract_silhouette(
        image, SilhouetteSettings(threshold=60, polarity="bright", min_area_px=0), morphology=False
    )
    np.testing.assert_array_equal(dark[0], [True, False, False])
    np.testing.assert_array_equal(bright[0], [False, False, True])


def test_background_difference_finds_the_shapes_whatever_their_shade() -> None:
    _, truth = _scene()
    rng = np.random.default_rng(5)
    background = rng.integers(60, 200, (H, W)).astype(np.uint8)  # a textured scene
    # The object is darker than the scene in one place and brighter in another.
    scene = np.where(truth, np.where(np.arange(W) < 40, background - 50, background + 50), background)
    settings = SilhouetteSettings(method="background", threshold=25)
    mask = extract_silhouette(scene.astype(np.uint8), settings, background=background, morphology=False)
    np.testing.assert_array_equal(mask, truth)
    assert not extract_silhouette(background, settings, background=background).any()


def test_specks_below_min_area_are_removed() -> None:
    image = np.full((H, W), BG, np.uint8)
    image[5:8, 5:8] = FG  # 9 px: a speck
    image[30:36, 40:45] = FG  # 30 px: kept
    image[50:54, 70:75] = FG  # 20 px: exactly min_area_px, kept
    mask = extract_silhouette(image, SilhouetteSettings(min_area_px=20), morphology=False)
    expected = image < 60
    expected[5:8, 5:8] = False
    np.testing.assert_array_equal(mask, expected)


def test_a_single_small_blob_is_removed() -> None:
    image = np.full((H, W), BG, np.uint8)
    image[5:8, 5:8] = FG
    assert not extract_silhouette(image, SilhouetteSettings(min_area_px=20), morphology=False).any()


def test_morphology_removes_isolated_pixels_and_fills_pinholes() -> None:
    image, truth = _scene(noise=0.0)
    image[2, 2] = FG  # an isolated dark pixel
    image[30, 23] = BG  # a pinhole in the bar
    mask = extract_silhouette(image, SilhouetteSettings(min_area_px=0))
    assert not mask[2, 2]
    assert mask[30, 23]
    # The bar's and disc's straight edges survive the 3x3 cross; only the bar's 4 corner
    # pixels (which the cross opening cannot reach) may go.
    assert (mask != truth).sum() <= 4


@pytest.mark.parametrize("width_px", [2, 3])
def test_a_tube_two_or_three_pixels_wide_is_not_opened_away(width_px: int) -> None:
    """A thin or far tube is all spur to the 3x3 cross: the opening would take it whole (two
    pixels wide) or cut it where its edges step (three). Drawn as a slanted band, with an
    isolated pixel beside it."""
    image = np.full((H, W), BG, np.uint8)
    rng = np.random.default_rng(width_px)
    for x in range(10, W - 10):
        y = 10 + (x * 7) // 10 + int(rng.integers(0, 2))  # a staircase edge, jittered
        image[y : y + width_px, x] = FG
    image[2, W - 3] = FG
    mask = extract_silhouette(image, SilhouetteSettings(min_area_px=20))
    band = image < 60
    band[2, W - 3] = False
    assert mask[band].mean() > 0.99  # the band kept (the closing may add a pixel at a step)
    n, _ = cv2.connectedComponents(mask.view(np.uint8))
    assert n - 1 == 1  # one piece, the speck gone (its blob is under min_area_px)


@pytest.mark.parametrize(
    ("method", "polarity", "value"),
    [
        ("threshold", "dark", 128),
        ("threshold", "dark", 255),
        ("threshold", "bright", 0),
        ("threshold", "bright", 30),
        *[("otsu", p, v) for p in ("dark", "bright") for v in (0, 128, 255)],
        *[("background", p, v) for p in ("dark", "bright") for v in (0, 128, 255)],
    ],
)
def test_an_empty_scene_gives_an_all_false_mask(method: str, polarity: str, value: int) -> None:
    rng = np.random.default_rng(value)
    image = np.clip(value + rng.normal(0, 2, (H, W)), 0, 255).astype(np.uint8)
    settings = SilhouetteSettings(method=method, polarity=polarity, threshold=60)
    background = image.copy() if method == "background" else None
    mask = extract_silhouette(image, settings, background=background)
    assert mask.shape == (H, W)
    assert mask.dtype == np.bool_
    # Uniform grey with 2-level noise: Otsu's split stays under its 20-level contrast floor.
    assert not mask.any()


def test_a_zero_pixel_image_gives_an_empty_mask() -> None:
    mask = extract_silhouette(np.zeros((0, 5), np.uint8), SilhouetteSettings(method="otsu"))
    assert mask.shape == (0, 5)
    assert mask.dtype == np.bool_


def test_remove_small_blobs_keeps_uint8_mask() -> None:
    mask = np.zeros((10, 10), np.uint8)
    mask[1:4, 1:4] = 1
    mask[6:9, 6:9] = 1
    mask[0, 9] = 1
    out = remove_small_blobs(mask, 5)
    assert out.dtype == np.uint8
    assert out.sum() == 18
    assert out[0, 9] == 0
