import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from processing.mapping import IncrementalMap, MapParams, TrackingParams
from processing.mapping.graph_optimiser import (
    DENSE_UP_TO,
    GraphOptions,
    PoseGraphArrays,
    graph_arrays,
    open3d_graph,
    open3d_optimise,
    optimise_graph,
    optimise_pose_graph,
)
from processing.metrics import absolute_trajectory_error
from robot_link.sim.tof_sweeps import TofSweepConfig, tof_sweep

reg = o3d.pipelines.registration


def _step(rng: np.random.Generator, deg: float, m: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(0, np.radians(deg), 3)).as_matrix()
    T[:3, 3] = rng.normal(0, m, 3)
    return T


@pytest.fixture(scope="module")
def map_graph() -> tuple[reg.PoseGraph, GraphOptions]:
    """The graph a map of a two-lane sweep along the girder optimises: odometry, ICP and
    loop-closure edges, plane landmarks and their sightings."""
    sweep = tof_sweep(TofSweepConfig(seed=21, step_m=0.02))
    params = MapParams(tracking=TrackingParams(enabled=False))
    shape = (int(sweep.intrinsics["height"]), int(sweep.intrinsics["width"]))
    graph_map = IncrementalMap(params)
    for cloud, guess in zip(sweep.clouds, sweep.odometry):
        graph_map.add(cloud, guess, shape)
    graph, _ = graph_map.full_graph()
    return graph, GraphOptions(max_correspondence_m=params.icp.max_correspondence_m)


def test_the_sparse_optimisation_is_open3ds_on_a_maps_graph(map_graph) -> None:
    graph, options = map_graph
    assert len(graph.nodes) > DENSE_UP_TO  # a graph the station optimises sparsely
    assert any(e.uncertain for e in graph.edges)
    theirs = graph_arrays(open3d_optimise(graph, options))
    ours = optimise_graph(graph_arrays(graph), options)
    before = graph_arrays(graph).poses
    moved = np.abs(theirs.poses[:, :3, 3] - before[:, :3, 3]).max()
    assert moved > 1e-3  # the optimisation had work to do
    assert np.abs(ours.poses - theirs.poses).max() < 1e-8
    assert np.array_equal(ours.source, theirs.source)
    assert np.array_equal(ours.target, theirs.target)
    assert np.allclose(ours.confidence, theirs.confidence, atol=1e-8)


def test_a_loop_closure_that_disagrees_is_pruned_and_the_rest_hold_the_truth() -> None:
    rng = np.random.default_rng(4)
    n = 2 * DENSE_UP_TO
    truth = [np.eye(4)]
    for _ in range(n - 1):
        step = np.eye(4)
        step[:3, :3] = Rotation.from_euler("z", 3, degrees=True).as_matrix()
        step[0, 3] = 0.05
        truth.append(truth[-1] @ step)
    truth = np.array(truth)
    source, target, measured, info, uncertain = [], [], [], [], []
    for i in range(1, n):  # odometry with errors: certain edges, weak
        source.append(i)
        target.append(i - 1)
        measured.append(np.linalg.inv(truth[i - 1]) @ truth[i] @ _step(rng, 0.5, 0.005))
        info.append(np.diag([1 / np.radians(0.5) ** 2] * 3 + [1 / 0.005**2] * 3))
        uncertain.append(False)
    for i in range(30, n, 10):  # exact loop closures, strong
        j = i - 30
        source.append(i)
        target.append(j)
        measured.append(np.linalg.inv(truth[j]) @ truth[i])
        info.append(np.eye(6) * 1e6)
        uncertain.append(True)
    source.append(n - 1)  # one wrong closure, 0.3 m and 10 degrees off
    target.append(n // 2)
    measured.append(np.linalg.inv(truth[n // 2]) @ truth[n - 1] @ _step(rng, 10, 0.3))
    info.append(np.eye(6) * 1e6)
    uncertain.append(True)
    odometry = [truth[0]]
    for k in range(n - 1):
        odometry.append(odometry[-1] @ measured[k])
    g = PoseGraphArrays(
        np.array(odometry),
        np.array(source),
        np.array(target),
        np.array(measured),
        np.array(info),
        np.array(uncertain),
        np.ones(len(source)),
    )
    options = GraphOptions(max_correspondence_m=0.05)
    ours = optimise_graph(g, options)
    assert not np.any((ours.source == n - 1) & (ours.target == n // 2))
    assert len(ours.source) == len(source) - 1  # only the wrong one went
    assert absolute_trajectory_error(ours.poses, truth) < 0.1 * absolute_trajectory_error(
        g.poses, truth
    )
    theirs = graph_arrays(open3d_optimise(open3d_graph(g), options))
    assert np.abs(ours.poses - theirs.poses).max() < 1e-8


def test_a_graph_in_two_parts_is_left_as_it_is() -> None:
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, 0, 3] = [0.0, 0.1, 0.5, 0.7]
    g = PoseGraphArrays(
        poses,
        np.array([1, 3]),
        np.array([0, 2]),
        np.tile(np.eye(4), (2, 1, 1)),
        np.tile(np.eye(6), (2, 1, 1)),
        np.zeros(2, bool),
        np.ones(2),
    )
    assert np.array_equal(optimise_graph(g).poses, poses)
    small = optimise_pose_graph(open3d_graph(g))  # Open3D's own does the same
    assert np.allclose(graph_arrays(small).poses, poses)
