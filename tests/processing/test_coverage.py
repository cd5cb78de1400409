"""Coverage on the simulator's painted steel: footprints of real camera frames placed by
pose, frames judged by resolution, sharpness and exposure, and the holes where a lane was
left out or a frame did not count."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from processing.coverage import (
    CoverageParams,
    coverage_map,
    footprint,
    frame_quality,
    frame_verdicts,
)
from robot_link.sim.sensors import DownwardCamera
from robot_link.sim.structure import make_structure

CAMERA = DownwardCamera()
PX_PER_M = 1 / CAMERA.m_per_px
SIZE = (CAMERA.width, CAMERA.height)


@pytest.fixture(scope="module")
def structure():  # type: ignore[no-untyped-def]
    return make_structure(np.random.default_rng(11))


def lane(y: float, xs: np.ndarray) -> list[np.ndarray]:
    return [footprint(np.array([x, y, 0.0]), PX_PER_M, SIZE) for x in xs]


def test_footprint_is_the_cameras_field_on_the_surface() -> None:
    corners = footprint(np.array([1.0, 0.5, np.pi / 2]), PX_PER_M, SIZE)
    along, across = CAMERA.footprint_m
    sides = sorted(np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1))
    assert sides == pytest.approx([across, across, along, along], rel=1e-6)
    assert corners.mean(axis=0) == pytest.approx([1.0, 0.5])


def test_a_missed_strip_between_lanes_is_one_hole_where_it_is() -> None:
    along, across = CAMERA.footprint_m
    xs = np.arange(0.0, 1.0, along * 0.8)
    gap = 0.05  # metres of surface between the two lanes nobody imaged
    feet = lane(0.0, xs) + lane(across + gap, xs)
    cov = coverage_map(feet, [True] * len(feet))
    assert len(cov.holes) == 1
    hole = cov.holes[0]
    assert hole.y_m == pytest.approx(across / 2 + gap / 2, abs=2 * cov.cell_m)
    assert hole.bbox_m[3] == pytest.approx(gap, abs=2 * cov.cell_m)
    assert hole.area_m2 == pytest.approx(gap * (xs[-1] - xs[0] + along), rel=0.1)
    assert cov.fraction == pytest.approx(1 - hole.area_m2 / cov.area_surface_m2, abs=0.02)
    # the lanes touching: nothing missed
    touching = lane(0.0, xs) + lane(across * 0.9, xs)
    full = coverage_map(touching, [True] * len(touching))
    assert full.holes == [] and full.fraction > 0.99


def test_blurred_dark_and_coarse_frames_do_not_count(structure) -> None:  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(5)
    along, _ = CAMERA.footprint_m
    poses = [np.array([0.3 + i * along * 0.8, 0.3, 0.0]) for i in range(8)]
    images = [CAMERA.render(structure, p, rng) for p in poses]
    gray = [cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) for im in images]
    gray[3] = cv2.GaussianBlur(gray[3], (0, 0), 3.0)  # motion or focus blur
    gray[5] = (gray[5] * 0.15).astype(np.uint8)  # the lamp off
    verdicts = frame_verdicts([frame_quality(g) for g in gray], 1000 / PX_PER_M, CoverageParams())
    assert verdicts == ["", "", "", "blurred", "", "too dark", "", ""]
    coarse = frame_verdicts([frame_quality(g) for g in gray], 0.5, CoverageParams())
    assert all("coarser than the required" in v for v in coarse)
    feet = [footprint(p, PX_PER_M, SIZE) for p in poses]
    cov = coverage_map(feet, [not v for v in verdicts])
    # frames overlap by a fifth: each rejected frame leaves a hole of about 3/5 of its footprint
    assert len(cov.holes) == 2
    assert sorted(h.x_m for h in cov.holes) == pytest.approx(
        [poses[3][0], poses[5][0]], abs=along * 0.1
    )


def test_a_hole_is_placed_where_nothing_was_imaged_and_slivers_are_no_holes() -> None:
    """A lane out, a turn, half a lane back: the hull spans the strip between the lanes and
    the half lane not driven, an L around the lane back. The hole is reported at a point
    no footprint covers (its centroid lies in the lane back); two frames a twentieth of a
    footprint apart leave a sliver, no hole."""
    poses = [(x, 0.0, 0.0) for x in np.arange(0.0, 1.0, 0.05)]
    poses += [(1.0 + 0.2 * np.sin(a), 0.2 - 0.2 * np.cos(a), a) for a in np.linspace(0, np.pi, 9)]
    poses += [(x, 0.40, np.pi) for x in np.arange(1.0, 0.45, -0.05)]
    prints = [footprint(np.array(p), PX_PER_M, SIZE) for p in poses]
    cov = coverage_map(prints, [True] * len(prints))
    assert cov.holes, "the strip between the lanes is not imaged"
    spot = (float(cov.holes[0].x_m), float(cov.holes[0].y_m))
    for p in prints:
        assert cv2.pointPolygonTest(p.astype(np.float32), spot, False) < 0
    w = np.linalg.norm(prints[0][1] - prints[0][0])
    pair = [footprint(np.array([x, 0.0, 0.0]), PX_PER_M, SIZE) for x in (0.0, 1.05 * w)]
    assert coverage_map(pair, [True, True]).holes == []
