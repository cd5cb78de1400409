"""The telemetry's fields and their units.

A telemetry sample is a JSON object (``TelemetryMeta`` and whatever else a robot sends).
The protocol names a quantity's unit by the suffix of its key (``distance_m``,
``wheel_speed_mps``, ``battery_v``); a group or a list takes its key's unit for every
member (``battery_v.main`` is in volts, ``wheel_speed_mps[2]`` in m/s). A key without a
known suffix is a count or a ratio (``frames``, ``adhesion_margin``).
"""

from __future__ import annotations

import math
from typing import Any

# the longest suffix that matches wins ("_radps" before "_ps"-like shorter ones)
UNIT_SUFFIXES: dict[str, str] = {
    "_mps": "m/s",
    "_radps": "rad/s",
    "_dps": "°/s",
    "_mm": "mm",
    "_mm2": "mm²",
    "_m2": "m²",
    "_m": "m",
    "_v": "V",
    "_a": "A",
    "_w": "W",
    "_ms": "ms",
    "_s": "s",
    "_hz": "Hz",
    "_deg": "°",
    "_rad": "rad",
    "_c": "°C",
    "_percent": "%",
    "_pa": "Pa",
    "_n": "N",
}
MAX_DEPTH = 6  # nesting a sample may have that is still read as fields
# the pose's members are named x, y, yaw: the protocol's Pose2D is in metres and radians
POSE_UNITS = {"x": "m", "y": "m", "yaw": "rad"}


def key_unit(key: str) -> str:
    """The unit a key's suffix names ("" when it names none)."""
    k = key.lower()
    for suffix in sorted(UNIT_SUFFIXES, key=len, reverse=True):
        if k.endswith(suffix) and len(k) > len(suffix):
            return UNIT_SUFFIXES[suffix]
    return ""


def field_unit(path: str) -> str:
    """The unit of a flattened field (``"battery_v.main"``, ``"wheel_speed_mps[0]"``,
    ``"pose.yaw"``): its own key's suffix, else the nearest enclosing key's."""
    parts = [p.split("[", 1)[0] for p in path.split(".")]
    if len(parts) == 2 and parts[0] == "pose" and parts[1] in POSE_UNITS:
        return POSE_UNITS[parts[1]]
    for key in reversed(parts):
        unit = key_unit(key)
        if unit:
            return unit
    return ""


def numeric_fields(sample: dict[str, Any]) -> dict[str, float]:
    """Every finite number in a telemetry sample, by its flattened path (objects joined with
    ``.``, list members as ``[i]``); booleans, strings and nulls are not quantities."""
    out: dict[str, float] = {}

    def walk(value: Any, path: str, depth: int) -> None:
        if isinstance(value, bool) or value is None or depth > MAX_DEPTH:
            return
        if isinstance(value, int | float):
            if math.isfinite(value):
                out[path] = float(value)
        elif isinstance(value, dict):
            for k, v in value.items():
                walk(v, f"{path}.{k}" if path else str(k), depth + 1)
        elif isinstance(value, list):
            for i, v in enumerate(value):
                walk(v, f"{path}[{i}]", depth + 1)

    walk(sample, "", 0)
    return out
