"""Selection of unorganised ToF clouds (a tool that stored the points without their pixel
grid, in any order): the grid is recovered from the rays, so they are filtered, selected
and mapped as the organised clouds are."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from processing.mapping import register_clouds, select
from processing.mapping.selection import regrid
from processing.metrics import absolute_trajectory_error
from robot_link.sim.scene_sweeps import SceneSweepConfig, scene_sweep


def _unorganised(cloud: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    points = cloud[np.isfinite(cloud).all(axis=1)]
    return points[rng.permutation(len(points))]


def test_the_pixel_grid_comes_back_from_the_rays() -> None:
    sweep = scene_sweep(SceneSweepConfig(kind="box_girder", seed=6, clouds=3))
    h, w = int(sweep.intrinsics["height"]), int(sweep.intrinsics["width"])
    rng = np.random.default_rng(0)
    for cloud in sweep.clouds:
        found = regrid(_unorganised(cloud, rng))
        assert found is not None
        grid, (gh, gw) = found
        assert gh <= h and gw <= w
        # each point at its own pixel, the grid shifted by the rows and columns left empty
        organised = cloud.reshape(h, w, 3)
        rows = np.flatnonzero(np.isfinite(organised[..., 2]).any(axis=1))
        cols = np.flatnonzero(np.isfinite(organised[..., 2]).any(axis=0))
        expect = organised[rows[0] : rows[0] + gh, cols[0] : cols[0] + gw].reshape(-1, 3)
        np.testing.assert_array_equal(np.isnan(grid), np.isnan(expect))
        np.testing.assert_allclose(grid, expect, atol=1e-6, equal_nan=True)


def test_unorganised_clouds_are_selected_and_mapped_as_organised_ones() -> None:
    sweep = scene_sweep(SceneSweepConfig(kind="cross_frames", seed=7, clouds=16))
    shape = (int(sweep.intrinsics["height"]), int(sweep.intrinsics["width"]))
    rng = np.random.default_rng(1)
    loose = [_unorganised(c, rng) for c in sweep.clouds]
    a, b = select(sweep.clouds[3], shape=shape), select(loose[3])
    assert abs(len(a.points) - len(b.points)) <= 0.02 * len(a.points)
    organised = register_clouds(sweep.clouds, sweep.odometry, shape=shape).poses
    unorganised = register_clouds(loose, sweep.odometry).poses
    ate = [absolute_trajectory_error(p, sweep.truth) for p in (organised, unorganised)]
    assert ate[1] <= 1.2 * ate[0], ate


def test_clouds_that_are_no_grid_are_selected_without_one() -> None:
    sweep = scene_sweep(SceneSweepConfig(kind="box_girder", seed=6, clouds=2))
    cloud = sweep.clouds[1]
    points = cloud[np.isfinite(cloud).all(axis=1)]
    # thinned by another tool (a voxel grid): its rays no longer fall on pixels
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    thinned = np.asarray(pcd.voxel_down_sample(0.05).points)
    assert regrid(thinned) is None
    assert len(select(thinned).points) > 0
    # in a world frame, behind the sensor: not a sensor's own cloud
    assert regrid(points * [1, 1, -1]) is None
    # random points
    rng = np.random.default_rng(2)
    assert regrid(rng.uniform(0.5, 2.0, (5000, 3))) is None
