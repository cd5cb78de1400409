"""The agent's safety layer, on board and independent of the link: what motion is allowed
now. The MCU's firmware enforces the same rules again (two layers, as real robots have).

- link lost: stop (the operator can neither see nor stop the robot);
- e-stop: latched until the operator resumes;
- dead-man: an operator's drive command holds ``deadman_s``, then the robot stops;
- MCU line silent or garbled: stop;
- battery below ``min_battery_v`` or adhesion margin of eq. (1) below ``min_adhesion``:
  no driving;
- edges (the paper's Algorithm 1): no forward motion while a front IR sensor sees no
  surface, no reverse at the rear, nothing with three or more out.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from robot_link.agent.config import SafetyConfig

FRONT, REAR = (0, 1), (2, 3)  # IR sensor indices (IR_NAMES order)


@dataclass
class SafetyInputs:
    """What the safety layer looks at."""

    link_up: bool = True
    estop: bool = False
    mcu_error: str | None = None
    battery_v: float | None = None
    adhesion: float | None = None
    ir_out: list[int] = field(default_factory=list)


@dataclass(frozen=True)
class Verdict:
    """The allowed motion and why it differs from the commanded one."""

    v: float
    w: float
    reasons: tuple[str, ...] = ()

    @property
    def halted(self) -> bool:
        """Whether every motion is refused."""
        return any(not r.startswith("edge") for r in self.reasons)


def allowed_motion(v: float, w: float, s: SafetyInputs, cfg: SafetyConfig) -> Verdict:
    """The motion (``v`` m/s, ``w`` rad/s) the robot may make now."""
    reasons = []
    if not s.link_up:
        reasons.append("link lost")
    if s.estop:
        reasons.append("e-stop latched")
    if s.mcu_error:
        reasons.append(f"MCU: {s.mcu_error}")
    if s.battery_v is not None and s.battery_v < cfg.min_battery_v:
        reasons.append(f"battery {s.battery_v:.2f} V below {cfg.min_battery_v} V")
    if s.adhesion is not None and s.adhesion < cfg.min_adhesion:
        reasons.append(f"adhesion margin {s.adhesion:.2f} below {cfg.min_adhesion} (eq. (1))")
    if reasons:
        return Verdict(0.0, 0.0, tuple(reasons))
    v = max(-cfg.max_speed_mps, min(cfg.max_speed_mps, v))
    w = max(-cfg.max_turn_radps, min(cfg.max_turn_radps, w))
    out = set(s.ir_out)
    if len(out) >= 3:
        return Verdict(0.0, 0.0, ("edge: three IR sensors see no surface",))
    if v > 0 and out & set(FRONT):
        return Verdict(0.0, w, ("edge ahead",))
    if v < 0 and out & set(REAR):
        return Verdict(0.0, w, ("edge behind",))
    return Verdict(v, w)
