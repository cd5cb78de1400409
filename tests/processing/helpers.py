"""What many tests share: simulated camera sweeps over painted steel and their frames, a
frame cut at a pose, a textured plate."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from processing.poses import frame_to_mosaic
from robot_link.sim.sweeps import Sweep, SweepConfig, make_sweep, painted_steel, texture_size_for


def texture(seed: int = 0, shape: tuple[int, int] = (900, 1600)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 255, (shape[0] // 8, shape[1] // 8), dtype=np.uint8)
    img = cv2.resize(small, shape[::-1], interpolation=cv2.INTER_CUBIC)
    img = cv2.add(img, rng.integers(0, 20, shape, dtype=np.uint8))
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)


def cut(tex: np.ndarray, cx: float, cy: float, w: int = 320, h: int = 240) -> np.ndarray:
    M = np.float32([[1, 0, cx - (w - 1) / 2], [0, 1, cy - (h - 1) / 2]])
    return cv2.warpAffine(tex, M, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)


def sweep(
    frames: int = 12, pattern: str = "lawnmower", seed: int = 5, cracked: bool = False, **kw: object
) -> Sweep:
    """A sweep over painted steel; ``cracked`` draws one dark meandering hairline crack
    across the plate's middle (the plate alone has scratches, never cracks)."""
    cfg = SweepConfig(
        frames=frames, pattern=pattern, lanes=3, frame_size=(320, 240), seed=seed, **kw
    )  # type: ignore[arg-type]
    need = texture_size_for(cfg)
    plate = painted_steel((need[1], need[0]), seed=seed)
    if cracked:
        rng = np.random.default_rng(seed)
        x = np.linspace(0.1, 0.9, 80) * need[0]
        y = need[1] / 2 + np.cumsum(rng.normal(0, 2.0, x.size))
        line = np.stack([x, y], axis=1).round().astype(np.int32)
        cv2.polylines(plate, [line], False, (40, 40, 40), 2, cv2.LINE_AA)
    return make_sweep(plate, cfg)


def decoded(s: Sweep) -> list[np.ndarray]:
    return [cv2.imdecode(np.frombuffer(j, np.uint8), cv2.IMREAD_COLOR) for j in s.frames]


def worst_pair_error(est: np.ndarray, truth: np.ndarray, size: tuple[int, int]) -> float:
    """Worst corner displacement (px) of the relative placement of truly overlapping frames."""
    w, h = size
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float).T
    worst = 0.0
    for i in range(len(truth)):
        for j in range(i + 1, len(truth)):
            if (
                abs(truth[j, 0] - truth[i, 0]) < 0.8 * w
                and abs(truth[j, 1] - truth[i, 1]) < 0.8 * h
            ):
                e = np.linalg.inv(frame_to_mosaic(est[i], size)) @ frame_to_mosaic(est[j], size)
                t = np.linalg.inv(frame_to_mosaic(truth[i], size)) @ frame_to_mosaic(truth[j], size)
                worst = max(
                    worst, float(np.linalg.norm((e @ corners - t @ corners)[:2], axis=0).max())
                )
    return worst


def frame_at(tex: np.ndarray, pose: np.ndarray, size: tuple[int, int] = (320, 240)) -> np.ndarray:
    """Grey frame whose centre sits at ``pose`` (x, y, θ) on the texture."""
    A = frame_to_mosaic(pose, size)
    return cv2.warpAffine(
        cv2.cvtColor(tex, cv2.COLOR_BGR2GRAY),
        A[:2],
        size,
        flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
    ).astype(np.float32)


def textured_plate(
    shape: tuple[int, int], seed: int, *, width: int, depth: float
) -> tuple[np.ndarray, np.ndarray]:
    """Painted steel: grain, blotches, uneven light, and a crack of ``width`` px that is
    ``depth`` grey levels darker than the paint."""
    rng = np.random.default_rng(seed)
    h, w = shape
    grain = cv2.GaussianBlur(rng.normal(0, 1, shape).astype(np.float32), (0, 0), 1.2) * 10
    blotch = cv2.GaussianBlur(rng.normal(0, 1, shape).astype(np.float32), (0, 0), 12) * 40
    light = np.linspace(1.0, 0.7, w, dtype=np.float32)[None, :]
    truth = np.zeros(shape, np.uint8)
    pts = np.cumsum(rng.normal(0, 3, (12, 2)), axis=0) + (h * 0.2, w * 0.1)
    pts[:, 1] += np.linspace(0, w * 0.8, 12)
    pts[:, 0] += np.linspace(0, h * 0.6, 12)
    cv2.polylines(truth, [pts[:, ::-1].astype(np.int32)], False, 255, width)
    img = (150 + grain + blotch - depth * (truth > 0)) * light + rng.normal(0, 2, shape)
    return np.clip(img, 0, 255).astype(np.uint8), truth > 0


def crack_dataset(root: Path, n: int, seed: int) -> Path:
    """A dataset folder (``images/``, ``masks/``) of ``n`` small :func:`textured_plate`
    images with 2-px cracks, as the training commands read them."""
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    for i in range(n):
        gray, truth = textured_plate((96, 128), seed + i, width=2, depth=50)
        cv2.imwrite(str(root / "images" / f"{i:03d}.png"), gray)
        cv2.imwrite(str(root / "masks" / f"{i:03d}.png"), truth.astype(np.uint8) * 255)
    return root
