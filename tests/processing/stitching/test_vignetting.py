import numpy as np

from processing.poses import frame_i_to_j, relative_se2
from processing.stitching import plan_mosaic
from processing.stitching.vignetting import overlap_samples, radius2, solve_photometry
from tests.processing.helpers import decoded, sweep, worst_pair_error


def vignette(size: tuple[int, int], strength: float = 0.15) -> np.ndarray:
    w, h = size
    xx, yy = np.meshgrid(np.arange(w), np.arange(h))
    return (1 - strength * radius2(xx, yy, size) / 2).astype(np.float32)


def test_falloff_and_gains_come_out_of_registered_overlaps() -> None:
    s = sweep(frames=12, seed=14)
    v = vignette((320, 240))
    frames = [
        np.clip(f * v[..., None] * g, 0, 255).astype(np.uint8)
        for f, g in zip(decoded(s), np.linspace(0.8, 1.2, 12))
    ]
    grey = [f.mean(axis=2).astype(np.float32) for f in frames]
    pairs = []
    for k in range(11):
        delta = relative_se2(s.truth[k], s.truth[k + 1])
        ri, rj, lr = overlap_samples(grey[k], grey[k + 1], frame_i_to_j(delta, (320, 240)))
        pairs.append((k, k + 1, ri, rj, lr))
    photo = solve_photometry(12, pairs)
    assert photo is not None
    assert np.abs(photo.flat_field((320, 240)) - v / v.mean()).max() < 0.01
    ratio = photo.compensation() * np.linspace(0.8, 1.2, 12) * s.gains  # the sweep's own gains too
    assert ratio.std() / ratio.mean() < 0.01


def test_stitcher_corrects_vignetting_and_places_frames_as_without_it() -> None:
    s = sweep(frames=12, seed=15)
    v = vignette((320, 240), 0.2)
    frames = [np.clip(f * v[..., None], 0, 255).astype(np.uint8) for f in decoded(s)]
    layout, loaded = plan_mosaic(frames, s.odometry)
    assert loaded.inv_flat is not None
    assert np.abs(1 / loaded.inv_flat - v / v.mean()).max() < 0.01
    assert worst_pair_error(layout.poses_px, s.truth, (320, 240)) < 0.3


def test_no_samples_no_answer() -> None:
    assert solve_photometry(3, []) is None
    dark = np.full((240, 320), 10, np.float32)
    ri, rj, lr = overlap_samples(dark, dark, frame_i_to_j(np.array([100.0, 0, 0]), (320, 240)))
    assert len(lr) == 0  # too dark to trust
