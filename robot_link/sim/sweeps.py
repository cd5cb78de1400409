"""Camera sweeps over a surface texture with exact ground truth, for stitching benchmarks.

A sweep is what the robot's downward camera sees while it drives a straight run or a
lawn-mower pattern: frames cut from a large texture at known centres and headings, with
the robot's imperfections (heading jitter, exposure gain, sensor noise, JPEG) and an
odometry guess that drifts like wheel odometry does.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from robot_link.sim.imaging import warp_affine_exact
from robot_link.sim.structure import paint_texture

Pattern = Literal["straight", "lawnmower"]


@dataclass(frozen=True)
class SweepConfig:
    """How a sweep is driven and imaged."""

    frames: int = 40
    pattern: Pattern = "lawnmower"
    lanes: int = 4
    frame_size: tuple[int, int] = (640, 480)  # (w, h)
    overlap: float = 0.35
    rotation_deg: float = 2.0  # heading jitter, ±
    turn_lanes: bool = True  # return lanes are driven turned by 180° (a robot turns around)
    gain: tuple[float, float] = (0.8, 1.2)
    noise_sigma: float = 2.0
    jpeg_quality: int = 90
    odometry_drift: float = 0.02  # random-walk position error per step, fraction of the step
    odometry_yaw_deg: float = 0.3  # random-walk heading error per step
    scale: float = 1.0  # texture pixels per frame pixel
    seed: int = 0


@dataclass
class Sweep:
    """Frames (JPEG bytes) with their true poses and a drifting odometry guess.

    Poses are (N, 3): frame-centre x, y in texture pixels divided by ``scale`` (so frame
    pixels) and heading in radians (frame x axis from the texture's x axis, towards y).
    """

    frames: list[bytes]
    truth: NDArray[np.float64]
    odometry: NDArray[np.float64]
    config: SweepConfig
    gains: NDArray[np.float64]  # the exposure gain of each frame


def texture_from_images(
    images: Sequence[NDArray[np.uint8]], columns: int, cell: tuple[int, int] = (544, 384)
) -> NDArray[np.uint8]:
    """A large BGR texture from real photographs laid side by side in a grid (each image
    resized to ``cell`` (w, h)); each image appears once, so nothing repeats."""
    if not images:
        raise ValueError("no images to build a texture from")
    rows = -(-len(images) // columns)
    out = np.zeros((rows * cell[1], columns * cell[0], 3), np.uint8)
    for k, img in enumerate(images):
        img = (
            cast(NDArray[np.uint8], cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)) if img.ndim == 2 else img
        )
        r, c = divmod(k, columns)
        out[r * cell[1] : (r + 1) * cell[1], c * cell[0] : (c + 1) * cell[0]] = cv2.resize(
            img, cell, interpolation=cv2.INTER_AREA
        )
    return out


def painted_steel(shape: tuple[int, int], seed: int = 0) -> NDArray[np.uint8]:
    """Low-texture painted steel, (h, w, 3), as the simulator paints its plates."""
    img = paint_texture(np.random.default_rng(seed), shape)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def sweep_poses(cfg: SweepConfig, rng: np.random.Generator) -> NDArray[np.float64]:
    """True frame poses (N, 3) in frame pixels, starting near (0, 0)."""
    w, h = cfg.frame_size
    step_x, step_y = (1 - cfg.overlap) * w, (1 - cfg.overlap) * h
    jitter = np.radians(cfg.rotation_deg)
    if cfg.pattern == "straight":
        lanes, per_lane = 1, cfg.frames
    else:
        lanes = cfg.lanes
        per_lane = -(-cfg.frames // lanes)
    poses = []
    for k in range(cfg.frames):
        lane, i = divmod(k, per_lane)
        back = lane % 2 == 1
        x = (per_lane - 1 - i if back else i) * step_x
        y = lane * step_y
        heading = np.pi if back and cfg.turn_lanes else 0.0
        poses.append(
            (x + rng.normal(0, 2), y + rng.normal(0, 2), heading + rng.uniform(-jitter, jitter))
        )
    return np.array(poses, float)


def drifting_odometry(
    truth: NDArray[np.float64], cfg: SweepConfig, rng: np.random.Generator
) -> NDArray[np.float64]:
    """Odometry guess: each true step (in the robot's frame) with a random error, integrated
    from the first pose, so heading errors accumulate into position drift as on a robot."""
    from processing.poses import compose_se2, relative_se2

    odo = [truth[0].copy()]
    for k in range(len(truth) - 1):
        step = relative_se2(truth[k], truth[k + 1])
        length = float(np.hypot(step[0], step[1]))
        step[:2] += rng.normal(0, cfg.odometry_drift * length, 2)
        step[2] += rng.normal(0, np.radians(cfg.odometry_yaw_deg))
        odo.append(compose_se2(odo[-1], step))
    return np.array(odo)


def render_frame(
    texture: NDArray[np.uint8],
    pose: NDArray[np.floating],
    cfg: SweepConfig,
    rng: np.random.Generator,
    gain: float | None = None,
) -> bytes:
    """One camera frame (JPEG) centred at ``pose`` (frame pixels) on the texture, with an
    exposure ``gain`` (drawn from ``cfg.gain`` when None)."""
    w, h = cfg.frame_size
    c, s = np.cos(pose[2]), np.sin(pose[2])
    half = np.array([(w - 1) / 2, (h - 1) / 2])
    R = cfg.scale * np.array([[c, -s], [s, c]])
    centre = cfg.scale * np.asarray(pose[:2]) + _margin(cfg)
    M = np.hstack([R, (centre - R @ half)[:, None]])  # frame pixel -> texture pixel
    # not cv2.warpAffine: it rounds positions to 1/32 px
    img = warp_affine_exact(texture, M, (w, h))
    gain = rng.uniform(*cfg.gain) if gain is None else gain
    img = img * np.float32(gain) + rng.normal(0, cfg.noise_sigma, img.shape).astype(np.float32)
    ok, buf = cv2.imencode(
        ".jpg",
        np.clip(img + 0.5, 0, 255).astype(np.uint8),
        [cv2.IMWRITE_JPEG_QUALITY, cfg.jpeg_quality],
    )
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()


def _margin(cfg: SweepConfig) -> NDArray[np.float64]:
    w, h = cfg.frame_size
    pad = 0.05 * w + 10  # heading jitter and position noise
    return (np.array([w / 2, h / 2]) + pad) * cfg.scale


def texture_size_for(cfg: SweepConfig) -> tuple[int, int]:
    """(w, h) of texture a sweep needs, margins included."""
    w, h = cfg.frame_size
    per_lane = cfg.frames if cfg.pattern == "straight" else -(-cfg.frames // cfg.lanes)
    lanes = 1 if cfg.pattern == "straight" else cfg.lanes
    pad = 0.05 * w + 10
    width = ((per_lane - 1) * (1 - cfg.overlap) * w + w + 2 * pad) * cfg.scale
    height = ((lanes - 1) * (1 - cfg.overlap) * h + h + 2 * pad) * cfg.scale
    return int(np.ceil(width)), int(np.ceil(height))


def make_sweep(texture: NDArray[np.uint8], cfg: SweepConfig = SweepConfig()) -> Sweep:
    """Drive a sweep over ``texture`` (large enough: see :func:`texture_size_for`)."""
    need = texture_size_for(cfg)
    if texture.shape[1] < need[0] or texture.shape[0] < need[1]:
        raise ValueError(
            f"texture {texture.shape[1]}x{texture.shape[0]} is smaller than the sweep needs ({need[0]}x{need[1]})"
        )
    rng = np.random.default_rng(cfg.seed)
    truth = sweep_poses(cfg, rng)
    gains = rng.uniform(*cfg.gain, size=len(truth))
    frames = [render_frame(texture, p, cfg, rng, g) for p, g in zip(truth, gains)]
    return Sweep(frames, truth, drifting_odometry(truth, cfg, rng), cfg, gains)


class TiledSurface:
    """An unbounded painted-steel surface generated tile by tile from a seed, so that
    sweeps of any length need no giant texture in memory (tiles are cached, LRU)."""

    def __init__(self, seed: int = 0, tile: int = 512, cache_tiles: int = 400) -> None:
        self.seed, self.tile, self.cache_tiles = seed, tile, cache_tiles
        self._tiles: dict[tuple[int, int], NDArray[np.uint8]] = {}

    def _tile(self, tx: int, ty: int) -> NDArray[np.uint8]:
        key = (tx, ty)
        hit = self._tiles.pop(key, None)
        if hit is None:
            rng = np.random.default_rng([self.seed, tx + 2**20, ty + 2**20])
            hit = np.clip(paint_texture(rng, (self.tile, self.tile)) + 0.5, 0, 255).astype(np.uint8)
        self._tiles[key] = hit
        while len(self._tiles) > self.cache_tiles:
            self._tiles.pop(next(iter(self._tiles)))
        return hit

    def patch(self, x0: int, y0: int, w: int, h: int) -> NDArray[np.uint8]:
        """The surface's pixels [y0, y0 + h) x [x0, x0 + w)."""
        out = np.empty((h, w, 3), np.uint8)
        t = self.tile
        for ty in range(y0 // t, (y0 + h - 1) // t + 1):
            for tx in range(x0 // t, (x0 + w - 1) // t + 1):
                sx0, sy0 = max(x0, tx * t), max(y0, ty * t)
                sx1, sy1 = min(x0 + w, (tx + 1) * t), min(y0 + h, (ty + 1) * t)
                out[sy0 - y0 : sy1 - y0, sx0 - x0 : sx1 - x0] = self._tile(tx, ty)[
                    sy0 - ty * t : sy1 - ty * t, sx0 - tx * t : sx1 - tx * t
                ]
        return out


class LazySweep:
    """A sweep over a :class:`TiledSurface` whose frames are rendered when asked for (a
    frame source for runs of any length); ``truth`` and ``odometry`` as in :class:`Sweep`."""

    def __init__(self, cfg: SweepConfig, surface: TiledSurface | None = None) -> None:
        self.cfg = cfg
        self.surface = surface or TiledSurface(cfg.seed)
        rng = np.random.default_rng(cfg.seed)
        self.truth = sweep_poses(cfg, rng)
        self.odometry = drifting_odometry(self.truth, cfg, rng)

    def __len__(self) -> int:
        return len(self.truth)

    def __getitem__(self, k: int) -> NDArray[np.uint8]:
        cfg = self.cfg
        w, h = cfg.frame_size
        reach = int(np.ceil(np.hypot(w, h) / 2 * cfg.scale)) + 2
        centre = cfg.scale * self.truth[k, :2] + _margin(cfg)
        x0, y0 = int(centre[0]) - reach, int(centre[1]) - reach
        patch = self.surface.patch(x0, y0, 2 * reach, 2 * reach)
        pose = np.array(
            [
                (centre[0] - x0 - _margin(cfg)[0]) / cfg.scale,
                (centre[1] - y0 - _margin(cfg)[1]) / cfg.scale,
                self.truth[k, 2],
            ]
        )
        rng = np.random.default_rng([cfg.seed, k])
        jpeg = render_frame(patch, pose, cfg, rng)
        frame = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        assert frame is not None  # a JPEG just encoded
        return cast(NDArray[np.uint8], frame)
