"""Tracking: clouds registered to the map of all earlier ones, held by a measured prior."""

import numpy as np
import pytest

from processing.mapping import (
    MapParams,
    SelectParams,
    Tracker,
    TrackingParams,
    register_clouds,
    register_to_map,
    select,
)
from processing.mapping.tracking import search_distances
from processing.metrics import absolute_trajectory_error
from processing.poses import se3_exp, se3_log
from robot_link.sim.scene_sweeps import SceneSweepConfig, scene_sweep
from robot_link.sim.tof_sweeps import TofSweepConfig, tof_sweep


def _corner(rng: np.random.Generator, n: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    """Points and normals of three faces of a box corner with a bolt-like step: every
    direction observable."""
    u = rng.uniform(0, 0.6, (n, 2))
    faces = [
        (np.column_stack([u[:, 0], u[:, 1], np.zeros(n)]), (0, 0, 1)),
        (np.column_stack([u[:, 0], np.zeros(n), u[:, 1]]), (0, 1, 0)),
        (np.column_stack([np.zeros(n), u[:, 0], u[:, 1]]), (1, 0, 0)),
    ]
    points = np.concatenate([p for p, _ in faces]) + [0.1, 0.1, 0.6]
    normals = np.concatenate([np.tile(nrm, (n, 1)) for _, nrm in faces]).astype(float)
    return points, normals


def test_a_cloud_is_pulled_onto_the_map_from_centimetres_off() -> None:
    rng = np.random.default_rng(0)
    points, normals = _corner(rng)
    truth = se3_exp(np.array([0.02, -0.03, 0.01, 0.05, 0.02, -0.01]))
    map_points = points @ truth[:3, :3].T + truth[:3, 3] + rng.normal(0, 0.003, points.shape)
    map_normals = normals @ truth[:3, :3].T
    weak = np.diag([1 / np.radians(10) ** 2] * 3 + [1 / 0.1**2] * 3)
    T, matched, _, _ = register_to_map(
        points,
        normals,
        map_points,
        map_normals,
        np.eye(4),
        weak,
        [0.2, 0.1, 0.05, 0.03],
        TrackingParams(),
    )
    error = se3_log(np.linalg.inv(truth) @ T)
    assert matched > 0.9 * len(points)
    assert np.abs(error[3:]).max() < 1e-3 and np.degrees(np.abs(error[:3]).max()) < 0.1


def test_where_the_geometry_says_nothing_the_prediction_holds() -> None:
    """A plate alone (normals estimated from noisy points): sliding along it and turning
    about its normal are the prediction's."""
    rng = np.random.default_rng(1)
    xs, ys = np.meshgrid(np.linspace(-0.4, 0.4, 80), np.linspace(-0.3, 0.3, 60))
    plate = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, 0.5)])
    seen = [select(plate + rng.normal(0, 0.002, plate.shape)) for _ in range(2)]
    prediction = se3_exp(np.array([0, 0, 0.02, 0.03, -0.01, 0.0]))
    prior = np.diag([1 / np.radians(5) ** 2] * 3 + [1 / 0.05**2] * 3)
    T, _, _, information = register_to_map(
        np.asarray(seen[0].points),
        np.asarray(seen[0].normals),
        np.asarray(seen[1].points),
        np.asarray(seen[1].normals),
        prediction,
        prior,
        [0.1, 0.05, 0.03],
        TrackingParams(),
    )
    assert np.allclose(T[:2, 3], prediction[:2, 3], atol=2e-3)
    assert abs(se3_log(np.linalg.inv(prediction) @ T)[2]) < np.radians(0.2)
    # the pose's information: the prior's alone along the plate and about its normal, the
    # geometry's many times over across it
    assert np.allclose(information[[2, 3, 4], [2, 3, 4]], prior[[2, 3, 4], [2, 3, 4]], rtol=0.05)
    assert information[5, 5] > 100 * prior[5, 5]


def test_search_distances_run_from_the_motion_error_down_to_the_voxel() -> None:
    p = TrackingParams()
    wide = search_distances(np.radians(2), 0.02, 1.0, p, 0.02)
    assert wide[0] == pytest.approx(
        3 * (2 * np.sin(np.radians(2) * np.sqrt(3) / 2) + 0.02 * np.sqrt(3))
    )
    assert wide[-1] == pytest.approx(0.03) and all(a > b for a, b in zip(wide, wide[1:]))
    assert search_distances(np.radians(0.1), 0.001, 1.0, p, 0.02) == [pytest.approx(0.03)]
    assert search_distances(1.0, 1.0, 1.0, p, 0.02)[0] == p.max_distance_m


def test_the_prior_is_measured_tight_for_good_odometry_and_loose_for_poor() -> None:
    good = tof_sweep(TofSweepConfig(lanes_y_m=(0.56,), revisit=False, seed=5))
    poor = scene_sweep(SceneSweepConfig(kind="box_girder", seed=5, clouds=20))
    sigmas = []
    for sweep in (good, poor):
        shape = (int(sweep.intrinsics["height"]), int(sweep.intrinsics["width"]))
        tracker = Tracker()
        for cloud, guess in zip(sweep.clouds, sweep.odometry):
            tracker.track(select(cloud, SelectParams(), shape), guess)
        sigmas.append(tracker.sigmas())
    (good_rad, good_m), (poor_rad, poor_m) = sigmas
    assert good_m < 0.5 * poor_m and good_rad < 0.5 * poor_rad
    assert 0.005 < poor_m < 0.05  # the scene's odometry is off by 2 cm per axis and step


def test_tracking_keeps_the_map_on_a_structure_it_was_not_tuned_on() -> None:
    """A box girder with 2 cm / 2° odometry: registered to the map of all earlier clouds,
    the trajectory is several times closer to the truth than registered pair by pair."""
    sweep = scene_sweep(SceneSweepConfig(kind="box_girder", seed=4))
    shape = (int(sweep.intrinsics["height"]), int(sweep.intrinsics["width"]))
    tracked = register_clouds(sweep.clouds, sweep.odometry, shape=shape)
    pairwise = register_clouds(
        sweep.clouds,
        sweep.odometry,
        shape=shape,
        params=MapParams(tracking=TrackingParams(enabled=False)),
    )
    error = absolute_trajectory_error(tracked.poses, sweep.truth)
    assert error < 0.5 * absolute_trajectory_error(pairwise.poses, sweep.truth)
    assert error < 0.15 * absolute_trajectory_error(sweep.odometry, sweep.truth)


def test_a_plate_seen_far_off_does_not_pull_a_cloud_back_to_where_the_sensor_was() -> None:
    """On a gusset plate the view holds the plate and the chord's wall beside it, both along
    the route: little fixes the distance along it. Far off, the plate comes back as rows of
    returns whose normals only the pixel rows set; registered from a prediction off along
    the route, a cloud keeps about the prediction's distance instead of sliding towards
    the previous cloud's pose (18 mm typical with normals of every point)."""
    from processing.mapping.tracking import register_near
    from processing.mapping.voxel_map import VoxelMap

    sweep = scene_sweep(SceneSweepConfig(kind="gusset_joint", seed=2))
    shape = (int(sweep.intrinsics["height"]), int(sweep.intrinsics["width"]))
    params = MapParams()
    slides = []
    for k in (2, 3, 4, 5):
        seen = VoxelMap(params.select.voxel_m)
        previous = select(sweep.clouds[k - 1], params.select, shape)
        R, t = sweep.truth[k - 1][:3, :3], sweep.truth[k - 1][:3, 3]
        seen.add(np.asarray(previous.points) @ R.T + t, np.asarray(previous.normals) @ R.T)
        cloud = select(sweep.clouds[k], params.select, shape)
        for off in (-0.025, 0.0, 0.025):
            prediction = sweep.truth[k].copy()
            prediction[0, 3] += off
            found = register_near(
                np.asarray(cloud.points),
                np.asarray(cloud.normals),
                seen,
                prediction,
                (np.radians(2), 0.02),
                params.tracking,
            )
            assert found is not None
            slides.append(found.pose[0, 3] - prediction[0, 3])
    assert np.median(np.abs(slides)) < 0.006


def test_only_points_whose_neighbours_span_a_surface_keep_a_normal() -> None:
    """A plate patch keeps its points with the plate's normal facing the sensor; a lone row
    of returns (a plate seen edge-on far off) has no normal and is left out."""
    rng = np.random.default_rng(3)
    xs, ys = np.meshgrid(np.arange(-0.2, 0.2, 0.01), np.arange(-0.2, 0.2, 0.01))
    patch = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, 0.6)])
    row = np.column_stack([np.arange(-0.5, 0.5, 0.01), np.full(100, 0.5), np.full(100, 1.5)])
    pcd = select(np.concatenate([patch, row]) + rng.normal(0, 0.0005, (xs.size + 100, 3)))
    points, normals = np.asarray(pcd.points), np.asarray(pcd.normals)
    assert len(points) > 0.9 * len(select(patch).points)
    assert np.all(points[:, 2] < 1.0)  # the row is gone
    assert np.all(normals[:, 2] < -0.99)  # the patch's normal, towards the sensor


def test_a_cloud_of_lone_rows_keeps_no_point_and_is_placed_by_the_odometry() -> None:
    row = np.column_stack([np.arange(-0.5, 0.5, 0.01), np.full(100, 0.3), np.full(100, 1.5)])
    assert len(select(row).points) == 0
    sweep = tof_sweep(TofSweepConfig(lanes_y_m=(0.6,), x_range_m=(0.4, 0.6), revisit=False, seed=3))
    clouds = list(sweep.clouds)
    clouds[2] = row.astype(np.float32)
    result = register_clouds(clouds, sweep.odometry)
    assert result.used_odometry[2] and not result.used_odometry[3]
    assert np.isfinite(result.poses).all()
