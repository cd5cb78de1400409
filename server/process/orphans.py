"""Worker processes end with the station: each watches its parent and exits at once when
the parent is gone (killed, crashed), so no job writes results for a station that died and
no worker outlives it."""

from __future__ import annotations

import os
import threading

from server.process.allocator import keep_arrays_on_heap

PARENT_POLL_S = 0.5


def exit_with_parent(poll_s: float = PARENT_POLL_S) -> None:
    """Start a daemon thread that ends this process when its parent process is gone."""
    parent = os.getppid()

    def watch() -> None:
        stop = threading.Event()
        while not stop.wait(poll_s):
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def init_worker() -> None:
    """Initializer of the job and live-map worker processes."""
    exit_with_parent()
    keep_arrays_on_heap()
