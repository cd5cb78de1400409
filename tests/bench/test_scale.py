"""How the scale benchmark compares one worker with two: interleaved rounds, best runs."""

from __future__ import annotations

from bench.scale import best_of, round_order


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
