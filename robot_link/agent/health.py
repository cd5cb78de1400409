"""The agent's own health and the telemetry sample it sends: odometry, Hall wheel speeds,
IR, batteries, adhesion, the drive and safety state, the MCU line, the link and the
on-board computer (CPU, temperature, sensor rates)."""

from __future__ import annotations

import os
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from robot_link.mcu.packets import Flag
from robot_link.sim.robot import IR_NAMES

if TYPE_CHECKING:
    from robot_link.agent.agent import RobotAgent

THERMAL = Path("/sys/class/thermal/thermal_zone0/temp")


@dataclass
class AgentHealth:
    """Sensor rates and device errors."""

    camera_error: str | None = None
    tof_error: str | None = None
    events: dict[str, deque[float]] = field(default_factory=dict)
    _cpu: tuple[float, float] = field(
        default_factory=lambda: (time.monotonic(), time.process_time())
    )

    def count(self, what: str) -> None:
        """Note one ``what`` (frames, clouds, preview) now."""
        self.events.setdefault(what, deque(maxlen=200)).append(time.monotonic())

    def rate_hz(self, what: str, window_s: float = 5.0) -> float:
        """``what`` per second over the last ``window_s``."""
        now = time.monotonic()
        return round(sum(1 for t in self.events.get(what, ()) if now - t <= window_s) / window_s, 2)

    def cpu_percent(self) -> float:
        """This process's CPU use since the last call, % of one core."""
        wall, cpu = time.monotonic(), time.process_time()
        (wall0, cpu0), self._cpu = self._cpu, (wall, cpu)
        return round(100 * (cpu - cpu0) / max(wall - wall0, 1e-6), 1)


def _temperature_c() -> float | None:
    try:
        return round(int(THERMAL.read_text()) / 1000, 1)
    except (OSError, ValueError):
        return None


def telemetry_meta(agent: RobotAgent) -> dict[str, Any]:
    """One telemetry sample."""
    c = agent.control
    s = c.latest
    flags = s.flags if s is not None else Flag.NONE
    v, w = c.verdict.v, c.verdict.w
    meta: dict[str, Any] = {
        "pose": agent.odometry.as_meta(),
        "distance_m": round(agent.odometry.distance_m, 4),
        "mode": c.mode,
        "drive": {
            "linear_mps": round(v, 4),
            "angular_radps": round(w, 4),
            "commanded_linear_mps": round(c.commanded()[0], 4),
            "blocked_by": [IR_NAMES[i] for i in c.safety.ir_out]
            if "edge" in " ".join(c.verdict.reasons)
            else [],
            "hold_ms": agent.cfg.safety.deadman_s * 1000,
        },
        "safety": list(c.verdict.reasons),
        "edge_action": _edge_action(c.safety.ir_out, flags),
        "estop": c.safety.estop,
        "lift": dict(c.lifts),
        "auto_capture": {"on": agent.auto_capture, "spacing_m": round(agent.spacing_m(), 4)},
        "frames": agent.frames_sent,
        "adhesion_margin": round(c.adhesion(), 3),
        "inclination_deg": agent.cfg.safety.inclination_deg,
        "mcu": agent.mcu.health.as_meta(),
        "onboard": {
            "cpu_percent": agent.health.cpu_percent(),
            "load_1m": round(os.getloadavg()[0], 2),
            "temperature_c": _temperature_c(),
            "camera_hz": agent.health.rate_hz("frames"),
            "preview_hz": agent.health.rate_hz("preview"),
            "tof_hz": agent.health.rate_hz("clouds"),
            "camera_error": agent.health.camera_error,
            "tof_error": agent.health.tof_error,
        },
    }
    if s is not None:
        meta.update(
            {
                "ir_range_m": [round(r, 4) for r in s.ir_m],
                "ir_no_surface": [IR_NAMES[i] for i in c.safety.ir_out],
                "battery_v": {"main": round(s.battery_v[0], 3), "logic": round(s.battery_v[1], 3)},
                "motor_current_a": [round(a, 3) for a in s.current_a],
                "mcu_faults": str(s.faults.name or "") if s.faults else "",
            }
        )
    if agent.sweep is not None:
        p = agent.sweep.progress
        meta["sweep"] = {
            "state": c.sweep_state,
            "phase": p.phase,
            "lanes_done": p.lanes_done,
            "edges_found": [e[:2] for e in p.edges_found[-40:]],
            "lanes": p.lanes[-60:],
            "next_lane": p.next_lane,
            "holes_visited": p.holes_visited,
        }
        outline = agent.sweep.plate_outline()
        if outline is not None:
            meta["sweep"]["plate_outline"] = np.round(outline, 4).tolist()
    if agent.link is not None:
        link = agent.link
        meta["link"] = {
            "pending": link.pending,
            "resent": link.stats.resent,
            "ack_latency_ms": round(link.stats.last_ack_latency_s * 1000, 2),
            "reconnects": link.stats.reconnects,
            "video_dropped": link.stats.video_dropped,
            "spool_bytes": link.stats.spool_bytes,
        }
    return meta


def _edge_action(out: list[int], flags: Flag) -> str:
    if flags & Flag.BLOCKED_FORWARD:
        return "block_forward"
    if flags & Flag.BLOCKED_REVERSE:
        return "block_reverse"
    return "edge_near" if out else "none"
