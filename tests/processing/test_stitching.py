import cv2
import numpy as np
import pytest

from processing.stitching import stitch_frames


def texture(seed: int = 0, shape: tuple[int, int] = (900, 1600)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 255, (shape[0] // 8, shape[1] // 8), dtype=np.uint8)
    img = cv2.resize(small, shape[::-1], interpolation=cv2.INTER_CUBIC)
    img = cv2.add(img, rng.integers(0, 20, shape, dtype=np.uint8))
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)


def cut(tex: np.ndarray, cx: float, cy: float, w: int = 320, h: int = 240) -> np.ndarray:
    M = np.float32([[1, 0, cx - (w - 1) / 2], [0, 1, cy - (h - 1) / 2]])
    return cv2.warpAffine(tex, M, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)


def test_odometry_errors_are_corrected_by_template_matching() -> None:
    tex = texture()
    centres = np.array([[300 + 200 * i, 400.0] for i in range(6)])  # 37.5 % overlap
    frames = [cut(tex, x, y) for x, y in centres]
    rng = np.random.default_rng(1)
    odo = centres + np.cumsum(rng.normal(0, 3, centres.shape), axis=0)  # drifting odometry, px
    poses = np.column_stack([odo / 100.0, np.zeros(len(odo))])  # metres at 100 px/m
    mosaic = stitch_frames(frames, poses, px_per_m=100.0)
    rel_true = centres - centres[0]
    rel_est = mosaic.frame_poses_px[:, :2] - mosaic.frame_poses_px[0, :2]
    assert np.abs(rel_est - rel_true).max() < 0.5
    assert mosaic.confident.all()
    # world mapping: frame 0's centre maps back to its odometry position
    x, y = mosaic.to_world(*mosaic.frame_poses_px[0, :2])
    assert (x, y) == pytest.approx(tuple(poses[0, :2]), abs=1e-6)


def test_frames_stitch_from_images_alone() -> None:
    tex = texture(2)
    centres = np.array([[300 + 190 * i, 420.0 + 7 * i] for i in range(5)])
    frames = [cut(tex, x, y) for x, y in centres]
    mosaic = stitch_frames(frames, None)
    rel_est = mosaic.frame_poses_px[:, :2] - mosaic.frame_poses_px[0, :2]
    assert np.abs(rel_est - (centres - centres[0])).max() < 0.5


def test_bad_inputs_raise_value_error() -> None:
    f = np.zeros((10, 10, 3), np.uint8)
    with pytest.raises(ValueError, match="empty"):
        stitch_frames([], None)
    with pytest.raises(ValueError, match="frame 1"):
        stitch_frames([f, np.zeros((12, 10, 3), np.uint8)], None)
    with pytest.raises(ValueError, match="poses must be"):
        stitch_frames([f, f], np.zeros((3, 3)), px_per_m=1.0)
