"""The camera's mounting checked against the ToF's steps: a lever arm or a turn off by what
a tape measure gets wrong is found and corrected; a right mounting is left as stated, and
so is one where only a stretch of the ToF's own steps slipped; on a simulated structure
the map of a wrongly stated mounting comes back to the right one's."""

from dataclasses import replace

import numpy as np
import pytest
from numpy.typing import NDArray

from processing.mapping import register_clouds
from processing.mapping.camera_motion import (
    CameraFactors,
    CameraModel,
    FootStep,
    camera_factors,
    foot,
)
from processing.mapping.camera_mounting import MountingFit, MountingParams, fit_mounting
from processing.mapping.frame_pairs import frame_deltas
from processing.metrics import absolute_trajectory_error
from processing.poses import se2_to_se3, se3_exp
from robot_link.sim.camera_frames import camera_sweep
from robot_link.sim.scene_sweeps import SceneSweepConfig, scene_camera, scene_sweep

HEIGHT = 0.09  # the camera above the plate (m)
DEG = np.radians(1)


def _stated() -> NDArray[np.float64]:
    """A downward camera 12 cm ahead of the ToF, 3 cm to the side, 9 cm above the plate."""
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = [0.12, 0.03, HEIGHT]
    return T


def _route(rng: np.random.Generator, n: int = 100) -> list[NDArray[np.float64]]:
    """Lanes 5 cm a step with a 45° turn every tenth step, as the sweeps drive."""
    out = []
    for k in range(n):
        yaw = rng.choice([np.pi / 4, -np.pi / 4]) if k % 10 == 9 else rng.normal(0, 0.02)
        out.append(se2_to_se3(0.05 + rng.normal(0, 0.005), rng.normal(0, 0.002), yaw))
    return out


def _camera_steps(
    rng: np.random.Generator,
    route: list[NDArray[np.float64]],
    mounting: NDArray[np.float64],
    noise: float = 1e-4,
) -> list[FootStep | None]:
    """What a camera mounted at ``mounting`` measures of each step (``noise`` m and rad),
    its pixels scaled to metres by the stated mounting's distance to the plate."""
    true_distance = float(mounting[2, 3])  # the camera looks straight down
    out: list[FootStep | None] = []
    for A in route:
        X = np.linalg.inv(mounting) @ A @ mounting
        measured = foot(X, true_distance) * (HEIGHT / true_distance, HEIGHT / true_distance, 1)
        out.append(FootStep(measured + rng.normal(0, noise, 3), np.diag([1e-8] * 3)))
    return out


def _tof_steps(rng: np.random.Generator, route: list[NDArray[np.float64]]) -> NDArray[np.float64]:
    """The ToF's registration of each step: 2 mrad and 1 mm off."""
    return np.array(
        [A @ se3_exp(np.r_[rng.normal(0, 0.002, 3), rng.normal(0, 0.001, 3)]) for A in route]
    )


@pytest.mark.parametrize(
    "error",
    [
        np.array([DEG, DEG, 0, 0.01, 0.01, 0]),  # 1 cm and 1° off about two axes
        np.array([0, 0, DEG, 0, 0, 0]),  # turned 1° about the optical axis
    ],
)
def test_a_mounting_off_by_a_centimetre_or_a_degree_is_found(error: NDArray[np.float64]) -> None:
    rng = np.random.default_rng(3)
    route = _route(rng)
    true_mounting = _stated() @ se3_exp(error)
    steps = _camera_steps(rng, route, true_mounting)
    distances = np.full(len(route), HEIGHT)
    fit = fit_mounting(steps, _tof_steps(rng, route), distances, _stated())
    assert fit is not None and fit.corrected, fit
    # the corrected mounting predicts the camera's footprint steps from the true motion to
    # within a millimetre, half or less of what the stated one misses by
    corrected = _stated() @ se3_exp(fit.xi)

    def worst(mounting: NDArray[np.float64]) -> float:
        predicted = _camera_steps(rng, route, mounting, noise=0.0)
        truth = _camera_steps(rng, route, true_mounting, noise=0.0)
        return max(
            float(np.abs(p.delta[:2] - m.delta[:2]).max())
            for p, m in zip(predicted, truth)
            if p is not None and m is not None
        )

    assert worst(corrected) < min(0.001, worst(_stated()) / 2), (worst(corrected), worst(_stated()))


def test_a_right_mounting_is_left_as_stated() -> None:
    for seed in range(5):
        rng = np.random.default_rng(seed)
        route = _route(rng)
        steps = _camera_steps(rng, route, _stated())
        fit = fit_mounting(steps, _tof_steps(rng, route), np.full(100, HEIGHT), _stated())
        assert fit is not None and not fit.corrected, (seed, fit)


def test_a_stretch_where_the_tof_slipped_is_not_taken_for_the_mounting() -> None:
    """In the first half every turning step disagrees as a lever arm 2 cm off would (a
    stretch where the ToF's registration slid in the turns), in the second half nothing
    does: the whole route rejects the stated mounting, the second half does not, and the
    mounting stays as stated."""
    rng = np.random.default_rng(4)
    route = _route(rng)
    slipped = _stated() @ se3_exp(np.array([0, 0, 0, 0.02, -0.02, 0]))
    steps = _camera_steps(rng, route[:50], slipped) + _camera_steps(rng, route[50:], _stated())
    fit = fit_mounting(steps, _tof_steps(rng, route), np.full(100, HEIGHT), _stated())
    assert fit is not None and not fit.corrected, fit
    assert fit.statistic > 27.9 and fit.halves[0] > 11.3 > fit.halves[1], fit


def test_too_few_steps_seen_by_both_give_no_check() -> None:
    rng = np.random.default_rng(5)
    route = _route(rng, 24)
    steps: list[FootStep | None] = list(_camera_steps(rng, route, _stated()))
    steps[:5] = [None] * 5
    tof, distances = _tof_steps(rng, route), np.full(24, HEIGHT)
    assert fit_mounting(steps, tof, distances, _stated()) is None
    steps[:5] = _camera_steps(rng, route[:5], _stated())
    assert fit_mounting(steps, tof, distances, _stated()) is not None
    usable = np.arange(24) >= 5  # the first five placed by odometry alone
    assert fit_mounting(steps, tof, distances, _stated(), usable) is None
    with pytest.raises(ValueError, match="one ToF step, distance and usable flag"):
        fit_mounting(steps, tof, distances, _stated(), usable[:10])


def test_remounted_factors_measure_from_the_moved_camera() -> None:
    """A camera moved 1 cm up its axis: its distances grow by 1 cm and its steps by
    (z + 1 cm) / z."""
    model = CameraModel(320, 240, 250.0, 250.0, 160.0, 120.0, _stated())
    step = FootStep(np.array([0.05, 0.01, 0.1]), np.diag([1e-8, 1e-8, 1e-8]))
    factors = CameraFactors(model, [step, None], np.array([HEIGHT, HEIGHT, HEIGHT]))
    moved = factors.remounted(np.array([0, 0, 0, 0, 0, -0.01]))
    assert np.allclose(moved.distances_m, HEIGHT + 0.01)
    k = (HEIGHT + 0.01) / HEIGHT
    assert moved.steps[0] is not None and moved.steps[1] is None
    assert np.allclose(moved.steps[0].delta, [0.05 * k, 0.01 * k, 0.1])
    assert np.allclose(np.diag(moved.steps[0].cov), [1e-8 * k * k, 1e-8 * k * k, 1e-8])
    assert np.allclose(moved.camera.T_tof_camera[:3, 3], [0.12, 0.03, HEIGHT + 0.01])


def test_the_map_of_a_wrongly_stated_mounting_comes_back_to_the_right_ones() -> None:
    """A box girder's sweep with its camera stated 1 cm and 1° off about two axes: the map
    corrects the mounting and lands near the map of the right one (unchecked, the wrong
    mounting drifts several times more); the right mounting is left as stated."""
    config = SceneSweepConfig(kind="box_girder", seed=5, clouds=40)
    sweep, tof = scene_sweep(config), scene_camera(config)
    frames = camera_sweep(sweep.truth, tof.T_robot_tof, 5, tof.structure.mesh)
    shape = (int(sweep.intrinsics["height"]), int(sweep.intrinsics["width"]))
    times = np.arange(len(sweep.clouds), dtype=float)
    deltas = frame_deltas(frames.frames)
    right = CameraModel.of(frames.camera)
    wrong = replace(
        right, T_tof_camera=right.T_tof_camera @ se3_exp(np.r_[DEG, DEG, 0, 0.01, 0.01, 0])
    )

    def drift(
        model: CameraModel, mounting: MountingParams = MountingParams()
    ) -> tuple[float, object]:
        factors, _ = camera_factors(
            frames.frames, frames.timestamps, sweep.clouds, times, model, deltas=deltas
        )
        result = register_clouds(
            sweep.clouds, sweep.odometry, shape=shape, camera=factors, mounting=mounting
        )
        return absolute_trajectory_error(
            result.poses, sweep.truth
        ) / sweep.path_length_m, result.camera_mounting

    as_stated, right_fit = drift(right)
    corrected, wrong_fit = drift(wrong)
    unchecked, _ = drift(wrong, MountingParams(enabled=False))
    assert isinstance(right_fit, MountingFit) and not right_fit.corrected
    assert isinstance(wrong_fit, MountingFit) and wrong_fit.corrected
    summary = wrong_fit.summary()  # as map_report.json says it
    assert summary["corrected"] is True and summary["steps"] == wrong_fit.steps >= 20
    # the camera sits about 1 cm back along both of its axes from where it was stated
    assert all(-16 < v < -4 for v in summary["translation_mm"][:2]), summary
    assert corrected < 1.5 * as_stated and 2 * corrected < unchecked, (
        as_stated,
        corrected,
        unchecked,
    )
