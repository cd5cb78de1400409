"""The least trajectory error any map could reach (the Cramér–Rao bound) on simulated
sequences: it agrees with the error of odometry drawn many times where odometry is all
there is, and a view fixes only the directions its surfaces face."""

import numpy as np

from bench.map_bound import (
    aligned_error_bound,
    camera_information,
    no_slip_information,
    pose_information,
    trajectory_bound,
)
from processing.mapping.camera_motion import foot
from processing.metrics import absolute_trajectory_error
from processing.poses import se3_exp, wrap_angle
from robot_link.sim.camera_frames import DownCamera
from robot_link.sim.scene_sweeps import (
    SceneSweepConfig,
    drifting_odometry,
    scene_camera,
    scene_sweep,
)


def test_with_odometry_alone_the_bound_is_the_odometrys_own_error() -> None:
    """Odometry alone is the only estimate there is: the root mean square of its aligned
    error over many draws is the bound (small errors, where the bound's linearisation holds)."""
    truth = scene_sweep(SceneSweepConfig(kind="truss", seed=5, clouds=30)).truth
    config = SceneSweepConfig(odometry_deg=0.2, odometry_m=0.002)
    sigmas = config.odometry_sigmas
    nothing = [np.zeros((6, 6))] * len(truth)
    bound = aligned_error_bound(pose_information(nothing, truth, sigmas), truth)
    rng = np.random.default_rng(0)
    drawn = [
        absolute_trajectory_error(drifting_odometry(truth, config, rng), truth) for _ in range(1000)
    ]
    assert abs(np.sqrt(np.mean(np.square(drawn))) / bound - 1) < 0.04


def test_a_view_fixes_what_its_surfaces_face() -> None:
    """A box girder's views (webs, flanges, stiffeners, cross-frames) leave a small share of
    the odometry's error; zero range noise leaves none."""
    config = SceneSweepConfig(kind="box_girder", seed=3, clouds=16)
    sweep, camera = scene_sweep(config), scene_camera(config)
    sigmas = config.odometry_sigmas
    nothing = [np.zeros((6, 6))] * len(sweep.truth)
    alone = aligned_error_bound(pose_information(nothing, sweep.truth, sigmas), sweep.truth)
    bound = trajectory_bound(camera, sweep.truth, sigmas)
    assert bound < 0.1 * alone
    camera.noise_sigma_m = 1e-6
    assert trajectory_bound(camera, sweep.truth, sigmas) < 1e-3 * bound


def _sideways(truth: np.ndarray, T_robot_sensor: np.ndarray) -> np.ndarray:
    """Each step's sideways part (m): across the mean of the robot's two headings."""
    robot = truth @ np.linalg.inv(T_robot_sensor)
    r, heading = robot[:, :2, 3], np.arctan2(robot[:, 1, 0], robot[:, 0, 0])
    mean = heading[:-1] + np.angle(np.exp(1j * np.diff(heading))) / 2
    return np.sum(np.stack([-np.sin(mean), np.cos(mean)], 1) * np.diff(r, axis=0), axis=1)


def test_the_wheels_fix_each_steps_sideways_part() -> None:
    """The simulated robot's steps have no sideways part; moving the poses a little changes
    it as the wheels' information says (its square, summed over the steps), and the wheels
    lower the bound of odometry alone."""
    config = SceneSweepConfig(kind="truss", seed=5, clouds=30)
    truth, camera = scene_sweep(config).truth, scene_camera(config)
    mount = camera.T_robot_tof
    assert np.abs(_sideways(truth, mount)).max() < 1e-9
    H = no_slip_information(truth, mount, sigma_m=1.0)
    rng = np.random.default_rng(1)
    for _ in range(5):
        xi = rng.normal(0, 1e-5, (len(truth), 6))
        moved = np.array([se3_exp(x) @ T for x, T in zip(xi, truth)])
        change = _sideways(moved, mount)
        assert np.isclose(np.sum(change**2), xi.ravel() @ H @ xi.ravel(), rtol=1e-3, atol=0)
    sigmas = config.odometry_sigmas
    odometry = pose_information([np.zeros((6, 6))] * len(truth), truth, sigmas)
    wheels = odometry + no_slip_information(truth, mount)
    assert aligned_error_bound(wheels, truth) < aligned_error_bound(odometry, truth)


def test_the_camera_measures_each_steps_foot_and_turn() -> None:
    """Moving the poses a little changes each step's footprint step as the camera's
    information says (its squares over their variances, summed); the camera lowers the
    bound of the same views and odometry, the less the more frame pairs it chains between
    two clouds."""
    config = SceneSweepConfig(kind="i_girder", seed=4, clouds=16)
    sweep, tof = scene_sweep(config), scene_camera(config)
    down = DownCamera()
    T_tc = np.linalg.inv(tof.T_robot_tof) @ down.T_robot_camera
    size = (down.width, down.height)
    H = camera_information(sweep.truth, T_tc, down.height_m, down.f, size, sigma_px=1.0)

    def steps(poses: np.ndarray) -> np.ndarray:
        out = []
        for a, b in zip(poses[:-1], poses[1:]):
            out.append(foot(np.linalg.inv(a @ T_tc) @ b @ T_tc, down.height_m))
        return np.array(out)

    sigma_m = down.height_m / down.f
    sigma_turn = 1.0 / (0.5 * np.hypot(*size))
    rng = np.random.default_rng(2)
    for _ in range(5):
        xi = rng.normal(0, 1e-6, (len(sweep.truth), 6))
        moved = np.array([se3_exp(x) @ T for x, T in zip(xi, sweep.truth)])
        d = steps(moved) - steps(sweep.truth)
        d[:, 2] = wrap_angle(d[:, 2])
        seen = np.sum(d[:, :2] ** 2) / sigma_m**2 + np.sum(d[:, 2] ** 2) / sigma_turn**2
        assert np.isclose(seen, xi.ravel() @ H @ xi.ravel(), rtol=1e-3, atol=0)
    sigmas = config.odometry_sigmas
    without = trajectory_bound(tof, sweep.truth, sigmas)
    sigma_px = 0.3
    down_info = camera_information(sweep.truth, T_tc, down.height_m, down.f, size, sigma_px)
    with_camera = trajectory_bound(tof, sweep.truth, sigmas, down=down_info)
    assert with_camera < 0.85 * without
    # chaining more frame pairs between two poses: less information, a higher bound
    chained = camera_information(sweep.truth, T_tc, down.height_m, down.f, size, sigma_px, 4)
    assert with_camera < trajectory_bound(tof, sweep.truth, sigmas, down=chained) < without
