"""A simulated structure visited again: every crack longer at a tip by the stated amount
(its painted pixels too), rust patches larger, one new patch, the rest of the plate as it
was."""

from __future__ import annotations

import numpy as np
import pytest

from robot_link.sim.aging import age_structure
from robot_link.sim.structure import make_structure


def test_a_later_visit_grows_every_defect_by_what_it_says() -> None:
    before = make_structure(3, plate_size_m=(0.8, 0.5), defect_region_m=(0.1, 0.1, 0.7, 0.4))
    after, growth = age_structure(before, seed=30)
    cracks = {g.defect_id: g for g in growth if g.defect_class == "crack"}
    assert cracks and all(0.005 <= g.length_m <= 0.03 for g in cracks.values())
    old = {d.id: d for d in before.defects}
    for d in after.defects:
        if d.id in cracks:
            assert d.length_m == pytest.approx(old[d.id].length_m + cracks[d.id].length_m, abs=1e-4)
            w0, h0 = old[d.id].bbox_m[2:]
            assert max(d.bbox_m[2], d.bbox_m[3]) >= max(w0, h0) - 1e-9
    assert after.crack_mask.sum() > before.crack_mask.sum()
    assert after.corrosion_mask.sum() > before.corrosion_mask.sum()
    assert [g.new for g in growth].count(True) == 1
    # away from the defects the plate looks as it did
    untouched = ~(after.crack_mask | after.corrosion_mask)
    untouched[:10, :] = False
    diff = np.abs(after.texture.astype(int) - before.texture.astype(int))[untouched]
    assert np.percentile(diff, 99) <= 40 and np.median(diff) == 0


def test_weathering_relights_the_plate_and_leaves_the_defects_where_they_were() -> None:
    before = make_structure(3, plate_size_m=(0.8, 0.5), defect_region_m=(0.1, 0.1, 0.7, 0.4))
    plain, _ = age_structure(before, seed=31)
    weathered, growth = age_structure(before, seed=31, weathering=0.2)
    assert np.array_equal(plain.crack_mask, weathered.crack_mask)
    assert [d.bbox_m for d in plain.defects] == [d.bbox_m for d in weathered.defects]
    ratio = weathered.texture.astype(float).mean((0, 1)) / plain.texture.astype(float).mean((0, 1))
    assert np.all(np.abs(ratio - 1) < 0.5) and np.any(np.abs(ratio - 1) > 0.02)
    # a smooth light: neighbouring pixels keep their contrast
    diff = weathered.texture.astype(float) - plain.texture.astype(float)
    assert np.std(diff) > 3 and np.median(np.abs(np.diff(diff[..., 1], axis=1))) < 6


def test_a_third_visit_grows_the_second_visits_new_patch() -> None:
    first = make_structure(4, plate_size_m=(0.8, 0.5), defect_region_m=(0.1, 0.1, 0.7, 0.4))
    second, g2 = age_structure(first, seed=40)
    third, g3 = age_structure(second, seed=41)
    new = next(g.defect_id for g in g2 if g.new)
    assert next(d for d in second.defects if d.id == new).width_m > 0.02
    assert next(g for g in g3 if g.defect_id == new).area_m2 > 0
    assert len(third.defects) == len(first.defects) + 2


def test_some_cracks_widen_by_a_pixel_on_each_side() -> None:
    before = make_structure(5, plate_size_m=(0.8, 0.5), defect_region_m=(0.1, 0.1, 0.7, 0.4))
    after, growth = age_structure(before, seed=50, widen_share=1.0)
    old = {d.id: d for d in before.defects}
    cracks = [g for g in growth if g.defect_class == "crack"]
    assert cracks and all(g.width_m == pytest.approx(2 * before.m_per_px) for g in cracks)
    for d in after.defects:
        if d.defect_class == "crack":
            assert d.width_m == pytest.approx(old[d.id].width_m + 2 * before.m_per_px)
    # the painted crack is wider: more of its pixels, darker than the paint around them
    assert after.crack_mask.sum() > 1.8 * before.crack_mask.sum()
    ring = after.crack_mask & ~before.crack_mask
    assert after.texture[ring].mean() < before.texture[ring].mean() - 30
    none, growth = age_structure(before, seed=50, widen_share=0.0)
    assert all(g.width_m == 0 for g in growth)
