"""Still pictures of a 3D map: an oblique orthographic view, points coloured by height."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

MAX_POINTS = 400_000


def view_rotation(azimuth_deg: float, elevation_deg: float) -> NDArray[np.float64]:
    """World → view rotation: turn ``azimuth`` about world z, then tilt by ``elevation``
    (view x right, y down the picture, z into it)."""
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    Rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(e), -np.sin(e)], [0.0, np.sin(e), np.cos(e)]])
    return Rx @ Rz


def render_points(
    points: NDArray[np.floating],
    *,
    size: tuple[int, int] = (1200, 800),
    azimuth_deg: float = 30.0,
    elevation_deg: float = 55.0,
    height_axis: int = 2,
    path: NDArray[np.floating] | None = None,
    point_px: int = 2,
    background: tuple[int, int, int] = (255, 255, 255),
) -> NDArray[np.uint8]:
    """BGR image of a point cloud seen obliquely, nearer points drawn over farther ones,
    coloured by the coordinate ``height_axis`` (turbo colour map); ``path`` (M, 3), when
    given, is drawn as a black polyline (the robot's trajectory)."""
    width, height = size
    image = np.full((height, width, 3), background, np.uint8)
    pts = np.asarray(points, dtype=np.float64)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) == 0:
        return image
    if len(pts) > MAX_POINTS:
        pts = pts[np.random.default_rng(0).choice(len(pts), MAX_POINTS, replace=False)]
    R = view_rotation(azimuth_deg, elevation_deg)
    centre = np.median(pts, axis=0)
    v = (pts - centre) @ R.T
    extra = (
        (np.asarray(path, dtype=np.float64) - centre) @ R.T
        if path is not None and len(path)
        else np.empty((0, 3))
    )
    both = np.vstack([v[:, :2], extra[:, :2]])
    lo, hi = np.percentile(both, 0.5, axis=0), np.percentile(both, 99.5, axis=0)
    scale = 0.92 * min(width / max(hi[0] - lo[0], 1e-9), height / max(hi[1] - lo[1], 1e-9))
    offset = np.array([width, height]) / 2 - scale * (lo + hi) / 2

    h = pts[:, height_axis]
    h_lo, h_hi = np.percentile(h, 2), np.percentile(h, 98)
    level = np.clip((h - h_lo) / max(h_hi - h_lo, 1e-9) * 255, 0, 255).astype(np.uint8)
    colours = cv2.applyColorMap(level.reshape(-1, 1), cv2.COLORMAP_TURBO).reshape(-1, 3)

    uv = np.round(v[:, :2] * scale + offset).astype(np.int64)
    order = np.argsort(-v[:, 2])  # far first, near last: near points overwrite
    uv, colours = uv[order], colours[order]
    for dy in range(point_px):
        for dx in range(point_px):
            x, y = uv[:, 0] + dx, uv[:, 1] + dy
            ok = (x >= 0) & (x < width) & (y >= 0) & (y < height)
            image[y[ok], x[ok]] = colours[ok]
    if len(extra) > 1:
        line = np.round(extra[:, :2] * scale + offset).astype(np.int32)
        cv2.polylines(image, [line.reshape(-1, 1, 2)], False, (0, 0, 0), 2, cv2.LINE_AA)
    return image
