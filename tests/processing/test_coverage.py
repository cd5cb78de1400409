"""Coverage on the simulator's painted steel: footprints of real camera frames placed by
pose, frames judged by resolution, sharpness and exposure, and the holes where a lane was
left out or a frame did not count."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from processing.coverage import (
    CoverageParams,
    SurfaceVotes,
    coverage_map,
    dark_tiles,
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


def frame_tiles(structure, cam: np.ndarray):  # type: ignore[no-untyped-def]
    """A real frame's footprint and which of its tiles are dark."""
    image = CAMERA.render(structure, cam, np.random.default_rng(0))
    dark = dark_tiles(frame_quality(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)), CoverageParams())
    assert dark is not None
    return footprint(cam, PX_PER_M, SIZE), dark


def test_the_part_of_a_frame_past_the_plates_edge_is_no_surface(structure) -> None:  # type: ignore[no-untyped-def]
    """A lane along the plate's y = 0 edge with the footprint 4 cm past it: what the camera
    saw past the edge is dark, images nothing and is not in view; no hole lies there."""
    across = CAMERA.footprint_m[1]
    y = across / 2 - 0.04
    xs = np.arange(0.3, 0.9, 0.1)
    parts = [frame_tiles(structure, np.array([x, y, 0.0])) for x in xs]
    feet, tiles = [p[0] for p in parts], [p[1] for p in parts]
    assert all(t.any() and not t.all() for t in tiles)
    plain = coverage_map(feet, [True] * len(feet))
    cov = coverage_map(feet, [True] * len(feet), dark=tiles)
    cell = cov.cell_m
    rows = np.nonzero(cov.surface.any(axis=1))[0]
    lowest = cov.origin_m[1] + rows.min() * cell
    tile = CAMERA.footprint_m[1] / 48
    assert -tile - cell <= lowest <= cell  # the edge, to within a tile
    assert plain.origin_m[1] + np.nonzero(plain.surface.any(axis=1))[0].min() * cell < -0.035
    assert cov.area_imaged_m2 == pytest.approx(cov.area_surface_m2)
    assert cov.area_imaged_m2 < plain.area_imaged_m2 - 0.5 * 0.04 * 0.6
    assert not cov.holes


def test_the_depth_cameras_votes_decide_what_no_frame_saw() -> None:
    """Two lanes with a gap: where the depth camera saw the plane, the gap is a hole; where
    it saw past an edge, or nothing saw, it is not in view; a frame's own view wins."""
    along, across = CAMERA.footprint_m
    xs = np.arange(0.2, 1.0, along / 2)
    feet = lane(0.2, xs) + lane(0.2 + 2 * across, xs)
    gap = np.mgrid[0.25:0.55:0.002, 0.2 + across / 2 + 0.005 : 0.2 + 1.5 * across - 0.005 : 0.002]
    gap = gap.reshape(2, -1).T
    left, right = gap[gap[:, 0] < 0.4], gap[gap[:, 0] >= 0.4]
    under = np.array([[0.3, 0.2]])  # in a frame, but a vote against it
    votes = SurfaceVotes(
        np.vstack([left, right, under]),
        np.r_[np.ones(len(left), bool), np.zeros(len(right), bool), False],
        np.ones(len(left) + len(right) + 1),
    )
    cov = coverage_map(feet, [True] * len(feet), surface_votes=votes)
    assert len(cov.holes) == 1
    h = cov.holes[0]
    assert 0.25 <= h.x_m < 0.4 and h.area_m2 == pytest.approx(0.15 * across, rel=0.15)
    plain = coverage_map(feet, [True] * len(feet))
    assert plain.holes[0].area_m2 > 0.5 * (xs[-1] - xs[0]) * across
    assert cov.area_imaged_m2 == pytest.approx(plain.area_imaged_m2)
