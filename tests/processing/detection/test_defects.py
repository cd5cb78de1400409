import cv2
import numpy as np
import pytest

from processing.detection.defects import RESOLVED_PX, measure_defects, resolved


def test_measurements_of_a_drawn_line() -> None:
    mask = np.zeros((100, 200), np.uint8)
    cv2.line(mask, (20, 50), (170, 50), 1, 5)
    width = int(mask[:, 100].sum())  # cv2 draws thickness 5 as 7 pixels across
    (d,) = measure_defects(mask > 0, "crack", mm_per_px=0.5)
    assert d.length_px == pytest.approx(150, abs=8)
    assert d.max_width_px == pytest.approx(width, abs=0.5)
    assert d.orientation_deg == pytest.approx(0, abs=1) or d.orientation_deg == pytest.approx(
        180, abs=1
    )
    assert d.length_mm == pytest.approx(d.length_px * 0.5, abs=0.01)
    assert d.bbox[0] <= 20 and d.bbox[0] + d.bbox[2] >= 170


def test_each_component_is_one_defect_with_increasing_ids() -> None:
    mask = np.zeros((50, 50), bool)
    mask[5:8, 5:30] = True
    mask[30:45, 30:45] = True
    defects = measure_defects(mask, "corrosion", first_id=7)
    assert [d.id for d in defects] == [7, 8]
    assert {d.defect_class for d in defects} == {"corrosion"}
    assert defects[0].length_mm is None
    assert sorted(d.area_px for d in defects) == [75, 225]


def test_width_at_half_contrast_ignores_a_blurred_rim() -> None:
    img = np.full((60, 120), 200.0, np.float32)
    img[28:33, 10:110] = 60.0  # a 5-px dark crack
    blurred = cv2.GaussianBlur(img, (0, 0), 2.0)
    contrast = 200.0 - blurred
    mask = contrast > 10  # a generous detector that includes the rim
    (loose,) = measure_defects(mask, "crack")
    (fwhm,) = measure_defects(mask, "crack", contrast=contrast)
    assert loose.max_width_px > 8
    assert (
        fwhm.max_width_px == pytest.approx(5, abs=2.0)
        and fwhm.max_width_px < loose.max_width_px - 2
    )
    assert fwhm.length_px == pytest.approx(loose.length_px, rel=0.1)


@pytest.mark.parametrize("threshold", [0.58, 0.5, 0.3])
def test_components_have_opencvs_statistics(threshold: float) -> None:
    from processing.detection.defects import Components

    rng = np.random.default_rng(4)
    mask = cv2.GaussianBlur(rng.random((400, 500)), (0, 0), 2) > threshold  # sparse to dense
    comps = Components.of(mask)
    n, labels, stats, centroids = cv2.connectedComponentsWithStats(
        mask.astype(np.uint8), connectivity=8
    )
    assert np.array_equal(comps.labels, labels)
    assert np.array_equal(comps.stats[1:], stats[1:]) and comps.stats[0, 4] == stats[0, 4]
    assert np.allclose(comps.centroids[1:], centroids[1:])
    assert comps.keep[1:].all() and not comps.keep[0]


def test_specks_below_the_cameras_resolution_are_not_resolved() -> None:
    mask = np.zeros((40, 60), bool)
    mask[5, 5:7] = True  # a two-pixel crack speck
    mask[20, 10:40] = True  # a 30-px crack
    found = measure_defects(mask, "crack")
    assert [resolved(d) for d in found] == [False, True]
    assert found[0].length_px < RESOLVED_PX <= found[1].length_px
    rust = np.zeros((40, 60), bool)
    rust[2:4, 2:4] = True  # 4 px: smaller than a resolved patch of 3 x 3
    rust[20:30, 20:30] = True
    assert [resolved(d) for d in measure_defects(rust, "corrosion")] == [False, True]
