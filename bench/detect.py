"""``steelscan bench detect``: crack segmentation (PI, SI, DSC, eqs. (18)–(20)) of every
method on every crack dataset, in normal and in uneven low light; ``proposed`` with its
parameters chosen leaving each set out (:mod:`bench.detect_loo`); corrosion on the rust
sets; the detectors' speed per image and on a mosaic.

``--models DIR`` scores each set with ``DIR/<set>.onnx``, a network trained without that
set (``steelscan train-detector --leave-one-out``); without it the shipped network is used,
and results say ``"left_out": false`` for sets it was trained on; the shipped network is
also scored on the images of those sets it was not fitted to (``learned_held_back``) and
on some it was fitted to (``learned_fit``). Rendered steel of a held-back seed is a set of
its own (``steel-synthetic``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from bench.common import Result
from bench.detect_loo import leave_one_out_proposed
from processing.detection import detect_cracks, to_gray
from processing.detection.corrosion import detect_corrosion
from processing.detection.learned import MODEL_PATH, LearnedParams, learned_cracks, load_model
from processing.learning.data import Sample, load_dataset, split_holdout
from processing.metrics import PooledCounts
from server.config import PROJECT_ROOT
from server.errors import CommandError

DATASETS_ROOT = PROJECT_ROOT.parent / "shared" / "datasets"
CRACK_METHODS = ("sauvola", "otsu", "paper", "proposed", "learned")
Detector = Callable[[NDArray[np.uint8]], NDArray[np.bool_]]
FIT_IMAGES = 30  # training images of each set the network is scored on (its fit)
STEEL_IMAGES, STEEL_SEED = 60, 1000  # rendered steel held back: training draws seed 0


def is_corrosion_set(root: Path) -> bool:
    """Whether a dataset folder holds corrosion (area) labels: its README's title says so."""
    readme = root / "README.md"
    title = readme.read_text(errors="replace").splitlines()[0].lower() if readme.is_file() else ""
    return "rust" in title or "corrosion" in title


def find_datasets(root: Path = DATASETS_ROOT) -> list[Path]:
    """Dataset folders (with ``images/`` and ``masks/``) under ``root``, by name."""
    if not root.is_dir():
        return []
    return sorted(p for p in root.iterdir() if (p / "images").is_dir() and (p / "masks").is_dir())


def low_light(gray: NDArray[np.uint8], rng: np.random.Generator) -> NDArray[np.uint8]:
    """Uneven low light: illumination falling to ~20 % across the frame, gamma 1.4, noise."""
    x = gray.astype(np.float32) / 255.0
    h, w = x.shape
    angle = rng.uniform(0, 2 * np.pi)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    t = np.cos(angle) * xx / w + np.sin(angle) * yy / h
    t = (t - t.min()) / max(float(t.max() - t.min()), 1e-6)
    out = (x * (1.0 - 0.8 * t)) ** 1.4 * 255 + rng.normal(0, 4, x.shape)
    return np.clip(out, 0, 255).astype(np.uint8)


def _detector(method: str, model: Path | None) -> Detector:
    if method == "learned":
        params = LearnedParams(model_path=model or MODEL_PATH)
        return lambda gray: learned_cracks(gray, params)
    return lambda gray: detect_cracks(gray, method=method)  # type: ignore[arg-type]


def score_set(samples: list[Sample], detect: Detector) -> dict:
    """Pooled tolerant (2 px) and strict scores of one detector on one set, and how many
    images with a crack got an empty mask."""
    tol, strict, empty = PooledCounts(2), PooledCounts(0), 0
    for s in samples:
        pred = detect(s.gray)
        tol.add(pred, s.truth)
        strict.add(pred, s.truth)
        empty += int(s.truth.any() and not pred.any())
    t, st = tol.scores(), strict.scores()
    return {
        "value": t.dsc,
        "pi": t.pi,
        "si": t.si,
        "strict": {"pi": st.pi, "si": st.si, "dsc": st.dsc},
        "empty_masks": empty,
    }


def bench_detect(
    dataset: Path | None = None, limit: int | None = None, models: Path | None = None
) -> Iterator[Result]:
    """Every crack method on every crack set (and its low-light variant) against the
    paper's Sauvola baseline; corrosion on the rust sets; speed."""
    roots = [dataset] if dataset is not None else find_datasets()
    if not roots:
        raise CommandError(f"no datasets under {DATASETS_ROOT} (use --dataset)")
    trained_on = set(load_model().record.get("datasets", {}))
    rng = np.random.default_rng(0)
    crack_sets: dict[str, list[Sample]] = {}
    sauvola: dict[str, float] = {}
    for root in roots:
        samples = load_dataset(root, limit)
        if not samples:
            raise CommandError(f"{root}: no image/mask pairs")
        if is_corrosion_set(root):
            yield from _corrosion(root, limit)
            continue
        model = models / f"{root.name}.onnx" if models is not None else None
        if model is not None and not model.is_file():
            model = None
        crack_sets[root.name] = samples
        dim = [Sample(s.name, low_light(s.gray, rng), s.truth) for s in samples]
        for variant, items in (("", samples), ("lowlight.", dim)):
            baseline = None
            for method in CRACK_METHODS:
                scores = score_set(items, _detector(method, model))
                baseline = baseline if baseline is not None else scores["value"]
                if not variant and method == "sauvola":
                    sauvola[root.name] = scores["value"]
                extra = {}
                if method == "learned":
                    extra["left_out"] = model is not None or root.name not in trained_on
                name = f"detect.{root.name}.{variant}{method}.dsc_tol2"
                yield _scored(name, scores, baseline, len(items), **extra)
        if root.name in trained_on and len(samples) > 5:
            yield from _held_back(root.name, samples)
    if dataset is None:
        yield from _synthetic_steel(limit)
    if len(crack_sets) >= 2:
        yield from leave_one_out_proposed(crack_sets, sauvola)
    yield from _speed(load_dataset(roots[0], min(limit or 40, 40)))
    yield from _mosaic_throughput()


def _held_back(name: str, samples: list[Sample]) -> Iterator[Result]:
    """The shipped network on the images of a set it was trained on but never fitted to
    (every tenth, :func:`processing.learning.data.split_holdout`; they chose its threshold),
    and on up to 30 of the images it was fitted to: a network that does not reach a high
    score on its own training images lacks capacity or training, not data."""
    fit, held = split_holdout(samples)
    scores = score_set(held, _detector("learned", None))
    base = score_set(held, _detector("sauvola", None))["value"]
    yield _scored(f"detect.{name}.learned_held_back.dsc_tol2", scores, base, len(held))
    yield _confidence_error(name, held)
    fit = fit[:: max(1, len(fit) // FIT_IMAGES)][:FIT_IMAGES]
    scores = score_set(fit, _detector("learned", None))
    base = score_set(fit, _detector("sauvola", None))["value"]
    yield _scored(f"detect.{name}.learned_fit.dsc_tol2", scores, base, len(fit))


def _synthetic_steel(limit: int | None) -> Iterator[Result]:
    """Every method on rendered steel (:mod:`robot_link.sim.steel_crops`: weld toes, bolt
    heads, plate edges, scratches, fatigue cracks) of a seed no network was trained on."""
    from robot_link.sim.steel_crops import steel_samples

    items = [
        Sample(n, g, t)
        for n, g, t in steel_samples(min(limit or STEEL_IMAGES, STEEL_IMAGES), STEEL_SEED)
    ]
    baseline = None
    for method in CRACK_METHODS:
        scores = score_set(items, _detector(method, None))
        baseline = baseline if baseline is not None else scores["value"]
        yield _scored(
            f"detect.steel-synthetic.{method}.dsc_tol2",
            scores,
            baseline,
            len(items),
            seed=STEEL_SEED,
        )
    yield _confidence_error("steel-synthetic", items)


def _confidence_error(name: str, items: list[Sample]) -> Result:
    """Expected calibration error of the shipped network's per-defect confidence on a
    set's images, against the network's own probability (the mean of its components'
    logits, squashed) as the baseline; ``fitted_on`` says whether these images chose the
    calibration (held-back images of its training sets did; rendered steel of another seed
    did not)."""
    from processing.detection.confidence import Calibration, reliability
    from processing.learning.calibration import labelled_components

    model = load_model()
    cal = Calibration.from_record(model.record)
    feats, labels = [np.zeros((0, 2))], [np.zeros(0, bool)]
    for s in items:
        f, y = labelled_components(model.probability(s.gray), s.truth, model.threshold)
        feats.append(f)
        labels.append(y)
    x, y = np.concatenate(feats), np.concatenate(labels)
    raw, raw_rows = reliability(1 / (1 + np.exp(-x[:, 0])), y)
    ece, rows = reliability(cal.confidence(x), y) if cal is not None else (raw, raw_rows)
    return {
        "name": f"detect.{name}.learned_confidence.ece",
        "value": ece,
        "unit": "ece",
        "baseline": raw,
        "ratio": round(ece / max(raw, 1e-9), 3),
        "components": len(y),
        "true_share": round(float(y.mean()), 3) if len(y) else None,
        "calibrated": cal is not None,
        "fitted_on": name != "steel-synthetic",
        "reliability": rows,
    }


def _scored(name: str, scores: dict, baseline: float, images: int, **extra: object) -> Result:
    return {
        "name": name,
        "unit": "dsc",
        **scores,
        "baseline": baseline,
        "ratio": round(scores["value"] / max(baseline, 1e-9), 3),
        "images": images,
        **extra,
    }


def _corrosion(root: Path, limit: int | None) -> Iterator[Result]:
    """The rust detector's pooled scores (strict: rust is an area) against Otsu on the
    saturation channel."""
    ours, base = PooledCounts(0), PooledCounts(0)
    paths = sorted((root / "images").glob("*"))[:limit]
    for p in paths:
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        mask = cv2.imread(str(root / "masks" / f"{p.stem}.png"), cv2.IMREAD_GRAYSCALE)
        if img is None or mask is None or mask.shape != img.shape[:2]:
            continue
        truth = mask > 127
        ours.add(detect_corrosion(img), truth)
        sat = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)[..., 1]
        _, otsu = cv2.threshold(sat, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        base.add(otsu > 0, truth)
    o, b = ours.scores(), base.scores()
    yield {
        "name": f"detect.{root.name}.corrosion.dsc",
        "value": o.dsc,
        "unit": "dsc",
        "pi": o.pi,
        "si": o.si,
        "baseline": b.dsc,
        "ratio": round(o.dsc / max(b.dsc, 1e-9), 3),
        "what": "rust colour detector vs Otsu on saturation",
        "images": len(paths),
    }


def _speed(samples: list[Sample]) -> Iterator[Result]:
    """Milliseconds per 544×384 image of each method, against the paper's Sauvola."""
    images = [cv2.resize(s.gray, (544, 384), interpolation=cv2.INTER_AREA) for s in samples]
    times: dict[str, float] = {}
    for method in ("sauvola", "proposed", "paper", "learned"):
        detect = _detector(method, None)
        detect(images[0])  # warm-up: model load, compiled kernels
        t0 = time.perf_counter()
        for img in images:
            detect(img)
        times[method] = 1000 * (time.perf_counter() - t0) / len(images)
        yield {
            "name": f"detect.{method}.time_per_544x384",
            "value": round(times[method], 2),
            "unit": "ms",
            "baseline": round(times["sauvola"], 2),
            "ratio": round(times[method] / times["sauvola"], 3),
        }


def _mosaic_throughput() -> Iterator[Result]:
    """Megapixels per second of the detect job's whole mosaic pass on a simulated
    9-megapixel mosaic (surface mask, crack and rust masks with seams, every defect
    measured) with each crack method, against scikit-image's Sauvola on the same image;
    and each crack filter alone."""
    from skimage.filters import threshold_sauvola

    from processing.detection import detect_cracks_tiled, find_defects
    from processing.detection.learned import crack_probability
    from processing.detection.surface import on_surface
    from robot_link.sim.structure import make_structure

    mosaic = make_structure(11).texture
    h, w = mosaic.shape[:2]
    mp = h * w / 1e6
    coverage = np.full((h, w), 255, np.uint8)
    seams = np.zeros((h, w), bool)
    seams[::400, :] = seams[:, ::500] = True  # where frames would meet
    t0 = time.perf_counter()
    gray = to_gray(mosaic)
    _ = gray < threshold_sauvola(gray, window_size=25, k=0.2)
    base = mp / (time.perf_counter() - t0)
    for method in ("proposed", "learned"):
        find_defects(mosaic[:512, :512], 0.25, method=method)  # warm-up
        runs = []
        for _ in range(3):
            t0 = time.perf_counter()
            _, _, found = find_defects(
                mosaic, 0.25, on_surface(mosaic, coverage), seams, method=method
            )
            runs.append(time.perf_counter() - t0)
        yield _throughput(
            f"detect.{method}.mosaic_throughput",
            mp / float(np.median(runs)),
            base,
            mp,
            defects=len(found),
            what="surface mask + crack and rust masks (seams) + measurement, 2 threads",
        )
    filters: dict[str, Callable[[], object]] = {
        "proposed": lambda: detect_cracks_tiled(mosaic),
        "learned": lambda: crack_probability(gray),
    }
    for method, run in filters.items():
        t0 = time.perf_counter()
        run()
        rate = mp / (time.perf_counter() - t0)
        yield _throughput(f"detect.{method}.crack_filter_throughput", rate, base, mp)


def _throughput(name: str, rate: float, base: float, mp: float, **extra: object) -> Result:
    """A megapixels-per-second result against the baseline's rate on the same image."""
    return {
        "name": name,
        "value": round(rate, 2),
        "unit": "MP/s",
        "baseline": round(base, 2),
        "ratio": round(rate / base, 3),
        "megapixels": round(mp, 1),
        **extra,
    }
