"""Parametric steel members as triangle meshes: plates, angles, wide-flange sections,
bolt and stud patterns, composable into structures (:mod:`robot_link.sim.scenes`).

Every member is placed by its end points (or its centre and axes) in the world frame,
metres; all return ``open3d.geometry.TriangleMesh`` that add up with ``+``.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike, NDArray

Mesh = o3d.geometry.TriangleMesh


def box(x0: float, x1: float, y0: float, y1: float, z0: float, z1: float) -> Mesh:
    """An axis-aligned box between the given bounds (in either order)."""
    x0, x1 = sorted((x0, x1))
    y0, y1 = sorted((y0, y1))
    z0, z1 = sorted((z0, z1))
    mesh = Mesh.create_box(x1 - x0, y1 - y0, z1 - z0)
    mesh.translate((x0, y0, z0))
    return mesh


def oriented_box(centre: ArrayLike, axes: NDArray[np.float64], size: ArrayLike) -> Mesh:
    """A box of ``size`` (3,) along the columns of ``axes`` (3, 3, orthonormal) about ``centre``."""
    size = np.asarray(size, float)
    mesh = Mesh.create_box(*size)
    mesh.translate(-size / 2)
    mesh.rotate(np.asarray(axes, float), center=(0, 0, 0))
    mesh.translate(np.asarray(centre, float))
    return mesh


def _frame(axis: NDArray[np.float64], up: ArrayLike) -> NDArray[np.float64]:
    """Axes (columns) with x along ``axis`` and y as close to ``up`` as is perpendicular."""
    x = axis / np.linalg.norm(axis)
    y = np.asarray(up, float) - (np.asarray(up, float) @ x) * x
    if np.linalg.norm(y) < 1e-9:
        raise ValueError("up must not be parallel to the member's axis")
    y /= np.linalg.norm(y)
    return np.column_stack([x, y, np.cross(x, y)])


def plate(
    centre: ArrayLike, normal: ArrayLike, along: ArrayLike, size: tuple[float, float], t: float
) -> Mesh:
    """A plate of ``size`` (along, across) and thickness ``t`` about ``centre``, its faces
    perpendicular to ``normal``, its length along ``along``."""
    n = np.asarray(normal, float)
    axes = _frame(np.asarray(along, float), n)  # x along, y normal
    return oriented_box(centre, axes[:, [0, 2, 1]], (size[0], size[1], t))


def angle(p0: ArrayLike, p1: ArrayLike, legs: tuple[float, float], t: float, up: ArrayLike) -> Mesh:
    """An L-section (angle) from ``p0`` to ``p1``: its heel on that line, one leg of
    ``legs[0]`` towards ``up``, the other of ``legs[1]`` perpendicular to both."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    axes = _frame(p1 - p0, up)
    length = float(np.linalg.norm(p1 - p0))
    mid = (p0 + p1) / 2
    x, y, z = axes.T
    leg_a = oriented_box(mid + y * legs[0] / 2 + z * t / 2, axes, (length, legs[0], t))
    leg_b = oriented_box(mid + z * legs[1] / 2 + y * t / 2, axes, (length, t, legs[1]))
    return leg_a + leg_b


def wide_flange(
    p0: ArrayLike,
    p1: ArrayLike,
    depth: float,
    width: float,
    t_web: float,
    t_flange: float,
    up: ArrayLike,
) -> Mesh:
    """An I-section from ``p0`` to ``p1`` (its centre line), web towards ``up``."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    axes = _frame(p1 - p0, up)
    length = float(np.linalg.norm(p1 - p0))
    mid = (p0 + p1) / 2
    y = axes[:, 1]
    mesh = oriented_box(mid, axes, (length, depth - 2 * t_flange, t_web))
    for side in (-1, 1):
        mesh += oriented_box(
            mid + side * y * (depth - t_flange) / 2, axes, (length, t_flange, width)
        )
    return mesh


def bolts(
    centres: Iterable[ArrayLike], normal: ArrayLike, radius: float = 0.012, height: float = 0.012
) -> Mesh:
    """Hexagonal bolt heads (or nuts) standing ``height`` out of a face along ``normal``."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, n)
    if np.linalg.norm(axis) < 1e-9:
        R = np.eye(3) if n[2] > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        R = o3d.geometry.get_rotation_matrix_from_axis_angle(
            axis / np.linalg.norm(axis) * np.arccos(np.clip(n @ z, -1, 1))
        )
    mesh = Mesh()
    for c in centres:
        head = Mesh.create_cylinder(radius=radius, height=height, resolution=6)
        head.translate((0, 0, height / 2)).rotate(R, center=(0, 0, 0))
        head.translate(np.asarray(c, float))
        mesh += head
    return mesh


def grid(
    origin: ArrayLike, u: ArrayLike, v: ArrayLike, rows: int, cols: int, pitch: tuple[float, float]
) -> list[NDArray[np.float64]]:
    """``rows`` x ``cols`` points from ``origin``, ``pitch`` apart along unit vectors u and v."""
    o, u, v = (np.asarray(a, float) for a in (origin, u, v))
    return [o + r * pitch[0] * u + c * pitch[1] * v for r in range(rows) for c in range(cols)]
