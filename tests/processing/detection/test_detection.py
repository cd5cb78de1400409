import cv2
import numpy as np
import pytest

from processing.detection import detect_cracks
from processing.detection.corrosion import detect_corrosion


def plate_with_crack(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    img = np.clip(rng.normal(140, 6, (240, 320)), 0, 255).astype(np.uint8)
    truth = np.zeros_like(img)
    cv2.line(truth, (40, 60), (280, 170), 255, 3)
    img[truth > 0] = 50
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), truth > 0


def test_dark_line_on_noisy_plate_is_found() -> None:
    img, truth = plate_with_crack()
    mask = detect_cracks(img)
    tp = (mask & truth).sum()
    assert tp / truth.sum() > 0.8
    assert tp / max(mask.sum(), 1) > 0.6


@pytest.mark.parametrize("method", ["proposed", "otsu", "sauvola"])
def test_blank_and_constant_images_give_no_cracks_with_proposed(method: str) -> None:
    blank = np.full((100, 120), 128, np.uint8)
    mask = detect_cracks(blank, method=method)
    assert mask.shape == blank.shape
    assert not mask.any()


def test_sixteen_bit_and_tiny_images_are_handled() -> None:
    img, _ = plate_with_crack()
    gray16 = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.uint16) * 257
    assert detect_cracks(gray16).any()
    assert not detect_cracks(np.zeros((2, 2), np.uint8)).any()


def test_bad_shapes_and_types_raise_value_error() -> None:
    with pytest.raises(ValueError, match="image must be"):
        detect_cracks(np.zeros((4, 4, 2), np.uint8))
    with pytest.raises(ValueError, match="uint8 or uint16"):
        detect_cracks(np.zeros((4, 4), np.float64))
    with pytest.raises(ValueError, match="method"):
        detect_cracks(np.zeros((4, 4), np.uint8), method="magic")  # type: ignore[arg-type]


def test_rust_patch_is_corrosion_and_grey_paint_is_not() -> None:
    img = np.full((200, 200, 3), (118, 112, 104), np.uint8)
    cv2.circle(img, (100, 100), 30, (28, 62, 140), -1)
    mask = detect_corrosion(img)
    assert mask[100, 100] and not mask[10, 10]
    assert abs(int(mask.sum()) - int(np.pi * 30**2)) < 0.2 * np.pi * 30**2


def test_paper_pipeline_finds_a_crack_on_a_plate() -> None:
    img, truth = plate_with_crack(3)
    mask = detect_cracks(img, method="paper")
    assert (mask & truth).sum() / truth.sum() > 0.7


def test_proposed_is_insensitive_to_uneven_low_light() -> None:
    img, truth = plate_with_crack(4)
    gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float32)
    ramp = np.linspace(1.0, 0.2, gray.shape[1])[None, :]  # light falls off to 20 %
    dim = np.clip(gray * ramp, 0, 255).astype(np.uint8)
    bright_mask, dim_mask = detect_cracks(img), detect_cracks(dim)
    assert (dim_mask & truth).sum() > 0.7 * (bright_mask & truth).sum()
    assert (dim_mask & ~truth).sum() < 0.05 * truth.size


def test_tiled_detection_matches_whole_image_detection_away_from_tile_seams() -> None:
    from processing.detection import detect_cracks_tiled

    rng = np.random.default_rng(5)
    img = np.clip(rng.normal(150, 6, (700, 900)), 0, 255).astype(np.uint8)
    cv2.line(img, (20, 30), (880, 650), 45, 3)  # crosses several tile borders
    cv2.line(img, (100, 600), (400, 500), 55, 2)
    whole = detect_cracks(img)
    tiled = detect_cracks_tiled(img, tile_px=300, overlap_px=60)
    assert whole.sum() > 1000
    assert (whole ^ tiled).sum() < 0.02 * whole.sum()
    n, _ = cv2.connectedComponents(tiled.astype(np.uint8))
    assert n - 1 == 2  # each crack stays one object across tiles


@pytest.mark.parametrize("fraction", [0.0, 0.02, 0.5, 0.98, 1.0])
def test_select_components_equals_a_lookup_whatever_the_share_kept(fraction: float) -> None:
    from processing.detection.thresholds import select_components

    rng = np.random.default_rng(3)
    mask = cv2.GaussianBlur(rng.random((300, 400)), (0, 0), 3) > 0.52
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    assert n > 20
    keep = rng.random(n) < fraction
    expected = keep[labels] & (labels > 0)
    assert np.array_equal(select_components(labels, stats, keep), expected)


@pytest.mark.parametrize("seed", [21, 22, 23])
def test_proposed_finds_a_hairline_on_textured_paint(seed: int) -> None:
    from tests.processing.helpers import textured_plate

    gray, truth = textured_plate((320, 480), seed, width=1, depth=35)
    mask = detect_cracks(gray)
    k = np.ones((5, 5), np.uint8)
    recall = ((cv2.dilate(mask.view(np.uint8), k) > 0) & truth).sum() / truth.sum()
    precision = (mask & (cv2.dilate(truth.view(np.uint8), k) > 0)).sum() / max(mask.sum(), 1)
    assert recall > 0.6 and precision > 0.5, (recall, precision)


def test_surface_statistics_of_frames_apply_to_a_mosaic_of_them() -> None:
    from processing.detection.crack_filter import SurfaceStats, measure_surface, proposed_cracks
    from tests.processing.helpers import textured_plate

    frames = [textured_plate((240, 320), s, width=2, depth=30)[0] for s in range(3)]
    pooled = SurfaceStats.pooled([measure_surface(f) for f in frames])
    own = measure_surface(frames[0])
    assert abs(pooled.line_spread - own.line_spread) < 0.5 * own.line_spread
    gray, truth = textured_plate((240, 320), 9, width=2, depth=30)
    assert (proposed_cracks(gray, surface=pooled) & truth).sum() > 0.5 * truth.sum()
