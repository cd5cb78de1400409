"""``steelscan map``: a folder of point clouds (organised ToF clouds with ``sensor.json``, or
unorganised ``.ply``/``.pcd`` from other tools) registered into ``map.ply``, ``poses.tum``
and ``map_report.json``.

Foreign input is checked before any work: the folder, ``sensor.json`` and the odometry
(every line: eight finite numbers, one pose per cloud) before Open3D is imported, so a bad
argument is answered at once; clouds in millimetres are recognised by their ranges and
refused (``--units mm`` converts them), empty and all-NaN clouds are skipped (placed by the
odometry, or by the previous step's motion without it) and reported. Odometry written with
its quaternions w-first is recognised by the clouds (:mod:`processing.mapping.quaternion_order`),
read in that order and reported. Long runs log their progress on stderr.
"""

from __future__ import annotations

import json
import logging
import re
import time
from pathlib import Path
from typing import Literal

import numpy as np

from server.cli.camera_input import camera_factors, read_camera_input
from server.cli.inputs import list_files, read_odometry_rows
from server.errors import CommandError
from server.storage.files import write_atomic

log = logging.getLogger(__name__)

CLOUD_EXTS = {".ply", ".pcd"}
# a ToF camera's range is a few metres; a median range beyond this is millimetres
MAX_PLAUSIBLE_RANGE_M = 50.0
UNITS_SAMPLE = 1000  # points of each cloud whose ranges decide the units
Units = Literal["auto", "m", "mm"]
PROGRESS_EVERY_S = 2.0  # a long run says how far it is at most this often


class Progress:
    """Logs "<what> i of n" when ``PROGRESS_EVERY_S`` have passed since the last line."""

    def __init__(self, what: str, n: int) -> None:
        self.what, self.n = what, n
        self.last = time.monotonic()

    def __call__(self, i: int) -> None:
        now = time.monotonic()
        if now - self.last >= PROGRESS_EVERY_S and i < self.n:
            self.last = now
            log.info("%s %d of %d", self.what, i, self.n)


def _read_sensor(folder: Path) -> dict | None:
    path = folder / "sensor.json"
    if not path.is_file():
        return None
    try:
        sensor = json.loads(path.read_text())
        if int(sensor["width"]) <= 0 or int(sensor["height"]) <= 0:
            raise ValueError("width and height must be positive")
    except (ValueError, KeyError, TypeError, OSError) as exc:
        raise CommandError(f"{path}: {exc}") from None
    return sensor


def _read_cloud(path: Path, sensor: dict | None) -> np.ndarray:
    """(K, 3) float64 points; (0, 3) for a file without points (reported, not refused)."""
    import open3d as o3d

    pcd = o3d.io.read_point_cloud(str(path), remove_nan_points=False, remove_infinite_points=False)
    pts = np.asarray(pcd.points)
    if pts.size == 0:  # Open3D reads nothing from an empty cloud and from a broken file alike
        if not re.search(rb"element vertex 0\b|POINTS 0\b", path.read_bytes()[:4096]):
            raise CommandError(f"{path}: not a readable .ply/.pcd point cloud")
        return np.zeros((0, 3))
    if sensor and len(pts) != int(sensor["width"]) * int(sensor["height"]):
        raise CommandError(
            f"{path}: {len(pts)} points, but sensor.json says {sensor['width']}x{sensor['height']}"
        )
    return pts


def _check_units(clouds: list[np.ndarray], units: Units, folder: Path) -> list[np.ndarray]:
    """Clouds in metres: converted from millimetres with ``units="mm"``; with ``"auto"``
    clouds whose median range is beyond any ToF camera's are refused."""
    if units == "mm":
        return [c / 1000.0 for c in clouds]
    if units == "auto":
        # a sample of every cloud's points decides it: metres and millimetres are 1000x apart
        sample = [c[:: max(1, len(c) // UNITS_SAMPLE)] for c in clouds]
        ranges = [np.linalg.norm(c[np.isfinite(c).all(axis=1)], axis=1) for c in sample]
        finite = np.concatenate(ranges) if ranges else np.zeros(0)
        median = float(np.median(finite)) if len(finite) else 0.0
        if median > MAX_PLAUSIBLE_RANGE_M:
            raise CommandError(
                f"{folder}: the clouds' median range is {median:.0f}; clouds must be "
                "in metres (these look like millimetres: pass --units mm to convert them)"
            )
    return clouds


def _unusable(
    files: list[Path], clouds: list[np.ndarray], folder: Path, *, by_odometry: bool
) -> dict[str, str]:
    """The clouds with no finite point, by file name, and why (logged: they are placed by
    the odometry, or the previous motion); an error when none is left."""
    skipped = {
        p.name: ("no points" if len(c) == 0 else "every point is NaN or infinite")
        for p, c in zip(files, clouds)
        if not np.isfinite(c).all(axis=1).any()
    }
    if len(skipped) == len(clouds):
        raise CommandError(f"{folder}: no cloud has a finite point")
    for name, why in skipped.items():
        placed = "odometry" if by_odometry else "the previous motion"
        log.warning("%s: %s; skipped (placed by %s)", name, why, placed)
    return skipped


def _write_map(out: Path, points: np.ndarray) -> None:
    """``map.ply``, written whole or not at all."""
    import open3d as o3d

    out.mkdir(parents=True, exist_ok=True)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    tmp = out / ".map.tmp.ply"
    if not o3d.io.write_point_cloud(str(tmp), pcd):
        raise CommandError(f"could not write {out / 'map.ply'}")
    tmp.replace(out / "map.ply")


def _odometry(
    rows: np.ndarray | None, clouds: list[np.ndarray]
) -> tuple[np.ndarray | None, dict[str, object] | None]:
    """The odometry's poses, in the quaternion order the clouds agree with, and what was
    found of the order (None without odometry)."""
    if rows is None:
        return None, None
    from processing.mapping.quaternion_order import check_order
    from processing.poses import poses_of_tum_rows

    given, w_first = poses_of_tum_rows(rows), poses_of_tum_rows(rows, w_first=True)
    check = check_order(clouds, given, w_first)
    order: dict[str, object] = {
        "quaternion_order": "qw qx qy qz" if check.swap else "qx qy qz qw",
        "voxels_given_order": check.given_voxels,
        "voxels_w_first": check.other_voxels,
    }
    if check.swap:
        log.warning(
            "the odometry's quaternions read as TUM's qx qy qz qw place the clouds over "
            "%.1fx the voxels of qw qx qy qz: read w-first (write TUM files as "
            "t tx ty tz qx qy qz qw)",
            check.ratio,
        )
        return w_first, order
    return given, order


def _fixed_by(k: int, result: object, odometry: bool) -> list[str]:
    """What placed cloud ``k``: the camera's step into it, or the camera's steps either side
    carried over a stretch its frames did not register (``motion``), the ToF's
    registration, the odometry (alone, when no other)."""
    out = []
    if len(result.camera_steps) > k and result.camera_steps[k]:  # type: ignore[attr-defined]
        out.append("camera")
    if len(result.motion_steps) > k and result.motion_steps[k]:  # type: ignore[attr-defined]
        out.append("motion")
    if k > 0 and not result.used_odometry[k]:  # type: ignore[attr-defined]
        out.append("tof")
    if odometry and (k == 0 or not out):
        out.append("odometry")
    return out


def map_folder(
    clouds_dir: Path,
    out: Path,
    *,
    odometry: Path | None,
    units: Units = "auto",
    frames: Path | None = None,
) -> None:
    """Write ``map.ply``, ``poses.tum`` (one pose per input cloud) and ``map_report.json``;
    with ``frames`` (the downward camera's images and ``camera.json``) the images' motion
    joins the clouds' in the pose graph."""
    files = list_files(clouds_dir, CLOUD_EXTS, "point cloud")
    sensor = _read_sensor(clouds_dir)
    rows = read_odometry_rows(odometry, len(files), "clouds") if odometry else None
    cloud_times = rows[:, 0] if rows is not None else np.arange(len(files), dtype=float)
    if rows is not None and (np.diff(cloud_times) <= 0).any():
        raise CommandError(f"{odometry}: timestamps must increase (one pose per cloud, in order)")
    given = read_camera_input(frames, cloud_times) if frames else None
    # the arguments hold: now the heavy imports and the work
    from processing.mapping import register_clouds
    from processing.poses import format_tum

    reading = Progress("read cloud", len(files))
    clouds = []
    for i, path in enumerate(files):
        clouds.append(_read_cloud(path, sensor))
        reading(i + 1)
    clouds = _check_units(clouds, units, clouds_dir)
    skipped = _unusable(files, clouds, clouds_dir, by_odometry=rows is not None)
    init, order = _odometry(rows, clouds)
    factors, camera_report = (
        camera_factors(given, clouds, cloud_times) if given is not None else (None, None)
    )
    shape = (int(sensor["height"]), int(sensor["width"])) if sensor else None
    try:
        result = register_clouds(
            clouds,
            init,
            shape=shape,
            progress=Progress("registered cloud", len(clouds)),
            camera=factors,  # type: ignore[arg-type]
        )
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    if camera_report is not None:
        fit = result.camera_mounting
        mounting = None if fit is None else fit.summary()
        if fit is not None and fit.corrected and given is not None:
            from processing.poses import se3_exp

            # the mounting the map took: camera.json's, for the next run on this robot
            stated = np.asarray(given.camera["T_tof_camera"], np.float64)
            corrected = stated @ se3_exp(fit.xi)
            mounting = {**(mounting or {}), "T_tof_camera": np.round(corrected, 6).tolist()}
        camera_report["mounting"] = mounting
        camera_report["cloud_steps_carried"] = int(result.motion_steps.sum())
        if mounting is not None and mounting["corrected"]:
            log.warning(
                "camera: the ToF's steps put the camera %s mm and %s deg (its own axes) from "
                "where T_tof_camera says; the map takes its steps through the corrected mounting",
                mounting["translation_mm"],
                mounting["rotation_deg"],
            )
    _write_map(out, result.points)
    write_atomic(
        out / "poses.tum", format_tum(np.arange(len(clouds), dtype=float), result.poses).encode()
    )
    report = {
        "clouds": len(clouds),
        "skipped": [{"file": k, "reason": v} for k, v in skipped.items()],
        "organised": sensor is not None,
        "map_points": len(result.points),
        "loop_closures": result.loop_closures,
        "placed_by_odometry": [files[k].name for k in np.flatnonzero(result.used_odometry)],
        "clouds_with_unobservable_directions": int((result.degenerate_dims > 0).sum()),
        "odometry_error_scale": round(float(result.odometry_error_scale), 2),
        "plane_landmarks": result.plane_landmarks,
        "odometry": order,
        "camera": camera_report,
        "factors": [
            {"file": f.name, "fixed_by": _fixed_by(k, result, rows is not None)}
            for k, f in enumerate(files)
        ],
    }
    write_atomic(out / "map_report.json", json.dumps(report, indent=1).encode())
    log.info(
        "%d clouds mapped (%d skipped): %d loop closures, %d placed by odometry alone, %d with "
        "directions only the odometry fixed (a flat view)",
        len(clouds),
        len(skipped),
        result.loop_closures,
        int(result.used_odometry.sum()),
        report["clouds_with_unobservable_directions"],
    )
