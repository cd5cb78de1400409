"""``steelscan sim``: the simulated robot against a ground station (an inspection, or a
robot an operator drives)."""

from __future__ import annotations

import argparse
import json
import logging
import os
from pathlib import Path

from server.errors import CommandError


def cmd_sim(args: argparse.Namespace) -> int:
    """Run the simulated robot against a ground station."""
    import asyncio

    from robot_link.client import LinkError, RobotLink
    from robot_link.sim.inspection import InspectionSim, SimConfig

    token = args.token or os.environ.get("STEELSCAN_ROBOT_TOKEN")
    if not token:
        raise CommandError(
            "a robot token is needed: --token or STEELSCAN_ROBOT_TOKEN (make one with 'steelscan admin create-robot NAME')"
        )
    config = SimConfig(
        seed=args.seed,
        lanes=args.lanes,
        time_scale=args.time_scale,
        flush_timeout_s=args.flush_timeout,
    )

    async def main() -> dict:
        from robot_link.spool import Spool

        spool = (
            Spool(Path(args.spool), max_bytes=int(args.spool_max_mb * 2**20))
            if args.spool
            else None
        )
        link = RobotLink(args.server, token, spool=spool, ca_file=args.ca_file)
        await link.start()
        if args.teleop:
            from robot_link.sim.teleop import TeleopConfig, TeleopSim

            sim: InspectionSim = TeleopSim(
                link,
                SimConfig(seed=args.seed, time_scale=1.0, dt_s=0.02, telemetry_hz=10.0),
                TeleopConfig(duration_s=args.duration),
            )
        else:
            sim = InspectionSim(
                link,
                config,
                progress=lambda f, m: logging.getLogger("sim").info("%3.0f%% %s", f * 100, m),
            )
        try:
            result = await sim.run()
            if not args.exit_when_done:
                print(json.dumps(result.summary()), flush=True)
                await asyncio.Event().wait()  # stay connected for commands until interrupted
        finally:
            await link.close()
        return result.summary()

    try:
        summary = asyncio.run(main())
    except (LinkError, ValueError, OSError) as exc:
        raise CommandError(str(exc)) from None
    print(json.dumps(summary), flush=True)
    return 0
