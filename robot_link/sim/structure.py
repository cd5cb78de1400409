"""A simulated steel structure: a painted deck plate beside an I-girder, with known defects.

World frame: x along the girder, y across the plate, z into the plate (the robot drives
on the plate's surface z = 0 from the z < 0 side), metres. The surface texture is an image
with ``m_per_px`` metres per pixel whose pixel (0, 0) is world (0, 0).

The plate is the inspected panel (its edges are what the IR sensors detect); the girder
beside it runs on beyond both of its ends, as a bridge girder does, with transverse
stiffeners repeating along it: the forward-looking ToF camera sees that structure ahead.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import cast

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray


@dataclass(frozen=True)
class TrueDefect:
    """A defect the simulator painted, with its world bounding box in metres."""

    id: int
    defect_class: str  # "crack" or "corrosion"
    bbox_m: tuple[float, float, float, float]  # x, y, w, h
    length_m: float
    width_m: float


@dataclass
class SteelStructure:
    """Geometry (triangle mesh), surface texture and ground-truth defects."""

    plate_size_m: tuple[float, float]
    m_per_px: float
    texture: NDArray[np.uint8]
    crack_mask: NDArray[np.bool_]
    corrosion_mask: NDArray[np.bool_]
    defects: list[TrueDefect]
    mesh: o3d.geometry.TriangleMesh = field(repr=False)

    def on_plate(self, x: NDArray[np.floating], y: NDArray[np.floating]) -> NDArray[np.bool_]:
        """Whether world points (x, y) lie on the plate's surface."""
        w, h = self.plate_size_m
        return (x >= 0) & (x <= w) & (y >= 0) & (y <= h)


def _noise(rng: np.random.Generator, shape: tuple[int, int], cell: int) -> NDArray[np.float32]:
    small = rng.standard_normal((max(2, shape[0] // cell), max(2, shape[1] // cell))).astype(
        np.float32
    )
    return cast(
        NDArray[np.float32],
        cv2.resize(small, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC),
    )


def paint_texture(rng: np.random.Generator, shape: tuple[int, int]) -> NDArray[np.float32]:
    """Painted steel: grey-blue paint with blotches, grain, brush marks and scratches."""
    base = np.array([118, 112, 104], np.float32)  # BGR
    tone = 10 * _noise(rng, shape, 200) + 6 * _noise(rng, shape, 40) + 4 * _noise(rng, shape, 8)
    grain = rng.normal(0, 5, shape).astype(np.float32)
    img = base[None, None, :] + (tone + grain)[..., None]
    img[..., 0] += 4 * _noise(rng, shape, 120)
    for _ in range(int(shape[0] * shape[1] / 60000)):  # light scratches (not defects)
        p = rng.uniform((0, 0), shape[::-1])
        d = rng.normal(size=2)
        d /= np.linalg.norm(d)
        q = p + d * rng.uniform(20, 120)
        cv2.line(
            img, tuple(int(v) for v in p), tuple(int(v) for v in q), (150, 146, 140), 1, cv2.LINE_AA
        )
    return img


def _draw_crack(
    rng: np.random.Generator,
    img: NDArray[np.float32],
    mask: NDArray[np.uint8],
    start: NDArray[np.float64],
    length_px: float,
    width_px: float,
    heading: float | None = None,
    turn_sigma: float = 0.25,
) -> NDArray[np.bool_]:
    """Paint a dark meandering crack from ``start`` (along ``heading``, else a random one,
    turning by ``turn_sigma`` rad a step); returns the full-size mask of its pixels."""
    if heading is None:
        heading = rng.uniform(0, np.pi)
    pts = [start]
    step = 4.0
    for _ in range(max(1, int(length_px / step))):
        heading += rng.normal(0, turn_sigma)
        pts.append(pts[-1] + step * np.array([np.cos(heading), np.sin(heading)]))
    arr = np.array(pts)
    pad = int(width_px) + 4
    x0, y0 = np.maximum(np.floor(arr.min(axis=0)).astype(int) - pad, 0)
    x1, y1 = np.ceil(arr.max(axis=0)).astype(int) + pad
    x1, y1 = min(x1, mask.shape[1]), min(y1, mask.shape[0])
    poly = np.round((arr - (x0, y0)) * 16).astype(np.int32).reshape(-1, 1, 2)
    layer = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.polylines(layer, [poly], False, 255, max(1, int(round(width_px))), cv2.LINE_AA, shift=4)
    alpha = (layer.astype(np.float32) / 255.0)[..., None] * 0.85
    region = img[y0:y1, x0:x1]
    region[:] = region * (1 - alpha) + np.array([38, 36, 34], np.float32) * alpha
    mine = np.zeros(mask.shape, bool)
    mine[y0:y1, x0:x1] = layer > 127
    mask[mine] = 255
    return mine


def _draw_corrosion(
    rng: np.random.Generator,
    img: NDArray[np.float32],
    mask: NDArray[np.uint8],
    centre: NDArray[np.float64],
    radius_px: float,
) -> NDArray[np.bool_]:
    """Paint a rust patch; returns the full-size mask of its pixels."""
    h, w = mask.shape
    r = int(radius_px * 1.6)
    x0, y0 = int(max(0, centre[0] - r)), int(max(0, centre[1] - r))
    x1, y1 = int(min(w, centre[0] + r)), int(min(h, centre[1] + r))
    yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float32)
    ang = np.arctan2(yy - centre[1], xx - centre[0])
    wobble = (
        1 + 0.25 * np.sin(3 * ang + rng.uniform(0, 6)) + 0.15 * np.sin(5 * ang + rng.uniform(0, 6))
    )
    dist = np.hypot(xx - centre[0], yy - centre[1]) / (radius_px * wobble)
    blotch = _noise(rng, (y1 - y0, x1 - x0), 12)
    inside = dist + 0.15 * blotch < 1.0
    rust = np.array([28, 62, 140], np.float32) + 18 * blotch[..., None] * np.array(
        [0.5, 0.8, 1.0], np.float32
    )
    region = img[y0:y1, x0:x1]
    region[inside] = rust[inside]
    mask[y0:y1, x0:x1][inside] = 255
    mine = np.zeros(mask.shape, bool)
    mine[y0:y1, x0:x1] = inside
    return mine


def _box(
    x0: float, x1: float, y0: float, y1: float, z0: float, z1: float
) -> o3d.geometry.TriangleMesh:
    box = o3d.geometry.TriangleMesh.create_box(x1 - x0, y1 - y0, z1 - z0)
    box.translate((x0, y0, z0))
    return box


def girder_geometry(
    plate_w: float, plate_h: float, girder_overhang_m: float = 0.0, stiffener_spacing_m: float = 0.5
) -> o3d.geometry.TriangleMesh:
    """Plate, I-girder (web, top flange, stiffeners, bolts) and an edge angle, as one mesh;
    the girder extends ``girder_overhang_m`` beyond both ends of the plate, a stiffener every
    ``stiffener_spacing_m`` (one at x = 0.55)."""
    x0, x1 = -girder_overhang_m, plate_w + girder_overhang_m
    mesh = _box(0, plate_w, 0, plate_h, 0, 0.012)  # deck plate, top face at z = 0
    mesh += _box(x0, x1, plate_h, plate_h + 0.012, -0.5, 0.0)  # girder web
    mesh += _box(x0, x1, plate_h - 0.09, plate_h + 0.1, -0.512, -0.5)  # top flange
    first = 0.55 - stiffener_spacing_m * np.floor((0.55 - x0) / stiffener_spacing_m)
    # transverse stiffeners welded to the web
    for sx in np.arange(first, x1 - 0.006, stiffener_spacing_m):
        mesh += _box(sx - 0.006, sx + 0.006, plate_h - 0.12, plate_h, -0.45, 0.0)
    mesh += _box(0, plate_w, -0.01, 0.0, -0.08, 0.0)  # edge angle along y = 0
    for bx in np.arange(x0 + 0.08, x1, 0.16):  # bolt heads on the web
        for bz in (-0.12, -0.3):
            bolt = o3d.geometry.TriangleMesh.create_cylinder(
                radius=0.012, height=0.02, resolution=10
            )
            bolt.rotate(
                o3d.geometry.get_rotation_matrix_from_xyz((np.pi / 2, 0, 0)), center=(0, 0, 0)
            )
            bolt.translate((bx, plate_h - 0.01, bz))
            mesh += bolt
    mesh.compute_vertex_normals()
    return mesh


def make_structure(
    seed: int = 7,
    *,
    plate_size_m: tuple[float, float] = (1.6, 0.9),
    m_per_px: float = 0.0004,
    n_cracks: int = 6,
    n_corrosion: int = 3,
    defect_region_m: tuple[float, float, float, float] = (0.25, 0.14, 1.35, 0.54),
    girder_overhang_m: float = 1.6,
    stiffener_spacing_m: float = 0.5,
) -> SteelStructure:
    """Build a structure with ``n_cracks`` cracks and ``n_corrosion`` rust patches.

    The girder runs ``girder_overhang_m`` beyond each end of the plate (0: it ends with the
    plate, and a forward-looking ToF sees mostly bare plate and then nothing), with a
    transverse stiffener every ``stiffener_spacing_m``.

    Defects are placed at random (from ``seed``) inside ``defect_region_m`` (x0, y0, x1, y1),
    apart from one another, so the route's camera footprint covers each of them.
    """
    rng = np.random.default_rng(seed)
    w_px, h_px = int(round(plate_size_m[0] / m_per_px)), int(round(plate_size_m[1] / m_per_px))
    img = paint_texture(rng, (h_px, w_px))
    crack = np.zeros((h_px, w_px), np.uint8)
    rust = np.zeros((h_px, w_px), np.uint8)
    defects: list[TrueDefect] = []
    centres: list[NDArray[np.float64]] = []
    x0, y0, x1, y1 = defect_region_m

    def free_spot(min_gap_m: float) -> NDArray[np.float64]:
        for _ in range(500):
            c = rng.uniform((x0, y0), (x1, y1))
            if all(np.linalg.norm(c - o) > min_gap_m for o in centres):
                centres.append(c)
                return c
        raise ValueError("defect_region_m is too small for that many defects")

    for _ in range(n_corrosion):
        c = free_spot(0.15)
        radius = rng.uniform(0.02, 0.035)
        mine = _draw_corrosion(rng, img, rust, c / m_per_px, radius / m_per_px)
        defects.append(
            _true_defect(len(defects) + 1, "corrosion", mine, m_per_px, 2 * radius, 2 * radius)
        )
    for _ in range(n_cracks):
        c = free_spot(0.12)
        length = rng.uniform(0.04, 0.10)
        width = rng.uniform(0.0005, 0.0012)
        mine = _draw_crack(rng, img, crack, c / m_per_px, length / m_per_px, width / m_per_px)
        defects.append(_true_defect(len(defects) + 1, "crack", mine, m_per_px, length, width))
    texture = np.clip(img, 0, 255).astype(np.uint8)
    return SteelStructure(
        plate_size_m,
        m_per_px,
        texture,
        crack > 0,
        rust > 0,
        defects,
        girder_geometry(*plate_size_m, girder_overhang_m, stiffener_spacing_m),
    )


def _true_defect(
    i: int, cls: str, pixels: NDArray[np.bool_], m_per_px: float, length: float, width: float
) -> TrueDefect:
    ys, xs = np.nonzero(pixels)
    bbox = (
        xs.min() * m_per_px,
        ys.min() * m_per_px,
        (xs.max() - xs.min() + 1) * m_per_px,
        (ys.max() - ys.min() + 1) * m_per_px,
    )
    x, y, w, h = (round(float(v), 5) for v in bbox)
    return TrueDefect(i, cls, (x, y, w, h), round(length, 4), round(width, 5))
