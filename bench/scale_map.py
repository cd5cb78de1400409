"""The map job of a long ToF session on one and on two workers (:mod:`bench.scale`)."""

from __future__ import annotations

import asyncio
import uuid

import numpy as np

from bench.common import Result, robot_session, speedup
from processing.poses import se2_of_matrix
from robot_link.protocol import Message, MessageType, decode_message, encode_message

# six lanes 2.35 m long and back: about 530 organised clouds
LANES_Y_M = (0.26, 0.38, 0.5, 0.62, 0.74, 0.86)
X_RANGE_M = (0.15, 2.5)


def record_clouds(port: int, token: str, limit: int | None = None) -> str:
    """A session of organised ToF clouds with wheel odometry and no camera frames (the map
    job registers them itself), through the robot protocol; with ``limit``, two lanes."""
    from robot_link.clouds import encode_depth_png
    from robot_link.sim.sensors import tof_mount
    from robot_link.sim.tof_sweeps import TofSweepConfig, tof_sweep

    lanes = LANES_Y_M[:2] if limit else LANES_Y_M
    sweep = tof_sweep(TofSweepConfig(lanes_y_m=lanes, x_range_m=X_RANGE_M, seed=43))
    mount = tof_mount()
    h, w = int(sweep.intrinsics["height"]), int(sweep.intrinsics["width"])
    sid = uuid.uuid4()
    calib = {"tof": {**sweep.intrinsics, "T_robot_tof": mount.tolist()}}

    async def run() -> None:
        async with robot_session(port, token, sid, "long girder", calib) as ws:
            for k, (cloud, T) in enumerate(zip(sweep.clouds, sweep.odometry)):
                x, y, yaw = se2_of_matrix(T @ np.linalg.inv(mount))
                pose = {"x": float(x), "y": float(y), "yaw": float(yaw)}
                meta = {"encoding": "png16_depth_mm", **sweep.intrinsics, "pose": pose}
                payload = encode_depth_png(cloud[:, 2].reshape(h, w))
                msg = Message(MessageType.CLOUD, sid, k + 2, float(k), meta, payload)
                await ws.send(encode_message(msg))
                decode_message(await ws.recv())
            end = Message(MessageType.SESSION_END, sid, len(sweep.clouds) + 2, 0.0, {})
            await ws.send(encode_message(end))
            await ws.recv()

    asyncio.run(run())
    return str(sid)


def map_results(one: dict, one_s: float, two: dict, two_s: float, target: float) -> list[Result]:
    """The map job's pair stage and whole job, one worker against two."""
    return [
        speedup(
            "map_pairs_speedup",
            one["result"]["seconds"]["pairs"],
            two["result"]["seconds"]["pairs"],
            target,
            stage="map job, each run of clouds registered to the clouds before it (spread "
            "over workers; loops and the pose graph on the job's worker)",
            clouds=one["result"]["clouds"],
        ),
        speedup(
            "map_job_speedup",
            round(one_s, 1),
            round(two_s, 1),
            graph_s=two["result"]["seconds"]["graph"],
        ),
    ]
