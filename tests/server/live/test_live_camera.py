"""The live map's frame chain: frames registered as they arrive, a cloud step's camera edge
given once frames past its end have come, agreeing with the true motion."""

import cv2
import numpy as np

from processing.poses import se2_to_se3
from server.live.live_camera import FrameChain

PX_PER_M = 2000.0


def _texture(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = rng.normal(128, 40, (700, 1600)).astype(np.float32)
    return np.clip(cv2.GaussianBlur(noise, (0, 0), 2.0), 0, 255).astype(np.uint8)


def _tof_mount() -> np.ndarray:
    T = se2_to_se3(0.1, 0.0, 0.0, z=0.08)
    T[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]
    return T


def test_a_cloud_steps_edge_waits_for_its_frames_and_follows_the_truth() -> None:
    texture = _texture()
    calibration = {"px_per_m": PX_PER_M, "T_robot_camera": [0.0, 0.0, 0.0]}
    T_rt = _tof_mount()
    chain = FrameChain(calibration, T_rt)
    rng = np.random.default_rng(1)
    xs = 0.02 * np.arange(12)  # a frame every 2 cm straight ahead (x along the image's x)

    def frame(k: int) -> np.ndarray:
        u = int(round(xs[k] * PX_PER_M))
        return texture[100:340, u : u + 320].copy()

    # the odometry errs by millimetres: the registration, not the odometry, makes the steps
    odometry = [np.array([x + rng.normal(0, 0.003), rng.normal(0, 0.002), 0.0]) for x in xs]
    for k in range(6):
        chain.add(frame(k), float(k), odometry[k])
    truth = np.array([se2_to_se3(x, 0.0, 0.0) @ T_rt for x in xs])
    # a cloud between frames 4.5 and 7.5: its step waits for frame 8
    chain.waiting.append((1, 4.5, 7.5))
    poses = np.array([truth[4], truth[7]])  # (clouds 0 and 1, where the graph has them)
    assert chain.edges(poses) == [] and chain.waiting
    for k in range(6, 12):
        chain.add(frame(k), float(k), odometry[k])
    edges = chain.edges(poses)
    assert not chain.waiting and len(edges) == 1
    source, target, T, information = edges[0]
    assert (source, target) == (1, 0)
    true_step = np.linalg.inv(se2_to_se3(xs[4] + 0.01, 0, 0) @ T_rt) @ (
        se2_to_se3(xs[7] + 0.01, 0, 0) @ T_rt
    )
    assert np.abs(T[:3, 3] - true_step[:3, 3]).max() < 2e-4  # a fifth of a millimetre
    assert np.linalg.matrix_rank(information, tol=1e-6 * np.abs(information).max()) == 3
    step = chain.step(4.5, 7.5)
    assert step is not None and abs(step.delta[0] - 0.06) < 2e-4


def test_frames_out_of_order_or_unlinked_give_no_step() -> None:
    texture = _texture(2)
    chain = FrameChain({"px_per_m": PX_PER_M}, _tof_mount())
    blank = np.full((240, 320), 128, np.uint8)
    chain.add(texture[:240, :320].copy(), 0.0, np.zeros(3))
    chain.add(blank, 1.0, np.array([0.02, 0.0, 0.0]))  # bare paint: does not register
    chain.add(texture[:240, 80:400].copy(), 2.0, np.array([0.04, 0.0, 0.0]))
    chain.add(texture[:240, :320].copy(), 1.5, np.zeros(3))  # late: ignored
    assert chain.times == [0.0, 1.0, 2.0]
    assert chain.step(0.0, 2.0) is None
    assert chain.step(0.0, 3.0) is None  # past the last frame
