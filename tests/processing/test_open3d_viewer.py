"""Open3D imported through ``processing`` leaves its plotly viewer for later, and the viewer
still works when called."""

import subprocess
import sys

SCRIPT = """
import sys
import processing
import open3d as o3d
assert "dash" not in sys.modules and "plotly" not in sys.modules, "viewer imported with Open3D"
from open3d.visualization import get_plotly_fig
cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]))
figure = get_plotly_fig([cloud])
assert type(figure).__name__ == "Figure", type(figure)
assert len(figure.data) == 1 and len(figure.data[0].x) == 2
assert "dash" in sys.modules
print("ok")
"""


def test_the_viewer_is_imported_on_first_use_and_works() -> None:
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=120, check=False
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == "ok"


def test_open3d_imported_first_keeps_its_own_viewer() -> None:
    script = (
        "import sys, open3d, processing\n"
        "from processing.open3d_viewer import VIEWER, _DeferredViewer\n"
        "assert not isinstance(sys.modules[VIEWER], _DeferredViewer)\n"
        "print('ok')\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=False
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
