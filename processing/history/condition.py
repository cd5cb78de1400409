"""Element-level condition by the AASHTO Manual for Bridge Element Inspection: each
element's quantity in condition states CS1-CS4 from the defects found on it.

An element is a rectangle in the structure's own coordinates (metres) with a quantity in
its unit: ``m`` (girders, stringers, floor beams: length along the element's axis, the
rectangle's longer side), ``m2`` (decks, the protective coating: area), ``each`` (gusset
plates, pins: whole elements). A defect counts on the element holding its centre, with its
AASHTO defect code (crack → 1010, corrosion → 1000, unless a reviewer set another) and its
condition state. Where defects overlap, the worst state counts (a length or an area is in
one state only); the rest of the element is CS1. The parts are scaled to the element's
quantity by the fraction of its rectangle they cover.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

DEFECT_CODES = {"crack": 1010, "corrosion": 1000}
# the state a defect takes until a reviewer sets one: an unarrested crack that does not yet
# warrant a structural review (CS3), freckled rust (CS2)
DEFAULT_STATES = {"crack": 3, "corrosion": 2}
AREA_CELLS = 200  # cells along an area element's longer side


@dataclass(frozen=True)
class ElementType:
    """One AASHTO element: number, name, unit and the defect codes it takes."""

    number: int
    name: str
    unit: str  # m, m2 or each
    defects: tuple[int, ...]


@cache
def element_types() -> dict[int, ElementType]:
    """The AASHTO steel elements and the protective coating, by element number."""
    data = json.loads((Path(__file__).with_name("aashto_elements.json")).read_text())
    return {
        e["number"]: ElementType(e["number"], e["name"], e["unit"], tuple(e["defects"]))
        for e in data["elements"]
    }


@cache
def defect_names() -> dict[int, str]:
    """AASHTO defect names by code."""
    data = json.loads((Path(__file__).with_name("aashto_elements.json")).read_text())
    return {int(k): v for k, v in data["defects"].items()}


@dataclass(frozen=True)
class Element:
    """An element of one structure: its AASHTO number, quantity and rectangle."""

    id: int
    number: int
    quantity: float
    box: tuple[float, float, float, float]  # x0, y0, x1, y1, structure frame (m)

    @property
    def unit(self) -> str:
        """m, m2 or each (from the element number)."""
        return element_types()[self.number].unit


@dataclass(frozen=True)
class CodedDefect:
    """A defect as the condition rules see it: its rectangle in the structure's frame,
    AASHTO defect code and condition state (1-4)."""

    id: int
    box: tuple[float, float, float, float]
    code: int
    state: int


def element_of(box: tuple[float, float, float, float], elements: Sequence[Element]) -> int | None:
    """Id of the smallest element whose rectangle holds the centre of ``box`` (None: none)."""
    cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
    holding = [e for e in elements if e.box[0] <= cx <= e.box[2] and e.box[1] <= cy <= e.box[3]]
    if not holding:
        return None
    return min(holding, key=lambda e: (e.box[2] - e.box[0]) * (e.box[3] - e.box[1])).id


def state_quantities(element: Element, defects: Sequence[CodedDefect]) -> dict[int, float]:
    """The element's quantity in CS1..CS4 (keys 1-4) from the defects on it."""
    x0, y0, x1, y1 = element.box
    states = [d.state for d in defects if 1 <= d.state <= 4]
    out = {1: 0.0, 2: 0.0, 3: 0.0, 4: 0.0}
    if element.unit == "each":
        out[max(states, default=1)] = element.quantity
        return out
    if element.unit == "m":
        axis = 0 if (x1 - x0) >= (y1 - y0) else 1
        lo, hi = (x0, x1) if axis == 0 else (y0, y1)
        worst = _worst_along(lo, hi, [(d.box[axis], d.box[axis + 2], d.state) for d in defects])
    else:
        worst = _worst_over(element.box, defects)
    for s in range(1, 5):
        out[s] = round(float((worst == s).mean()) * element.quantity, 4)
    return out


def _worst_along(lo: float, hi: float, spans: list[tuple[float, float, int]]) -> np.ndarray:
    """Worst state at each of the element's length cells (1 where no defect)."""
    n = 1000
    centres = lo + (np.arange(n) + 0.5) * (hi - lo) / n
    worst = np.ones(n, np.int8)
    for a, b, s in spans:
        hit = _inside(centres, a, b)
        worst[hit] = np.maximum(worst[hit], s)
    return worst


def _inside(centres: np.ndarray, a: float, b: float) -> np.ndarray:
    """Cells (evenly spaced ``centres``) whose centre lies in [a, b]; for a span narrower
    than a cell, the cell holding its middle."""
    hit = (centres >= a) & (centres <= b)
    step = float(centres[1] - centres[0]) if len(centres) > 1 else np.inf
    mid = (a + b) / 2
    if not hit.any() and centres[0] - step / 2 <= mid <= centres[-1] + step / 2:
        hit[int(np.argmin(np.abs(centres - mid)))] = True
    return hit


def _worst_over(
    box: tuple[float, float, float, float], defects: Sequence[CodedDefect]
) -> np.ndarray:
    """Worst state at each cell of an area element's grid (1 where no defect)."""
    x0, y0, x1, y1 = box
    cell = max(x1 - x0, y1 - y0) / AREA_CELLS
    nx, ny = max(1, round((x1 - x0) / cell)), max(1, round((y1 - y0) / cell))
    xs = x0 + (np.arange(nx) + 0.5) * (x1 - x0) / nx
    ys = y0 + (np.arange(ny) + 0.5) * (y1 - y0) / ny
    worst = np.ones((ny, nx), np.int8)
    for d in defects:
        block = np.ix_(_inside(ys, d.box[1], d.box[3]), _inside(xs, d.box[0], d.box[2]))
        worst[block] = np.maximum(worst[block], d.state)
    return worst


def code_of(defect_class: str, reviewed_code: int | None = None) -> int:
    """The AASHTO defect code of a defect: the reviewer's, else its class's."""
    return reviewed_code if reviewed_code is not None else DEFECT_CODES.get(defect_class, 1000)


def state_of(defect_class: str, reviewed_state: str | int | None) -> int:
    """A defect's condition state 1-4: the reviewer's ("CS3" or 3), else its class's default."""
    if reviewed_state is not None:
        text = str(reviewed_state).upper().removeprefix("CS")
        if text.isdigit() and 1 <= int(text) <= 4:
            return int(text)
    return DEFAULT_STATES.get(defect_class, 2)
