import cv2
import numpy as np
import pytest

from robot_link.sim.imaging import warp_affine_exact


def _rotation(theta: float, tx: float, ty: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, tx], [s, c, ty]])


def test_a_rotated_ramp_is_sampled_at_the_exact_position() -> None:
    """Cubic convolution reproduces a linear image exactly, so what differs is position:
    ours is exact, OpenCV's warp rounds positions to 1/32 px (why the sweeps do not use it)."""
    texture = np.tile(np.arange(256, dtype=np.uint8), (200, 1))  # grey level = x
    M = _rotation(np.radians(1.7), 60.31, 40.77)
    gy, gx = np.mgrid[0:100, 0:120].astype(np.float64)
    qx = M[0, 0] * gx + M[0, 1] * gy + M[0, 2]
    ours = warp_affine_exact(texture, M, (120, 100))
    opencv = cv2.warpAffine(
        texture.astype(np.float32), M, (120, 100), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP
    )
    assert np.abs(ours - qx).max() < 1e-3
    assert np.abs(opencv - qx).max() > 5e-3


def test_integer_shifts_copy_pixels_and_reflect_at_the_edges() -> None:
    rng = np.random.default_rng(0)
    texture = rng.integers(0, 256, (40, 50), dtype=np.uint8)
    out = warp_affine_exact(texture, _rotation(0.0, 5.0, 7.0), (20, 10))
    assert out.shape == (10, 20) and out.dtype == np.float32
    assert np.array_equal(out, texture[7:17, 5:25].astype(np.float32))
    M = _rotation(0.0, -3.0, -2.0)
    edge = warp_affine_exact(texture, M, (50, 40))
    want = cv2.warpAffine(
        texture,
        M,
        (50, 40),
        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REFLECT,
    )
    assert np.array_equal(edge, want.astype(np.float32))


def test_beyond_the_edges_a_constant_border_reads_its_value() -> None:
    texture = np.full((20, 30), 200, np.uint8)
    out = warp_affine_exact(texture, _rotation(0.0, -10.0, 0.0), (30, 20), border=25.0)
    # within 2 px of the edge: blended
    assert np.allclose(out[:, :8], 25.0) and np.allclose(out[:, 12:], 200.0)
    want = cv2.warpAffine(
        texture,
        _rotation(0.0, -10.0, 0.0),
        (30, 20),
        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=25,
    )
    # an integer shift: taps land on pixels, no blending
    assert np.array_equal(out, want.astype(np.float32))


def test_colour_channels_are_warped_alike() -> None:
    rng = np.random.default_rng(1)
    grey = rng.integers(0, 256, (30, 30), dtype=np.uint8)
    M = _rotation(0.3, 10.5, 4.25)
    colour = warp_affine_exact(np.dstack([grey, grey, grey]), M, (12, 12))
    assert colour.shape == (12, 12, 3)
    assert np.array_equal(colour[..., 2], warp_affine_exact(grey, M, (12, 12)))


def test_a_wrong_matrix_is_refused() -> None:
    with pytest.raises(ValueError, match="2x3"):
        warp_affine_exact(np.zeros((4, 4), np.uint8), np.eye(3), (2, 2))
