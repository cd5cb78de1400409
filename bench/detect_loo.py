"""Leave-one-dataset-out scores of ``proposed``: for each crack set, the parameters are
chosen on the other sets (the grid below, for the largest worst-case ratio of pooled
2-px DSC to the paper's Sauvola on those sets) and scored on the one left out.

The line response and darkness of each image are computed once; every parameter set is
then a cheap selection of components (:func:`processing.detection.crack_filter.select_cracks`).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import replace

import numpy as np

from bench.common import Result
from processing.detection.crack_filter import CrackParams, line_and_dark_spreads, select_cracks
from processing.learning.data import Sample
from processing.metrics import PooledCounts

GRID = {
    "grow_spreads": (1.5, 2.5, 4.0),
    "dark_spreads": (0.0, 1.0, 2.0),
    "significance": (10.0, 20.0, 40.0),
    "elongation": (3.0, 6.0),
}


def _grid() -> list[CrackParams]:
    keys = list(GRID)
    return [
        replace(CrackParams(), **dict(zip(keys, values)))
        for values in itertools.product(*GRID.values())
    ]


def leave_one_out_proposed(
    sets: dict[str, list[Sample]], sauvola_dsc: dict[str, float]
) -> Iterator[Result]:
    """For each set in ``sets`` (name → samples): the parameters chosen without it and its
    pooled scores with them. ``sauvola_dsc``: each set's 2-px DSC by the paper's Sauvola."""
    grid = _grid()
    tol = {(name, i): PooledCounts(2) for name in sets for i in range(len(grid))}
    strict = {(name, i): PooledCounts(0) for name in sets for i in range(len(grid))}
    for name, samples in sets.items():
        for s in samples:
            z, dark, _ = line_and_dark_spreads(s.gray)
            for i, params in enumerate(grid):
                mask = select_cracks(z, dark, params)
                tol[name, i].add(mask, s.truth)
                strict[name, i].add(mask, s.truth)
    dsc = {k: c.scores().dsc for k, c in tol.items()}
    for left in sets:
        others = [n for n in sets if n != left] or [left]

        def worst_ratio(i: int, others: list[str] = others) -> float:
            return min(dsc[n, i] / max(sauvola_dsc[n], 1e-9) for n in others)

        best = max(range(len(grid)), key=worst_ratio)
        t, st = tol[left, best].scores(), strict[left, best].scores()
        yield {
            "name": f"detect.{left}.proposed_left_out.dsc_tol2",
            "value": t.dsc,
            "unit": "dsc",
            "pi": t.pi,
            "si": t.si,
            "strict": {"pi": st.pi, "si": st.si, "dsc": st.dsc},
            "baseline": sauvola_dsc[left],
            "ratio": round(t.dsc / max(sauvola_dsc[left], 1e-9), 3),
            "chosen_on": others,
            "params": {k: getattr(grid[best], k) for k in GRID},
            "worst_ratio_on_others": round(float(worst_ratio(best)), 3),
            "images": len(sets[left]),
        }
    all_sets = list(sets)
    best_all = max(
        range(len(grid)),
        key=lambda i: min(dsc[n, i] / max(sauvola_dsc[n], 1e-9) for n in all_sets),
    )
    yield {
        "name": "detect.proposed.params_chosen_on_all_sets",
        "value": float(
            np.round(min(dsc[n, best_all] / max(sauvola_dsc[n], 1e-9) for n in all_sets), 3)
        ),
        "unit": "worst ratio to sauvola",
        "params": {k: getattr(grid[best_all], k) for k in GRID},
        "shipped": {k: getattr(CrackParams(), k) for k in GRID},
    }
