"""Two visits of one surface aligned: a shift, a turn up to 10°, a scale change up to 5 %,
other lighting — to a fraction of a pixel; two different surfaces refused."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from processing.history.align import AlignmentError, align_visits
from processing.history.pairs import corner_error_px, make_pair, viewpoint
from robot_link.sim.structure import make_structure

SHARED = Path(__file__).resolve().parents[4] / "shared" / "datasets"


def steel(seed: int, size: tuple[int, int] = (640, 480)) -> np.ndarray:
    """A patch of the simulator's painted steel with its defects."""
    s = make_structure(
        seed,
        plate_size_m=(0.4, 0.3),
        n_cracks=2,
        n_corrosion=1,
        defect_region_m=(0.05, 0.05, 0.35, 0.25),
    )
    return cv2.resize(s.texture, size, interpolation=cv2.INTER_AREA)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_second_visit_aligns_to_a_fraction_of_a_pixel(seed: int) -> None:
    rng = np.random.default_rng(seed)
    before = steel(seed)
    B2A = viewpoint((640, 480), rng.uniform(-10, 10), rng.uniform(0.95, 1.05), (30.0, -25.0))
    after = cv2.warpPerspective(before, B2A, (640, 480), borderMode=cv2.BORDER_REFLECT)
    after = np.clip(after.astype(np.float32) * 1.25 - 20, 0, 255).astype(np.uint8)  # brighter
    result = align_visits(before, after)
    assert corner_error_px(result.after_to_before, np.linalg.inv(B2A), (640, 480)) < 0.5
    assert result.residual_px < 1.0 and 0.6 < result.overlap <= 1.0


def test_two_different_surfaces_are_refused() -> None:
    with pytest.raises(AlignmentError):
        align_visits(steel(4), cv2.flip(steel(5), 0))
    with pytest.raises(AlignmentError, match="texture"):
        align_visits(np.full((200, 200), 128, np.uint8), np.full((200, 200), 128, np.uint8))


@pytest.mark.skipif(not (SHARED / "deepcrack-train").is_dir(), reason="DeepCrack absent")
def test_real_crack_photographs_align_within_a_pixel() -> None:
    rng = np.random.default_rng(11)
    images = sorted((SHARED / "deepcrack-train" / "images").iterdir())[::40][:5]
    errors = []
    for path in images:
        mask = cv2.imread(str(SHARED / "deepcrack-train" / "masks" / f"{path.stem}.png"), 0) > 127
        pair = make_pair(cv2.imread(str(path)), mask, rng)
        if pair is None:
            continue
        result = align_visits(pair.before, pair.after)
        errors.append(
            corner_error_px(result.after_to_before, pair.after_to_before, mask.shape[::-1])
        )
    assert len(errors) >= 3 and max(errors) < 1.0
