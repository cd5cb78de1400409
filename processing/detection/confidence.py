"""How sure the network is of each crack it found: a calibrated confidence per defect.

A found crack is one connected component of the probability map above the model's
threshold. Two numbers say how sure the network is of it: the mean logit of its pixels
(how far above the threshold the whole component lies, not only its best pixel) and the
log of its pixel count (a speck is more often texture than a long crack). A logistic
model of the two (Platt scaling) turns them into the probability that the component is a
true crack, fitted on images held back from training
(:func:`processing.learning.calibration.fit_calibration`) and stored in the model's
record, so a reviewer can trust "0.9" to mean nine in ten.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import expit

FEATURES = ("mean_logit", "log_pixels")
LOGIT_RANGE = 8.0  # logits are taken within ±8 (probabilities 0.0003 … 0.9997)
_CODE_STEPS = 255 / (2 * LOGIT_RANGE)  # codes 0 … 255 span -8 … +8 exactly


def logit_code(probability: NDArray[np.floating]) -> NDArray[np.uint8]:
    """(H, W) uint8 code of a probability map's logits (255 steps over ±8), for bands of a
    mosaic stored on disk; :func:`probability_of_code` reverses it."""
    z = _logit(probability)
    return np.clip(np.rint((z + LOGIT_RANGE) * _CODE_STEPS), 0, 255).astype(np.uint8)


def probability_of_code(code: NDArray[np.uint8]) -> NDArray[np.float32]:
    """(H, W) probability of :func:`logit_code`'s codes."""
    z = code.astype(np.float32) / _CODE_STEPS - LOGIT_RANGE
    return expit(z).astype(np.float32)


def _logit(probability: NDArray[np.floating]) -> NDArray[np.float64]:
    """Logits of a probability map, within ±:data:`LOGIT_RANGE`."""
    p = np.clip(probability.astype(np.float64), 1e-12, 1 - 1e-12)
    return np.clip(np.log(p) - np.log1p(-p), -LOGIT_RANGE, LOGIT_RANGE)


def component_features(
    probability: NDArray[np.floating], labels: NDArray[np.integer], n: int
) -> NDArray[np.float64]:
    """(n, 2) features of the components ``1 … n - 1`` of ``labels`` ((H, W), 0 the
    background) on an (H, W) ``probability`` map: mean logit of their pixels and log of
    their pixel count (row 0, the background, is zeros)."""
    if probability.shape != labels.shape:
        raise ValueError(f"probability {probability.shape} and labels {labels.shape} differ")
    logit = _logit(probability)
    flat = labels.ravel()
    count = np.bincount(flat, minlength=n)[:n].astype(np.float64)
    total = np.bincount(flat, weights=logit.ravel(), minlength=n)[:n]
    out = np.zeros((n, 2))
    has = count > 0
    out[has, 0] = total[has] / count[has]
    out[has, 1] = np.log(count[has])
    out[0] = 0.0
    return out


@dataclass(frozen=True)
class Calibration:
    """P(true crack) = σ(coef · features + intercept), features :data:`FEATURES`."""

    coef: tuple[float, float]
    intercept: float

    @classmethod
    def from_record(cls, record: dict[str, Any]) -> Calibration | None:
        """The calibration stored in a model's training record (None if it has none)."""
        c = record.get("calibration")
        if not isinstance(c, dict) or c.get("features") != list(FEATURES):
            return None
        return cls((float(c["coef"][0]), float(c["coef"][1])), float(c["intercept"]))

    def to_record(self) -> dict[str, Any]:
        """JSON form for the model's record."""
        return {
            "features": list(FEATURES),
            "coef": [round(v, 6) for v in self.coef],
            "intercept": round(self.intercept, 6),
        }

    def confidence(self, features: NDArray[np.floating]) -> NDArray[np.float64]:
        """(N,) probability that each of (N, 2) ``features`` is a true crack."""
        z = np.asarray(features, np.float64) @ np.asarray(self.coef) + self.intercept
        return np.asarray(expit(z), np.float64)


def reliability(
    confidence: NDArray[np.floating], correct: NDArray[np.bool_], bins: int = 10
) -> tuple[float, list[dict[str, float]]]:
    """Expected calibration error (the gap between stated confidence and the share found
    true, weighted by how many fall in each of ``bins`` equal bins of confidence) and the
    reliability diagram's rows (bin, count, mean confidence, share true)."""
    conf = np.asarray(confidence, np.float64)
    ok = np.asarray(correct, bool)
    if conf.shape != ok.shape:
        raise ValueError(f"confidence {conf.shape} and correct {ok.shape} differ")
    if conf.size == 0:
        return 0.0, []
    which = np.minimum((conf * bins).astype(int), bins - 1)
    ece, rows = 0.0, []
    for b in range(bins):
        sel = which == b
        if not sel.any():
            continue
        gap = abs(float(conf[sel].mean()) - float(ok[sel].mean()))
        ece += gap * sel.sum() / conf.size
        rows.append(
            {
                "bin": round(b / bins, 2),
                "count": int(sel.sum()),
                "confidence": round(float(conf[sel].mean()), 3),
                "true": round(float(ok[sel].mean()), 3),
            }
        )
    return round(ece, 4), rows
