"""Point clouds as PLY files: writing the binary form, reading any (Open3D's reader)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
from numpy.typing import NDArray


def ply_bytes(points: NDArray[np.floating]) -> bytes:
    """Binary little-endian PLY of the finite rows of an (N, 3) cloud."""
    pts = np.ascontiguousarray(points[np.isfinite(points).all(axis=1)], dtype="<f4")
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment steelscan\n"
        f"element vertex {len(pts)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    )
    return header.encode("ascii") + pts.tobytes()


def read_ply_points(path: Path) -> NDArray[np.float64]:
    """(N, 3) vertex positions of a PLY file (Open3D's reader); ValueError when it has none."""
    if not path.is_file():
        raise ValueError(f"{path.name} does not exist")
    points = np.asarray(o3d.io.read_point_cloud(str(path)).points)
    if len(points) == 0:
        raise ValueError(f"{path.name} holds no points")
    return points
