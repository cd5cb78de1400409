"""``steelscan robot`` (the on-board agent) and ``steelscan mcu-emulator`` (the robot's
microcontroller on a pseudo-terminal, for tests and a first run without hardware)."""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from pathlib import Path
from typing import Any

from server.errors import CommandError


def add_robot_commands(sub: Any) -> None:
    """Add ``robot`` and ``mcu-emulator`` to the sub-commands."""
    s = sub.add_parser("robot", help="the on-board agent of a real robot (robot.toml)")
    s.add_argument("--config", required=True, help="robot.toml (docs/robot.md)")
    s.add_argument(
        "--sweep",
        action="store_true",
        help="inspect the plate on its own: lanes edge to edge, then end the session and exit",
    )
    s.set_defaults(func=cmd_robot)

    s = sub.add_parser("mcu-emulator", help="the robot's MCU, emulated on a pseudo-terminal")
    s.add_argument("--seed", type=int, default=0, help="the plate's size, defects and start pose")
    s.add_argument("--plate", help="plate size WxH in metres (default: from the seed)")
    s.add_argument(
        "--inclination", type=float, default=90.0, help="the plate's inclination, degrees"
    )
    s.set_defaults(func=cmd_mcu_emulator)


def cmd_robot(args: argparse.Namespace) -> int:
    """Run the on-board agent; its summary as the last line of stdout."""
    from robot_link.agent.agent import RobotAgent
    from robot_link.agent.camera import CameraError
    from robot_link.agent.config import ConfigError, load_config
    from robot_link.agent.tof import TofError
    from robot_link.client import LinkError
    from robot_link.mcu.link import McuError

    try:
        config = load_config(Path(args.config))
    except ConfigError as exc:
        raise CommandError(str(exc)) from None

    async def main() -> dict[str, Any]:
        return await RobotAgent(config, sweep=args.sweep).run()

    try:
        summary = asyncio.run(main())
    except (McuError, CameraError, TofError, LinkError) as exc:
        raise CommandError(str(exc)) from None
    sys.stdout.write(json.dumps(summary) + "\n")
    if summary.get("sweep_error"):
        raise CommandError(f"the sweep could not cover the plate: {summary['sweep_error']}")
    return 0


def cmd_mcu_emulator(args: argparse.Namespace) -> int:
    """Run the MCU emulator until SIGTERM."""
    from robot_link.emulator.run import run_emulator
    from robot_link.emulator.world import make_world

    plate = None
    if args.plate:
        try:
            w, h = (float(v) for v in args.plate.lower().split("x"))
        except ValueError:
            raise CommandError(
                f"--plate {args.plate!r}: give WxH in metres, e.g. 1.2x0.8"
            ) from None
        plate = (w, h)
    try:
        world = make_world(args.seed, plate)
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    world.inclination_deg = args.inclination
    run_emulator(world)
    return 0
