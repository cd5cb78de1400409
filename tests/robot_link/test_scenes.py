import numpy as np
import open3d as o3d
import pytest

from robot_link.sim.members import angle, bolts, box, wide_flange
from robot_link.sim.scene_sweeps import SceneSweepConfig, scene_sweep
from robot_link.sim.scenes import SCENES, make_scene


def test_an_angle_is_two_legs_meeting_at_its_heel() -> None:
    mesh = angle((0, 0, 0), (1, 0, 0), (0.1, 0.08), 0.01, (0, 0, -1))
    # heel along x, one leg of 0.1 towards "up" (-z), the other of 0.08 along +y
    assert np.allclose(mesh.get_min_bound(), (0, 0, -0.1), atol=1e-9)
    assert np.allclose(mesh.get_max_bound(), (1, 0.08, 0), atol=1e-9)
    # an L, not a box: the corner opposite the heel is empty
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    inside = scene.compute_occupancy(
        o3d.core.Tensor([[0.5, 0.005, -0.005], [0.5, 0.05, -0.05]], o3d.core.float32)
    )
    assert inside.numpy().tolist() == [1, 0]


def test_members_compose_and_bolts_stand_on_their_face() -> None:
    mesh = box(0, 1, 0, 1, 0, 0.01) + bolts([(0.5, 0.5, 0.0)], (0, 0, -1), height=0.012)
    assert mesh.get_min_bound()[2] == pytest.approx(-0.012)
    beam = wide_flange((0, 0, 0), (0, 0, -2), 0.3, 0.2, 0.01, 0.015, (1, 0, 0))
    assert np.ptp(np.asarray(beam.vertices), axis=0) == pytest.approx([0.3, 0.2, 2.0])


@pytest.mark.parametrize("kind", list(SCENES))
def test_each_structure_type_is_drawn_from_its_seed(kind: str) -> None:
    a, b, c = make_scene(kind, 3), make_scene(kind, 3), make_scene(kind, 4)
    assert np.array_equal(np.asarray(a.mesh.vertices), np.asarray(b.mesh.vertices))
    assert not np.array_equal(np.asarray(a.mesh.vertices), np.asarray(c.mesh.vertices))
    assert a.x_range_m[0] < a.x_range_m[1] and a.lanes_y_m[0] < a.lanes_y_m[1]


@pytest.mark.parametrize("kind", list(SCENES))
def test_a_sweep_sees_structure_beyond_the_face_it_drives_on(kind: str) -> None:
    sweep = scene_sweep(SceneSweepConfig(kind=kind, seed=5, clouds=12))
    assert len(sweep.clouds) == 12 and sweep.truth.shape == sweep.odometry.shape == (12, 4, 4)
    w, h = int(sweep.intrinsics["width"]), int(sweep.intrinsics["height"])
    off_face = 0
    for cloud, T in zip(sweep.clouds, sweep.truth):
        assert cloud.shape == (w * h, 3)
        pts = cloud[np.isfinite(cloud).all(axis=1)].astype(float)
        world = pts @ T[:3, :3].T + T[:3, 3]
        off_face += int((world[:, 2] < -0.05).sum())  # 5 cm or more off the face z = 0
    assert off_face > 1000
    # the odometry drifts from the truth; the truth rocks (roll/pitch) on the face
    assert not np.allclose(sweep.odometry[-1], sweep.truth[-1], atol=0.01)
    z_axes = sweep.truth[:, :3, 1]  # sensor y (down in the image)
    assert np.ptp(z_axes[:, 2]) > 0.001


def test_odometry_errors_scale_with_the_configuration() -> None:
    from processing.metrics import absolute_trajectory_error

    small = scene_sweep(
        SceneSweepConfig(kind="truss", seed=2, clouds=20, odometry_m=0.002, odometry_deg=0.2)
    )
    large = scene_sweep(SceneSweepConfig(kind="truss", seed=2, clouds=20))
    assert absolute_trajectory_error(small.odometry, small.truth) < 0.3 * absolute_trajectory_error(
        large.odometry, large.truth
    )
