"""The pieces a mosaic's PNG is unpacked in: runs of its segments, as many as workers can
share and no more; one piece for a PNG another tool wrote."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from server.jobs.banded import MAX_PIECES, pieces_of
from server.storage.png_segments import join_segments, write_segment


def test_pieces_are_runs_of_whole_segments_covering_every_row(tmp_path: Path) -> None:
    image = np.random.default_rng(3).integers(0, 255, (150, 40), dtype=np.uint8)
    for y in range(0, 150, 2):  # 75 segments of 2 rows: more than workers could share
        write_segment(tmp_path / "png", y, image[y : y + 2])
    join_segments(tmp_path / "png", tmp_path / "m.png", 40, 150, 1)
    pieces = pieces_of(tmp_path / "m.png", 150)
    assert len(pieces) == MAX_PIECES < 75
    assert pieces[0][0] == 0 and pieces[-1][1] == 150
    assert all(a[1] == b[0] for a, b in zip(pieces, pieces[1:]))  # no gap, no overlap
    assert all(y0 % 2 == 0 and y1 % 2 == 0 for y0, y1 in pieces)  # whole segments
    cv2.imwrite(str(tmp_path / "other.png"), image)
    assert pieces_of(tmp_path / "other.png", 150) == [(0, 150)]
