"""A processed session's coverage over REST: every frame's footprint and verdict, the
areas, and a grid of the holes that adds up to them."""

from __future__ import annotations

import httpx
import pytest

from tests.conftest import LiveServer


def test_coverage_of_the_session_with_frames_holes_and_a_grid(
    inspected: tuple[LiveServer, str],
) -> None:
    live, sid = inspected
    cov = httpx.get(f"{live.url}/api/sessions/{sid}/coverage").raise_for_status().json()
    frames = httpx.get(f"{live.url}/api/sessions/{sid}/frames", params={"limit": 1}).json()
    assert len(cov["frames"]) == frames["count"]
    assert all(f["counts"] and len(f["footprint"]) == 4 for f in cov["frames"])
    assert cov["camera_mm_per_px"] < cov["required_mm_per_px"] == 0.3
    grid = cov["grid"]
    assert grid["rows"] == len(grid["holes_rle"]) > 10 and grid["cols"] > 10
    hole_cells = sum(sum(r[1::2]) for r in grid["holes_rle"])
    gaps = cov["area_surface_m2"] - cov["area_imaged_m2"]
    assert hole_cells * grid["cell_m"] ** 2 == pytest.approx(gaps, abs=1e-9)
    assert httpx.get(f"{live.url}/api/sessions/nope/coverage").status_code == 404
