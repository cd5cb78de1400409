"""The downward camera's factors: footprint steps chained to the clouds' times, edges that
agree with the truth and tie only what the camera sees, the surface distance from the ToF,
and the map with them, on simulated structures."""

import numpy as np
import pytest

from processing.mapping import register_clouds
from processing.mapping.camera_motion import (
    CameraFactors,
    CameraModel,
    FootStep,
    camera_factors,
    cloud_steps,
    scale_error,
    with_scale_error,
)
from processing.mapping.graph_optimiser import _linearised
from processing.mapping.surface_distance import surface_distances
from processing.metrics import absolute_trajectory_error
from robot_link.sim.camera_frames import CameraSweep


def _model(frames: CameraSweep) -> CameraModel:
    return CameraModel.of(frames.camera)


def test_frame_steps_chain_to_the_clouds_times() -> None:
    """Three frames a cloud, turning steadily: the chained step between clouds is the sum
    of the frames' (composed in SE(2)), with the variance of the frames it spans."""
    step = FootStep(np.array([0.01, 0.0, 0.02]), np.diag([1e-8, 1e-8, 1e-8]))
    frame_times = np.arange(10) / 3
    steps = cloud_steps(frame_times, [step] * 9, np.array([0.0, 1.0, 2.0, 3.0]))
    assert len(steps) == 3 and all(s is not None for s in steps)
    expected = np.zeros(3)
    for _ in range(3):
        c, s = np.cos(expected[2]), np.sin(expected[2])
        expected = expected + [c * 0.01, s * 0.01, 0.02]
    assert np.allclose(steps[0].delta, expected, atol=1e-12)
    assert steps[0].cov[2, 2] == pytest.approx(3e-8)
    broken = cloud_steps(frame_times, [step] * 4 + [None] + [step] * 4, np.arange(4.0))
    assert broken[0] is not None and broken[1] is None and broken[2] is not None


def test_the_scale_error_is_the_routes_scatter_of_distances_along_each_step() -> None:
    """Distances that agree leave the steps' length as sure as the floor; distances that
    scatter (a plate on the plate, a surface the ToF did not see) make it that unsure, along
    the step only: its width and heading keep their information."""
    rng = np.random.default_rng(0)
    steady = 0.09 + 0.0001 * rng.standard_normal(40)
    assert scale_error(steady) == pytest.approx(0.005)
    scattered = np.where(np.arange(40) % 3 == 0, 0.076, 0.09) + 0.004 * rng.standard_normal(40)
    scattered[5] = np.nan
    assert 0.03 < scale_error(scattered) < 0.2
    assert scale_error(np.full(3, np.nan)) == pytest.approx(0.005)
    step = FootStep(np.array([0.06, 0.0, 0.01]), np.diag([1e-8, 1e-8, 1e-6]))
    widened = with_scale_error(step, 0.1)
    assert widened is not None and with_scale_error(None, 0.1) is None
    assert widened.cov[0, 0] == pytest.approx(1e-8 + (0.1 * 0.06) ** 2)
    assert widened.cov[1, 1] == pytest.approx(1e-8) and widened.cov[2, 2] == pytest.approx(1e-6)


def test_the_surface_distance_follows_the_truth(sequence) -> None:  # type: ignore[no-untyped-def]
    sweep, frames, _ = sequence
    model = _model(frames)
    measured = surface_distances(sweep.clouds, model)
    camera_in_world = sweep.truth @ model.T_tof_camera
    truth = -camera_in_world[:, 2, 3] / camera_in_world[:, 2, 2]  # to the plate z = 0
    assert np.median(np.abs(measured - truth)) < 0.001


def test_edges_agree_with_the_truth_and_tie_only_what_the_camera_sees(sequence) -> None:  # type: ignore[no-untyped-def]
    sweep, frames, _ = sequence
    model = _model(frames)
    factors, registered = camera_factors(
        frames.frames,
        frames.timestamps,
        sweep.clouds,
        np.arange(len(sweep.clouds), dtype=float),
        model,
    )
    # smooth, textureless paint leaves a few pairs unregistered: their steps are not linked
    assert registered >= 0.9 * (len(frames.frames) - 1)
    edges = factors.edges(sweep.truth)
    assert len(edges) == sum(s is not None for s in factors.steps) >= 0.8 * len(factors.steps)
    chi2 = []
    for source, target, X, information in edges:
        assert np.linalg.matrix_rank(information, tol=1e-6 * np.abs(information).max()) == 3
        zeta = _linearised(
            np.linalg.inv(X) @ np.linalg.inv(sweep.truth[target]) @ sweep.truth[source]
        )
        chi2.append(zeta @ information @ zeta)
    assert np.mean(chi2) < 3 * 3  # three measured directions a step, errors as modelled


def test_the_camera_cuts_the_drift_and_a_gap_is_held_by_the_tof(sequence, sequence_factors) -> None:  # type: ignore[no-untyped-def]
    sweep, frames, shape = sequence
    factors = sequence_factors
    model = factors.camera
    path = sweep.path_length_m
    without = absolute_trajectory_error(
        register_clouds(sweep.clouds, sweep.odometry, shape=shape).poses, sweep.truth
    )
    fused = register_clouds(sweep.clouds, sweep.odometry, shape=shape, camera=factors)
    with_camera = absolute_trajectory_error(fused.poses, sweep.truth)
    assert with_camera < 0.4 * without and 100 * with_camera / path < 0.5
    linked = [s is not None for s in factors.steps]
    assert list(fused.camera_steps) == [False, *linked]
    gap = CameraFactors(
        model,
        [None if 10 <= k < 16 else s for k, s in enumerate(factors.steps)],
        factors.distances_m,
    )
    gapped = register_clouds(sweep.clouds, sweep.odometry, shape=shape, camera=gap)
    assert not gapped.camera_steps[11:17].any()
    # across six steps the camera did not see, the ToF holds the map: near the map without
    # frames (not yet never above it), below the odometry alone
    odometry = absolute_trajectory_error(sweep.odometry, sweep.truth)
    assert absolute_trajectory_error(gapped.poses, sweep.truth) < min(1.5 * without, odometry)
