import cv2
import numpy as np
import pytest

from processing.poses import relative_se2
from robot_link.sim.sweeps import (
    LazySweep,
    SweepConfig,
    TiledSurface,
    make_sweep,
    painted_steel,
    texture_from_images,
    texture_size_for,
)


def test_lawnmower_sweep_overlaps_as_configured_and_turns_at_lane_ends() -> None:
    cfg = SweepConfig(frames=9, lanes=3, frame_size=(160, 120), seed=1)
    need = texture_size_for(cfg)
    s = make_sweep(painted_steel((need[1], need[0])), cfg)
    assert len(s.frames) == 9 and s.truth.shape == s.odometry.shape == (9, 3)
    step = relative_se2(s.truth[0], s.truth[1])
    assert step[0] == pytest.approx(0.65 * 160, abs=6)
    assert abs(abs(s.truth[3, 2]) - np.pi) < np.radians(3)  # second lane driven turned around
    assert cv2.imdecode(np.frombuffer(s.frames[0], np.uint8), cv2.IMREAD_COLOR).shape == (
        120,
        160,
        3,
    )
    assert ((s.gains >= 0.8) & (s.gains <= 1.2)).all()


def test_odometry_drifts_but_each_step_stays_close() -> None:
    cfg = SweepConfig(frames=30, pattern="straight", frame_size=(160, 120), seed=2)
    need = texture_size_for(cfg)
    s = make_sweep(painted_steel((need[1], need[0])), cfg)
    steps = np.array(
        [
            relative_se2(s.odometry[k], s.odometry[k + 1])
            - relative_se2(s.truth[k], s.truth[k + 1])
            for k in range(29)
        ]
    )
    assert np.abs(steps[:, :2]).max() < 0.1 * 104  # a step is off by a few percent
    assert np.linalg.norm(s.odometry[-1, :2] - s.truth[-1, :2]) > 5  # ... but errors add up


def test_too_small_texture_is_refused() -> None:
    with pytest.raises(ValueError, match="smaller than the sweep needs"):
        make_sweep(np.zeros((100, 100, 3), np.uint8), SweepConfig(frames=4))


def test_texture_from_images_lays_each_image_once() -> None:
    imgs = [np.full((20, 30), v, np.uint8) for v in (10, 20, 30)]
    tex = texture_from_images(imgs, columns=2, cell=(30, 20))
    assert tex.shape == (40, 60, 3)
    assert (
        tex[5, 5, 0] == 10 and tex[5, 35, 0] == 20 and tex[25, 5, 0] == 30 and tex[25, 35, 0] == 0
    )


def test_lazy_sweep_is_deterministic_and_continuous_across_tiles() -> None:
    cfg = SweepConfig(frames=6, lanes=2, frame_size=(160, 120), seed=4)
    a, b = LazySweep(cfg), LazySweep(cfg)
    assert np.array_equal(a[3], b[3])
    surface = TiledSurface(seed=1, tile=64)
    whole = surface.patch(0, 0, 200, 150)
    assert np.array_equal(surface.patch(50, 60, 100, 80), whole[60:140, 50:150])
