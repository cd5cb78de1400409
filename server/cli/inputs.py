"""Input folders and odometry files of the file-based commands, checked before any work."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from processing.poses import poses_of_tum_rows, tum_rows
from server.errors import CommandError


def list_files(folder: Path, exts: set[str], what: str) -> list[Path]:
    """The files of ``folder`` with one of ``exts`` (lower case), in name order; at least one."""
    if not folder.is_dir():
        raise CommandError(f"{folder}: not a directory")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in exts)
    if not files:
        raise CommandError(f"{folder}: no {what} files ({', '.join(sorted(exts))})")
    return files


def read_odometry_rows(path: Path, n: int, what: str) -> np.ndarray:
    """(n, 8) checked rows of a TUM file with one pose per input (``what``: "frames",
    "clouds"); an error names the file and its first bad line."""
    try:
        rows = tum_rows(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise CommandError(f"{path}: {exc}") from None
    if len(rows) != n:
        raise CommandError(f"{path}: {len(rows)} poses for {n} {what}; need one per {what[:-1]}")
    return rows


def read_odometry(path: Path, n: int, what: str) -> np.ndarray:
    """(n, 4, 4) poses from a TUM file with one pose per input (``what``: "frames", "clouds")."""
    return poses_of_tum_rows(read_odometry_rows(path, n, what))
