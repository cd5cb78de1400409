"""The station's calibrated downward camera as the map's camera factors: frame motion laid
out as the mosaic lays it out, chained to the clouds' times, gives back the ToF's true
motion on a tilted mount; a mirrored image would not."""

import numpy as np
import pytest

from processing.mapping.planar_camera import camera_height, downward_camera, planar_factors
from processing.poses import compose_se2, relative_se2, se2_to_se3

PX_PER_M = 3555.0
MOUNT = (-0.12, 0.03, np.radians(5.0))


def _robot(n: int = 31) -> np.ndarray:
    """(n, 3) robot poses: straight, a turn, straight."""
    poses = [np.zeros(3)]
    for k in range(n - 1):
        step = np.array([0.02, 0.001, np.radians(3.0) if 10 < k < 20 else 0.0])
        poses.append(compose_se2(poses[-1], step))
    return np.array(poses)


def _tof_mount() -> np.ndarray:
    T = se2_to_se3(0.1, 0.0, 0.0, z=0.08)
    T[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]  # looking ahead along the robot's x
    return T


def _deltas(robot: np.ndarray, mirrored: bool = False) -> list[np.ndarray]:
    """Each frame pair's motion in the first frame's image, as the mosaic lays frames out
    (image x along the camera's heading, y to its left)."""
    cameras = np.array([compose_se2(r, np.array(MOUNT)) for r in robot])
    out = []
    for a, b in zip(cameras[:-1], cameras[1:]):
        d = relative_se2(a, b)
        sign = -1.0 if mirrored else 1.0
        out.append(np.array([d[0] * PX_PER_M, sign * d[1] * PX_PER_M, sign * d[2]]))
    return out


@pytest.mark.parametrize("every", [1, 3])
def test_frame_motion_gives_the_tofs_true_motion(every: int) -> None:
    robot = _robot()
    T_rt = _tof_mount()
    model = downward_camera(640, 480, PX_PER_M, MOUNT, T_rt)
    times = np.arange(len(robot), dtype=float)
    clouds = np.arange(0, len(robot), every)
    # the clouds half-way between frames: the steps are interpolated to their times
    cloud_times = np.clip(times[clouds] + 0.5, 0, times[-1])
    factors = planar_factors(
        _deltas(robot), times, cloud_times, model, camera_height(640, PX_PER_M)
    )
    assert all(s is not None for s in factors.steps)
    truth_robot = []
    for t in cloud_times:
        k = min(int(t), len(robot) - 2)
        truth_robot.append(compose_se2(robot[k], (t - k) * relative_se2(robot[k], robot[k + 1])))
    truth = np.array([se2_to_se3(*r) @ T_rt for r in truth_robot])
    guided = factors.guided(truth, len(truth))
    assert np.abs(guided[:, :3, 3] - truth[:, :3, 3]).max() < 2e-4
    assert np.abs(guided[:, :3, :3] - truth[:, :3, :3]).max() < 1e-3
    # each step as sure as its pixels and the calibrated scale: a tenth of a millimetre
    assert max(np.sqrt(s.cov[0, 0]) for s in factors.steps if s is not None) < 1e-3


def test_a_mirrored_image_does_not_give_the_tofs_motion() -> None:
    robot = _robot()
    T_rt = _tof_mount()
    model = downward_camera(640, 480, PX_PER_M, MOUNT, T_rt)
    times = np.arange(len(robot), dtype=float)
    factors = planar_factors(
        _deltas(robot, mirrored=True), times, times, model, camera_height(640, PX_PER_M)
    )
    truth = np.array([se2_to_se3(*r) @ T_rt for r in robot])
    guided = factors.guided(truth, len(truth))
    assert np.abs(guided[:, :3, 3] - truth[:, :3, 3]).max() > 0.01


def test_the_camera_looks_down_from_its_mount_at_its_calibrated_scale() -> None:
    T_rt = _tof_mount()
    model = downward_camera(640, 480, PX_PER_M, MOUNT, T_rt, height_m=0.09)
    mount = T_rt @ model.T_tof_camera  # the camera in the robot's frame
    assert mount[:3, 3] == pytest.approx([MOUNT[0], MOUNT[1], 0.09])
    assert mount[:3, 2] == pytest.approx([0, 0, -1])  # its optical axis down
    assert model.fx / 0.09 == pytest.approx(PX_PER_M)
    assert camera_height(640, PX_PER_M) == pytest.approx(640 / PX_PER_M)
