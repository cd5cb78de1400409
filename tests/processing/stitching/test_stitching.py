import cv2
import numpy as np
import pytest

from processing.poses import compose_se2, frame_to_mosaic, relative_se2
from processing.stitching import (
    StitchParams,
    camera_poses,
    estimate_flat_field,
    feather_weight,
    paper_blend_mask,
    plan_mosaic,
    render_bands,
    stitch_frames,
)
from tests.processing.helpers import cut, decoded, sweep, texture, worst_pair_error


def test_lawnmower_sweep_with_drifting_odometry_is_placed_to_a_fraction_of_a_pixel() -> None:
    s = sweep()
    layout, _ = plan_mosaic(decoded(s), s.odometry)
    assert layout.confident.all()
    assert worst_pair_error(layout.poses_px, s.truth, (320, 240)) < 0.3
    assert worst_pair_error(s.odometry, s.truth, (320, 240)) > 5  # the guess really was off
    # the return lane was driven turned around, and the mosaic knows it
    assert abs(abs(np.degrees(layout.poses_px[5, 2] - layout.poses_px[0, 2])) - 180) < 3


def test_frames_stitch_from_images_alone_even_when_lanes_turn_around() -> None:
    s = sweep(seed=8)
    layout, _ = plan_mosaic(decoded(s), None)
    assert layout.confident.all()
    assert worst_pair_error(layout.poses_px, s.truth, (320, 240)) < 0.3


def test_a_pair_phase_correlation_cannot_place_is_registered_from_its_neighbours_motion(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """On a straight run nothing else overlaps a pair: when no phase-correlation guess of
    it verifies (here: they all point elsewhere), the neighbouring pairs' steps are tried."""
    import processing.stitching.alignment as alignment

    s = sweep(frames=8, pattern="straight")
    frames = decoded(s)
    genuine = alignment.phase_candidates

    def thumbnail(gray: np.ndarray) -> np.ndarray:
        return cv2.resize(
            np.asarray(gray, np.float32), (40, 30), interpolation=cv2.INTER_AREA
        ).ravel()

    fourth = thumbnail(cv2.cvtColor(frames[3], cv2.COLOR_BGR2GRAY))
    misled = []

    def misleading(gray_a, gray_b, **kw):  # type: ignore[no-untyped-def]
        seen = thumbnail(gray_a.small if isinstance(gray_a, alignment.PhaseView) else gray_a)
        if np.corrcoef(seen, fourth)[0, 1] > 0.8:  # pair 3-4 (others: < 0.5)
            misled.append(True)
            return [(np.array([40.0, 150.0, np.pi]), 0.3)]  # a turned-around guess far off
        return genuine(gray_a, gray_b, **kw)

    monkeypatch.setattr(alignment, "phase_candidates", misleading)
    layout, _ = plan_mosaic(frames, None)
    assert misled
    assert worst_pair_error(layout.poses_px, s.truth, s.config.frame_size) < 0.5


@pytest.mark.parametrize("seed", [4, 6])
def test_images_only_small_frames_whose_overlap_cannot_hold_the_wide_search_are_placed(
    seed: int,
) -> None:
    """320x240 frames overlap by ~110 px: the images-only search of ±80 px leaves no
    template, so the search narrows instead of being skipped (frames turned by 3.7°
    relative to each other were then refined from no rotation and lost)."""
    s = sweep(seed=seed)
    layout, _ = plan_mosaic(decoded(s), None)
    assert layout.confident.all()
    assert worst_pair_error(layout.poses_px, s.truth, s.config.frame_size) < 0.5


def test_pairs_the_quarter_resolution_phase_correlation_misplaces_are_placed_at_half() -> None:
    """Images only: phase correlation runs at a quarter of the resolution first; where none
    of its guesses verifies surely, the step of the pair before and then the
    half-resolution guesses are tried (the first pair of each thread's run has no pair
    before it)."""
    import processing.stitching.alignment as alignment

    s = sweep(frames=8, pattern="straight", seed=6)
    genuine = alignment.phase_candidates
    scales = []

    def quarter_misleads(view_a, view_b, **kw):  # type: ignore[no-untyped-def]
        scales.append(view_a.scale)
        if view_a.scale == 4:
            return [(np.array([40.0, 150.0, np.pi]), 0.9)]  # confidently wrong
        return genuine(view_a, view_b, **kw)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(alignment, "phase_candidates", quarter_misleads)
        layout, _ = plan_mosaic(decoded(s), None)
    assert scales.count(4) == 7 and 1 <= scales.count(2) < 7
    assert layout.confident.all()
    assert worst_pair_error(layout.poses_px, s.truth, s.config.frame_size) < 0.5


def test_exposure_gains_are_compensated() -> None:
    s = sweep(seed=9, gain=(0.7, 1.3))
    layout, _ = plan_mosaic(decoded(s), s.odometry)
    corrected = layout.gains * s.gains  # constant when every frame is brought to one exposure
    assert corrected.std() / corrected.mean() < 0.02


def test_mosaic_matches_the_surface_and_maps_to_the_world() -> None:
    tex = texture()
    centres = np.array([[300 + 200 * i, 400.0] for i in range(6)])  # 37.5 % overlap
    frames = [cut(tex, x, y) for x, y in centres]
    rng = np.random.default_rng(1)
    odo = centres + np.cumsum(rng.normal(0, 3, centres.shape), axis=0)  # drifting odometry, px
    poses = np.column_stack([odo / 100.0, np.zeros(len(odo))])  # metres at 100 px/m
    mosaic = stitch_frames(frames, poses, px_per_m=100.0)
    rel_est = mosaic.frame_poses_px[:, :2] - mosaic.frame_poses_px[0, :2]
    assert np.abs(rel_est - (centres - centres[0])).max() < 0.1
    # the mosaic shows the surface: a patch between frames 1 and 2, where they are blended
    u, v = mosaic.frame_poses_px[0, :2]
    patch = cv2.getRectSubPix(mosaic.image, (200, 120), (float(u) + 400, float(v))).astype(float)
    truth = cv2.getRectSubPix(
        tex, (200, 120), (float(centres[0, 0]) + 400, float(centres[0, 1]))
    ).astype(float)
    assert np.abs(patch - truth).mean() < 1.5
    # world mapping: frame 0's centre maps back to its odometry position, and back again
    x, y = mosaic.to_world(u, v)
    assert (x, y) == pytest.approx(tuple(poses[0, :2]), abs=1e-6)
    assert mosaic.layout.to_mosaic(x, y) == pytest.approx((u, v), abs=1e-6)


def test_bands_of_any_height_make_the_same_mosaic() -> None:
    s = sweep(frames=6, pattern="straight")
    frames = decoded(s)
    layout, loaded = plan_mosaic(frames, s.odometry)
    whole = np.vstack(
        [b.image for b in render_bands(layout, loaded, StitchParams(band_bytes=2**40))]
    )
    small = StitchParams(band_bytes=1)  # the minimum band height
    bands = list(render_bands(layout, loaded, small))
    assert len(bands) > 3
    diff = np.abs(np.vstack([b.image for b in bands]).astype(int) - whole)
    assert diff.max() <= 2 and diff.mean() < 0.05  # fixed-point interpolation may differ by a level


@pytest.mark.parametrize("blend", ["feather", "paper", "newest"])
def test_every_blend_covers_the_swept_area(blend: str) -> None:
    s = sweep(frames=6, pattern="straight")
    m = stitch_frames(decoded(s), s.odometry, params=StitchParams(blend=blend))  # type: ignore[arg-type]
    assert m.coverage.mean() > 0.85
    assert (
        m.image[m.coverage].reshape(-1, 3).mean(axis=1) > 20
    ).mean() > 0.99  # no black holes inside


def test_paper_blend_rule_takes_the_significantly_brighter_pixel() -> None:
    """Eq. (2): I = I2 where τ·I2 > I1, else I1; the new frame's region median-filled."""
    old = np.full((9, 9), 100, np.uint8)
    new = np.full((9, 9), 105, np.uint8)
    new[:, 5:] = 150  # clearly brighter on the right
    new[2, 7] = 100  # an isolated darker pixel inside the brighter region: a gap to fill
    covered = np.ones((9, 9), bool)
    take = paper_blend_mask(old, new, covered, tau=0.9, median_px=3)
    assert take[:, 6:].all() and not take[:, :4].any()
    assert take[2, 7]
    assert paper_blend_mask(old, new, np.zeros((9, 9), bool), 0.9, 3).all()  # nothing there yet


def test_flat_field_recovers_vignetting_and_ignores_texture() -> None:
    tex = texture(3)
    rng = np.random.default_rng(0)
    h, w = 240, 320
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    vignette = (
        1
        - 0.15
        * (((xx - (w - 1) / 2) / ((w - 1) / 2)) ** 2 + ((yy - (h - 1) / 2) / ((h - 1) / 2)) ** 2)
        / 2
    )
    plain = [cut(tex, *rng.uniform((200, 200), (1400, 700))) for _ in range(16)]
    shaded = [np.clip(f * vignette[..., None], 0, 255).astype(np.uint8) for f in plain]
    flat = estimate_flat_field(shaded)
    truth = vignette / vignette.mean()
    assert np.abs(flat - truth).max() < 0.04
    assert np.abs(estimate_flat_field(plain) - 1).max() < 0.05  # a first guess; overlaps refine it


def test_feather_weight_peaks_in_the_middle() -> None:
    wt = feather_weight((8, 6))
    assert wt.shape == (6, 8)
    assert wt[3, 4] == wt.max() and wt[0, 0] == wt.min() > 0


def test_camera_poses_follow_the_frame_chain() -> None:
    robot = np.array([[1.0, 2.0, 0.3], [1.5, 2.0, np.pi]])
    mount = [-0.12, 0.01, 0.0]
    px = camera_poses(robot, mount, 1000.0)
    for p, r in zip(px, robot):
        expected = compose_se2(r, np.array(mount))
        assert p[:2] == pytest.approx(expected[:2] * 1000.0)
        assert p[2] == pytest.approx(expected[2])


def test_textureless_frames_fall_back_to_odometry_and_are_flagged() -> None:
    s = sweep(frames=6, pattern="straight")
    frames = decoded(s)
    frames[3] = np.full_like(frames[3], 120)  # lens cap on: nothing to match
    layout, _ = plan_mosaic(frames, s.odometry)
    assert not layout.confident[3] and layout.confident[[0, 1, 5]].all()
    step = relative_se2(layout.poses_px[2], layout.poses_px[3])
    odo = relative_se2(s.odometry[2], s.odometry[3])
    assert np.abs(step[:2] - odo[:2]).max() < 5  # held where the odometry put it


def test_bad_inputs_raise_value_error() -> None:
    f = np.zeros((10, 10, 3), np.uint8)
    with pytest.raises(ValueError, match="empty"):
        stitch_frames([], None)
    with pytest.raises(ValueError, match="frame 1"):
        stitch_frames([f, np.zeros((12, 10, 3), np.uint8)], None)
    with pytest.raises(ValueError, match="poses must be"):
        stitch_frames([f, f], np.zeros((3, 3)), px_per_m=1.0)
    with pytest.raises(ValueError, match="NaN"):
        stitch_frames([f, f], np.full((2, 3), np.nan), px_per_m=1.0)
    with pytest.raises(ValueError, match="8-bit"):
        stitch_frames([f, f.astype(np.uint16)], None)
    with pytest.raises(ValueError, match="px_per_m"):
        stitch_frames([f], None, px_per_m=0)


@pytest.mark.parametrize("grey", [False, True])
def test_feathered_mosaic_reproduces_the_surface_in_colour_and_grey(grey: bool) -> None:
    """Frames cut from one texture at known poses blend back into that texture (8-bit
    warps and weights cost at most a grey level or so away from the frames' edges)."""
    tex = texture(3)
    centres = [(400.5 + 200 * i, 300.5 + 90 * (i % 2)) for i in range(5)]  # whole-pixel crops
    frames = [cut(tex, cx, cy) for cx, cy in centres]
    if grey:
        frames = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in frames]
    poses = np.array([[cx, cy, 0.0] for cx, cy in centres])
    params = StitchParams(gain_compensation=False, vignetting=False)
    layout, fr = plan_mosaic(frames, poses, params=params)
    mosaic = np.vstack([b.image for b in render_bands(layout, fr, params)])
    assert mosaic.ndim == (2 if grey else 3)
    # the mosaic seen from frame 1 (it overlaps frames 0 and 2), away from the borders
    to_mosaic = frame_to_mosaic(layout.poses_px[1], layout.frame_size)[:2]
    seen = cv2.warpAffine(
        mosaic, to_mosaic, layout.frame_size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    )
    diff = np.abs(seen.astype(int) - frames[1].astype(int))[10:-10, 10:-10]
    assert diff.mean() < 0.5, diff.mean()


@pytest.mark.parametrize("wrong", [(3 * 320.0, 0.0, 0.0), (0.0, 0.0, np.pi)])
def test_a_look_alike_far_from_the_odometry_does_not_place_a_frame(
    monkeypatch: pytest.MonkeyPatch, wrong: tuple[float, float, float]
) -> None:
    """A pair the odometry's guess cannot register is measured from the images alone; a
    match more than a frame from where the odometry put it is a look-alike patch, not wheel
    slip, and the frame stays where its other pairs and the odometry hold it (a look-alike
    three frames along, or the same place turned around)."""
    import processing.stitching.alignment as alignment
    from processing.stitching.registration import PairMeasurement

    s = sweep()
    k = 4  # the pair across the turn to the second lane
    genuine_pair = alignment.measure_pair
    genuine_blind = alignment._PairRegistrar.measure_blind

    def failing(load, request):  # type: ignore[no-untyped-def]
        if (request.i, request.j) == (k, k + 1) and request.angles == (0.0,):
            return None  # the odometry-guided registration of this pair fails
        return genuine_pair(load, request)

    def look_alike(self, j, next_too=False, previous=None):  # type: ignore[no-untyped-def]
        m, step = genuine_blind(self, j, next_too, previous)
        if j != k or m is None:
            return m, step
        far = m.delta + wrong
        return PairMeasurement(m.i, m.j, far, 0.99, m.mean_i, m.mean_j), far

    monkeypatch.setattr(alignment, "measure_pair", failing)
    monkeypatch.setattr(alignment._PairRegistrar, "measure_blind", look_alike)
    layout, _ = plan_mosaic(decoded(s), s.odometry)
    assert worst_pair_error(layout.poses_px, s.truth, (320, 240)) < 1.0
