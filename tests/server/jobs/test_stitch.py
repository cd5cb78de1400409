"""The stitch job's pair registrations as parts of the job: a worker that helps loads the
session's frames itself, with the flat-field correction in use, and measures exactly what
the job's own threads would."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from processing.stitching import StitchParams, plan_mosaic, render_bands
from processing.stitching.vignetting import radius2
from robot_link.sim.sweeps import LazySweep, SweepConfig
from server.jobs.stitch import fill_over_workers, spread_pairs
from server.storage.files import SessionFiles
from server.storage.mosaic_files import StoredImages, write_mosaic
from tests.server.helping import helped_context


def test_pairs_and_bands_done_by_another_process_equal_those_of_the_jobs_threads(
    tmp_path: Path,
) -> None:
    sweep = LazySweep(SweepConfig(frames=24, lanes=2, frame_size=(320, 240), seed=5))
    # a lens falloff: the flat field is measured and every pair registered again with it
    xx, yy = np.meshgrid(np.arange(320), np.arange(240))
    falloff = (1 - 0.1 * radius2(xx, yy, (320, 240)))[..., None]
    files = SessionFiles(tmp_path)
    where = []
    for k in range(len(sweep)):
        image = np.clip(sweep[k] * falloff, 0, 255).astype(np.uint8)
        ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])
        assert ok
        rel = f"sessions/s/frames/{k:04d}.jpg"
        files.write(rel, jpeg.tobytes())
        where.append((rel, None, len(jpeg)))
    guess = np.asarray(sweep.odometry, dtype=np.float64)
    params = StitchParams(band_bytes=2**20)  # many bands
    ctx, done_by_helper = helped_context(tmp_path)

    def source() -> StoredImages:
        return StoredImages(lambda k: files.read(*where[k]), len(where))

    here, loaded = plan_mosaic(source(), guess, params=params)
    assert loaded.inv_flat is not None
    timed: list[float] = []  # seconds of each batch of pairs
    spread, _ = plan_mosaic(source(), guess, params=params, spread=spread_pairs(ctx, where, timed))
    # consecutive, then other pairs; again with the flat field
    assert len(done_by_helper) == 4 and all(n > 0 for n in done_by_helper)
    assert len(timed) == 4 and all(s > 0 for s in timed)
    assert spread.pairs == here.pairs > len(sweep) - 1  # lane neighbours too
    np.testing.assert_allclose(spread.poses_px, here.poses_px, atol=1e-9)
    np.testing.assert_allclose(spread.gains, here.gains, atol=1e-9)

    mine = write_mosaic(tmp_path / "here", here, render_bands(here, loaded, params))
    done_by_helper.clear()
    theirs = write_mosaic(
        tmp_path / "results",
        here,
        fill_over_workers(ctx, where, here, loaded, params),
        save_map=ctx.map,
        data_dir=tmp_path,
    )
    # the bands rendered by the helper, then the PNGs, overview and pyramid saved by it
    assert len(done_by_helper) == 2 and done_by_helper[0] > 1 and done_by_helper[1] == 4
    for a, b in (
        (mine.mosaic, theirs.mosaic),
        (mine.coverage, theirs.coverage),
        (mine.overview, theirs.overview),
        (mine.dzi.parent / "mosaic_files/0/0_0.jpg", theirs.dzi.parent / "mosaic_files/0/0_0.jpg"),
    ):
        np.testing.assert_array_equal(cv2.imread(str(a)), cv2.imread(str(b)))
    assert mine.dzi.read_text() == theirs.dzi.read_text()
    assert not any((tmp_path / ".parts").iterdir())  # the plans are cleared
