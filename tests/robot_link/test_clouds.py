import numpy as np
import pytest

from robot_link.clouds import (
    decode_cloud,
    decode_depth_png,
    depth_to_points,
    encode_depth_png,
    encode_xyz,
)
from robot_link.protocol import ProtocolError


def test_depth_png_roundtrip_is_millimetre_exact_and_keeps_holes() -> None:
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.2, 3.5, (17, 23)).astype(np.float32)
    depth[3, 4] = np.nan
    out = decode_depth_png(encode_depth_png(depth), 23, 17)
    assert np.isnan(out[3, 4])
    ok = ~np.isnan(depth)
    assert np.max(np.abs(out[ok] - depth[ok])) <= 0.0005 + 1e-6


def test_depth_png_with_wrong_size_is_rejected() -> None:
    data = encode_depth_png(np.ones((4, 5), np.float32))
    with pytest.raises(ProtocolError):
        decode_depth_png(data, 4, 4)


def test_back_projection_puts_the_principal_point_on_the_axis() -> None:
    depth = np.full((3, 3), 2.0, np.float32)
    pts = depth_to_points(depth, fx=100, fy=100, cx=1, cy=1).reshape(3, 3, 3)
    assert np.allclose(pts[1, 1], (0, 0, 2))
    assert np.allclose(pts[1, 2], (0.02, 0, 2))


def test_xyz_cloud_decodes_to_the_same_points() -> None:
    pts = np.arange(12, dtype=np.float32).reshape(4, 3)
    out = decode_cloud(encode_xyz(pts), {"encoding": "xyz_f32", "width": 4, "height": 1})
    assert np.array_equal(out, pts)
