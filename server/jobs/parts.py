"""One job's independent parts spread over several workers through the shared data
directory: only ids and a folder's name pass through the broker.

The job's worker writes a *plan* (the part function, what every part shares, the chunks of
items) into ``DATA/.parts/<name>/``, asks other workers for help (a Celery group of
``steelscan.part`` tasks) and works through the chunks itself too. A chunk is taken by
creating its claim file exclusively, done, and its result written atomically beside it; the
claim file is touched while the chunk runs, and says which way its worker is heading. A
worker goes through consecutive chunks, so that what it decoded and cached for one serves
the next, and when it meets a taken chunk it moves to the widest stretch nobody has taken,
heading towards whoever works into it (:func:`next_stretch`): a helper joining the job's
worker starts at the last chunk and the two meet wherever their speeds put them. A claim is
silent when its modification time stops changing for a lease, timed on the job's worker's
own clock (the helper's or the file server's clock may be set differently). Chunks another
worker took but left silent for a lease are done again by the job's worker, so a helper
lost mid-chunk costs time, never a result; helpers that come late find every chunk taken
and return. Nothing waits on a helper, so a job never deadlocks on a busy queue.

A plan's folder is named by its job, attempt and the digest of the plan. When the job's
worker is lost and a new attempt makes the same plan (same function, same shared data, same
chunks), it adopts the results the earlier attempts' chunks left and does only the rest: a
long job loses to a lost worker only the chunks that were running. Plans that name
something of their attempt (its staging folder) are never the same, and start afresh.
"""

from __future__ import annotations

import hashlib
import logging
import os
import pickle
import shutil
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from server.jobs.context import JobContext, Part
from server.storage.files import SessionFiles, write_atomic

log = logging.getLogger(__name__)

PARTS_DIR = ".parts"
POLL_S = 0.05
FORWARDS, BACKWARDS = b"+", b"-"  # a claim file's content: which way its worker heads
CHUNKS_PER_WORKER = 4  # chunks per worker taking part, at least: evens out unequal costs
MAX_CHUNKS = 64  # a plan's chunks when the items allow: a worker left waiting at the end
# waits for one small chunk (a chunk costs a claim file and a result file)


def chunked(items: Sequence[Any], pieces: int) -> list[list[Any]]:
    """``items`` in ``pieces`` consecutive runs of near-equal length (none empty)."""
    pieces = max(1, min(pieces, len(items)))
    edges = [round(len(items) * k / pieces) for k in range(pieces + 1)]
    return [list(items[a:b]) for a, b in zip(edges, edges[1:]) if b > a]


class FolderFanout:
    """:class:`~server.jobs.context.Fanout` over the shared data directory; ``ask(job_id,
    name, helpers)`` asks ``helpers`` other workers to call :func:`help_with`."""

    def __init__(self, ask: Callable[[int, str, int], None], helpers: int, lease_s: float) -> None:
        self.ask, self.helpers, self.lease_s = ask, helpers, lease_s

    def __call__(self, ctx: JobContext, fn: Part, shared: Any, items: Sequence[Any]) -> list[Any]:
        chunks = chunked(items, max(MAX_CHUNKS, CHUNKS_PER_WORKER * (self.helpers + 1)))
        plan = pickle.dumps((fn, shared, chunks))
        digest = hashlib.blake2b(plan, digest_size=8).hexdigest()
        name = f"{ctx.job_id}-{ctx.attempt}-{digest}-{uuid.uuid4().hex[:8]}"
        folder = ctx.files.data_dir / PARTS_DIR / name
        folder.mkdir(parents=True)
        try:
            write_atomic(folder / "plan.pkl", plan)
            adopted = adopt_earlier(folder, ctx.job_id, ctx.attempt, digest)
            if adopted:
                log.info(
                    "job %d attempt %d: %d of %d chunks done by an earlier attempt",
                    ctx.job_id,
                    ctx.attempt,
                    adopted,
                    len(chunks),
                )
            if self.helpers and len(chunks) - adopted > 1:
                self.ask(ctx.job_id, name, min(self.helpers, len(chunks) - adopted - 1))
            work_through(folder, ctx.files, self.lease_s / 4, stop=ctx.check)
            results = _collect(folder, ctx.files, len(chunks), self.lease_s, ctx)
        finally:
            clear(folder)
        return [r for chunk in results for r in chunk]


def adopt_earlier(folder: Path, job_id: int, attempt: int, digest: str) -> int:
    """Take into ``folder`` the chunk results that earlier attempts of the job left for the
    same plan (``digest``), each marked taken, and remove those attempts' folders; the
    number of chunks adopted. Results are written atomically, so every one found is whole."""
    adopted = 0
    for old in folder.parent.glob(f"{job_id}-*-{digest}-*"):
        fields = old.name.split("-")
        if len(fields) != 4 or not fields[1].isdigit() or int(fields[1]) >= attempt:
            continue
        for result in old.glob("*.pkl"):
            target = folder / result.name
            if not result.stem.isdigit() or target.exists():
                continue
            try:
                os.link(result, target)
            except FileExistsError:
                continue
            except OSError:  # a file system without hard links
                try:
                    write_atomic(target, result.read_bytes())
                except OSError:
                    continue
            _take(folder / f"{result.stem}.claim")
            adopted += 1
        clear(old)
    return adopted


def clear(folder: Path) -> None:
    """Remove a plan's folder, renamed away first: a helper never sees it half removed (its
    claim files gone, its chunks seemingly free) and takes nothing more from it."""
    gone = folder.with_name(f".cleared-{folder.name}")
    try:
        os.rename(folder, gone)
    except FileNotFoundError:
        return
    shutil.rmtree(gone, ignore_errors=True)


def help_with(data_dir: Path, name: str, lease_s: float) -> int:
    """A helper's part: work through a plan's chunks that nobody has taken; the number done
    (0 when the plan is gone or every chunk was taken)."""
    folder = Path(data_dir) / PARTS_DIR / name
    if not (folder / "plan.pkl").is_file():
        return 0
    return work_through(folder, SessionFiles(Path(data_dir)), lease_s / 4)


def widest_gap(taken: set[int], n: int) -> tuple[int, int] | None:
    """The longest run ``lo .. hi - 1`` of a plan's ``n`` chunks that nobody has taken (the
    first of equals); None when every chunk is taken."""
    best, start = None, None
    for i in range(n + 1):
        if i < n and i not in taken:
            start = i if start is None else start
        elif start is not None:
            if best is None or i - start > best[1] - best[0]:
                best = (start, i)
            start = None
    return best


def next_stretch(lo: int, hi: int, from_left: bool, from_right: bool) -> range:
    """The chunks ``lo .. hi - 1`` in the order a worker goes through them, given whether a
    worker is heading into them from the left (forwards from ``lo - 1``) or from the right
    (backwards from ``hi``): towards the one worker coming, so the two meet and neither
    jumps again; from the middle forwards when one comes from each side; from ``lo`` when
    none does."""
    if from_left and not from_right:
        return range(hi - 1, lo - 1, -1)
    if from_left and from_right:
        return range(lo + (hi - lo) // 2, hi)
    return range(lo, hi)


def work_through(
    folder: Path, files: SessionFiles, touch_s: float, stop: Callable[[], None] = lambda: None
) -> int:
    """Take and do chunks until none is left to take, stretch by stretch (see
    :func:`next_stretch`); the number done."""
    try:
        fn, shared, chunks = pickle.loads((folder / "plan.pkl").read_bytes())
    except (OSError, EOFError, pickle.UnpicklingError):
        return 0  # the plan was removed: the job finished without us
    done = 0
    while (taken := _taken(folder)) is not None and (gap := widest_gap(taken, len(chunks))):
        lo, hi = gap
        order = next_stretch(
            lo, hi, _heading(folder, lo - 1) == FORWARDS, _heading(folder, hi) == BACKWARDS
        )
        for i in order:  # until the chunk of whoever comes the other way
            stop()
            if not _take(folder / f"{i}.claim", FORWARDS if order.step > 0 else BACKWARDS):
                break
            _run_chunk(folder, files, fn, shared, chunks, i, touch_s)
            done += 1
    return done


def _taken(folder: Path) -> set[int] | None:
    """The chunks of the plan in ``folder`` that are taken; None once the plan is cleared."""
    try:
        names = os.listdir(folder)
    except FileNotFoundError:
        return None
    return {int(m[: -len(".claim")]) for m in names if m.endswith(".claim") and m[0].isdigit()}


def _heading(folder: Path, i: int) -> bytes:
    """Which way the worker that took chunk ``i`` was heading (empty when unknown)."""
    try:
        return (folder / f"{i}.claim").read_bytes()[:1]
    except OSError:
        return b""


def _take(claim: Path, heading: bytes = b"") -> bool:
    """Create ``claim`` holding ``heading`` unless it exists: written beside it first and
    hard-linked into place, so no worker ever reads a claim without its heading (exclusive
    creation where the file system has no hard links)."""
    if not heading:
        return _create(claim)
    tmp = claim.with_name(f".{claim.name}.{uuid.uuid4().hex}")
    try:
        tmp.write_bytes(heading)
    except FileNotFoundError:  # the folder is gone
        return False
    try:
        os.link(tmp, claim)
    except (FileExistsError, FileNotFoundError):
        return False
    except OSError:  # no hard links here
        return _create(claim, heading)
    finally:
        tmp.unlink(missing_ok=True)
    return True


def _create(claim: Path, heading: bytes = b"") -> bool:
    try:
        fd = os.open(claim, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except (FileExistsError, FileNotFoundError):  # taken, or the folder is gone
        return False
    try:
        os.write(fd, heading)
    finally:
        os.close(fd)
    return True


def _run_chunk(
    folder: Path,
    files: SessionFiles,
    fn: Part,
    shared: Any,
    chunks: list[list[Any]],
    i: int,
    touch_s: float,
) -> None:
    claim, stop = folder / f"{i}.claim", threading.Event()

    def touch() -> None:
        while not stop.wait(touch_s):
            try:
                os.utime(claim)
            except OSError:
                return

    toucher = threading.Thread(target=touch, name="part-claim", daemon=True)
    toucher.start()
    try:
        result = [fn(files, shared, item) for item in chunks[i]]
    finally:
        stop.set()
        toucher.join()
    try:
        write_atomic(folder / f"{i}.pkl", pickle.dumps(result))
    except FileNotFoundError:
        pass  # the job's worker finished the chunk itself and cleared the plan


def _collect(
    folder: Path, files: SessionFiles, n: int, lease_s: float, ctx: JobContext
) -> list[list[Any]]:
    """Every chunk's result, in order: waits for helpers' chunks, redoing those whose claim
    went silent for a lease."""
    fn, shared, chunks = pickle.loads((folder / "plan.pkl").read_bytes())
    results: list[list[Any] | None] = [None] * n
    touched: dict[int, tuple[float, float]] = {}  # chunk: (claim's mtime, when first seen so)
    while True:
        ctx.check()
        for i in range(n):
            if results[i] is not None:
                continue
            out = folder / f"{i}.pkl"
            if out.is_file():
                results[i] = pickle.loads(out.read_bytes())
                continue
            if _silent(folder / f"{i}.claim", i, touched, lease_s):
                log.warning(
                    "job %d: part %d of %s lost its worker; doing it here",
                    ctx.job_id,
                    i,
                    folder.name,
                )
                _run_chunk(folder, files, fn, shared, chunks, i, lease_s / 4)
        if all(r is not None for r in results):
            return results  # type: ignore[return-value]
        time.sleep(POLL_S)


def _silent(claim: Path, i: int, touched: dict[int, tuple[float, float]], lease_s: float) -> bool:
    """Whether chunk ``i``'s claim went unchanged for ``lease_s`` of this process's monotonic
    clock (or is gone); ``touched`` remembers each claim's last mtime and when it was seen."""
    try:
        mtime = claim.stat().st_mtime
    except FileNotFoundError:
        return True
    now = time.monotonic()
    last = touched.get(i)
    if last is None or last[0] != mtime:
        touched[i] = (mtime, now)
        return False
    return now - last[1] > lease_s
