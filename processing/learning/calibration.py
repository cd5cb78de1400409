"""Fitting the crack network's per-defect confidence (:mod:`processing.detection.confidence`).

On images held back from training, every component the network finds is labelled true
when most of its pixels lie within the tolerance of a labelled crack; a logistic model of
its features (Platt scaling) is fitted to those labels by maximum likelihood with a small
ridge, and stored in the ONNX model's record beside the threshold.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize
from scipy.special import expit

from processing.detection.confidence import Calibration, component_features, reliability
from processing.learning.data import Sample, split_holdout

log = logging.getLogger(__name__)

Probability = Callable[[NDArray[np.uint8]], NDArray[np.float32]]


def labelled_components(
    probability: NDArray[np.float32],
    truth: NDArray[np.bool_],
    threshold: float,
    tolerance_px: int = 2,
    min_on_truth: float = 0.5,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """(N, 2) features and (N,) labels of the N components of ``probability > threshold``:
    true when at least ``min_on_truth`` of a component's pixels lie within
    ``tolerance_px`` of ``truth`` (both (H, W))."""
    n, found = cv2.connectedComponents((probability > threshold).astype(np.uint8), connectivity=8)
    labels = cast(NDArray[np.int32], found)
    if n <= 1:
        return np.zeros((0, 2)), np.zeros(0, bool)
    k = 2 * tolerance_px + 1
    near = cv2.dilate(truth.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    flat = labels.ravel()
    count = np.bincount(flat, minlength=n)
    on = np.bincount(flat, weights=near.ravel().astype(np.float64), minlength=n)
    feats = component_features(probability, labels, n)[1:]
    return feats, (on[1:] >= min_on_truth * count[1:])


def fit_calibration(
    features: NDArray[np.floating], labels: NDArray[np.bool_], ridge: float = 1e-3
) -> Calibration:
    """Logistic regression of ``labels`` (N,) on ``features`` (N, 2), features
    standardised for the fit, by L-BFGS on the mean log-loss plus ``ridge`` × |w|².

    Raises
    ------
    ValueError
        Fewer than ten components, or all of one label: nothing to calibrate on.
    """
    x = np.asarray(features, np.float64)
    y = np.asarray(labels, np.float64)
    if len(y) < 10 or y.min() == y.max():
        raise ValueError(
            f"calibration needs ten or more components of both kinds, got {len(y)} "
            f"({int(y.sum())} true)"
        )
    mu, sd = x.mean(axis=0), np.maximum(x.std(axis=0), 1e-9)
    z = (x - mu) / sd

    def loss(w: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        s = z @ w[:2] + w[2]
        p = expit(s)
        value = float(np.mean(np.logaddexp(0.0, s) - y * s) + ridge * (w[:2] @ w[:2]))
        g = p - y
        grad = np.concatenate([z.T @ g / len(y) + 2 * ridge * w[:2], [g.mean()]])
        return value, grad

    w = minimize(loss, np.zeros(3), jac=True, method="L-BFGS-B").x
    coef = w[:2] / sd
    return Calibration((float(coef[0]), float(coef[1])), float(w[2] - coef @ mu))


def calibrate(
    probability: Probability, holdout: dict[str, list[Sample]], threshold: float
) -> tuple[Calibration, dict[str, Any]]:
    """Fit the confidence on every held-back image of every set (``probability``: the
    network's map of an image); returns it with its record (components, share true,
    expected calibration error on the fit)."""
    feats, labels = [], []
    for samples in holdout.values():
        for s in samples:
            f, y = labelled_components(probability(s.gray), s.truth, threshold)
            feats.append(f)
            labels.append(y)
    if not feats:
        raise ValueError("calibration needs held-back images: sets of ten or more images")
    x, y = np.concatenate(feats), np.concatenate(labels)
    cal = fit_calibration(x, y)
    ece, _ = reliability(cal.confidence(x), y)
    return cal, {
        **cal.to_record(),
        "components": len(y),
        "true_share": round(float(y.mean()), 3),
        "ece_fit": ece,
    }


def store_calibration(path: Path, record: dict[str, Any]) -> None:
    """Write ``record`` as the ``calibration`` of the ONNX model at ``path`` (its other
    metadata kept)."""
    import onnx

    model = onnx.load(str(path))
    meta = {p.key: p.value for p in model.metadata_props}
    steelscan = json.loads(meta.get("steelscan", "{}"))
    steelscan["calibration"] = record
    del model.metadata_props[:]
    for key, value in {**meta, "steelscan": json.dumps(steelscan)}.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    tmp = path.with_suffix(".tmp.onnx")
    onnx.save(model, str(tmp))
    tmp.replace(path)


def calibrate_exported(
    path: Path, datasets: dict[str, list[Sample]], *, threads: int = 2, strict: bool = False
) -> dict[str, Any] | None:
    """Fit the per-defect confidence of the exported model at ``path`` (as it ships: int8
    logits differ from float ones) on the held-back images of ``datasets`` and store it in
    the model; returns the fit's record. Too few components to fit: a warning and None
    (``strict``: the ValueError)."""
    from processing.detection.learned import CrackModel

    hold = {name: split_holdout(samples)[1] for name, samples in datasets.items()}
    model = CrackModel(path, threads)
    try:
        _, record = calibrate(model.probability, hold, model.threshold)
    except ValueError as exc:  # too few components to say how sure
        if strict:
            raise
        log.warning("no confidence calibration: %s", exc)
        return None
    store_calibration(path, record)
    return record
