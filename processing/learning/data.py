"""Crack datasets and the training crops drawn from them (NumPy and OpenCV only).

A dataset is a folder with ``images/<stem>.<ext>`` and ``masks/<stem>.png`` (255 = defect),
the layout of the sets in ``shared/datasets``. Images are read as 8-bit grey: cracks are
darker than their surroundings whatever the colour of the surface, and one channel makes
the network indifferent to paint and lighting colour.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff")


@dataclass(frozen=True)
class Sample:
    """One labelled image: (H, W) uint8 grey and (H, W) bool truth."""

    name: str
    gray: NDArray[np.uint8]
    truth: NDArray[np.bool_]


def load_dataset(root: Path, limit: int | None = None) -> list[Sample]:
    """Every image of ``root/images`` with its ``root/masks/<stem>.png``, sorted by name;
    pairs whose files are missing, unreadable or of different sizes are skipped."""
    paths = sorted(p for p in (root / "images").glob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
    out: list[Sample] = []
    for p in paths[:limit]:
        gray = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        mask = cv2.imread(str(root / "masks" / f"{p.stem}.png"), cv2.IMREAD_GRAYSCALE)
        if gray is None or mask is None or gray.shape != mask.shape:
            continue
        out.append(Sample(p.name, cast(NDArray[np.uint8], gray), mask > 127))
    return out


def split_holdout(samples: list[Sample], every: int = 10) -> tuple[list[Sample], list[Sample]]:
    """(train, holdout): every ``every``-th sample (by name order) held out for choosing the
    probability threshold; the rest for fitting."""
    hold = [s for i, s in enumerate(samples) if i % every == every // 2]
    fit = [s for i, s in enumerate(samples) if i % every != every // 2]
    return fit, hold


@dataclass(frozen=True)
class AugmentParams:
    """Ranges of the random changes made to each training crop.

    Scale and rotation cover cracks of other widths and directions than the sets hold;
    gain, gamma, uneven light, blur, noise and JPEG re-compression cover the camera; thin
    bright lines (scratches through paint to bare metal, reflections) drawn on a share
    ``bright_lines`` of the crops teach that a crack is dark.
    """

    crop_px: int = 256
    scale: tuple[float, float] = (0.6, 1.6)
    gain: tuple[float, float] = (0.5, 1.3)
    gamma: tuple[float, float] = (0.6, 1.6)
    uneven_light: float = 0.6
    blur_sigma: tuple[float, float] = (0.0, 1.2)
    noise_sigma: tuple[float, float] = (0.0, 8.0)
    jpeg_quality: tuple[int, int] = (40, 95)
    crack_fraction: float = 0.8
    bright_lines: float = 0.3


def random_crop(
    sample: Sample, rng: np.random.Generator, params: AugmentParams = AugmentParams()
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """One augmented (crop, crop) pair: grey in [0, 1] and truth in {0, 1}, float32.

    A random similarity transform (log-uniform scale, any rotation, a flip) maps a window
    of the image onto the crop, centred on a crack pixel with probability
    ``params.crack_fraction``; borders are mirrored. Photometric changes follow.
    """
    n = params.crop_px
    h, w = sample.gray.shape
    s = math.exp(rng.uniform(*np.log(params.scale)))
    angle = rng.uniform(0.0, 360.0)
    ys, xs = np.nonzero(sample.truth)
    if len(ys) and rng.random() < params.crack_fraction:
        k = rng.integers(len(ys))
        cy, cx = float(ys[k]), float(xs[k])
        cy += rng.uniform(-0.3, 0.3) * n / s
        cx += rng.uniform(-0.3, 0.3) * n / s
    else:
        cy, cx = rng.uniform(0, h), rng.uniform(0, w)
    m = cast(NDArray[np.float64], cv2.getRotationMatrix2D((cx, cy), angle, s))
    m[:, 2] += (n / 2 - cx, n / 2 - cy)
    if rng.random() < 0.5:
        m[0] = -m[0]
        m[0, 2] += n - 1
    interp = cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR
    gray = cast(
        NDArray[np.uint8],
        cv2.warpAffine(sample.gray, m, (n, n), flags=interp, borderMode=cv2.BORDER_REFLECT_101),
    )
    truth = cv2.warpAffine(
        sample.truth.astype(np.float32),
        m,
        (n, n),
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REFLECT_101,
    )
    if rng.random() < params.bright_lines:
        add_bright_lines(gray, rng)
    return photometric(gray, rng, params), (truth > 0.35).astype(np.float32)


def add_bright_lines(gray: NDArray[np.uint8], rng: np.random.Generator) -> None:
    """Draw one to three thin straight lines brighter than the surface into ``gray``."""
    n = gray.shape[0]
    level = float(np.median(gray))
    for _ in range(int(rng.integers(1, 4))):
        p = rng.uniform(0, n, 2)
        q = p + rng.normal(size=2) * rng.uniform(0.1, 0.6) * n
        value = int(min(255, level + rng.uniform(20, 70)))
        cv2.line(
            gray,
            (int(p[0]), int(p[1])),
            (int(q[0]), int(q[1])),
            value,
            int(rng.integers(1, 3)),
            cv2.LINE_AA,
        )


def photometric(
    gray: NDArray[np.uint8], rng: np.random.Generator, params: AugmentParams = AugmentParams()
) -> NDArray[np.float32]:
    """(H, W) float32 in [0, 1]: gain, gamma, a linear light ramp, blur, sensor noise and
    JPEG re-compression of an (H, W) uint8 image, each drawn from ``params``."""
    h, w = gray.shape
    if rng.random() < 0.5:
        q = int(rng.integers(*params.jpeg_quality))
        ok, buf = cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, q])
        if ok:
            decoded = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
            assert decoded is not None  # a JPEG just encoded
            gray = cast(NDArray[np.uint8], decoded)
    x = gray.astype(np.float32) / 255.0
    sigma = rng.uniform(*params.blur_sigma)
    if sigma > 0.3:
        x = cast(NDArray[np.float32], cv2.GaussianBlur(x, (0, 0), sigma))
    x = np.clip(x, 0, 1) ** rng.uniform(*params.gamma)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    a = rng.uniform(0, 2 * np.pi)
    ramp = (np.cos(a) * xx + np.sin(a) * yy) / max(h, w)
    light = 1.0 - params.uneven_light * rng.random() * (ramp - ramp.min())
    x = x * light * rng.uniform(*params.gain) + rng.uniform(-0.1, 0.1)
    x = x + rng.normal(0.0, rng.uniform(*params.noise_sigma) / 255.0, x.shape)
    return np.clip(x, 0.0, 1.0).astype(np.float32)


def centre_line_weights(
    gray: NDArray[np.float32],
    truth: NDArray[np.float32],
    centre_weight: float,
    faint_contrast: float = 0.1,
) -> NDArray[np.float32]:
    """(N, N) per-pixel loss weights of an augmented crop: 1, plus ``centre_weight`` on the
    truth's centre line, twice that where the crack is faint.

    A hairline is all centre line and a wide crack mostly area, so weighting the centre
    line makes a missed hairline cost as much as a missed wide crack; a centre-line pixel
    less than ``faint_contrast`` (of the grey range) darker than the surface around the
    crack counts double, so faint cracks are not given up.
    """
    from skimage.morphology import skeletonize

    w = np.ones(truth.shape, np.float32)
    if centre_weight <= 0 or not truth.any():
        return w
    crack = truth > 0.5
    line = skeletonize(crack)
    around = (~crack).astype(np.float32)
    blur = cast(NDArray[np.float32], cv2.GaussianBlur(gray * around, (0, 0), 4.0))
    norm = cast(NDArray[np.float32], cv2.GaussianBlur(around, (0, 0), 4.0))
    surface = blur / np.maximum(norm, 1e-3)
    # deep inside a wide crack no plate is near enough to measure: not faint there
    faint = ((surface - gray) < faint_contrast) & (norm > 0.05)
    w[line] += centre_weight * (1.0 + faint[line])
    return w


def balanced_batch(
    sets: list[list[Sample]],
    batch: int,
    rng: np.random.Generator,
    params: AugmentParams = AugmentParams(),
    centre_weight: float = 0.0,
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
    """(B, 1, N, N) images, truths and loss weights (:func:`centre_line_weights`), each
    crop drawn from a set chosen uniformly, so that a large set does not outweigh a small
    one."""
    xs, ys, ws = [], [], []
    for _ in range(batch):
        group = sets[int(rng.integers(len(sets)))]
        x, y = random_crop(group[int(rng.integers(len(group)))], rng, params)
        xs.append(x)
        ys.append(y)
        ws.append(centre_line_weights(x, y, centre_weight))
    return np.stack(xs)[:, None], np.stack(ys)[:, None], np.stack(ws)[:, None]
