import numpy as np
import pytest

from processing.poses import (
    compose_se2,
    format_tum,
    half_se2,
    image_to_world,
    parse_tum,
    se2_to_se3,
)


def test_image_to_world_follows_the_camera_yaw() -> None:
    size = (641, 481)  # centre pixel (320, 240)
    pose = np.array([1.0, 2.0, 0.0])
    assert image_to_world(np.array([[320, 240]]), pose, 100.0, size)[0] == pytest.approx([1.0, 2.0])
    assert image_to_world(np.array([[420, 240]]), pose, 100.0, size)[0] == pytest.approx([2.0, 2.0])
    turned = np.array([1.0, 2.0, np.pi / 2])  # image x now points along world +y
    assert image_to_world(np.array([[420, 240]]), turned, 100.0, size)[0] == pytest.approx(
        [1.0, 3.0]
    )
    assert image_to_world(np.array([[320, 340]]), turned, 100.0, size)[0] == pytest.approx(
        [0.0, 2.0]
    )


def test_tum_roundtrip_and_bad_lines() -> None:
    poses = np.array([se2_to_se3(0.1 * i, -0.2 * i, 0.3 * i, z=0.05) for i in range(4)])
    times, back = parse_tum(format_tum(np.arange(4.0), poses))
    assert np.allclose(back, poses, atol=1e-6) and list(times) == [0, 1, 2, 3]
    with pytest.raises(ValueError, match="line 1"):
        parse_tum("0 1 2 3\n")
    with pytest.raises(ValueError, match="zero length"):
        parse_tum("0 0 0 0 0 0 0 0\n")
    for bad in ("nan", "inf", "-1e999"):
        with pytest.raises(ValueError, match="line 3: NaN or infinite"):
            parse_tum(f"# t x y z qx qy qz qw\n0 0 0 0 0 0 0 1\n1 {bad} 0 0 0 0 0 1\n")


def test_quaternions_read_in_either_order_match_scipy() -> None:
    from scipy.spatial.transform import Rotation

    from processing.poses import poses_of_tum_rows, quaternion_matrices, tum_rows

    turns = Rotation.random(40, random_state=5)
    assert np.allclose(quaternion_matrices(turns.as_quat()), turns.as_matrix(), atol=1e-12)
    poses = np.tile(np.eye(4), (40, 1, 1))
    poses[:, :3, :3] = turns.as_matrix()
    rows = tum_rows(format_tum(np.arange(40.0), poses))
    w_first = rows.copy()
    w_first[:, 4:] = np.roll(rows[:, 4:], 1, axis=1)  # written qw qx qy qz
    assert np.allclose(poses_of_tum_rows(w_first, w_first=True), poses, atol=1e-6)
    assert not np.allclose(poses_of_tum_rows(w_first), poses, atol=0.1)


def test_compose_se2_matches_matrix_product() -> None:
    a, b = np.array([1.0, 0.0, np.pi / 2]), np.array([0.5, 0.0, 0.0])
    assert compose_se2(a, b) == pytest.approx([1.0, 0.5, np.pi / 2])


@pytest.mark.parametrize("step", [(0.3, -0.1, 0.0), (0.05, 0.02, 1.2), (-0.2, 0.4, -3.0)])
def test_half_se2_taken_twice_is_the_step(step: tuple[float, float, float]) -> None:
    half = half_se2(np.array(step))
    assert np.allclose(compose_se2(half, half), step, atol=1e-12)
    assert half[2] == pytest.approx(step[2] / 2)


def test_se3_exp_and_log_are_rodrigues_and_its_inverse_at_every_angle() -> None:
    from scipy.spatial.transform import Rotation

    from processing.poses import se3_exp, se3_log

    rng = np.random.default_rng(3)
    for scale in (1e-12, 1e-6, 1e-2, 0.5, 2.0, 3.0, 3.14):
        for _ in range(50):
            axis = rng.normal(size=3)
            xi = np.concatenate([axis / np.linalg.norm(axis) * scale, rng.normal(size=3)])
            T = se3_exp(xi)
            assert np.allclose(T[:3, :3], Rotation.from_rotvec(xi[:3]).as_matrix(), atol=1e-12)
            assert np.allclose(T[:3, 3], xi[3:]) and np.allclose(T[3], [0, 0, 0, 1])
            assert np.allclose(se3_log(T), xi, atol=1e-9 if scale < 3.0 else 1e-6)
