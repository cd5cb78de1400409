"""Stopping a pool of worker processes when the station stops."""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor

JOIN_S = 5.0  # how long a stopped worker may take to go


def stop_pool(pool: ProcessPoolExecutor, join_s: float = JOIN_S) -> None:
    """Shut a process pool down at once: work not begun is cancelled, the workers are
    stopped (a job in progress is not finished: the station runs it again when it starts
    next), and the pool's queues are closed, so their semaphores are released rather than
    left to the interpreter's exit ("leaked semaphore objects")."""
    workers = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for p in workers:
        if p.is_alive():
            p.terminate()
    for p in workers:
        p.join(join_s)
    pool.shutdown(wait=True)
