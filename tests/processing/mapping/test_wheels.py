"""The wheel model: fitted to a ToF camera's trajectory on a rolling robot, refused where
the camera slides, and its graph edge."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from processing.mapping.wheels import fit_wheel_model, residuals, wheel_edge
from processing.poses import se2_to_se3
from robot_link.sim.sensors import tof_mount
from robot_link.sim.tof_sweeps import TofSweepConfig, route


def _camera_path(
    rng: np.random.Generator, mount: np.ndarray, *, slide_m: float = 0.0, rock_deg: float = 2.0
) -> np.ndarray:
    """T_world_sensor along the two-lane route with half-circle turns, the robot rocking
    ``rock_deg`` per pose and, if ``slide_m``, pushed sideways that much per pose."""
    robot = route(
        TofSweepConfig(lanes_y_m=(0.3, 0.52), x_range_m=(0.1, 0.8), step_m=0.05, turn_step_deg=0)
    )
    poses = []
    for x, y, yaw in robot[:40]:
        rock = np.eye(4)
        rock[:3, :3] = Rotation.from_euler(
            "xy", rng.uniform(-rock_deg, rock_deg, 2), degrees=True
        ).as_matrix()
        slide = rng.normal(0, slide_m)
        x, y = x - slide * np.sin(yaw), y + slide * np.cos(yaw)
        poses.append(se2_to_se3(x, y, yaw) @ rock @ mount)
    return np.array(poses)


@pytest.mark.parametrize("yaw_deg", [0.0, 35.0, -25.0])
def test_the_camera_place_on_the_robot_is_found_from_its_trajectory(yaw_deg: float) -> None:
    mount = tof_mount(0.15, 0.1, 20.0, yaw_deg)
    poses = _camera_path(np.random.default_rng(4), mount)
    model = fit_wheel_model(poses, odometry_sigma_m=0.02)
    assert model is not None
    # the sensor sits 15 cm ahead of the axle's centre, turned with its mount (either sense
    # of "forward" is the same model)
    assert abs(abs(model.ahead_m) - mount[0, 3]) < 0.01
    # the robot's up is the turns' axis: the mount's z (down) in the sensor frame
    assert abs(abs(model.up @ mount[:3, :3].T @ [0, 0, 1]) - 1) < 1e-3
    # the robot's rocking is all that is left
    assert model.sigma_m < 0.006
    assert np.sqrt(np.mean(residuals(model, np.linalg.inv(poses[:-1]) @ poses[1:]) ** 2)) < 0.01


def test_a_camera_that_slides_sideways_gets_no_model() -> None:
    poses = _camera_path(np.random.default_rng(5), tof_mount(), slide_m=0.02)
    assert fit_wheel_model(poses, odometry_sigma_m=0.02) is None


def test_the_edge_moves_a_step_onto_the_arc_along_the_law_only() -> None:
    mount = tof_mount(0.15, 0.1, 20.0, 30.0)
    poses = _camera_path(np.random.default_rng(7), mount)
    model = fit_wheel_model(poses, odometry_sigma_m=0.02)
    assert model is not None
    step = np.linalg.inv(poses[12]) @ poses[13]  # in the first turn
    pushed = step.copy()
    pushed[:3, 3] += 0.03 * model.left  # 3 cm sideways: off the arc
    measured, information = wheel_edge(model, pushed)
    assert abs(residuals(model, measured[None])[0]) < 1e-9
    np.testing.assert_allclose(measured[:3, :3], pushed[:3, :3])
    # one direction, in translation only, at the model's spread
    assert np.linalg.matrix_rank(information, tol=1e-9) == 1
    assert np.allclose(information[:3], 0) and np.allclose(information[:, :3], 0)
    assert np.isclose(np.trace(information), 1 / model.sigma_m**2)
