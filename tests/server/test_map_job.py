"""The map job's runs of clouds as parts of the job: a worker that helps loads the
session's clouds itself and registers exactly what the job's own threads would."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from processing.mapping import MapParams, TrackingParams, register_clouds, register_measured
from robot_link.clouds import encode_xyz
from robot_link.sim.tof_sweeps import TofSweepConfig, tof_sweep
from server.jobs.map import CloudRun, measure_run_part
from server.storage.files import SessionFiles
from tests.server.helping import helped_context


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
    np.testing.assert_allclose(spread.poses, whole.poses, atol=1e-6)
    assert spread.loop_closures == whole.loop_closures > 0
    # the fused map is float32: poses equal to 1e-6 m may round a coordinate one ulp apart
    assert spread.points.shape == whole.points.shape
    np.testing.assert_allclose(spread.points, whole.points, rtol=0, atol=1e-6)
