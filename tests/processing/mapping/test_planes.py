import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from processing.mapping import SelectParams, select
from processing.mapping.planes import (
    Plane,
    extract_planes,
    plane_edge,
    plane_frame,
    same_plane,
    to_frame,
)
from robot_link.clouds import depth_to_points
from robot_link.sim.sensors import TofCamera
from robot_link.sim.structure import make_structure

reg = o3d.pipelines.registration


@pytest.fixture(scope="module")
def view() -> tuple[o3d.geometry.PointCloud, np.ndarray]:
    """One ToF view along the girder (1 cm depth noise), selected as the map does, and its true pose."""
    tof = TofCamera(make_structure(3, n_cracks=1, n_corrosion=1), noise_sigma_m=0.01)
    T = tof.T_world_tof(np.array([0.6, 0.6, 0.3]))  # heading a little towards the web
    cloud = depth_to_points(tof.render(T, np.random.default_rng(3)), tof.fx, tof.fy, tof.cx, tof.cy)
    return select(cloud, SelectParams(), (172, 224)), T


def _transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def test_the_deck_plate_and_the_web_are_found_where_they_are(
    view: tuple[o3d.geometry.PointCloud, np.ndarray],
) -> None:
    """In a noisy ToF view the two large planes are the deck plate (z = 0) and the girder's
    web (y = 0.9 m), found within 1° and 1 cm, the same on every run."""
    pcd, T = view
    planes = extract_planes(np.asarray(pcd.points), np.asarray(pcd.normals))
    world = [to_frame(p, T) for p in planes]
    plate = [p for p in world if abs(p.normal[2]) > 0.9]
    web = [p for p in world if abs(p.normal[1]) > 0.9]
    assert len(plate) == 1 and len(web) == 1
    assert np.degrees(np.arccos(abs(plate[0].normal[2]))) < 1.0 and abs(plate[0].offset) < 0.01
    assert (
        np.degrees(np.arccos(abs(web[0].normal[1]))) < 1.0 and abs(abs(web[0].offset) - 0.9) < 0.01
    )
    for p in planes:  # normals face the sensor
        assert p.normal @ p.points.mean(axis=0) < 0
    again = extract_planes(np.asarray(pcd.points), np.asarray(pcd.normals))
    assert all(np.array_equal(a.normal, b.normal) for a, b in zip(planes, again))


def test_small_patches_are_not_landmarks() -> None:
    """A bolt-sized patch (5 cm) is not a plane to steer by, however flat; a large one is."""
    rng = np.random.default_rng(0)

    def patch(size: float, n: int) -> np.ndarray:
        uv = rng.uniform(-size / 2, size / 2, (n, 2))
        return np.column_stack([uv, np.full(n, 1.0) + rng.normal(0, 0.002, n)])

    assert extract_planes(patch(0.05, 200)) == []
    (found,) = extract_planes(patch(1.0, 400))
    assert (
        abs(found.normal[2]) > 0.999
        and abs(found.offset + (-1.0 if found.normal[2] < 0 else 1.0)) < 0.002
    )


def test_a_plane_through_two_separate_faces_is_refused() -> None:
    """A strip of web and, far away, another face parallel to it but 12 cm nearer (a row of
    stiffener edges): a plane tilted through both fits most points within tolerance, but its
    two halves do not agree with it, so it is not taken; the web's own strip is."""
    rng = np.random.default_rng(1)
    web = np.column_stack([rng.uniform(0.0, 0.3, 120), np.zeros(120), rng.uniform(0.0, 0.2, 120)])
    edges = np.column_stack(
        [rng.uniform(1.2, 1.5, 120), np.full(120, -0.12), rng.uniform(0.0, 0.2, 120)]
    )
    tilt = Plane(
        *_plane_through(web[:3].mean(axis=0), edges[:3].mean(axis=0)), np.vstack([web, edges])
    )
    from processing.mapping.planes import _halves_agree

    assert not _halves_agree(tilt, 2.0)
    strip = extract_planes(web, min_points=40)
    assert len(strip) == 1 and abs(strip[0].normal[1]) > 0.999


def _plane_through(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float]:
    """The vertical plane through two points (normal horizontal)."""
    d = (b - a) / np.linalg.norm(b - a)
    n = np.cross(d, [0.0, 0.0, 1.0])
    n /= np.linalg.norm(n)
    return n, float(-n @ a)


def test_the_same_plane_is_recognised_and_a_parallel_one_is_not() -> None:
    pts = np.column_stack([np.random.default_rng(2).uniform(-1, 1, (100, 2)), np.zeros(100)])
    a = Plane(np.array([0.0, 0.0, -1.0]), 0.0, pts)
    tilted = to_frame(
        a, _transform(Rotation.from_euler("x", 2, degrees=True).as_matrix(), np.zeros(3))
    )
    shifted = to_frame(a, _transform(np.eye(3), np.array([0.3, 0.0, 0.05])))
    assert same_plane(a, tilted, 5.0, 0.05) and not same_plane(a, tilted, 1.0, 0.05)
    assert not same_plane(a, shifted, 5.0, 0.03) and same_plane(
        a, to_frame(a, _transform(np.eye(3), np.array([0.3, 0.2, 0.0]))), 5.0, 0.03
    )


def test_a_plane_edge_fixes_the_planes_three_directions_in_open3d_s_pose_graph() -> None:
    """A cloud seeing a known plane, its estimate rotated 90° away from the landmark's frame
    and off in tilt and distance: optimising Open3D's pose graph with the plane edge (and a
    weak prior holding the rest) puts the plane where it belongs and leaves the directions
    a plane cannot see (sliding along it, turning about its normal) where the prior holds
    them. This checks that the information is in the frame where Open3D measures an edge's
    error (its source's): in the target's frame the same edge pulls the wrong axes."""
    rng = np.random.default_rng(5)
    # z = 0 in the landmark's frame
    landmark = Plane(np.array([0.0, 0.0, 1.0]), 0.0, np.zeros((1, 3)))
    # T_landmark_cloud
    truth = _transform(
        Rotation.from_euler("xz", [90, 30], degrees=True).as_matrix(), np.array([0.2, -0.1, 1.5])
    )
    on_plane = np.column_stack([rng.uniform(-1, 1, (300, 2)), np.zeros(300)])
    seen = Plane(
        np.linalg.inv(truth)[:3, :3] @ landmark.normal,
        0.0,
        on_plane @ np.linalg.inv(truth)[:3, :3].T + np.linalg.inv(truth)[:3, 3],
    )
    seen = Plane(seen.normal, float(-seen.normal @ seen.points.mean(axis=0)), seen.points)
    off = (
        _transform(
            Rotation.from_euler("xy", [2, -1.5], degrees=True).as_matrix(),
            np.array([0.05, 0.03, 0.04]),
        )
        @ truth
    )
    measurement, info = plane_edge(seen, landmark, off, sigma_m=0.01)
    assert np.linalg.matrix_rank(info, tol=1e-6 * np.abs(info).max()) == 3
    graph = reg.PoseGraph()
    graph.nodes.append(reg.PoseGraphNode(np.eye(4)))  # the landmark's frame, fixed
    graph.nodes.append(reg.PoseGraphNode(off))
    graph.edges.append(reg.PoseGraphEdge(1, 0, measurement, info, uncertain=False))
    graph.edges.append(reg.PoseGraphEdge(1, 0, off.copy(), np.eye(6) * 1e-2, uncertain=False))
    reg.global_optimization(
        graph,
        reg.GlobalOptimizationLevenbergMarquardt(),
        reg.GlobalOptimizationConvergenceCriteria(),
        reg.GlobalOptimizationOption(reference_node=0),
    )
    placed = to_frame(seen, np.asarray(graph.nodes[1].pose))
    assert np.degrees(np.arccos(min(1.0, placed.normal @ landmark.normal))) < 0.05
    assert np.abs(placed.points[:, 2]).max() < 0.002
    moved = np.asarray(graph.nodes[1].pose)[:3, 3] - off[:3, 3]
    assert np.hypot(moved[0], moved[1]) < 0.01  # along the plane: where the prior held it


def test_a_plane_frame_lies_on_its_plane() -> None:
    pts = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0], [0.0, 1.0, 2.0]])
    T = plane_frame(Plane(np.array([0.0, 0.0, -1.0]), 2.0, pts))
    assert np.allclose(T[:3, 2], [0, 0, -1]) and np.isclose(np.linalg.det(T[:3, :3]), 1.0)
    assert np.isclose(T[2, 3], 2.0)
