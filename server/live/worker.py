"""One worker process for a live view's heavy work (ICP, a detector), which would starve the
event loop and the viser server in the station's own process: at most ``max_pending``
items wait, beyond that items are skipped (the jobs after the session use every item),
and each result goes to a callback in the pool's thread. While the worker warms up (its
imports, a model: seconds on a busy machine) items wait however many arrive, up to
``WARMING_CAP``: skipping them would drop the session's first stretch in one run (the live
map could not tie the clouds on either side of it)."""

from __future__ import annotations

import logging
import multiprocessing
import threading
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any

from server.process.orphans import init_worker
from server.process.pools import stop_pool

log = logging.getLogger(__name__)
WARMING_CAP = 64  # items that may wait for a worker still warming up


class LiveWorker:
    """A lazily started single-process pool with a bound on waiting items."""

    def __init__(self, what: str, max_pending: int) -> None:
        self.what = what
        self.max_pending = max_pending
        self.skipped = 0
        self._pool: ProcessPoolExecutor | None = None
        self._pending = 0
        self._warming: Future[Any] | None = None
        self._lock = threading.Lock()

    def _started(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(
                1, mp_context=multiprocessing.get_context("spawn"), initializer=init_worker
            )
        return self._pool

    def warm(self, fn: Callable[[], Any]) -> None:
        """Start the worker and run ``fn`` there (imports, a model) ahead of the first item,
        which would otherwise wait for them while the items after it are skipped."""
        with self._lock:
            self._warming = self._started().submit(fn)

    def submit(self, fn: Callable[..., Any], *args: Any, done: Callable[[Any], None]) -> bool:
        """Run ``fn(*args)`` in the worker and hand its result to ``done``; False (skipped)
        when the worker is behind. A failure is logged: live views are a courtesy."""
        with self._lock:
            warming = self._warming is not None and not self._warming.done()
            if self._pending >= (WARMING_CAP if warming else self.max_pending):
                self.skipped += 1
                return False
            self._pending += 1
            pool = self._started()

        def finished(future: Future[Any]) -> None:
            with self._lock:
                self._pending -= 1
            try:
                result = future.result()
            except Exception:
                log.warning("%s: an item failed", self.what, exc_info=True)
                return
            done(result)

        pool.submit(fn, *args).add_done_callback(finished)
        return True

    def close(self) -> None:
        """Stop the worker."""
        if self._pool is not None:
            stop_pool(self._pool)
