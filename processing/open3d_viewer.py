"""Open3D's plotly viewer loaded when first used instead of with Open3D.

``import open3d`` imports ``open3d.visualization``, which imports its plotly viewer
(``draw_plotly``: plotly, dash, Flask, IPython, requests), a fifth of a second that a
command registering clouds never uses. :func:`defer_plotly_viewer` puts a stand-in for that
module in ``sys.modules`` before Open3D is imported: its three functions load the real
module on their first call, as does any other name read from it. Nothing changes for a
caller of the viewer but when its imports happen.
"""

from __future__ import annotations

import importlib.util
import sys
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

VIEWER = "open3d.visualization.draw_plotly"
FUNCTIONS = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")


class _DeferredViewer(types.ModuleType):
    """Stands in for :data:`VIEWER` until a name is read from it."""

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):  # the import system's questions (__path__, __spec__ ...)
            raise AttributeError(name)
        return getattr(_real_viewer(), name)


def _viewer_file() -> Path | None:
    """Where the viewer's source is, without importing Open3D."""
    spec = importlib.util.find_spec("open3d")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(spec.submodule_search_locations[0]) / "visualization" / "draw_plotly.py"
    return path if path.is_file() else None


def _real_viewer() -> types.ModuleType:
    module = sys.modules.get(VIEWER)
    if module is not None and not isinstance(module, _DeferredViewer):
        return module
    real_spec = importlib.util.spec_from_file_location(VIEWER, _viewer_file())
    assert real_spec is not None and real_spec.loader is not None
    module = importlib.util.module_from_spec(real_spec)
    sys.modules[VIEWER] = module
    real_spec.loader.exec_module(module)
    return module


def _calls_real(name: str) -> Callable[..., Any]:
    def call(*args: Any, **kwargs: Any) -> Any:
        return getattr(_real_viewer(), name)(*args, **kwargs)

    call.__name__ = call.__qualname__ = name
    return call


def defer_plotly_viewer() -> None:
    """Make the next ``import open3d`` skip the plotly viewer's imports (a no-op once Open3D
    is imported, or where this Open3D has no such module)."""
    if "open3d" in sys.modules or VIEWER in sys.modules or _viewer_file() is None:
        return
    stand_in = _DeferredViewer(VIEWER, "Open3D's plotly viewer, loaded on first use")
    for name in FUNCTIONS:
        setattr(stand_in, name, _calls_real(name))
    sys.modules[VIEWER] = stand_in
