"""The map's pose-graph optimisation on long sessions: the sparse optimiser
(:mod:`processing.mapping.graph_optimiser`) against Open3D's dense one on the same graph,
in the same run."""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np

from bench.common import Result

# lanes across the plate and the route's length along it: sessions of about 130, 380 and
# 530 clouds
SESSIONS = (
    ((0.56, 0.74), (0.15, 1.3)),
    ((0.5, 0.62, 0.74, 0.86), (0.15, 2.5)),
    ((0.26, 0.38, 0.5, 0.62, 0.74, 0.86), (0.15, 2.5)),
)


def bench_map_graph(limit: int | None = None) -> Iterator[Result]:
    """Seconds to optimise the graph of a long simulated session (every cloud's odometry,
    ICP and loop-closure edges, plane landmarks), ours against Open3D's
    ``global_optimization``, and how far apart the two leave the poses. With ``limit``,
    the shorter session only."""

    from processing.mapping import IncrementalMap, MapParams, TrackingParams
    from processing.mapping.graph_optimiser import (
        GraphOptions,
        graph_arrays,
        open3d_optimise,
        optimise_graph,
    )
    from robot_link.sim.tof_sweeps import TofSweepConfig, tof_sweep

    params = MapParams(tracking=TrackingParams(enabled=False))
    options = GraphOptions(max_correspondence_m=params.icp.max_correspondence_m)
    for lanes, x_range in SESSIONS[:1] if limit else SESSIONS:
        sweep = tof_sweep(TofSweepConfig(lanes_y_m=lanes, x_range_m=x_range, seed=41))
        shape = (int(sweep.intrinsics["height"]), int(sweep.intrinsics["width"]))
        graph_map = IncrementalMap(params)
        for cloud, guess in zip(sweep.clouds, sweep.odometry):
            graph_map.add(cloud, guess, shape)
        graph, _ = graph_map.full_graph()
        arrays = graph_arrays(graph)
        t0 = time.perf_counter()
        ours = optimise_graph(arrays, options)
        ours_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        theirs = open3d_optimise(graph, options)
        theirs_s = time.perf_counter() - t0
        gap = np.abs(ours.poses[:, :3, 3] - graph_arrays(theirs).poses[:, :3, 3]).max()
        yield {
            "name": f"map.graph_{len(sweep.clouds)}_clouds",
            "value": round(ours_s, 3),
            "unit": "s",
            "baseline": round(theirs_s, 3),
            "ratio": round(ours_s / theirs_s, 3),
            "baseline_is": "Open3D global_optimization (dense), same graph",
            "nodes": len(arrays.poses),
            "edges": len(arrays.source),
            "max_pose_difference_m": float(f"{gap:.1e}"),
        }
