"""What a stored robot message means for the jobs: a SESSION_END queues the session's
processing, data stored after the end has it processed again, and sessions the station
ended to make room for a robot's new one are processed as they are."""

from __future__ import annotations

import anyio

from robot_link.protocol import Message
from server.config import Settings
from server.jobs.runner import JobRunner
from server.link.ingest import StoreResult


class JobTriggers:
    """Queues processing as robot messages are stored (with ``auto_process`` on)."""

    def __init__(self, jobs: JobRunner, settings: Settings) -> None:
        self.jobs, self.auto = jobs, settings.auto_process

    async def on_stored(self, robot: str, message: Message, result: StoreResult) -> None:
        """Called after each stored message's ACK."""
        if not self.auto:
            return
        for old in result.superseded:  # ended by the station: processed as they are
            await anyio.to_thread.run_sync(self.jobs.enqueue_pipeline, old)
        sid = str(message.session_id)
        if result.session_ended:
            await anyio.to_thread.run_sync(self.jobs.enqueue_pipeline, sid)
        elif result.late:  # its results miss this: processed again once the rest is in
            self.jobs.mark_stale(sid)
