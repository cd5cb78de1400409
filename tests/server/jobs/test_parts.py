"""A job's parts spread through the data directory: helpers take chunks nobody has taken;
a chunk whose helper went silent is done again by the job's worker; results come back in
order, each item once."""

from __future__ import annotations

import multiprocessing
import os
import pickle
import threading
import time
from pathlib import Path
from typing import Any

from server.jobs.context import JobContext
from server.jobs.parts import (
    PARTS_DIR,
    FolderFanout,
    chunked,
    clear,
    help_with,
    next_stretch,
    widest_gap,
    work_through,
)
from server.storage.files import SessionFiles


def who_did_it(files: SessionFiles, shared: float, item: int) -> tuple[int, int]:
    time.sleep(shared)
    return item, threading.get_ident()


def context(tmp_path: Path, attempt: int = 1) -> JobContext:
    return JobContext(7, "s", None, SessionFiles(tmp_path), attempt=attempt)  # type: ignore[arg-type]


def doubled_or_die(files: SessionFiles, shared: None, item: int) -> tuple[int, int]:
    """Doubles ``item``, noting which process did it; the process dies at item 7 while the
    data directory holds a ``die`` file (a worker lost mid-job)."""
    (files.data_dir / "done").mkdir(exist_ok=True)
    (files.data_dir / "done" / f"{item}-{os.getpid()}").touch()
    if item == 7 and (files.data_dir / "die").exists():
        os._exit(3)
    return item * 2, os.getpid()


def fan_out(tmp_path: Path, helpers: int, items: list[int], pause: float) -> list[Any]:
    """``items`` through :func:`who_did_it` on the job's worker (this thread) and
    ``helpers`` helper threads asked through the queue; the results, helpers joined."""
    threads: list[threading.Thread] = []

    def ask(job_id: int, name: str, helpers: int) -> None:
        for _ in range(helpers):
            t = threading.Thread(target=help_with, args=(tmp_path, name, 5.0))
            t.start()
            threads.append(t)

    out = FolderFanout(ask, helpers, lease_s=5.0)(context(tmp_path), who_did_it, pause, items)
    for t in threads:
        t.join()
    return out


def test_chunks_cover_the_items_in_order() -> None:
    for n, pieces in ((10, 3), (3, 8), (1, 4), (100, 16)):
        chunks = chunked(list(range(n)), pieces)
        assert [x for c in chunks for x in c] == list(range(n))
        assert len(chunks) == min(n, pieces) and all(chunks)


def test_the_widest_gap_is_the_longest_run_nobody_took() -> None:
    assert widest_gap(set(), 8) == (0, 8)
    assert widest_gap({0, 1, 5, 9}, 10) == (2, 5)  # 2..4 beats 6..8 (the first of equals)
    assert widest_gap({0, 1, 2, 3, 4, 5, 8, 9}, 10) == (6, 8)
    assert widest_gap({0, 2}, 4) == (1, 2)
    assert widest_gap(set(range(5)), 5) is None


def test_a_worker_heads_towards_whoever_comes() -> None:
    """So that the two meet and neither jumps again: a helper joining the job's worker
    (coming forwards from chunk 0) starts at the last chunk."""
    assert list(next_stretch(1, 6, from_left=True, from_right=False)) == [5, 4, 3, 2, 1]
    assert list(next_stretch(1, 6, from_left=False, from_right=True)) == [1, 2, 3, 4, 5]
    assert list(next_stretch(0, 6, from_left=False, from_right=False)) == list(range(6))
    assert list(next_stretch(2, 10, from_left=True, from_right=True)) == [6, 7, 8, 9]


def test_a_helper_and_the_jobs_worker_meet_from_both_ends(tmp_path: Path) -> None:
    """Whichever comes second starts at the other end: the items split into a prefix and a
    suffix, one for each."""
    items = list(range(40))
    out = fan_out(tmp_path, 1, items, 0.005)
    who = [w for _, w in out]
    assert [i for i, _ in out] == items
    assert len(set(who)) == 2
    assert sum(a != b for a, b in zip(who, who[1:])) == 1


def test_each_worker_does_runs_of_consecutive_chunks(tmp_path: Path) -> None:
    """Two helpers and the job's worker, each doing its items in runs of consecutive ones;
    every item once, the results in order."""
    items = list(range(96))
    out = fan_out(tmp_path, 2, items, 0.005)
    assert [i for i, _ in out] == items
    who = [w for _, w in out]
    assert len(set(who)) == 3
    runs = 1 + sum(a != b for a, b in zip(who, who[1:]))
    # a run each, then the stretches left between them halved as workers meet: a score of
    # runs at most, where 64 chunks dealt out in turn would make about sixty
    assert runs <= 20


def test_helpers_take_chunks_and_results_come_back_in_order(tmp_path: Path) -> None:
    items = list(range(40))
    out = fan_out(tmp_path, 2, items, 0.01)
    assert [i for i, _ in out] == items
    assert len({who for _, who in out}) > 1  # the helpers did some of it
    assert not any((tmp_path / PARTS_DIR).iterdir())  # the plan is cleared


def test_a_chunk_a_lost_helper_took_is_done_again(tmp_path: Path) -> None:
    """A helper that claimed a chunk and died (its claim file no longer touched)."""

    def ask(job_id: int, name: str, helpers: int) -> None:
        folder = tmp_path / PARTS_DIR / name
        _, _, chunks = pickle.loads((folder / "plan.pkl").read_bytes())
        claim = folder / f"{len(chunks) - 1}.claim"
        claim.touch()
        os.utime(claim, (time.time() - 60, time.time() - 60))

    items: list[Any] = list(range(12))
    t0 = time.monotonic()
    out = FolderFanout(ask, 1, lease_s=1.0)(context(tmp_path), who_did_it, 0.0, items)
    assert [i for i, _ in out] == items
    assert time.monotonic() - t0 < 10


def test_a_helper_whose_clock_is_behind_is_not_taken_for_lost(tmp_path: Path) -> None:
    """A live helper on a machine whose clock is two minutes behind touches its claim with
    old times: they change, so the chunk stays the helper's."""
    helper: list[int] = []

    def help_late_clock(folder: Path) -> None:
        _, shared, chunks = pickle.loads((folder / "plan.pkl").read_bytes())
        i = len(chunks) - 1
        claim = folder / f"{i}.claim"
        claim.touch()  # taken before the job's worker gets there (it goes in order)
        helper.append(threading.get_ident())
        for k in range(15):
            t = time.time() - 120 + k * 0.1
            os.utime(claim, (t, t))
            time.sleep(0.1)
        result = [who_did_it(SessionFiles(tmp_path), shared, item) for item in chunks[i]]
        (folder / f"{i}.pkl").write_bytes(pickle.dumps(result))

    threads: list[threading.Thread] = []

    def ask(job_id: int, name: str, helpers: int) -> None:
        t = threading.Thread(target=help_late_clock, args=(tmp_path / PARTS_DIR / name,))
        t.start()
        threads.append(t)
        while not helper:
            time.sleep(0.01)

    items = list(range(8))
    out = FolderFanout(ask, 1, lease_s=1.0)(context(tmp_path), who_did_it, 0.0, items)
    threads[0].join()
    assert [i for i, _ in out] == items
    assert out[-1][1] == helper[0]  # the helper's result, not one done again


def first_attempt(tmp_path: Path, items: list[int]) -> None:
    """The first attempt's worker (a process of its own), lost mid-job."""
    FolderFanout(no_helpers, 0, lease_s=1.0)(context(tmp_path, 1), doubled_or_die, None, items)


def no_helpers(job_id: int, name: str, helpers: int) -> None:
    pass


def test_a_new_attempt_adopts_the_chunks_a_lost_attempt_finished(tmp_path: Path) -> None:
    items = list(range(12))  # a chunk an item: the first attempt dies in the eighth
    (tmp_path / "die").touch()
    lost = multiprocessing.get_context("spawn").Process(
        target=first_attempt, args=(tmp_path, items)
    )
    lost.start()
    lost.join(60)
    assert lost.exitcode == 3
    pid = lost.pid
    (tmp_path / "die").unlink()
    out = FolderFanout(no_helpers, 0, lease_s=1.0)(
        context(tmp_path, 2), doubled_or_die, None, items
    )
    assert [v for v, _ in out] == [2 * i for i in items]
    assert {who for _, who in out[:7]} == {pid}  # the chunks the lost attempt finished
    assert {who for _, who in out[7:]} == {os.getpid()}
    done = sorted(p.name for p in (tmp_path / "done").iterdir())
    assert [d for d in done if d.startswith("0-")] == [f"0-{pid}"]  # not done again
    assert not any((tmp_path / PARTS_DIR).iterdir())  # both attempts' folders are gone


def test_a_helper_coming_late_finds_nothing_to_do(tmp_path: Path) -> None:
    assert help_with(tmp_path, "7-1-gone", 5.0) == 0


def test_a_helper_takes_nothing_from_a_plan_being_cleared(tmp_path: Path) -> None:
    """The job's worker clears its plan once every result is in; a helper still going
    through it stops there, and the plan is gone whole (renamed away before it is removed,
    so no claim file is ever seen missing while the folder stands)."""
    folder = tmp_path / PARTS_DIR / "7-1-plan-x"
    folder.mkdir(parents=True)
    (folder / "plan.pkl").write_bytes(pickle.dumps((who_did_it, 0.0, [[0], [1], [2], [3]])))
    done = work_through(folder, SessionFiles(tmp_path), 1.0, stop=lambda: None)
    assert done == 4
    calls: list[int] = []

    def cleared_after_one() -> None:
        calls.append(1)
        if len(calls) == 2:
            clear(folder)

    for claim in folder.glob("*.claim"):
        claim.unlink()
    assert work_through(folder, SessionFiles(tmp_path), 1.0, stop=cleared_after_one) == 1
    assert not any((tmp_path / PARTS_DIR).iterdir())
