"""The simulated downward camera: frames of one textured surface along the trajectory,
registered pair by pair to the motion its true poses give."""

import numpy as np

from processing.mapping.camera_motion import foot
from processing.mapping.frame_pairs import frame_deltas
from robot_link.sim.camera_frames import camera_sweep
from robot_link.sim.scene_sweeps import SceneSweepConfig, scene_camera, scene_sweep


def test_consecutive_frames_show_the_true_motion() -> None:
    config = SceneSweepConfig(kind="box_girder", seed=11, clouds=8)
    sweep, tof = scene_sweep(config), scene_camera(config)
    frames = camera_sweep(sweep.truth, tof.T_robot_tof, 11, tof.structure.mesh)
    assert len(frames.frames) == len(frames.timestamps) == len(frames.truth)
    assert frames.timestamps[0] == 0 and frames.timestamps[-1] == len(sweep.clouds) - 1
    f = float(frames.camera["fx"])  # type: ignore[arg-type]
    errors_px = []
    deltas = frame_deltas(frames.frames)
    # stretches of smooth paint are textureless on purpose: a few pairs do not register
    assert sum(d is not None for d in deltas) >= 0.8 * len(deltas)
    for k, delta in enumerate(deltas):
        if delta is None:
            continue
        a, b = frames.truth[k], frames.truth[k + 1]
        distance = -a[2, 3] / a[2, 2]  # to the plate z = 0 along the optical axis
        true = foot(np.linalg.inv(a) @ b, distance)
        errors_px.append(np.abs(delta[:2] - true[:2] * f / distance).max())
        assert abs(delta[2] - true[2]) < 0.005
    # the robot rocks between frames: a view turned by a fraction of a degree is not a
    # rigid image motion, and the overlap's motion is not quite the centre's
    assert max(errors_px) < 1.0 and np.median(errors_px) < 0.3
    again = camera_sweep(sweep.truth, tof.T_robot_tof, 11, tof.structure.mesh)
    assert all((a == b).all() for a, b in zip(frames.frames, again.frames))
