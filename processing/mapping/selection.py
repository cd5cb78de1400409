"""Selection: a ToF cloud cleaned, its organised depth image filtered, voxel-downsampled, with normals."""

from __future__ import annotations

from collections.abc import Sequence
from typing import cast

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from processing.mapping.params import SelectParams


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


def select(
    points: NDArray[np.floating],
    params: SelectParams = SelectParams(),
    shape: tuple[int, int] | None = None,
) -> o3d.geometry.PointCloud:
    """Selection step: (organised) depth filtering, cleaning, voxel downsampling, the points
    whose normals the neighbourhood fixes, with them (:func:`with_normals`)."""
    if (
        shape is not None
        and params.depth_median_px
        and np.asarray(points).reshape(-1, 3).shape[0] == shape[0] * shape[1]
    ):
        points = filter_organised(points, shape, params.depth_median_px, params.pixel_stride)
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
