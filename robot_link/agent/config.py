"""``robot.toml``: the on-board agent's configuration (docs/robot.md, "Configuration").

Every section is checked when the file is read: a misspelt key or a value of the wrong
kind is a :class:`ConfigError` naming it, before any device is opened.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import tomllib
from pydantic import BaseModel, ConfigDict, Field, ValidationError

Positive = Annotated[float, Field(gt=0)]


class ConfigError(ValueError):
    """A robot.toml that cannot be used."""


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class StationConfig(_Section):
    """Where the ground station is and the robot's token (``steelscan admin create-robot``)."""

    url: str
    token: str = Field(min_length=1)
    ca_file: str | None = None
    spool: str | None = None  # folder of the durable send queue
    spool_max_mb: Positive = 512


class McuConfig(_Section):
    """The microcontroller's serial line."""

    device: str
    baud: int = Field(default=115200, gt=0)
    silent_ms: Positive = 300
    garbled_frames: int = Field(default=5, ge=1)


class CameraConfig(_Section):
    """The downward inspection camera. ``source``: "emulator", a V4L2 device index or path,
    a video file or a folder of images."""

    source: str | int
    width: int = Field(default=1280, gt=0)
    height: int = Field(default=960, gt=0)
    # surface pixels per metre at the mount height (from the lens and the mount)
    px_per_m: Positive = 3500.0
    mount_x_m: float = 0.0  # camera centre ahead of the robot's centre
    exposure: float | None = None  # fixed exposure (driver units); None: the driver's
    gain: float | None = None
    camera_matrix: list[list[float]] | None = None  # 3x3 K of the lens calibration
    distortion: list[float] | None = None  # OpenCV's k1 k2 p1 p2 [k3 ...]
    preview_fps: Positive = 10.0
    preview_quality: int = Field(default=70, ge=10, le=100)
    jpeg_quality: int = Field(default=90, ge=10, le=100)
    min_overlap: float = Field(default=0.3, ge=0.0, lt=0.95)


class TofConfig(_Section):
    """The ToF depth camera. ``source``: "emulator", "realsense", or a folder of organised
    clouds with sensor.json."""

    source: str
    T_robot_tof: list[list[float]] | None = None  # 4x4 mount, robot frame x fwd, y right, z down
    every_frames: int = Field(default=1, ge=1)  # one cloud per this many frames


class RobotGeometry(_Section):
    """The robot's geometry, where its MCU does not report it."""

    track_m: Positive = 0.20
    wheel_radius_m: Positive = 0.03
    edges_per_wheel_turn: int = Field(default=144, gt=0)
    ir_positions_m: list[tuple[float, float]] = [
        (0.13, -0.09),
        (0.13, 0.09),
        (-0.13, -0.09),
        (-0.13, 0.09),
    ]
    ir_calibrated_m: Positive = 0.03
    outline_m: tuple[float, float] = (0.30, 0.22)


class SafetyConfig(_Section):
    """The agent's own limits (the MCU enforces its own as well)."""

    deadman_s: Positive = 0.2
    ir_eps_m: Positive = 0.02
    min_battery_v: Positive = 10.8
    min_adhesion: Positive = 1.5
    inclination_deg: float = Field(default=90.0, ge=0, le=180)
    max_speed_mps: Positive = 0.15
    max_turn_radps: Positive = 0.8


class SweepConfig(_Section):
    """The autonomous coverage sweep."""

    speed_mps: Positive = 0.12
    turn_radps: Positive = 0.6
    lane_overlap: float = Field(default=0.3, ge=0.05, lt=0.9)
    first_turn: Literal["left", "right"] = "left"


class SessionInfo(_Section):
    """What the station records about the inspection."""

    structure: str = "unnamed structure"
    operator: str = "robot"
    location: str = ""
    robot: str = "steelscan-robot"


class RobotConfig(_Section):
    """The whole robot.toml."""

    station: StationConfig
    mcu: McuConfig
    camera: CameraConfig
    tof: TofConfig
    robot: RobotGeometry = RobotGeometry()
    safety: SafetyConfig = SafetyConfig()
    sweep: SweepConfig = SweepConfig()
    session: SessionInfo = SessionInfo()
    telemetry_hz: Positive = 10.0


def load_config(path: Path) -> RobotConfig:
    """Read and check ``path``; ConfigError with the first problem in words."""
    try:
        raw = tomllib.loads(path.read_text())
    except OSError as exc:
        raise ConfigError(f"cannot read {path}: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path} is not valid TOML: {exc}") from None
    try:
        return RobotConfig.model_validate(raw)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise ConfigError(f"{path}: {where}: {first['msg']}") from None
