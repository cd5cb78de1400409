"""Two visits' defects matched in the structure's frame: a crack longer by 8 mm is grown, one
longer by 1 mm unchanged, a rust patch 50 % larger grown, one only on the later visit new,
one only on the earlier gone; classes never mix; visits a few millimetres apart still pair."""

from __future__ import annotations

from processing.history.visits import VisitDefect, match_visits


def test_grown_unchanged_new_and_gone() -> None:
    before = [
        VisitDefect(1, "crack", (0.10, 0.10, 0.15, 0.12), length_mm=50.0, width_mm=0.6),
        VisitDefect(2, "crack", (0.40, 0.10, 0.45, 0.12), length_mm=50.0),
        VisitDefect(3, "corrosion", (0.70, 0.30, 0.75, 0.35), area_mm2=1000.0),
        VisitDefect(4, "crack", (0.90, 0.50, 0.95, 0.52), length_mm=40.0),
    ]
    shift = 0.004  # the visits' frames agree to a few millimetres
    after = [
        VisitDefect(
            11, "crack", (0.10 + shift, 0.10, 0.158 + shift, 0.12), length_mm=58.0, width_mm=0.8
        ),
        VisitDefect(12, "crack", (0.40 + shift, 0.10, 0.45 + shift, 0.12), length_mm=51.0),
        VisitDefect(13, "corrosion", (0.69, 0.29, 0.76, 0.36), area_mm2=1500.0),
        VisitDefect(14, "crack", (0.60, 0.60, 0.65, 0.62), length_mm=30.0),
        VisitDefect(
            15, "corrosion", (0.10, 0.10, 0.15, 0.12), area_mm2=200.0
        ),  # rust where a crack is
    ]
    changes = {
        (c.before.id if c.before else None, c.after.id if c.after else None): c
        for c in match_visits(before, after)
    }
    assert changes[(1, 11)].status == "grown" and changes[(1, 11)].delta("length_mm") == 8.0
    assert changes[(1, 11)].delta("width_mm") == 0.2
    assert changes[(2, 12)].status == "unchanged"
    assert changes[(3, 13)].status == "grown" and changes[(3, 13)].delta("area_mm2") == 500.0
    assert changes[(None, 14)].status == "new" and changes[(None, 15)].status == "new"
    assert changes[(4, None)].status == "gone"
    assert len(changes) == 6


def test_pieces_of_one_defect_are_one_change() -> None:
    """A crack seen whole before and in two pieces after is one crack whose length is the
    pieces' sum; short crack-like pieces inside a rust patch are that patch's texture, and
    pieces that come and go with it are no change of their own."""
    before = [
        VisitDefect(1, "crack", (0.10, 0.10, 0.16, 0.12), length_mm=60.0),
        VisitDefect(2, "corrosion", (0.50, 0.50, 0.58, 0.57), area_mm2=3000.0),
        VisitDefect(3, "crack", (0.52, 0.52, 0.521, 0.521), length_mm=1.0),  # in the rust
    ]
    after = [
        VisitDefect(11, "crack", (0.10, 0.10, 0.14, 0.12), length_mm=40.0),
        VisitDefect(12, "crack", (0.142, 0.10, 0.172, 0.12), length_mm=30.0),  # a gap of 2 mm
        VisitDefect(13, "corrosion", (0.50, 0.50, 0.58, 0.57), area_mm2=3100.0),
        VisitDefect(14, "crack", (0.55, 0.55, 0.552, 0.551), length_mm=2.0),  # in the rust
        VisitDefect(15, "crack", (0.53, 0.51, 0.535, 0.512), length_mm=1.5),  # in the rust
    ]
    changes = match_visits(before, after)
    assert len(changes) == 2
    crack = next(c for c in changes if c.after and c.after.defect_class == "crack")
    assert crack.status == "grown" and crack.delta("length_mm") == 10.0
    assert crack.parts_after == (11, 12) and crack.parts_before == (1,)
    assert crack.after is not None and crack.after.box == (0.10, 0.10, 0.172, 0.12)
    rust = next(c for c in changes if c.after and c.after.defect_class == "corrosion")
    assert rust.status == "unchanged" and set(rust.parts_after) == {13, 14, 15}
    assert rust.parts_before == (2, 3)


def test_a_long_crack_inside_a_rust_box_stays_a_crack() -> None:
    before = [VisitDefect(1, "crack", (0.10, 0.10, 0.16, 0.12), length_mm=60.0)]
    after = [
        VisitDefect(11, "crack", (0.10, 0.10, 0.16, 0.12), length_mm=61.0),
        VisitDefect(12, "corrosion", (0.09, 0.08, 0.17, 0.15), area_mm2=4000.0),
    ]
    changes = match_visits(before, after)
    assert sorted((c.status, c.parts_before, c.parts_after) for c in changes) == [
        ("new", (), (12,)),
        ("unchanged", (1,), (11,)),
    ]


def test_specks_seen_once_are_no_change_and_pieces_seen_once_are_one() -> None:
    """Crack pieces on one visit only that touch one another are one new crack; a speck
    shorter than the growth the matching can tell is not reported at all."""
    before = [VisitDefect(1, "crack", (0.10, 0.10, 0.16, 0.12), length_mm=60.0)]
    after = [
        VisitDefect(11, "crack", (0.10, 0.10, 0.16, 0.12), length_mm=60.5),
        VisitDefect(12, "crack", (0.50, 0.50, 0.53, 0.51), length_mm=30.0),  # a new crack,
        VisitDefect(13, "crack", (0.535, 0.50, 0.56, 0.51), length_mm=25.0),  # in two pieces
        VisitDefect(14, "crack", (0.80, 0.80, 0.8005, 0.8005), length_mm=0.5),  # a speck
    ]
    changes = match_visits(before, after)
    assert sorted((c.status, c.parts_after) for c in changes) == [
        ("new", (12, 13)),
        ("unchanged", (11,)),
    ]
    new = next(c for c in changes if c.status == "new")
    assert new.after is not None and new.after.length_mm == 55.0
