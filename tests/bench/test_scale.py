"""How the scale benchmark compares one worker with two: interleaved rounds, best runs."""

from __future__ import annotations

import math

from bench.scale import MAX_REPEATS, ROUNDS, SAMPLE_S, best_of, interleaved, round_order


def test_each_round_reverses_the_order_of_the_sides() -> None:
    assert round_order(3) == [1, 2, 2, 1, 1, 2]
    assert round_order(4) == [1, 2, 2, 1, 1, 2, 2, 1]
    order = round_order(5)
    assert order.count(1) == order.count(2) == 5
    # the side changes once a round: a worker starts or stops once a round
    assert sum(a != b for a, b in zip(order, order[1:])) == 5


def test_every_stage_and_the_job_count_their_shortest_run() -> None:
    runs = [
        ({"id": 1, "result": {"seconds": {"pairs": 9.0, "bands": 3.0}}}, 14.0),
        ({"id": 2, "result": {"seconds": {"pairs": 7.5, "bands": 4.0}}}, 13.0),
        ({"id": 3, "result": {"seconds": {"pairs": 8.0, "bands": 2.5}}}, 12.5),
    ]
    job, seconds = best_of(runs)
    assert job["result"]["seconds"] == {"pairs": 7.5, "bands": 2.5}
    assert job["id"] == 3 and seconds == 12.5
    assert runs[2][0]["result"]["seconds"] == {"pairs": 8.0, "bands": 2.5}  # left as it was


def test_a_short_job_runs_more_often_each_round_on_both_sides() -> None:
    seconds = {("stitch", 1): 50.0, ("stitch", 2): 30.0, ("map", 1): 15.0, ("map", 2): 9.0}
    seconds |= {("tiny", 1): 0.5, ("tiny", 2): 0.3}
    workers, calls = [0], []

    def run(kind: str, session: str) -> tuple[dict, float]:
        calls.append((workers[0], kind, session))
        s = seconds[kind, workers[0]] + 0.1 * len(calls)  # every run a little slower
        return {"result": {"seconds": {"stage": s / 2}}}, s

    jobs = [("stitch", "a"), ("map", "b"), ("tiny", "b")]
    best = interleaved(run, lambda n: workers.__setitem__(0, n), jobs)
    # the stitch (50.1 s, the first run) once a round; the map (15.2 s) as often as fits;
    # a job of a moment no more than MAX_REPEATS times
    repeat = math.ceil(SAMPLE_S / 15.2)
    assert 1 < repeat < MAX_REPEATS < SAMPLE_S / 1.0
    per_round = [("stitch", "a")] + [("map", "b")] * repeat + [("tiny", "b")] * MAX_REPEATS
    expected = [(n, *job) for n in round_order(ROUNDS) for job in per_round]
    assert calls == expected
    for n in (1, 2):
        for kind in ("stitch", "map", "tiny"):
            job, s = best[n][kind]
            first = 1 + next(i for i, c in enumerate(calls) if c == (n, kind, c[2]))
            assert s == seconds[kind, n] + 0.1 * first  # the earliest, so the shortest
            assert job["result"]["seconds"]["stage"] == s / 2
