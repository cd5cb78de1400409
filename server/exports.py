"""Plain data exports: defects as CSV, point clouds as binary PLY."""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from server.report import DEFECT_FIELDS

FORMULA_START = ("=", "+", "-", "@", "\t", "\r")


def _cell(value: Any) -> Any:
    """A CSV cell; text that a spreadsheet would run as a formula is quoted with a leading
    apostrophe (CSV injection), numbers and empty values pass as they are."""
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, str) and value.startswith(FORMULA_START):
        return "'" + value
    return value


def defects_csv(records: Iterable[dict[str, Any]]) -> Iterator[str]:
    """``defects.csv`` line by line: a UTF-8 byte-order mark (so spreadsheets read accents),
    a header, one row per defect record of :func:`server.report.build_report`."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\r\n")
    writer.writerow(DEFECT_FIELDS)
    yield "\ufeff" + buf.getvalue()
    for rec in records:
        buf.seek(0)
        buf.truncate()
        writer.writerow([_cell(rec.get(k)) for k in DEFECT_FIELDS])
        yield buf.getvalue()


def ply_bytes(points: NDArray[np.floating]) -> bytes:
    """Binary little-endian PLY of the finite rows of an (N, 3) cloud."""
    pts = np.ascontiguousarray(points[np.isfinite(points).all(axis=1)], dtype="<f4")
    header = ("ply\nformat binary_little_endian 1.0\ncomment steelscan\n"
              f"element vertex {len(pts)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n")
    return header.encode("ascii") + pts.tobytes()


def read_ply_points(path: Path) -> NDArray[np.float64]:
    """(N, 3) vertex positions of a PLY file (Open3D's reader); ValueError when it has none."""
    import open3d as o3d

    if not path.is_file():
        raise ValueError(f"{path.name} does not exist")
    points = np.asarray(o3d.io.read_point_cloud(str(path)).points)
    if len(points) == 0:
        raise ValueError(f"{path.name} holds no points")
    return points
