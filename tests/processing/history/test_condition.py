"""AASHTO element-level quantities: a girder's length, a coating's area and a gusset plate
each in its worst state where defects lie, CS1 elsewhere, overlaps counted once; defects
placed on the smallest element holding them; codes and default states from the class."""

from __future__ import annotations

import pytest

from processing.history.condition import (
    CodedDefect,
    Element,
    code_of,
    element_of,
    element_types,
    state_of,
    state_quantities,
)


def test_the_shipped_list_has_the_steel_elements_and_the_coating() -> None:
    types = element_types()
    assert types[107].unit == "m" and types[162].unit == "each" and types[515].unit == "m2"
    assert 1010 in types[107].defects and 1000 in types[102].defects


def test_a_girders_length_in_each_state() -> None:
    girder = Element(1, 107, 20.0, (0.0, 0.0, 20.0, 0.5))  # 20 m long, 0.5 m deep
    defects = [
        CodedDefect(1, (2.0, 0.1, 3.0, 0.2), 1010, 3),  # 1 m of crack
        CodedDefect(2, (2.5, 0.3, 4.0, 0.4), 1000, 2),  # overlaps the crack over 0.5 m
        CodedDefect(3, (10.0, 0.0, 10.2, 0.5), 1010, 4),
    ]
    q = state_quantities(girder, defects)
    assert q[3] == pytest.approx(1.0, abs=0.05)
    assert q[2] == pytest.approx(1.0, abs=0.05)  # 3.0-4.0: the worse crack holds 2.5-3.0
    assert q[4] == pytest.approx(0.2, abs=0.05)
    assert sum(q.values()) == pytest.approx(20.0)


def test_a_coatings_area_and_a_gusset_plate_whole() -> None:
    coating = Element(2, 515, 8.0, (0.0, 0.0, 4.0, 2.0))  # 8 m2
    q = state_quantities(coating, [CodedDefect(1, (1.0, 1.0, 2.0, 1.5), 1000, 3)])
    assert q[3] == pytest.approx(0.5, rel=0.05) and sum(q.values()) == pytest.approx(8.0)
    plate = Element(3, 162, 1.0, (0.0, 0.0, 0.6, 0.6))
    assert state_quantities(plate, [CodedDefect(1, (0.1, 0.1, 0.2, 0.2), 1010, 3)])[3] == 1.0
    assert state_quantities(plate, [])[1] == 1.0


def test_defects_are_placed_and_coded() -> None:
    girder = Element(1, 107, 20.0, (0.0, 0.0, 20.0, 1.0))
    plate = Element(2, 162, 1.0, (4.0, 0.0, 5.0, 1.0))  # on the girder
    assert element_of((4.4, 0.4, 4.6, 0.6), [girder, plate]) == 2
    assert element_of((8.0, 0.4, 8.2, 0.6), [girder, plate]) == 1
    assert element_of((30.0, 0.4, 30.2, 0.6), [girder, plate]) is None
    assert (
        code_of("crack") == 1010 and code_of("corrosion") == 1000 and code_of("crack", 1020) == 1020
    )
    assert (
        state_of("crack", None) == 3
        and state_of("corrosion", "CS4") == 4
        and state_of("crack", 2) == 2
    )
