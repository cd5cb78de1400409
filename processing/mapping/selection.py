"""Selection: a ToF cloud cleaned, its organised depth image filtered, voxel-downsampled, with normals."""

from __future__ import annotations

from collections.abc import Sequence
from typing import cast

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from processing.mapping.params import SelectParams

# rays (x/z, y/z) closer than this are one pixel's (float32 points carry ~1e-7 of rounding)
RAY_TOLERANCE = 1e-5


def clean_cloud(points: NDArray[np.floating], max_range_m: float) -> NDArray[np.float64]:
    """Drop NaN/inf points and returns beyond ``max_range_m``; returns (K, 3) float64."""
    pts = np.asarray(points).reshape(-1, 3)
    r2 = np.einsum("ij,ij->i", pts, pts)
    with np.errstate(invalid="ignore"):
        ok = r2 <= max_range_m**2  # NaN and inf compare False
    return pts[ok].astype(np.float64)


def filter_organised(
    points: NDArray[np.floating], shape: tuple[int, int], median_px: int, stride: int = 1
) -> NDArray[np.float32]:
    """Median-filter the depth of an organised cloud (H·W points, row-major), keeping each
    point on its pixel's ray (ToF noise is mostly along the ray), then average the
    consistent pixels of ``stride`` x ``stride`` blocks (NaN where a block has none)."""
    h, w = shape
    pts = np.asarray(points, dtype=np.float32).reshape(h, w, 3)
    z = pts[..., 2]
    valid = np.isfinite(z)
    z_filled = np.where(valid, z, np.float32(0))
    med = cv2.medianBlur(z_filled, median_px) if median_px in (3, 5) else z_filled
    # where the neighbourhood is mostly invalid the median is 0: keep the raw value there
    with np.errstate(invalid="ignore", divide="ignore"):
        good = valid & (med > 0) & (np.abs(med - z) < 0.05)
        scale = np.where(good, med / z, np.float32(1))
    out = pts * scale[..., None]
    out[~valid] = np.nan
    # stride x stride blocks averaged (the voxels average them anyway): fewer points, less noise
    if stride > 1:
        hb, wb = h // stride, w // stride
        ok = valid & good
        masked = np.where(ok[..., None], out, np.float32(0))
        crop = (slice(0, hb * stride), slice(0, wb * stride))
        # block means by OpenCV's area resampling (exact for a whole factor), of the
        # values with holes as 0 and of the valid mask: their ratio averages valid pixels only
        mean = cast(
            NDArray[np.float32],
            cv2.resize(masked[crop], (wb, hb), interpolation=cv2.INTER_AREA),
        )
        count = cast(
            NDArray[np.float32],
            cv2.resize(ok[crop].astype(np.float32), (wb, hb), interpolation=cv2.INTER_AREA),
        )
        with np.errstate(invalid="ignore", divide="ignore"):
            out = mean / count[..., None]
        out[count == 0] = np.nan
    return out.reshape(-1, 3)


def _grid_pitch(values: NDArray[np.float64], n: int) -> float:
    """The spacing of the columns (or rows) that a grid's rays fall on: the median gap
    between the distinct values (0 when the values are not a grid's few columns)."""
    distinct = np.unique(np.round(values / RAY_TOLERANCE))
    if len(distinct) < 3 or len(distinct) > 4 * np.sqrt(n) + 16:
        return 0.0
    return float(np.median(np.diff(distinct))) * RAY_TOLERANCE


def regrid(
    points: NDArray[np.floating], max_pixels: int = 4_000_000
) -> tuple[NDArray[np.float32], tuple[int, int]] | None:
    """An unorganised cloud of a ToF camera (K, 3 in its own frame, in any order) put back
    on its pixel grid: each point's ray (x/z, y/z) lies on the sensor's regular grid (a
    pixel's ray is fixed, whatever its depth), whose pitch per axis is the spacing of the
    distinct column and row values. Returns the
    organised points (H·W, 3; NaN where no point fell) and (H, W); None when the points do
    not lie in front of a sensor or fill too little of a grid (a cloud thinned or merged
    by another tool), where a grid would be mostly holes."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < 16 or np.mean(pts[:, 2] > 0) < 0.9:
        return None
    pts = pts[pts[:, 2] > 0]
    rays = pts[:, :2] / pts[:, 2:3]
    pitch = np.array([_grid_pitch(rays[:, 0], len(rays)), _grid_pitch(rays[:, 1], len(rays))])
    if not (pitch > 0).all():
        return None
    cell = np.rint((rays - rays.min(axis=0)) / pitch).astype(np.int64)
    w, h = int(cell[:, 0].max()) + 1, int(cell[:, 1].max()) + 1
    if w * h > max_pixels or len(pts) < 0.25 * w * h:
        return None
    grid = np.full((h * w, 3), np.nan, np.float32)
    grid[cell[:, 1] * w + cell[:, 0]] = pts  # two points in one pixel: one is kept
    return grid, (h, w)


def select(
    points: NDArray[np.floating],
    params: SelectParams = SelectParams(),
    shape: tuple[int, int] | None = None,
) -> o3d.geometry.PointCloud:
    """Selection step: depth filtering on the pixel grid (an organised cloud's ``shape``,
    else the grid its rays lie on, :func:`regrid`), cleaning, voxel downsampling, the
    points whose normals the neighbourhood fixes, with them (:func:`with_normals`)."""
    if (
        shape is not None
        and params.depth_median_px
        and np.asarray(points).reshape(-1, 3).shape[0] == shape[0] * shape[1]
    ):
        points = filter_organised(points, shape, params.depth_median_px, params.pixel_stride)
    elif shape is None and params.depth_median_px:
        # an unorganised ToF cloud: its pixel grid recovered from its rays, then the same
        gridded = regrid(points)
        if gridded is not None:
            points = filter_organised(
                gridded[0], gridded[1], params.depth_median_px, params.pixel_stride
            )
    pcd = o3d.geometry.PointCloud(
        o3d.utility.Vector3dVector(clean_cloud(points, params.max_range_m))
    )
    pcd = pcd.voxel_down_sample(params.voxel_m)
    if len(pcd.points) >= 3:
        pcd = with_normals(pcd, params.voxel_m)
    return pcd


def with_normals(pcd: o3d.geometry.PointCloud, voxel_m: float) -> o3d.geometry.PointCloud:
    """The points of a voxel-downsampled cloud (sensor frame) whose neighbourhood (3 voxels
    across) fixes a normal, with it, facing the sensor.

    A normal is the direction the neighbours spread least in; it is fixed only where they
    spread in two directions, across by at least a quarter voxel (the voxel's own sampling).
    A row of returns alone, as a plate seen at a grazing angle far off gives, leaves the
    normal free to turn about the row, and how it turns follows the sensor's pixel rows, not
    the structure: such normals would pull every registration towards the pose the sensor
    had before, along directions the structure does not fix."""
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=voxel_m * 3, max_nn=30)
    pcd.estimate_covariances(search)
    pcd.estimate_normals(search)  # the covariances' least eigenvector
    C, n = np.asarray(pcd.covariances), np.asarray(pcd.normals)
    # the middle eigenvalue from the characteristic polynomial's coefficients and the least
    # (nᵀCn): λ1 + λ2 = tr C − λ3, λ1·λ2 = (sum of principal 2x2 minors) − λ3·(λ1 + λ2)
    least = np.einsum("ni,nij,nj->n", n, C, n)
    total = C[:, 0, 0] + C[:, 1, 1] + C[:, 2, 2] - least
    minors = (
        C[:, 0, 0] * C[:, 1, 1]
        - C[:, 0, 1] ** 2
        + C[:, 0, 0] * C[:, 2, 2]
        - C[:, 0, 2] ** 2
        + C[:, 1, 1] * C[:, 2, 2]
        - C[:, 1, 2] ** 2
    )
    product = minors - least * total
    middle = (total - np.sqrt(np.maximum(total**2 - 4 * product, 0))) / 2
    kept = np.flatnonzero(middle > (voxel_m / 4) ** 2)
    out = pcd.select_by_index(kept)  # type: ignore[arg-type]  # Open3D takes an array; its stubs want a Sequence
    if len(out.points):  # a cloud of lone rows keeps nothing
        out.orient_normals_towards_camera_location(np.zeros(3))
    out.covariances = o3d.utility.Matrix3dVector()  # not carried into the map
    return out


def fuse_map(
    pcds: Sequence[o3d.geometry.PointCloud], poses: NDArray[np.float64], voxel_m: float
) -> NDArray[np.float32]:
    """All clouds in the world frame, voxel-filtered, as (M, 3) float32."""
    fused = o3d.geometry.PointCloud()
    for pcd, T in zip(pcds, poses):
        moved = o3d.geometry.PointCloud(pcd)
        moved.transform(T)
        fused += moved
    fused = fused.voxel_down_sample(voxel_m)
    return np.asarray(fused.points, dtype=np.float32)
