"""Each defect's history chained from the matches of consecutive visits: one track per
defect, a defect split in two continuing in two tracks, a repaired one ending as gone."""

from __future__ import annotations

from typing import Any

import pytest

from server.reports.history import Visit, chain_tracks

VISITS = [Visit("a", "2020-05-01"), Visit("b", "2022-05-03"), Visit("c", "2024-04-30")]


def _side(defect_id: int, number: int, length_mm: float) -> dict[str, Any]:
    return {
        "defect_id": defect_id,
        "number": number,
        "box_m": [0.0, 0.0, 0.1, 0.01],
        "length_mm": length_mm,
        "width_mm": 0.2,
        "area_mm2": None,
    }


def _change(
    status: str,
    before: dict[str, Any] | None,
    after: dict[str, Any] | None,
    parts_before: tuple[int, ...] = (),
    parts_after: tuple[int, ...] = (),
) -> dict[str, Any]:
    return {
        "status": status,
        "class": "crack",
        "before": before,
        "after": after,
        "parts_before": list(parts_before or ([before["defect_id"]] if before else [])),
        "parts_after": list(parts_after or ([after["defect_id"]] if after else [])),
    }


def test_a_crack_growing_over_three_visits_is_one_track() -> None:
    changes = [
        {"changes": [_change("grown", _side(1, 1, 40), _side(11, 3, 48))]},
        {"changes": [_change("grown", _side(11, 3, 48), _side(21, 2, 60))]},
    ]
    [track] = chain_tracks(VISITS, changes)
    assert track["track_id"] == 1 and track["class"] == "crack"
    assert [e["session_id"] for e in track["entries"]] == ["a", "b", "c"]
    assert [e["status"] for e in track["entries"]] == ["baseline", "grown", "grown"]
    assert [e["length_mm"] for e in track["entries"]] == [40, 48, 60]
    assert [e["number"] for e in track["entries"]] == [1, 3, 2]


def test_pieces_carry_a_defect_across_visits_cut_differently() -> None:
    # visit b's crack seen as pieces 11 + 12 against a, and the pair as two defects against c
    changes = [
        {
            "changes": [
                _change("grown", _side(1, 1, 40), _side(11, 1, 50), parts_after=(11, 12)),
                _change("unchanged", _side(2, 2, 9), _side(13, 3, 9)),
            ]
        },
        {
            "changes": [
                _change("unchanged", _side(12, 2, 20), _side(22, 2, 20)),
                _change("unchanged", _side(11, 1, 30), _side(21, 1, 30)),
                _change("new", None, _side(23, 3, 9)),
                _change("gone", _side(13, 3, 9), None),
            ]
        },
    ]
    tracks = chain_tracks(VISITS, changes)
    split = [t for t in tracks if t["entries"][0]["defect_id"] == 1]
    assert len(split) == 2  # one past, two futures
    assert all([e["defect_id"] for e in t["entries"][:2]] == [1, 11] for t in split)
    assert sorted(t["entries"][2]["defect_id"] for t in split) == [21, 22]
    assert [len(t["entries"]) for t in split] == [3, 3]
    [new] = [t for t in tracks if t["entries"][0]["session_id"] == "c"]
    assert [e["status"] for e in new["entries"]] == ["new"]
    [repaired] = [t for t in tracks if t["entries"][0]["defect_id"] == 2]
    assert [e["status"] for e in repaired["entries"]] == ["baseline", "unchanged", "gone"]
    assert repaired["entries"][-1]["defect_id"] is None


def test_a_single_visit_gives_its_defects_as_baselines() -> None:
    first = [{"class": "corrosion", **_side(5, 2, 0)}, {"class": "crack", **_side(4, 1, 30)}]
    tracks = chain_tracks(VISITS[:1], [], first)
    assert [t["entries"][0]["number"] for t in tracks] == [1, 2]
    assert {e["status"] for t in tracks for e in t["entries"]} == {"baseline"}
    assert chain_tracks([], []) == []
    with pytest.raises(ValueError, match="changes"):
        chain_tracks(VISITS, [])
