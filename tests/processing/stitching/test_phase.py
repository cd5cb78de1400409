import numpy as np
import pytest

from processing.poses import relative_se2, wrap_angle
from processing.stitching.phase import phase_candidates
from tests.processing.helpers import frame_at, texture


def test_phase_candidates_find_the_shift_without_any_guess() -> None:
    tex = texture(7)
    a, b = np.array([400.0, 400.0, 0]), np.array([610.0, 377.0, 0])
    cands = phase_candidates(frame_at(tex, a), frame_at(tex, b))
    best = cands[0][0]
    assert np.abs(best[:2] - relative_se2(a, b)[:2]).max() <= 2.5
    turned = np.array([420.0, 560.0, np.pi])
    best = phase_candidates(frame_at(tex, a), frame_at(tex, turned))[0][0]
    assert (
        np.abs(best[:2] - relative_se2(a, turned)[:2]).max() <= 2.5
        and abs(abs(best[2]) - np.pi) < 1e-6
    )


@pytest.mark.parametrize("turn", [0.0, np.pi])
@pytest.mark.parametrize("tilt_deg", [-7.5, 7.5])
def test_phase_candidates_find_frames_turned_several_degrees(turn: float, tilt_deg: float) -> None:
    """Phase correlation loses frames turned more than a few degrees from each other: b is
    tried tilted too, and the guess says by how much it was turned."""
    tex = texture(8, (1400, 1800))
    size = (640, 480)
    a, b = np.array([700.0, 700.0, 0.0]), np.array([1110.0, 690.0, turn + np.radians(tilt_deg)])
    true = relative_se2(a, b)
    best = phase_candidates(frame_at(tex, a, size), frame_at(tex, b, size))[0][0]
    assert np.abs(best[:2] - true[:2]).max() <= 10
    assert abs(float(wrap_angle(best[2] - true[2]))) < np.radians(2.5)
