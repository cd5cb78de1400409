"""A mosaic cut to a rectangle of the structure: the crop shows the ground under the box
wherever the session's datum puts its world frame, turned with it, and is transparent off
the mosaic."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from server.reports.mosaic_crop import crop_affine, crop_mosaic

STITCH = {"origin_m": [0.0, 0.0], "px_per_m": 100.0, "overview_scale": 1.0}


def _mosaic(tmp_path: Path, *, full: bool) -> Path:
    """A 2 m x 1 m mosaic at 100 px/m, dark, with a bright 10 cm square at (1.5, 0.2) m."""
    image = np.full((100, 200, 3), 40, np.uint8)
    image[20:30, 150:160] = 255
    cv2.imwrite(str(tmp_path / "mosaic_overview.png"), image)
    if full:  # the full-resolution mosaic at twice the overview's scale, no tile pyramid
        big = cv2.resize(image, (400, 200), interpolation=cv2.INTER_NEAREST)
        cv2.imwrite(str(tmp_path / "mosaic.png"), big)
        (tmp_path / "mosaic.json").write_text(
            json.dumps({"width_px": 400, "height_px": 200, "px_per_m": 200.0, "dzi": None})
        )
    return tmp_path


def _centre(mask: np.ndarray) -> tuple[float, float]:
    ys, xs = np.nonzero(mask)
    return float(xs.mean()), float(ys.mean())


@pytest.mark.parametrize("full", [False, True])
def test_the_crop_follows_the_datum(tmp_path: Path, full: bool) -> None:
    results = _mosaic(tmp_path, full=full)
    stitch = {**STITCH, "overview_path": "mosaic_overview.png"}
    if full:
        stitch = {**stitch, "px_per_m": 200.0, "overview_scale": 0.5}
    # the world frame turned a quarter and moved: world (wx, wy) is structure (3 - wy, 1 + wx)
    datum = {"x": 3.0, "y": 1.0, "yaw": np.pi / 2}
    box = (2.0, 1.0, 3.0, 3.0)  # the whole mosaic on the structure
    crop = crop_mosaic(results, stitch, datum, box, 400 if full else 200)
    scale = 2 if full else 1
    assert crop.shape == (200 * scale, 100 * scale, 4)
    assert crop[2:-2, 2:-2, 3].min() == 255
    # the square (1.5..1.6, 0.2..0.3) m is at structure x 2.7..2.8, y 2.5..2.6
    x, y = _centre(crop[..., 0] > 150)
    assert x / scale == pytest.approx(75, abs=1.5) and y / scale == pytest.approx(155, abs=1.5)


def test_off_the_mosaic_the_crop_is_transparent(tmp_path: Path) -> None:
    results = _mosaic(tmp_path, full=False)
    stitch = {**STITCH, "overview_path": "mosaic_overview.png"}
    half = crop_mosaic(results, stitch, None, (1.5, 0.0, 2.5, 1.0), 100)
    assert half[:, :45, 3].min() == 255 and half[:, 55:, 3].max() == 0
    away = crop_mosaic(results, stitch, None, (10.0, 10.0, 11.0, 11.0), 64)
    assert away.shape == (64, 64, 4) and away[..., 3].max() == 0


def test_a_box_must_have_extent() -> None:
    with pytest.raises(ValueError, match="box"):
        crop_affine((1.0, 0.0, 0.0, 1.0), 100, None, (0.0, 0.0), 100.0)
