import numpy as np
import pytest

from processing.poses import compose_se2, format_tum, image_to_world, parse_tum, se2_to_se3


def test_image_to_world_follows_the_camera_yaw() -> None:
    size = (641, 481)  # centre pixel (320, 240)
    pose = np.array([1.0, 2.0, 0.0])
    assert image_to_world(np.array([[320, 240]]), pose, 100.0, size)[0] == pytest.approx([1.0, 2.0])
    assert image_to_world(np.array([[420, 240]]), pose, 100.0, size)[0] == pytest.approx([2.0, 2.0])
    turned = np.array([1.0, 2.0, np.pi / 2])  # image x now points along world +y
    assert image_to_world(np.array([[420, 240]]), turned, 100.0, size)[0] == pytest.approx([1.0, 3.0])
    assert image_to_world(np.array([[320, 340]]), turned, 100.0, size)[0] == pytest.approx([0.0, 2.0])


def test_tum_roundtrip_and_bad_lines() -> None:
    poses = np.array([se2_to_se3(0.1 * i, -0.2 * i, 0.3 * i, z=0.05) for i in range(4)])
    times, back = parse_tum(format_tum(np.arange(4.0), poses))
    assert np.allclose(back, poses, atol=1e-6) and list(times) == [0, 1, 2, 3]
    with pytest.raises(ValueError, match="line 1"):
        parse_tum("0 1 2 3\n")
    with pytest.raises(ValueError, match="zero length"):
        parse_tum("0 0 0 0 0 0 0 0\n")


def test_compose_se2_matches_matrix_product() -> None:
    a, b = np.array([1.0, 0.0, np.pi / 2]), np.array([0.5, 0.0, 0.0])
    assert compose_se2(a, b) == pytest.approx([1.0, 0.5, np.pi / 2])
