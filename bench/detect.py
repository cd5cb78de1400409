"""``steelscan bench detect``: crack segmentation (PI, SI, DSC) of every method over the
development split, in normal and low light, and the detector's speed."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from bench.common import Result
from processing.detection import detect_cracks
from processing.peaks import dominant_peaks
from server.config import PROJECT_ROOT
from server.errors import CommandError

DEFAULT_CRACK_DATASET = PROJECT_ROOT.parent / "shared" / "datasets" / "deepcrack-train"


@dataclass
class Pooled:
    """Pixel counts pooled over a set of images, strict and with a tolerance."""

    tp_p: int = 0
    fp: int = 0
    tp_t: int = 0
    fn: int = 0

    def add(self, pred: NDArray[np.bool_], truth: NDArray[np.bool_], tolerance_px: int) -> None:
        """Accumulate one image's counts."""
        if tolerance_px:
            k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * tolerance_px + 1,) * 2)
            t_near = cv2.dilate(truth.astype(np.uint8), k) > 0
            p_near = cv2.dilate(pred.astype(np.uint8), k) > 0
        else:
            t_near, p_near = truth, pred
        self.tp_p += int((pred & t_near).sum())
        self.fp += int((pred & ~t_near).sum())
        self.tp_t += int((truth & p_near).sum())
        self.fn += int((truth & ~p_near).sum())

    def scores(self) -> tuple[float, float, float]:
        """PI, SI, DSC (paper eqs. 18-20) of the pooled counts."""
        pi = self.tp_p / max(self.tp_p + self.fp, 1)
        si = self.tp_t / max(self.tp_t + self.fn, 1)
        dsc = 2 * pi * si / (pi + si) if pi + si else 0.0
        return round(pi, 4), round(si, 4), round(dsc, 4)


def low_light(image: NDArray[np.uint8], rng: np.random.Generator) -> NDArray[np.uint8]:
    """Uneven low light: illumination falling to ~20 % across the frame, gamma, sensor noise."""
    gray = image.astype(np.float32) / 255.0
    h, w = gray.shape[:2]
    angle = rng.uniform(0, 2 * np.pi)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    t = np.cos(angle) * xx / w + np.sin(angle) * yy / h
    t = (t - t.min()) / max(float(t.max() - t.min()), 1e-6)
    light = 1.0 - 0.8 * t
    out = (gray * (light if gray.ndim == 2 else light[..., None])) ** 1.4
    out = out * 255 + rng.normal(0, 4, out.shape)
    return np.clip(out, 0, 255).astype(np.uint8)


def load_crack_dataset(
    root: Path, limit: int | None
) -> list[tuple[str, NDArray[np.uint8], NDArray[np.bool_]]]:
    """(name, image, truth) pairs of a folder with ``images/`` and ``masks/``."""
    images = sorted((root / "images").glob("*.jpg")) + sorted((root / "images").glob("*.png"))
    if not images:
        raise CommandError(f"{root}: no images/ with .jpg or .png files (use --dataset)")
    out = []
    for p in images[:limit]:
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        mask = cv2.imread(str(root / "masks" / f"{p.stem}.png"), cv2.IMREAD_GRAYSCALE)
        if img is None or mask is None:
            continue
        out.append((p.name, img, mask > 127))
    return out


def sauvola_tuned(image: NDArray[np.uint8]) -> NDArray[np.bool_]:
    """The strongest Sauvola baseline found on the dev split: window 61, k 0.4, components
    under 300 px removed (scikit-image's implementation)."""
    from skimage.filters import threshold_sauvola

    from processing.detection import to_gray
    from processing.thresholds import remove_small

    gray = to_gray(image)
    return remove_small(gray < threshold_sauvola(gray, window_size=61, k=0.4), 300)


def _method(name: str) -> Callable[[NDArray[np.uint8]], NDArray[np.bool_]]:
    if name == "sauvola_tuned":
        return sauvola_tuned
    return lambda img: detect_cracks(img, method=name)  # type: ignore[arg-type]


def bench_detect(dataset: Path | None = None, limit: int | None = None) -> Iterator[Result]:
    """Pooled PI/SI/DSC (strict and 2-px tolerant) of every method on the dataset and on a
    low-light variant, against the tuned Sauvola baseline; time per 480x320 image against
    scikit-image's Sauvola; mosaic throughput; peak detection time per histogram."""
    data = load_crack_dataset(dataset or DEFAULT_CRACK_DATASET, limit)
    rng = np.random.default_rng(0)
    variants = {"": data, "lowlight_": [(n, low_light(i, rng), t) for n, i, t in data]}
    for prefix, items in variants.items():
        baseline = 0.0
        for method in ("sauvola_tuned", "sauvola", "otsu", "paper", "proposed"):
            strict, tol = Pooled(), Pooled()
            fn = _method(method)
            for _, img, truth in items:
                pred = fn(img)
                strict.add(pred, truth, 0)
                tol.add(pred, truth, 2)
            pi, si, dsc = tol.scores()
            spi, ssi, sdsc = strict.scores()
            baseline = baseline or dsc
            yield {
                "name": f"detect.{prefix}{method}.dsc_tol2",
                "value": dsc,
                "unit": "dsc",
                "baseline": baseline,
                "ratio": round(dsc / max(baseline, 1e-9), 3),
                "pi": pi,
                "si": si,
                "strict": {"pi": spi, "si": ssi, "dsc": sdsc},
                "images": len(items),
            }
    small = [cv2.resize(i, (480, 320), interpolation=cv2.INTER_AREA) for _, i, _ in data[:60]]
    times = {}
    for method in ("sauvola", "proposed", "paper"):
        fn = _method(method)
        t0 = time.perf_counter()
        for img in small:
            fn(img)
        times[method] = 1000 * (time.perf_counter() - t0) / len(small)
        yield {
            "name": f"detect.{method}.time_per_480x320",
            "value": round(times[method], 2),
            "unit": "ms",
            "baseline": round(times["sauvola"], 2),
            "ratio": round(times[method] / times["sauvola"], 3),
        }
    yield from _mosaic_throughput()
    hists = [
        np.bincount(cv2.cvtColor(i, cv2.COLOR_BGR2GRAY).ravel(), minlength=256)
        for _, i, _ in data[:50]
    ]
    t0 = time.perf_counter()
    for h in hists:
        dominant_peaks(h)
    yield {
        "name": "detect.peak_detection_per_histogram",
        "value": round(1000 * (time.perf_counter() - t0) / len(hists), 3),
        "unit": "ms",
    }


def _mosaic_throughput() -> Iterator[Result]:
    """Megapixels per second of the detect job's whole mosaic pass on a simulated
    9-megapixel mosaic (surface mask, crack and rust masks with seams, every defect
    measured), against scikit-image's Sauvola on the same image; and the crack filter alone."""
    from skimage.filters import threshold_sauvola

    from processing.detection import detect_cracks_tiled
    from processing.surface import on_surface
    from robot_link.sim.structure import make_structure
    from server.jobs.detect import detect_in

    mosaic = make_structure(11).texture
    h, w = mosaic.shape[:2]
    mp = h * w / 1e6
    coverage = np.full((h, w), 255, np.uint8)
    seams = np.zeros((h, w), bool)
    seams[::400, :] = seams[:, ::500] = True  # where frames would meet
    detect_in(mosaic[:512, :512], 0.25)  # warm-up: compiled kernels, thread pools
    t0 = time.perf_counter()
    gray = cv2.cvtColor(mosaic, cv2.COLOR_BGR2GRAY)
    _ = gray < threshold_sauvola(gray, window_size=25, k=0.2)
    base = mp / (time.perf_counter() - t0)
    runs = []
    for _ in range(3):
        t0 = time.perf_counter()
        _, _, found = detect_in(mosaic, 0.25, on_surface(mosaic, coverage), seams)
        runs.append(time.perf_counter() - t0)
    ours = mp / float(np.median(runs))
    yield {
        "name": "detect.mosaic_throughput",
        "value": round(ours, 2),
        "unit": "MP/s",
        "baseline": round(base, 2),
        "ratio": round(ours / base, 3),
        "megapixels": round(mp, 1),
        "defects": len(found),
        "target": 20.0,
        "what": "surface mask + crack and rust masks (seams) + measurement, 2 threads",
    }
    t0 = time.perf_counter()
    detect_cracks_tiled(mosaic)
    cracks = mp / (time.perf_counter() - t0)
    yield {
        "name": "detect.crack_filter_throughput",
        "value": round(cracks, 2),
        "unit": "MP/s",
        "baseline": round(base, 2),
        "ratio": round(cracks / base, 3),
        "megapixels": round(mp, 1),
    }
