"""``steelscan bench changes``' scoring: a pair that truly did not grow is in no found rate."""

from bench.changes import _results


def test_pairs_under_the_tolerance_are_in_no_found_rate() -> None:
    scores = [
        {"align_px": 0.1, "found": 1.0, "false": 0.0, "changes": 1.0, "growth_error": 0.1},
        {"align_px": 0.2, "found": 0.0, "false": 0.0, "changes": 0.0},
        # grew by less than the unchanged tolerance, reported grown: a false change
        {"align_px": 0.1, "false": 1.0, "changes": 1.0},
    ]
    rows = {r["name"]: r for r in _results("set", scores)}
    assert rows["changes.set.found"]["value"] == 0.5
    assert rows["changes.set.found"]["grown_pairs"] == 2
    assert rows["changes.set.false"]["value"] == 0.5
    assert rows["changes.set.growth_error"]["value"] == 0.1
