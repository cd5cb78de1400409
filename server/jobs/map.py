"""The ``map`` job: the session's ToF clouds registered into one 3D map and trajectory."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, overload

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from processing.mapping import (
    CloudMeasurement,
    MapParams,
    TrackingParams,
    measure_run,
    register_clouds,
    register_measured,
)
from processing.poses import format_tum, se2_to_se3
from robot_link.clouds import decode_cloud
from server.jobs.context import JobContext, params_record
from server.jobs.map_camera import session_camera
from server.storage.files import SessionFiles, write_atomic
from server.storage.models import Cloud

RUN_CLOUDS = 32  # clouds a part registers (each also registers to the few before its first)


@dataclass(frozen=True)
class CloudRun:
    """What a worker registering a run of a session's clouds needs: where each usable
    cloud is stored with its decoding metadata, their odometry poses (N, 4, 4), the
    parameters and the organised shape."""

    where: list[tuple[str, int | None, int, dict[str, Any]]]
    guesses: NDArray[np.float64]
    params: MapParams
    shape: tuple[int, int] | None


class StoredClouds(Sequence[NDArray[np.float32]]):
    """A session's clouds as a sequence read from the data directory as they are used (one
    decoded cloud in memory at a time, however long the session)."""

    def __init__(
        self, files: SessionFiles, where: list[tuple[str, int | None, int, dict[str, Any]]]
    ) -> None:
        self.files, self.where = files, where

    def __len__(self) -> int:
        return len(self.where)

    @overload
    def __getitem__(self, i: int) -> NDArray[np.float32]: ...
    @overload
    def __getitem__(self, i: slice) -> list[NDArray[np.float32]]: ...
    def __getitem__(self, i: int | slice) -> Any:
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        path, offset, size, meta = self.where[i]
        return decode_cloud(self.files.read(path, offset, size), meta)


def measure_run_part(
    files: SessionFiles, run: CloudRun, span: tuple[int, int]
) -> list[CloudMeasurement]:
    """Clouds ``span`` (first, end) of a map job, each registered to the clouds before it
    (:func:`~processing.mapping.measure_run`), wherever the job queue runs it."""
    first, end = span
    start = max(0, first - run.params.neighbours)
    clouds = StoredClouds(files, run.where)[start:end]
    return measure_run(clouds, run.guesses[start:end], first, first - start, run.params, run.shape)


@dataclass
class _ReadableClouds:
    """The session's clouds that decode to at least one finite point: where each is stored
    (read again where it is registered: a long session's clouds are not all held in this
    worker's memory at once), its time, seq and odometry pose; and those skipped."""

    where: list[tuple[str, int | None, int, dict[str, Any]]] = field(default_factory=list)
    stamps: list[float] = field(default_factory=list)
    seqs: list[int] = field(default_factory=list)
    guesses: list[NDArray[np.float64]] = field(default_factory=list)
    skipped: list[int] = field(default_factory=list)


def run_map(ctx: JobContext) -> dict[str, Any]:
    """3D map from the session's ToF clouds: odometry-seeded point-to-plane ICP."""
    calib = ctx.session().calibration.get("tof", {})
    T_rt = np.array(calib.get("T_robot_tof", np.eye(4).tolist()), dtype=np.float64)
    with ctx.factory() as db:
        rows = list(db.scalars(ctx.rows(Cloud)))
    if not rows:
        raise ValueError("the session has no ToF clouds")
    shapes = {(c.height, c.width) for c in rows}
    shape = shapes.pop() if len(shapes) == 1 else None  # organised depth images: filtered as images
    if shape is not None and min(shape) < 2:
        shape = None
    clouds = _readable_clouds(ctx, rows, T_rt)
    usable = len(clouds.where)
    guesses = clouds.guesses
    # the station's own sessions: dense clouds and wheel odometry good to millimetres, which
    # the pairwise graph uses best (tracking is for sparse sequences with poor odometry)
    params = MapParams(tracking=TrackingParams(enabled=False))
    # the downward camera's motion beside the ToF and the odometry (the clouds' own times)
    camera = (
        session_camera(ctx, np.array(clouds.stamps, np.float64), T_rt)
        if len(guesses) == usable
        else None
    )
    ctx.progress(0.3, "registering")
    t0 = time.perf_counter()
    factors = None if camera is None else camera[0]
    if len(guesses) == usable:
        # each run of clouds registered to the clouds before it wherever the queue runs it
        # (from the camera's steps where it links them, as register_clouds starts them),
        # then joined into one graph with the camera's edges, its loops closed and
        # optimised here
        odometry = np.array(guesses)
        starts = odometry if factors is None else factors.guided(odometry, usable)
        run = CloudRun(clouds.where, starts, params, shape)
        spans = [(a, min(a + RUN_CLOUDS, usable)) for a in range(0, usable, RUN_CLOUDS)]
        measured = [m for part in ctx.map(measure_run_part, run, spans) for m in part]
        t_pairs = time.perf_counter() - t0
        ctx.progress(0.6, "joining the graph")
        result = register_measured(measured, odometry, params=params, camera=factors)
    else:
        result = register_clouds(
            StoredClouds(ctx.files, clouds.where), None, params=params, shape=shape
        )
        t_pairs = 0.0
    seconds = {  # the pairs spread over workers on a job queue; the graph on this one
        "pairs": round(t_pairs, 3),
        "graph": round(time.perf_counter() - t0 - t_pairs, 3),
    }
    _write_map(ctx.output_dir(), result, clouds.stamps)
    return {
        "map_path": str(ctx.results_dir() / "map.ply"),
        "trajectory_path": str(ctx.results_dir() / "trajectory.tum"),
        "points": len(result.points),
        "guided_by_mosaic": camera is not None and camera[1]["source"] == "mosaic",
        "camera": None if camera is None else _camera_facts(camera[1], result),
        "clouds": usable,
        "skipped_clouds": clouds.skipped,
        "cloud_seqs": clouds.seqs,
        **_registration_facts(result),
        "seconds": seconds,
        "params": params_record(params),
    }


def _readable_clouds(
    ctx: JobContext, rows: list[Cloud], T_rt: NDArray[np.float64]
) -> _ReadableClouds:
    """The clouds that can be registered (:class:`_ReadableClouds`); none is an error."""
    out = _ReadableClouds()
    for i, c in enumerate(rows):
        meta = {"encoding": c.encoding, "width": c.width, "height": c.height, **c.intrinsics}
        try:
            pts = decode_cloud(ctx.files.payload(c), meta)
        except (OSError, ValueError):
            out.skipped.append(c.seq)
            continue
        if not np.isfinite(pts).all(axis=1).any():
            out.skipped.append(c.seq)
            continue
        out.where.append((c.path, c.data_offset, c.size_bytes, meta))
        out.stamps.append(c.timestamp)
        out.seqs.append(c.seq)
        if c.pose_x is not None:
            out.guesses.append(se2_to_se3(c.pose_x, c.pose_y, c.pose_yaw) @ T_rt)
        if i % 10 == 0:
            ctx.progress(0.3 * i / len(rows), f"decoded {i}/{len(rows)} clouds")
    if not out.where:
        raise ValueError("no readable ToF cloud in the session")
    return out


def _write_map(out: Path, result: Any, stamps: list[float]) -> None:
    """The fused map as PLY and the trajectory as TUM, each written whole or not at all."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(result.points.astype(np.float64)))
    tmp = out / ".map.tmp.ply"
    if not o3d.io.write_point_cloud(str(tmp), pcd):
        raise OSError("could not write map.ply")
    tmp.replace(out / "map.ply")
    write_atomic(out / "trajectory.tum", format_tum(np.array(stamps), result.poses).encode())


def _registration_facts(result: Any) -> dict[str, Any]:
    """What the registration did, for the job's result."""
    return {
        "loop_closures": result.loop_closures,
        "odometry_fallbacks": int(result.used_odometry.sum()),
        # clouds whose view left some directions to the odometry (a flat plate: sliding along it)
        "clouds_with_unobservable_directions": int((result.degenerate_dims > 0).sum()),
        # the odometry's heading error measured against ICP, over the configured one (1: as
        # configured)
        "odometry_error_scale": round(result.odometry_error_scale, 2),
        # large planes (deck plate, web) tying the clouds that see them
        "plane_landmarks": result.plane_landmarks,
        "mean_fitness": float(result.fitness.mean()),
    }


def _camera_facts(report: dict[str, Any], result: Any) -> dict[str, Any]:
    """What the camera did in the map, for the job's result."""
    fit = result.camera_mounting
    return {
        **report,
        "clouds_placed_by_camera": int(result.camera_steps.sum()),
        # steps its frames did not see, carried over by the steps either side
        "clouds_placed_by_motion": int(result.motion_steps.sum()),
        "mounting": None if fit is None else fit.summary(),
    }
