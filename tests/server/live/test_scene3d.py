"""The 3D view's scene as the viser server holds it: where each node sits in the world once
its parents' transforms are applied (a node "/a/b" is placed relative to "/a")."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from numpy.typing import NDArray

from server.live.scene3d import DefectMarker, Scene3D


@pytest.fixture
def scene() -> Iterator[Scene3D]:
    view = Scene3D()
    try:
        yield view
    finally:
        view.close()


def rotation(wxyz: NDArray[np.float64]) -> NDArray[np.float64]:
    w, x, y, z = wxyz / np.linalg.norm(wxyz)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def T_world_node(view: Scene3D, name: str) -> NDArray[np.float64]:
    """A scene node's pose in the world: its ancestors' transforms composed with its own."""
    nodes = view.server.scene._handle_from_node_name
    T_world_a = np.eye(4)
    parts = name.split("/")
    for i in range(2, len(parts) + 1):
        ancestor = "/".join(parts[:i])
        if ancestor not in nodes:
            continue  # viser adds missing ancestors as frames at the origin
        T_parent_node = np.eye(4)
        T_parent_node[:3, :3] = rotation(np.asarray(nodes[ancestor].wxyz, dtype=np.float64))
        T_parent_node[:3, 3] = nodes[ancestor].position
        T_world_a = T_world_a @ T_parent_node
    return T_world_a


def test_each_defect_label_sits_just_above_its_marker(scene: Scene3D) -> None:
    markers = [
        DefectMarker(3, 1, "crack", 0.582, 0.507, 0.08, "**Defect 1**"),
        DefectMarker(9, 8, "corrosion", 1.25, 0.31, 0.03, "**Defect 8**"),
    ]
    scene.show_session("s", None, None, markers, "girder")
    for d in markers:
        sphere = T_world_node(scene, f"/defects/{d.id}")[:3, 3]
        label = T_world_node(scene, f"/defects/{d.id}/label")[:3, 3]
        assert sphere[:2] == pytest.approx([d.x, d.y], abs=1e-6)
        assert label[:2] == pytest.approx(sphere[:2], abs=1e-6)  # straight above it
        assert -0.08 < label[2] - sphere[2] < 0  # up is -z, within a few cm
