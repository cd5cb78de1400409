"""A simulated gusset joint driven over with the ToF and the downward camera, shared by the
camera's tests."""

import numpy as np
import pytest

from processing.mapping.camera_motion import CameraFactors, camera_factors
from robot_link.sim.camera_frames import CameraSweep, camera_sweep
from robot_link.sim.scene_sweeps import SceneSweepConfig, scene_camera, scene_sweep
from robot_link.sim.tof_sweeps import TofSweep


@pytest.fixture(scope="session")
def sequence() -> tuple[TofSweep, CameraSweep, tuple[int, int]]:
    """The clouds, the frames and the depth images' shape of one sequence."""
    # the harder odometry (2 cm and 2° on each axis a step): a gap in the camera's steps is
    # then held by the ToF below the odometry alone
    config = SceneSweepConfig(kind="gusset_joint", seed=7, odometry_per_axis=True)
    sweep, tof = scene_sweep(config), scene_camera(config)
    frames = camera_sweep(sweep.truth, tof.T_robot_tof, 7, tof.structure.mesh)
    return sweep, frames, (int(sweep.intrinsics["height"]), int(sweep.intrinsics["width"]))


@pytest.fixture(scope="session")
def sequence_factors(sequence) -> CameraFactors:  # type: ignore[no-untyped-def]
    """The camera's factors of :func:`sequence`, its frames registered once."""
    from processing.mapping.camera_motion import CameraModel

    sweep, frames, _ = sequence
    times = np.arange(len(sweep.clouds), dtype=float)
    model = CameraModel.of(frames.camera)
    factors, _ = camera_factors(frames.frames, frames.timestamps, sweep.clouds, times, model)
    return factors
