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


def test_a_lane_passed_again_is_registered_back_to_the_lane_before() -> None:
    texture = _texture(3)
    T_rt = _tof_mount()
    chain = FrameChain({"px_per_m": PX_PER_M, "T_robot_camera": [0.0, 0.0, 0.0]}, T_rt)
    h, w = 240, 320
    lane = 0.07  # the lanes 140 px apart: the frames share 100 of their 240 rows
    robot = [np.array([0.02 * k, 0.0, 0.0]) for k in range(8)]
    # back along the next lane from beyond the first one's end: the turn's frames do not
    # overlap, so the chain breaks there
    robot += [np.array([0.34 - 0.02 * k, lane, np.pi]) for k in range(14)]

    def frame(pose: np.ndarray) -> np.ndarray:
        # the image's centre over the pose, x along the heading and y to its left
        u0 = int(round(pose[0] * PX_PER_M)) + 400 - w // 2
        v0 = int(round(pose[1] * PX_PER_M)) + 200 - h // 2
        crop = texture[v0 : v0 + h, u0 : u0 + w]
        return crop.copy() if pose[2] == 0 else np.ascontiguousarray(crop[::-1, ::-1])

    # the turn onto the second lane: the odometry's heading 1.5° off from there on
    odometry = [p + ([0, 0, np.radians(1.5)] if k >= 8 else 0) for k, p in enumerate(robot)]
    for k, (pose, guess) in enumerate(zip(robot, odometry)):
        chain.add(frame(pose), float(k), guess)
    assert chain.revisits, "the second lane was not registered to the first"
    truth = np.array([se2_to_se3(*p) @ T_rt for p in robot])
    loops = chain.loops(truth, np.arange(len(robot), dtype=float))
    assert loops and not chain.revisits
    for source, target, T, _ in loops:
        assert target < 8 <= source  # from the second lane to the first
        true = np.linalg.inv(truth[target]) @ truth[source]
        assert np.abs(T[:3, 3] - true[:3, 3]).max() < 5e-4  # half a millimetre
