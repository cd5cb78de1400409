import numpy as np

from processing.detection.region_growing import grow_regions


def test_growth_follows_similar_pixels_and_stops_at_the_background() -> None:
    img = np.full((30, 30), 200, np.uint8)
    img[10:13, 2:28] = 50  # a dark stripe (the crack)
    seeds = np.zeros_like(img, bool)
    seeds[11, 12:15] = True  # only its middle was detected
    grown = grow_regions(img, seeds, max_diff=30)
    assert grown[10:13, 2:28].all()
    assert grown.sum() == 3 * 26
    assert grown[seeds].all() and seeds.sum() < grown.sum()


def test_no_seeds_or_zero_threshold_changes_nothing() -> None:
    img = np.zeros((5, 5), np.uint8)
    none = np.zeros((5, 5), bool)
    assert not grow_regions(img, none, 10).any()
    one = none.copy()
    one[2, 2] = True
    assert grow_regions(img, one, 0).sum() == 1
