"""The map job's runs of clouds as parts of the job: a worker that helps loads the
session's clouds itself and registers exactly what the job's own threads would."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from processing.mapping import MapParams, TrackingParams, register_clouds, register_measured
from robot_link.clouds import encode_xyz
from robot_link.sim.tof_sweeps import TofSweepConfig, tof_sweep
from server.jobs.map import CloudRun, measure_run_part
from server.storage.files import SessionFiles
from tests.server.helping import helped_context

SAME_M = 2e-4  # the same registration, run twice (see below)


def test_runs_of_clouds_registered_by_another_process_join_into_the_whole_map(
    tmp_path: Path,
) -> None:
    sweep = tof_sweep(TofSweepConfig(seed=17))
    h, w = int(sweep.intrinsics["height"]), int(sweep.intrinsics["width"])
    files = SessionFiles(tmp_path)
    where = []
    for k, cloud in enumerate(sweep.clouds):
        rel = f"sessions/s/clouds/{k:04d}.xyz"
        payload = encode_xyz(cloud)
        files.write(rel, payload)
        where.append((rel, None, len(payload), {"encoding": "xyz_f32", "width": w, "height": h}))
    ctx, done_by_helper = helped_context(tmp_path)
    params = MapParams(tracking=TrackingParams(enabled=False))
    run = CloudRun(where, sweep.odometry, params, (h, w))
    n = len(sweep.clouds)
    spans = [(a, min(a + 20, n)) for a in range(0, n, 20)]
    measured = [m for part in ctx.map(measure_run_part, run, spans) for m in part]
    assert done_by_helper == [len(spans)]  # one chunk a run: the helper took them all
    assert not any((tmp_path / ".parts").iterdir())  # the plan is cleared
    spread = register_measured(measured, sweep.odometry, params=params)
    whole = register_clouds(sweep.clouds, sweep.odometry, params=params, shape=(h, w))
    # Open3D's parallel sums (TBB) split the work as its threads steal it: on a busy
    # machine the last digits differ, and where an ICP stops one iteration sooner or later
    # the poses move by up to a tenth of a millimetre (equal to 1e-6 m on a quiet one)
    np.testing.assert_allclose(spread.poses, whole.poses, rtol=0, atol=SAME_M)
    assert spread.loop_closures == whole.loop_closures > 0
    # the fused maps alike: where a point crosses a voxel's edge, the voxel's average moves
    # (within the voxel) and there may be one voxel more or fewer
    assert abs(len(spread.points) - len(whole.points)) <= 0.001 * len(whole.points)
    for a, b in ((spread.points, whole.points), (whole.points, spread.points)):
        gap = cKDTree(b).query(a)[0]
        assert np.mean(gap <= SAME_M) >= 0.99 and gap.max() <= params.select.voxel_m
