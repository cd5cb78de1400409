"""Labelled steel-surface crops for crack segmentation (:mod:`robot_link.sim.steel_crops`)."""

import cv2
import numpy as np
from numpy.typing import NDArray
from skimage.morphology import skeletonize

from robot_link.sim.steel_crops import SteelCropParams, steel_sample, steel_samples

ALWAYS = SteelCropParams(crack_probability=1.0)
NEVER = SteelCropParams(crack_probability=0.0)


def _disk(radius: int) -> NDArray[np.uint8]:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _contrast(img: NDArray[np.uint8], truth: NDArray[np.bool_]) -> float:
    """Median grey 3-6 px around the truth minus the median grey on it (> 0: crack darker)."""
    t = truth.astype(np.uint8)
    ring = cv2.dilate(t, _disk(6)).astype(bool) & ~cv2.dilate(t, _disk(2)).astype(bool)
    return float(np.median(img[ring])) - float(np.median(img[truth]))


def _width_px(truth: NDArray[np.bool_]) -> float:
    """Mean width of the labelled cracks: their area over their skeleton's length."""
    return float(truth.sum() / skeletonize(truth).sum())


def _strong_log(img: NDArray[np.uint8]) -> float:
    """Share of pixels with |Laplacian of Gaussian (sigma 1.5 px)| above 4 grey levels/px²."""
    smooth = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 1.5)
    return float((np.abs(cv2.Laplacian(smooth, cv2.CV_32F)) > 4).mean())


def test_a_seed_always_gives_the_same_sample_and_other_seeds_differ() -> None:
    img, truth = steel_sample(7, ALWAYS)
    again_img, again_truth = steel_sample(7, ALWAYS)
    assert np.array_equal(img, again_img) and np.array_equal(truth, again_truth)
    other_img, other_truth = steel_sample(8, ALWAYS)
    assert not np.array_equal(img, other_img) and not np.array_equal(truth, other_truth)


def test_images_and_truths_have_the_size_asked_for() -> None:
    for size in [(384, 512), (120, 200)]:
        img, truth = steel_sample(3, SteelCropParams(size_px=size, crack_probability=1.0))
        assert img.shape == truth.shape == size
        assert img.dtype == np.uint8 and truth.dtype == np.bool_
    assert steel_sample(3)[0].shape == (384, 512)


def test_crack_probability_zero_never_labels_a_crack_and_one_always_does() -> None:
    for seed in range(20):
        assert not steel_sample(seed, NEVER)[1].any()
        assert steel_sample(seed, ALWAYS)[1].any()


def test_the_labelled_pixels_are_darker_than_the_plate_around_them() -> None:
    darker = [_contrast(*steel_sample(seed, ALWAYS)) > 0 for seed in range(20)]
    assert sum(darker) >= 16


def test_a_hairline_is_labelled_along_a_one_pixel_line() -> None:
    """0.05-0.1 mm at 0.4 mm/px covers a quarter of a pixel: the truth is its centre line."""
    hair = SteelCropParams(crack_probability=1.0, mm_per_px=(0.4, 0.4), crack_width_mm=(0.05, 0.1))
    widths = []
    for seed in range(10):
        truth = steel_sample(seed, hair)[1]
        assert truth.sum() >= 10
        widths.append(_width_px(truth))
    assert np.median(widths) <= 2.0


def test_a_wide_crack_is_labelled_across_its_width() -> None:
    """0.8-1 mm at 0.1 mm/px is 8-10 px wide at its widest, tapering towards its tips."""
    wide = SteelCropParams(crack_probability=1.0, mm_per_px=(0.1, 0.1), crack_width_mm=(0.8, 1.0))
    widths = [_width_px(steel_sample(seed, wide)[1]) for seed in range(10)]
    assert 5.0 <= np.median(widths) <= 10.0


def test_a_sub_pixel_hairline_is_fainter_than_a_wide_crack() -> None:
    """Area coverage: a 0.05 mm crack at 0.2 mm/px darkens its pixels by a fraction only."""

    def contrasts(width_mm: tuple[float, float]) -> list[float]:
        p = SteelCropParams(crack_probability=1.0, mm_per_px=(0.2, 0.2), crack_width_mm=width_mm)
        return [_contrast(*steel_sample(seed, p)) for seed in range(12)]

    hair, wide = contrasts((0.05, 0.06)), contrasts((0.8, 1.0))
    assert np.median(hair) > 0
    assert np.median(hair) < 0.3 * np.median(wide)


def test_images_without_cracks_still_hold_thin_crack_like_structures() -> None:
    """Hard negatives (weld toes, edges, scratches, pits...) give strong thin responses that
    bare surfaces (no distractors) mostly lack."""
    drawn = [_strong_log(steel_sample(seed, NEVER)[0]) for seed in range(20)]
    bare = SteelCropParams(crack_probability=0.0, distractors=0.0)
    plain = [_strong_log(steel_sample(seed, bare)[0]) for seed in range(20)]
    assert sum(f > 0.002 for f in drawn) >= 14
    assert np.mean(drawn) > 2 * np.mean(plain)


def test_samples_are_named_by_seed_and_index_and_do_not_depend_on_the_count() -> None:
    samples = steel_samples(4, 11, ALWAYS)
    assert [name for name, _, _ in samples] == [f"steel-11-{k:05d}" for k in range(4)]
    fewer = steel_samples(2, 11, ALWAYS)
    for (_, img, truth), (_, img2, truth2) in zip(samples, fewer):
        assert np.array_equal(img, img2) and np.array_equal(truth, truth2)
    assert not np.array_equal(samples[0][1], samples[1][1])
    assert not np.array_equal(samples[0][1], steel_samples(1, 12, ALWAYS)[0][1])
