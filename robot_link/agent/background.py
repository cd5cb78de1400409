"""The on-board agent in a thread of its own with its own event loop: for benchmarks and
tests that drive it from the outside while reading its logs."""

from __future__ import annotations

import asyncio
import threading
from dataclasses import dataclass, field
from typing import Any

from robot_link.agent.agent import RobotAgent
from robot_link.agent.config import RobotConfig


@dataclass
class AgentThread:
    """A running agent; ``summary`` once it ended, ``error`` if it failed."""

    agent: RobotAgent
    thread: threading.Thread
    loop: asyncio.AbstractEventLoop
    summary: dict[str, Any] = field(default_factory=dict)
    error: BaseException | None = None

    def stop(self, timeout_s: float = 120.0) -> None:
        """End the session (sent and acknowledged) and wait for the thread."""
        if self.thread.is_alive():
            self.loop.call_soon_threadsafe(self.agent.end_requested.set)
        self.thread.join(timeout_s)


def start_agent(
    config: RobotConfig, *, sweep: bool = False, timeout_s: float = 60.0
) -> AgentThread:
    """Start the agent and wait until its session is under way (RuntimeError if it failed)."""
    ready = threading.Event()
    holder: dict[str, Any] = {}

    def run() -> None:
        async def main() -> None:
            agent = RobotAgent(config, sweep=sweep)
            holder.update(agent=agent, loop=asyncio.get_running_loop())
            task = asyncio.create_task(agent.run())
            while agent.link is None and not task.done():
                await asyncio.sleep(0.05)
            ready.set()
            holder["summary"] = await task

        try:
            asyncio.run(main())
        except BaseException as exc:  # reported to the caller
            holder["error"] = exc
        finally:
            ready.set()

    thread = threading.Thread(target=run, name="robot-agent", daemon=True)
    thread.start()
    if not ready.wait(timeout_s) or "error" in holder or "agent" not in holder:
        raise RuntimeError(f"the agent did not start: {holder.get('error')}")
    handle = AgentThread(holder["agent"], thread, holder["loop"])

    def finish() -> None:
        thread.join()
        handle.summary = holder.get("summary", {})
        handle.error = holder.get("error")

    threading.Thread(target=finish, daemon=True).start()
    return handle
