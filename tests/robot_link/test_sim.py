import numpy as np
import pytest

from robot_link.sim.robot import EdgeAction, RobotSpec, SimRobot, adhesion_margin, edge_avoidance
from robot_link.sim.sensors import DownwardCamera, TofCamera
from robot_link.sim.structure import make_structure


@pytest.fixture(scope="module")
def structure():
    return make_structure(3)


def test_capture_spacing_is_derived_from_footprint_and_overlap() -> None:
    cam = DownwardCamera()
    spacing = cam.capture_spacing_m(0.30)
    assert spacing == pytest.approx(0.12)  # the paper's 12 cm for 18 cm x 14 cm
    overlap = 1 - spacing / cam.footprint_m[0]
    assert overlap >= 0.30
    assert cam.capture_spacing_m(0.5) == pytest.approx(0.09)


@pytest.mark.parametrize(
    "out, action",
    [
        ([], EdgeAction.none),
        ([1], EdgeAction.back_off_turn_left),  # front right sees no surface
        ([0], EdgeAction.back_off_turn_right),
        ([3], EdgeAction.back_off_turn_left),
        ([0, 1], EdgeAction.stop_and_wait),
        ([0, 2, 3], EdgeAction.stop_and_wait),
    ],
)
def test_edge_avoidance_follows_algorithm_1(out: list[int], action: EdgeAction) -> None:
    cal = np.full(4, 0.03)
    ranges = cal.copy()
    ranges[out] = 0.5
    got, which = edge_avoidance(ranges, cal, 0.02)
    assert got is action and which == out


def test_adhesion_margin_of_eq_1_is_safe_on_a_vertical_web_and_worse_than_flat() -> None:
    spec = RobotSpec()
    assert adhesion_margin(spec, 90) > 1
    assert adhesion_margin(spec, 90) < adhesion_margin(spec, 0)


def test_odometry_drifts_but_stays_close_over_a_metre() -> None:
    robot = SimRobot(RobotSpec(), np.random.default_rng(1))
    for _ in range(200):
        robot.step(0.1, 0.0, 0.05)
    assert robot.pose[0] == pytest.approx(1.0, abs=0.03)
    assert np.linalg.norm(robot.pose[:2] - robot.odom[:2]) < 0.03
    assert robot.pose[0] < robot.odom[0] + 1e-9  # slip makes the body fall behind the wheels


def test_ir_sensors_see_the_plate_edge(structure) -> None:
    robot = SimRobot(RobotSpec(), np.random.default_rng(0), pose=np.array([1.55, 0.3, 0.0]))
    ranges = robot.ir_ranges(structure.on_plate)
    assert ranges[0] > 0.3 and ranges[1] > 0.3  # front corners beyond x = 1.6
    assert ranges[2] < 0.05 and ranges[3] < 0.05


def test_camera_frame_shows_the_texture_at_its_pose(structure) -> None:
    cam = DownwardCamera(noise_sigma=0, gain_range=(1, 1))
    img = cam.render(structure, np.array([0.5, 0.4, 0.0]), np.random.default_rng(0))
    assert img.shape == (480, 640, 3)
    # centre pixel of the frame = texture at world (0.5, 0.4)
    tex = structure.texture[
        int(round(0.4 / structure.m_per_px)), int(round(0.5 / structure.m_per_px))
    ]
    assert np.abs(img[240, 320].astype(int) - tex.astype(int)).max() < 25


def test_defects_have_ground_truth_inside_the_plate(structure) -> None:
    assert {d.defect_class for d in structure.defects} == {"crack", "corrosion"}
    for d in structure.defects:
        x, y, w, h = d.bbox_m
        assert (
            0 < x < x + w < structure.plate_size_m[0] and 0 < y < y + h < structure.plate_size_m[1]
        )
    assert structure.crack_mask.any() and structure.corrosion_mask.any()


def test_tof_depth_matches_the_plate_geometry(structure) -> None:
    tof = TofCamera(structure, noise_sigma_m=0.0)
    T = tof.T_world_tof(np.array([0.5, 0.3, 0.0]))
    depth = tof.render(T, np.random.default_rng(0))
    assert depth.shape == (172, 224)
    assert np.isfinite(depth).mean() > 0.5
    # back-projected points of the lower image half lie on the plate surface z = 0
    v, u = 160, 112
    ray = np.array([(u - tof.cx) / tof.fx, (v - tof.cy) / tof.fy, 1.0]) * depth[v, u]
    world = T[:3, :3] @ ray + T[:3, 3]
    assert world[2] == pytest.approx(0.0, abs=0.003)


def test_the_girder_runs_on_beyond_the_plate_with_repeating_stiffeners(structure) -> None:
    """From the plate's far end the ToF sees the girder's web and stiffeners beyond it."""
    tof = TofCamera(structure, noise_sigma_m=0.0)
    T = tof.T_world_tof(np.array([1.5, 0.7, 0.0]))
    depth = tof.render(T, np.random.default_rng(0))
    v, u = np.nonzero(np.isfinite(depth))
    rays = (
        np.column_stack([(u - tof.cx) / tof.fx, (v - tof.cy) / tof.fy, np.ones(len(u))])
        * depth[v, u][:, None]
    )
    world = rays @ T[:3, :3].T + T[:3, 3]
    beyond = world[world[:, 0] > structure.plate_size_m[0] + 0.05]
    # no plate there: girder only
    assert len(beyond) > 500 and (beyond[:, 1] > structure.plate_size_m[1] - 0.125).all()
    stiffener_faces = beyond[np.abs(beyond[:, 1] - (structure.plate_size_m[1] - 0.06)) < 0.05]
    # more than one stiffener ahead
    assert len(np.unique(np.round(stiffener_faces[:, 0] / 0.5))) >= 2
    bare = make_structure(3, girder_overhang_m=0.0)
    assert bare.mesh.get_axis_aligned_bounding_box().get_max_bound()[0] == pytest.approx(
        structure.plate_size_m[0]
    )
