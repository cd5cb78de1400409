"""The camera and ToF adapters on emulated hardware: a folder of images, a video file, a
camera that is unplugged (clear error, then it works again once back), the emulator's
sensors, and a replay of organised ToF clouds with sensor.json."""

from __future__ import annotations

import asyncio
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest

from robot_link.agent.camera import CameraError, FolderCamera, OpenCVCamera, camera_source
from robot_link.agent.config import CameraConfig, TofConfig
from robot_link.agent.emulator_sensors import EmulatorSensors
from robot_link.agent.tof import ReplayTof, TofError, tof_source
from robot_link.emulator.process import EmulatorProcess
from robot_link.mcu.link import McuLink


def _images(folder: Path, n: int = 3) -> list[np.ndarray]:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 255, (48, 64, 3), np.uint8) for _ in range(n)]
    for i, im in enumerate(images):
        cv2.imwrite(str(folder / f"f{i:03d}.png"), im)
    return images


def test_a_folder_of_images_replays_in_name_order_and_again(tmp_path: Path) -> None:
    images = _images(tmp_path / "frames")

    async def main() -> list[np.ndarray]:
        cam = camera_source(CameraConfig(source=str(tmp_path / "frames")), None)
        assert isinstance(cam, FolderCamera)
        await cam.open()
        return [(await cam.grab()).image for _ in range(4)]

    got = asyncio.run(main())
    assert all(np.array_equal(a, b) for a, b in zip(got, [*images, images[0]], strict=True))


def test_a_video_file_is_read_frame_by_frame(tmp_path: Path) -> None:
    path = tmp_path / "sweep.avi"
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    for i in range(5):
        out.write(np.full((48, 64, 3), 40 * i, np.uint8))
    out.release()

    async def main() -> list[float]:
        cam = camera_source(CameraConfig(source=str(path)), None)
        assert isinstance(cam, OpenCVCamera)
        await cam.open()
        means = [float((await cam.grab()).image.mean()) for _ in range(6)]
        await cam.close()
        return means

    means = asyncio.run(main())
    assert means[:5] == pytest.approx([0, 40, 80, 120, 160], abs=3)
    assert means[5] == pytest.approx(0, abs=3)  # the replay starts again


def test_an_unplugged_camera_is_a_clear_error_and_works_again_when_back(tmp_path: Path) -> None:
    _images(tmp_path / "frames")

    async def main() -> None:
        cam = FolderCamera(CameraConfig(source=str(tmp_path / "frames")))
        await cam.open()
        await cam.grab()
        shutil.move(tmp_path / "frames", tmp_path / "away")
        with pytest.raises(CameraError, match="cannot read"):
            await cam.grab()
        with pytest.raises(CameraError, match="not a folder"):
            await cam.open()
        shutil.move(tmp_path / "away", tmp_path / "frames")
        await cam.open()
        assert (await cam.grab()).image.shape == (48, 64, 3)
        missing = OpenCVCamera(CameraConfig(source="/dev/video-none"))
        with pytest.raises(CameraError, match="cannot open"):
            await missing.open()

    asyncio.run(main())


def test_tof_replay_gives_the_organised_clouds_depth(tmp_path: Path) -> None:
    folder = tmp_path / "clouds"
    folder.mkdir()
    w, h = 8, 6
    (folder / "sensor.json").write_text(
        json.dumps({"width": w, "height": h, "fx": 10.0, "fy": 10.0, "cx": 3.5, "cy": 2.5})
    )
    z = np.linspace(0.3, 1.2, w * h).reshape(h, w)
    z[0, 0] = np.nan
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    pts = np.stack([(u - 3.5) / 10 * z, (v - 2.5) / 10 * z, z], -1).reshape(-1, 3)
    o3d.io.write_point_cloud(
        str(folder / "c000.pcd"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    )

    async def main() -> np.ndarray:
        tof = tof_source(TofConfig(source=str(folder)), None, {})
        assert isinstance(tof, ReplayTof)
        await tof.open()
        assert tof.intrinsics["width"] == w
        return (await tof.grab()).depth_m

    depth = asyncio.run(main())
    assert np.isnan(depth[0, 0]) and np.allclose(depth[1:], z[1:], atol=1e-6)
    (folder / "sensor.json").unlink()
    with pytest.raises(TofError, match="sensor.json"):
        asyncio.run(ReplayTof(TofConfig(source=str(folder))).open())


def test_the_emulators_camera_and_tof_come_over_its_socket(emulator: EmulatorProcess) -> None:
    async def main() -> tuple[np.ndarray, np.ndarray]:
        link = McuLink(emulator.device)
        reply = await link.open()
        info = reply.info["emulator"]
        sensors = EmulatorSensors(info["sensors"])
        image, _ = await sensors.request("camera")
        depth, _ = await sensors.request("tof")
        await sensors.close()
        await link.close()
        assert image.shape == (info["camera"]["height"], info["camera"]["width"], 3)
        return image, depth

    image, depth = asyncio.run(main())
    assert image.std() > 3  # painted steel, not a blank
    assert np.isfinite(depth).mean() > 0.3


def test_the_realsense_source_says_what_it_needs() -> None:
    """Without the RealSense library (or a camera) the ToF source fails with what to do."""
    tof = tof_source(TofConfig(source="realsense"), None, {})

    with pytest.raises(TofError, match="pyrealsense2|RealSense"):
        asyncio.run(tof.open())
