"""What a ToF cloud says of the plane the robot stands on, on the simulator's plate girder:
the plate where it is, nothing past its free edges, and the cloud's own noise."""

from __future__ import annotations

import numpy as np
import pytest

from processing.poses import compose_se2
from processing.surface_evidence import pixel_rays, range_noise, surface_evidence
from robot_link.clouds import depth_to_points
from robot_link.sim.sensors import TofCamera
from robot_link.sim.structure import make_structure


@pytest.fixture(scope="module")
def tof() -> TofCamera:
    return TofCamera(make_structure(3))


def read(tof: TofCamera, pose: tuple[float, float, float], seed: int = 0):  # type: ignore[no-untyped-def]
    depth = tof.render(tof.T_world_tof(np.array(pose)), np.random.default_rng(seed))
    grid = depth_to_points(depth, tof.fx, tof.fy, tof.cx, tof.cy).reshape(tof.height, tof.width, 3)
    rays = pixel_rays(tof.width, tof.height, tof.fx, tof.fy, tof.cx, tof.cy)
    ev = surface_evidence(grid, tof.T_robot_tof, rays)
    world = np.array([compose_se2(np.array(pose), np.array([x, y, 0.0]))[:2] for x, y in ev.xy])
    return ev, world, grid


def beyond_plate(world: np.ndarray, size: tuple[float, float]) -> np.ndarray:
    """How far each point lies past the plate's nearest edge (negative: on it)."""
    x, y = world[:, 0], world[:, 1]
    return np.maximum.reduce([-x, x - size[0], -y, y - size[1]])


def test_a_robot_mid_plate_sees_plate_all_round(tof: TofCamera) -> None:
    ev, world, _ = read(tof, (0.8, 0.45, 0.0))
    assert len(ev.on) > 10_000 and ev.on.mean() > 0.999
    assert (beyond_plate(world, tof.structure.plate_size_m) < 0).all()


def test_past_a_free_edge_the_plane_is_no_surface(tof: TofCamera) -> None:
    """Heading out over the plate's y = 0 edge (an edge angle stands up there) and to its far
    x edge (nothing beyond): the plane past them is no surface, to within a few mm; where
    the angle stands, its foot is read as plate to a few cm."""
    size = tof.structure.plate_size_m
    for pose, slack in (((1.2, 0.45, 0.0), 0.0), ((0.8, 0.10, -0.6), 0.02)):
        ev, world, _ = read(tof, pose)
        past = beyond_plate(world, size)
        assert (~ev.on).sum() > 1000, pose  # the edge is seen
        assert (ev.on[past > slack]).sum() == 0, pose
        assert (~ev.on[past < -0.01]).mean() < 0.01, pose


def test_the_tolerance_is_the_clouds_own_noise(tof: TofCamera) -> None:
    """The simulator's depth noise is 1 cm: the range noise read from the cloud is that
    (the range is a little longer than the depth off the optical axis), whatever the view."""
    for pose in ((0.8, 0.45, 0.0), (0.8, 0.8, 0.4), (0.8, 0.10, -0.6)):
        _, _, grid = read(tof, pose)
        sigma = range_noise(np.linalg.norm(grid, axis=2))
        assert 0.009 < sigma < 0.013, (pose, sigma)


def test_a_cloud_without_pixel_order_gives_evidence_of_its_returns_only(tof: TofCamera) -> None:
    ev, _, grid = read(tof, (0.8, 0.10, -0.6))
    points = grid.reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    loose = surface_evidence(np.random.default_rng(1).permutation(points), tof.T_robot_tof)
    assert len(loose.on) > 1000
    assert loose.on.sum() == pytest.approx(ev.on.sum(), rel=0.05)
    assert (~loose.on).sum() <= (~ev.on).sum()  # the rays with no return are not known


def test_no_rays_meet_the_plane_from_a_sensor_looking_up() -> None:
    T = np.eye(4)
    T[:3, 3] = (0, 0, -0.1)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # its optical axis (z) points away from the plate
    rays = pixel_rays(8, 6, 5.0, 5.0, 3.5, 2.5)
    ev = surface_evidence(np.full((6, 8, 3), np.nan), T, rays)
    assert len(ev.on) == 0
