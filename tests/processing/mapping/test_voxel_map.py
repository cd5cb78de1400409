"""The tracking map: points and normals summed per voxel, grown one cloud at a time."""

import numpy as np
import pytest

from processing.mapping.voxel_map import VoxelMap, voxel_mean


def test_voxel_mean_averages_points_and_normals_per_voxel() -> None:
    points = np.array([[0.001, 0.001, 0.001], [0.009, 0.001, 0.001], [0.5, 0.5, 0.5]])
    normals = np.array([[0, 0, 1.0], [0, 1.0, 0], [1.0, 0, 0]])
    mean, normal = voxel_mean(points, normals, 0.01)
    assert len(mean) == 2
    k = int(np.argmin(mean[:, 0]))
    assert mean[k] == pytest.approx([0.005, 0.001, 0.001])
    assert normal[k] == pytest.approx([0, np.sqrt(0.5), np.sqrt(0.5)])


def test_a_map_grown_cloud_by_cloud_is_the_voxel_mean_of_all_its_clouds() -> None:
    """Clouds that overlap in part (shared voxels are summed, new ones inserted in order),
    negative coordinates included, and an empty cloud."""
    rng = np.random.default_rng(3)
    clouds = [rng.uniform(-0.3, 0.3, (500, 3)) + [0.1 * k, 0, 0] for k in range(4)]
    clouds.insert(2, np.zeros((0, 3)))
    normals = [rng.normal(size=c.shape) for c in clouds]
    grown = VoxelMap(0.05)
    for c, n in zip(clouds, normals):
        grown.add(c, n)
    mean, normal = voxel_mean(np.concatenate(clouds), np.concatenate(normals), 0.05)
    assert len(grown) == len(mean)
    got_mean, got_normal = grown.crop(np.full(3, -np.inf), np.full(3, np.inf))
    order, got = np.lexsort(mean.T), np.lexsort(got_mean.T)
    assert np.allclose(got_mean[got], mean[order])
    assert np.allclose(got_normal[got], normal[order])


def test_a_crop_holds_the_voxels_whose_mean_lies_in_the_box() -> None:
    grown = VoxelMap(0.1)
    points = np.array([[0.01, 0.01, 0.01], [0.05, 0.05, 0.05], [0.55, 0.0, 0.0], [-0.5, 0, 0]])
    grown.add(points, np.tile([0, 0, 1.0], (4, 1)))
    mean, normal = grown.crop(np.array([0, -0.1, -0.1]), np.array([0.2, 0.1, 0.1]))
    assert mean == pytest.approx(np.array([[0.03, 0.03, 0.03]]))
    assert normal == pytest.approx(np.array([[0, 0, 1.0]]))
