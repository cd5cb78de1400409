"""The live views' worker process: items beyond the bound are skipped once it runs, but none
while it warms up, so a slow start does not drop a session's first stretch."""

from __future__ import annotations

import functools
import time

from server.live.worker import LiveWorker


def _collect(worker: LiveWorker, items: list[float]) -> tuple[list[bool], list[float]]:
    """Submit ``items`` (seconds to sleep) at once; whether each was taken, and the items
    done, in the order they came back."""
    results: list[float] = []
    taken = [worker.submit(time.sleep, s, done=lambda _, s=s: results.append(s)) for s in items]
    deadline = time.monotonic() + 60
    while len(results) < sum(taken):
        assert time.monotonic() < deadline, "the worker did not finish"
        time.sleep(0.05)
    return taken, results


def test_items_wait_while_the_worker_warms_up_and_are_skipped_beyond_the_bound_after() -> None:
    worker = LiveWorker("test", max_pending=2)
    try:
        worker.warm(functools.partial(time.sleep, 1.5))
        first = [0.001 * (k + 1) for k in range(10)]
        taken, results = _collect(worker, first)
        assert taken == [True] * 10  # all waited for the warm-up
        assert results == first  # in order
        assert worker.skipped == 0

        taken, results = _collect(worker, [0.5, 0.5, 0.5, 0.5])
        assert taken == [True, True, False, False]  # warm now: two at most wait
        assert worker.skipped == 2
        assert results == [0.5, 0.5]
    finally:
        worker.close()
