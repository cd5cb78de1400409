"""A processed session's coverage over REST: every frame's footprint and verdict, the
areas, and a grid of the holes that adds up to them."""

from __future__ import annotations

import httpx
import numpy as np
import pytest

from tests.conftest import TRUE_CAMERA_POSES, LiveServer


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


def test_frames_are_placed_by_the_mosaics_registration(inspected: tuple[LiveServer, str]) -> None:
    """After the stitch job the coverage places each frame where the mosaic put it: closer
    to where the camera truly was than its odometry pose."""
    live, sid = inspected
    cov = httpx.get(f"{live.url}/api/sessions/{sid}/coverage", params={"grid": False}).json()
    session = httpx.get(f"{live.url}/api/sessions/{sid}").json()
    frames = httpx.get(f"{live.url}/api/sessions/{sid}/frames", params={"limit": 1000}).json()
    truth = np.array(TRUE_CAMERA_POSES[sid])[:, :2]
    assert len(truth) == len(cov["frames"]) == frames["count"]
    by = [f["placed_by"] for f in cov["frames"]]
    assert by.count("mosaic") >= 0.9 * len(by)
    placed = np.array([np.mean(f["footprint"], axis=0) for f in cov["frames"]])
    mount = session["calibration"]["camera"]["T_robot_camera"][0]
    odometry = np.array(
        [
            [
                f["pose_x"] + mount * np.cos(f["pose_yaw"]),
                f["pose_y"] + mount * np.sin(f["pose_yaw"]),
            ]
            for f in frames["data"]
        ]
    )
    mosaic = [i for i, b in enumerate(by) if b == "mosaic"]
    err_placed = np.linalg.norm(placed[mosaic] - truth[mosaic], axis=1)
    err_odometry = np.linalg.norm(odometry[mosaic] - truth[mosaic], axis=1)
    print(
        f"placement error mean {err_placed.mean() * 1000:.2f} mm (odometry {err_odometry.mean() * 1000:.2f} mm)"
    )
    assert err_placed.mean() < err_odometry.mean()
