import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from processing.mapping import register_clouds
from processing.metrics import absolute_trajectory_error
from robot_link.clouds import depth_to_points
from robot_link.sim.sensors import TofCamera
from robot_link.sim.structure import make_structure


@pytest.fixture(scope="module")
def tof() -> TofCamera:
    return TofCamera(make_structure(5, n_cracks=1, n_corrosion=1), noise_sigma_m=0.003)


def test_known_motion_is_recovered_from_perturbed_odometry(tof: TofCamera) -> None:
    rng = np.random.default_rng(0)
    robot_poses = [np.array([0.4 + 0.06 * i, 0.45, 0.5 + 0.03 * i]) for i in range(8)]
    truth = np.array([tof.T_world_tof(p) for p in robot_poses])
    clouds = [depth_to_points(tof.render(T, rng), tof.fx, tof.fy, tof.cx, tof.cy) for T in truth]
    guess = truth.copy()
    for i in range(1, len(guess)):  # odometry off by up to ~2 cm and ~1 degree, accumulating
        d = np.eye(4)
        d[:3, :3] = Rotation.from_euler("z", rng.normal(0, 0.01)).as_matrix()
        d[:3, 3] = rng.normal(0, 0.01, 3) * (1, 1, 0)
        guess[i:] = guess[i:] @ d
    result = register_clouds(clouds, guess)
    assert result.poses.shape == (8, 4, 4)
    assert absolute_trajectory_error(result.poses, truth) < absolute_trajectory_error(guess, truth)
    assert absolute_trajectory_error(result.poses, truth) < 0.01
    assert len(result.points) > 1000


def test_empty_input_and_wrong_pose_count_raise() -> None:
    with pytest.raises(ValueError, match="empty"):
        register_clouds([])
    with pytest.raises(ValueError, match="initial_poses"):
        register_clouds([np.zeros((5, 3))], np.zeros((2, 4, 4)))
