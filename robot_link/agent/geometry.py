"""The robot's and the camera's geometry: as the MCU reports it (its HELLO reply), else as
robot.toml gives it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from robot_link.agent.config import RobotConfig
from robot_link.sim.robot import RobotSpec


@dataclass(frozen=True)
class CameraGeometry:
    """The inspection camera as the station needs it."""

    width: int
    height: int
    px_per_m: float
    mount_x_m: float

    @property
    def footprint_m(self) -> tuple[float, float]:
        """Surface seen (along the heading, across it), image x along the heading."""
        return self.width / self.px_per_m, self.height / self.px_per_m


def robot_spec(info: dict[str, Any] | None, config: RobotConfig) -> RobotSpec:
    """The robot's geometry: as its MCU reports it, else from the config."""
    g = config.robot
    info = info or {}
    ir = info.get("ir_positions_m") or g.ir_positions_m
    return RobotSpec(
        track_m=float(info.get("track_m", g.track_m)),
        wheelbase_m=float(info.get("wheelbase_m", 0.26)),
        wheel_radius_m=float(info.get("wheel_radius_m", g.wheel_radius_m)),
        magnets_per_wheel=int(info.get("edges_per_wheel_turn", g.edges_per_wheel_turn)) // 4,
        ir_corners_m=tuple((float(x), float(y)) for x, y in ir),
        ir_calibrated_m=float(info.get("ir_calibrated_m", g.ir_calibrated_m)),
    )


def camera_geometry(config: RobotConfig, emulator: dict[str, Any]) -> CameraGeometry:
    """The camera's size and scale: the emulator's when its camera is used, else the config's."""
    c = config.camera
    if c.source == "emulator" and "camera" in emulator:
        e = emulator["camera"]
        return CameraGeometry(
            int(e["width"]), int(e["height"]), float(e["px_per_m"]), float(e["mount_x_m"])
        )
    return CameraGeometry(c.width, c.height, c.px_per_m, c.mount_x_m)
