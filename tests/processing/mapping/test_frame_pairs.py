"""The camera's consecutive frames registered: from a standstill, into a turn, and over a
frame that matches neither neighbour, on a simulated structure."""

import numpy as np
import pytest

from processing.mapping.camera_motion import foot
from processing.mapping.frame_pairs import frame_deltas
from processing.poses import compose_se2
from robot_link.sim.camera_frames import CameraSweep, camera_sweep
from robot_link.sim.scene_sweeps import SceneSweepConfig, scene_camera, scene_sweep


@pytest.fixture(scope="module")
def turning() -> CameraSweep:
    """An I-girder's deck plate from a standstill (smooth, low-contrast paint) and through
    the turn to the second lane."""
    config = SceneSweepConfig(kind="i_girder", seed=1)
    sweep, tof = scene_sweep(config), scene_camera(config)
    return camera_sweep(sweep.truth, tof.T_robot_tof, 1, tof.structure.mesh)


def _true_px(frames: CameraSweep, k: int) -> np.ndarray:
    """Frame pair k's true motion (dx, dy px, dθ) on the plate z = 0."""
    T = frames.truth
    z = -T[k, 2, 3] / T[k, 2, 2]
    step = foot(np.linalg.inv(T[k]) @ T[k + 1], z)
    fx = float(frames.camera["fx"])  # type: ignore[arg-type]
    return np.array([step[0] * fx / z, step[1] * fx / z, step[2]])


@pytest.mark.parametrize(
    "first, last",
    [
        (0, 8),  # from a standstill: the pairs' phase correlation is windowed or it sees no shift
        (38, 48),  # a turn of 10° a frame begun between two frames: the best match is kept
    ],
)
def test_frame_pairs_register_from_a_standstill_and_into_a_turn(turning, first, last) -> None:  # type: ignore[no-untyped-def]
    deltas = frame_deltas(turning.frames[first : last + 1])
    for k, delta in enumerate(deltas, start=first):
        assert delta is not None, f"pair {k} did not register"
        error = delta - _true_px(turning, k)
        assert np.hypot(error[0], error[1]) < 1.5 and abs(np.degrees(error[2])) < 0.3, k


def test_a_frame_matching_neither_neighbour_is_stepped_over(turning) -> None:  # type: ignore[no-untyped-def]
    """A washed-out frame (the exposure saturated) between two good ones: its two pairs do
    not register, the frames either side of it do, and each half of that step is taken."""
    frames = list(turning.frames[:9])
    frames[4] = np.full_like(frames[4], 255)
    deltas = frame_deltas(frames)
    assert all(d is not None for d in deltas)
    across = compose_se2(deltas[3], deltas[4])
    error = across - compose_se2(_true_px(turning, 3), _true_px(turning, 4))
    assert np.allclose(deltas[3], deltas[4]) and np.hypot(error[0], error[1]) < 1.5
