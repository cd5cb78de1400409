"""Defects of two aligned visits matched: a crack that grew is one ``grown`` defect with its
growth in AFTER's pixels, a new one ``new``, one no longer seen ``gone``, the rest
``unchanged``; a crack cut by the other image's border does not grow for that."""

from __future__ import annotations

import cv2
import numpy as np

from processing.history.changes import match_defects
from processing.history.pairs import viewpoint


def line(
    shape: tuple[int, int], p: tuple[int, int], q: tuple[int, int], width: int = 3
) -> np.ndarray:
    m = np.zeros(shape, np.uint8)
    cv2.line(m, p, q, 1, width)
    return m.astype(bool)


def warp(mask: np.ndarray, B2A: np.ndarray) -> np.ndarray:
    h, w = mask.shape
    return cv2.warpPerspective(mask.astype(np.uint8), B2A, (w, h), flags=cv2.INTER_NEAREST).astype(
        bool
    )


def test_grown_new_gone_and_unchanged_cracks() -> None:
    shape = (400, 600)
    B2A = viewpoint((600, 400), 7.0, 1.04, (12.0, -9.0))
    grown_before = line(shape, (100, 100), (250, 120))
    grown_after = line(shape, (100, 100), (330, 131))  # 80 px longer along the same line
    steady = line(shape, (100, 300), (260, 280))
    gone = line(shape, (420, 80), (520, 90))
    new = line(shape, (400, 250), (500, 330))
    before = grown_before | steady | gone
    after = warp(grown_after | steady | new, B2A)
    changes = match_defects(before, after, np.linalg.inv(B2A))
    by_status = {c.status: c for c in changes}
    assert sorted(c.status for c in changes) == ["gone", "grown", "new", "unchanged"]
    true_growth = np.hypot(230, 31) - np.hypot(150, 20)
    # skeletons of rotated rasters gain a few px of spurs: far below the 20 px tolerance
    assert abs(by_status["grown"].growth_px - 1.04 * true_growth) < 10
    assert abs(by_status["unchanged"].growth_px) < 10
    assert by_status["new"].bbox_before is None and by_status["new"].length_before_px is None
    assert by_status["gone"].bbox_after is None and by_status["gone"].length_after_px is None


def test_a_crack_cut_by_the_other_images_border_does_not_grow() -> None:
    shape = (300, 400)
    crack = line(shape, (50, 150), (390, 160))
    shift = viewpoint((400, 300), 0.0, 1.0, (-120.0, 0.0))  # AFTER sees 120 px less on the left
    changes = match_defects(crack, warp(crack, shift), np.linalg.inv(shift))
    assert [c.status for c in changes] == ["unchanged"]
    assert abs(changes[0].growth_px) < 4


def test_a_crack_in_pieces_on_one_visit_is_one_defect() -> None:
    shape = (300, 400)
    whole = line(shape, (40, 150), (360, 150))
    pieces = whole.copy()
    pieces[:, 150:154] = False  # a gap of 4 px where the detector lost it
    pieces[:, 250:255] = False
    changes = match_defects(pieces, whole, np.eye(3))
    assert len(changes) == 1 and changes[0].status == "unchanged"
