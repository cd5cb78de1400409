"""The dashboard's commands as the on-board agent carries them out."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from robot_link.agent.agent import RobotAgent


def apply_command(agent: RobotAgent, cmd: str, args: dict[str, Any]) -> str:
    """Carry out ``cmd``; the reason it was refused, or ''."""
    c = agent.control
    if cmd == "drive":
        if c.safety.estop:
            return "emergency stop is engaged: resume first"
        try:
            v, w = float(args.get("linear_mps", 0.0)), float(args.get("angular_radps", 0.0))
        except (TypeError, ValueError):
            return "linear_mps and angular_radps must be numbers"
        if not (math.isfinite(v) and math.isfinite(w)):
            return "linear_mps and angular_radps must be finite"
        sent = args.get("sent_ms")
        c.drive(
            v,
            w,
            float(sent) if isinstance(sent, (int, float)) else None,
            key_event=bool(args.get("key_event")),
        )
    elif cmd in ("stop", "estop"):
        c.stop(estop=cmd == "estop")
    elif cmd == "resume":
        c.resume()
    elif cmd == "capture":
        agent.request_capture()
    elif cmd == "lift":
        axle = args.get("axle")
        if axle not in c.lifts:
            return "axle must be front or rear"
        c.lifts[axle] = bool(args.get("up", not c.lifts[axle]))
        agent.mcu.lift(axle, c.lifts[axle])
    elif cmd == "auto_capture":
        agent.auto_capture = bool(args.get("on", not agent.auto_capture))
    elif cmd == "sweep":
        return _sweep(agent, str(args.get("action", "start")))
    elif cmd == "end_session":
        agent.end_requested.set()
    else:
        return f"unknown command {cmd!r}"
    return ""


def _sweep(agent: RobotAgent, action: str) -> str:
    c = agent.control
    if action in ("start", "resume"):
        if c.safety.estop:
            return "emergency stop is engaged: resume first"
        agent.start_sweep()
    elif action == "pause":
        if c.sweep_state == "running":
            c.set_sweep("paused")
    elif action == "stop":
        c.set_sweep("stopped")
        agent.sweep = None
    else:
        return "action must be start, pause, resume or stop"
    return ""
