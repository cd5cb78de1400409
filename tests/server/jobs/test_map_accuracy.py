"""The map job on the processed simulated inspection, against the simulator's true ToF
poses: the mosaic's camera motion carried over to the clouds places every cloud to a
small fraction of a millimetre, far better than the wheel odometry, on the plate."""

from __future__ import annotations

import httpx
import numpy as np

from processing.metrics import absolute_trajectory_error
from processing.poses import parse_tum, se2_to_se3
from tests.conftest import TRUE_CLOUD_POSES, LiveServer


def test_the_mosaic_places_the_clouds_to_a_fraction_of_a_millimetre(
    inspected: tuple[LiveServer, str],
) -> None:
    live, sid = inspected
    api = f"{live.url}/api/sessions/{sid}"
    job = next(j for j in httpx.get(f"{api}/jobs").json() if j["kind"] == "map")
    result = job["result"]
    assert result["guided_by_mosaic"]
    _, poses = parse_tum(httpx.get(f"{api}/results/trajectory.tum").raise_for_status().text)
    seqs = result["cloud_seqs"]
    truth = np.array([TRUE_CLOUD_POSES[sid][s] for s in seqs])
    ate = absolute_trajectory_error(poses, truth)
    clouds = {
        c["seq"]: c for c in httpx.get(f"{api}/clouds", params={"limit": 1000}).json()["data"]
    }
    mount = np.array(httpx.get(api).json()["calibration"]["tof"]["T_robot_tof"])
    odometry = np.array(
        [
            se2_to_se3(clouds[s]["pose_x"], clouds[s]["pose_y"], clouds[s]["pose_yaw"]) @ mount
            for s in seqs
        ]
    )
    assert ate < 1e-4, ate
    assert ate < 0.2 * absolute_trajectory_error(odometry, truth)
    # on the plate: height and tilt as the robot holds them
    assert np.abs(poses[:, 2, 3] - truth[:, 2, 3]).max() < 1e-4
    tilt = np.degrees(
        np.arccos(
            np.clip(
                poses[:, 2, 2] * truth[:, 2, 2] + (poses[:, :2, 2] * truth[:, :2, 2]).sum(1), -1, 1
            )
        )
    )
    assert tilt.max() < 0.01
