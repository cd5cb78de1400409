import numpy as np
import open3d as o3d
import pytest

from bench.map import oracle_poses, sees_structure
from processing.metrics import absolute_trajectory_error

pytestmark = pytest.mark.slow  # an end-to-end run


def _pose(x: float, yaw: float) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    T[0, 3] = x
    return T


def _cloud(points: np.ndarray) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))


def test_only_clouds_with_points_off_the_plate_see_structure() -> None:
    rng = np.random.default_rng(0)
    plate = np.column_stack([rng.uniform(0, 1, (200, 2)), np.zeros(200)])
    wall = np.column_stack([np.full(40, 0.5), rng.uniform(0, 1, 40), rng.uniform(-0.3, -0.05, 40)])
    raised = np.eye(4)
    raised[2, 3] = -0.1  # a sensor 10 cm above the plate: its points are 10 cm further along its z
    plate_seen_from_above = plate + [0, 0, 0.1]
    seen = sees_structure(
        [
            _cloud(plate),
            _cloud(np.vstack([plate, wall])),
            _cloud(plate_seen_from_above),
            _cloud(np.zeros((0, 3))),
        ],
        np.stack([np.eye(4), np.eye(4), raised, np.eye(4)]),
    )
    assert seen.tolist() == [False, True, False, False]


def test_the_oracle_takes_true_steps_only_between_clouds_that_see_structure() -> None:
    truth = np.stack([_pose(0.04 * k, 0.0) for k in range(20)])
    odometry = np.stack([_pose(0.041 * k, 0.003 * k) for k in range(20)])
    all_seen = oracle_poses(truth, odometry, np.ones(20, bool))
    assert absolute_trajectory_error(all_seen, truth) < 1e-9
    none_seen = oracle_poses(truth, odometry, np.zeros(20, bool))
    assert np.allclose(none_seen, odometry)
    half = oracle_poses(truth, odometry, np.arange(20) < 10)
    assert (
        absolute_trajectory_error(all_seen, truth)
        < absolute_trajectory_error(half, truth)
        < absolute_trajectory_error(odometry, truth)
    )
