"""Draw docs/stitching-exposure.png: the same sweep (exposure gain 0.7-1.3 per frame)
stitched newest-on-top without gain compensation (above) and by steelscan's default,
gain-compensated feather blending (below)."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from processing.stitching import StitchParams, stitch_frames
from robot_link.sim.sweeps import SweepConfig, make_sweep, painted_steel, texture_size_for


def main(out: Path) -> None:
    cfg = SweepConfig(frames=12, lanes=3, gain=(0.7, 1.3), seed=31)
    need = texture_size_for(cfg)
    sweep = make_sweep(painted_steel((need[1], need[0]), seed=31), cfg)
    frames = [cv2.imdecode(np.frombuffer(j, np.uint8), cv2.IMREAD_COLOR) for j in sweep.frames]
    panels = []
    for label, params in (
        (
            "newest on top, no gain compensation",
            StitchParams(blend="newest", gain_compensation=False),
        ),
        ("steelscan: gains solved over all overlaps, feathered", StitchParams()),
    ):
        m = stitch_frames(frames, sweep.odometry, params=params)
        img = cv2.resize(m.image, None, fx=0.4, fy=0.4, interpolation=cv2.INTER_AREA)
        cv2.putText(
            img, label, (12, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 2, cv2.LINE_AA
        )
        panels.append(img)
    w = min(p.shape[1] for p in panels)
    cv2.imwrite(str(out), np.vstack([p[:, :w] for p in panels]))


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("docs/stitching-exposure.png"))
