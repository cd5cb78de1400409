"""Two visits' 3D maps of the simulated girder aligned: from the mosaics' planar pose
(a few millimetres off, and blind to height and tilt) ICP finds the later map's frame in
the earlier one's to a millimetre, along every direction the girder's web and stiffeners
observe; on a bare plate the mosaics' in-plane pose is kept."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from processing.history.map_align import MapAlignmentError, align_maps
from robot_link.sim.structure import girder_geometry


def _pose(x: float, y: float, z: float, rx: float, ry: float, yaw: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [rx, ry, yaw], degrees=True).as_matrix()
    T[:3, 3] = (x, y, z)
    return T


def _visits(mesh: o3d.geometry.TriangleMesh, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two scans of one structure (each its own sampling and 1 mm noise): BEFORE in the
    structure's frame, AFTER in a frame ``truth`` places in BEFORE's."""
    rng = np.random.default_rng(3)
    scans = []
    for seed in (1, 2):
        o3d.utility.random.seed(seed)
        pts = np.asarray(mesh.sample_points_uniformly(40000).points)
        scans.append(pts + rng.normal(0, 0.001, pts.shape))
    inv = np.linalg.inv(truth)
    return scans[0], scans[1] @ inv[:3, :3].T + inv[:3, 3]


def _worst_mm(T: np.ndarray, truth: np.ndarray, pts: np.ndarray) -> float:
    d = pts @ (T[:3, :3] - truth[:3, :3]).T + (T[:3, 3] - truth[:3, 3])
    return float(np.max(np.linalg.norm(d, axis=1)) * 1000)


def test_the_girder_holds_the_later_map_to_a_millimetre() -> None:
    mesh = girder_geometry(1.2, 0.6, 0.1, 0.4)
    truth = _pose(0.02, -0.01, 0.003, 0.4, -0.3, 2.0)
    before, after = _visits(mesh, truth)
    # the mosaics: in-plane a few millimetres and a tenth of a degree off, no height or tilt
    start = _pose(0.024, -0.013, 0.0, 0.0, 0.0, 1.9)
    found = align_maps(before, after, start)
    assert _worst_mm(found.after_to_before, truth, after) < 1.5
    assert _worst_mm(start, truth, after) > 5  # the start really was off
    assert found.rmse_m < 0.003 and found.fitness > 0.9
    assert found.correction_m > 0.004 and found.degenerate == 0


def test_a_bare_plate_keeps_the_mosaics_in_plane_pose() -> None:
    plate = o3d.geometry.TriangleMesh.create_box(1.0, 0.6, 0.01)
    plate.translate((0, 0, -0.01))
    truth = _pose(0.01, 0.0, 0.004, 0.3, 0.0, 1.0)
    before, after = _visits(plate, truth)
    start = _pose(0.013, 0.002, 0.0, 0.0, 0.0, 1.2)
    found = align_maps(before, after, start)
    T = found.after_to_before
    assert found.degenerate == 3  # x, y and the turn about the plate's normal
    assert T[:2, 3] == pytest.approx(start[:2, 3], abs=2e-4)
    yaw = np.degrees(np.arctan2(T[1, 0], T[0, 0]))
    assert yaw == pytest.approx(1.2, abs=0.02)
    # height and tilt came from the maps
    assert abs(float((T[:3, 3] - truth[:3, 3])[2])) < 0.001


def test_maps_of_different_places_do_not_align() -> None:
    mesh = girder_geometry(1.2, 0.6, 0.1, 0.4)
    before, after = _visits(mesh, np.eye(4))
    with pytest.raises(MapAlignmentError):
        align_maps(before, after + (3.0, 0.0, 0.0), np.eye(4))
