"""The ``learned`` crack detector: the shipped crack network run by ONNX Runtime on the CPU.

The model file (``processing/detection/models/crack_net.onnx``) is made by ``steelscan
train-detector`` (:mod:`processing.learning.train`); its metadata key ``steelscan`` holds
the training record, including the probability threshold chosen on held-back images.
Large images (mosaics) are run tile by tile with overlap; each tile contributes its core.
"""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from processing.detection.tiling import tile_core, tile_cores

MODEL_PATH = Path(__file__).parent / "models" / "crack_net.onnx"
_MULTIPLE = 32  # the network halves the resolution five times


@dataclass(frozen=True)
class LearnedParams:
    """Options of the learned detector: the model file, the probability threshold (None:
    the one stored with the model), tiling and threads."""

    model_path: Path = MODEL_PATH
    threshold: float | None = None
    tile_px: int = 2048
    overlap_px: int = 64
    threads: int = 2


class CrackModel:
    """An ONNX crack network: (H, W) uint8 grey → (H, W) crack probability."""

    def __init__(self, path: Path = MODEL_PATH, threads: int = 2) -> None:
        import onnxruntime as ort

        if not path.is_file():
            raise FileNotFoundError(
                f"crack model {path} not found (make it with `steelscan train-detector`)"
            )
        options = ort.SessionOptions()
        options.intra_op_num_threads = max(1, threads)
        options.inter_op_num_threads = 1
        self._session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        meta = self._session.get_modelmeta().custom_metadata_map
        self.record: dict[str, Any] = json.loads(meta.get("steelscan", "{}"))
        self.threshold = float(self.record.get("threshold", 0.5))
        self._input = self._session.get_inputs()[0].name
        self._lock = threading.Lock()

    def probability(self, gray: NDArray[np.uint8]) -> NDArray[np.float32]:
        """(H, W) probability of an (H, W) uint8 image run whole (mirror-padded to a
        multiple of 32)."""
        h, w = gray.shape
        x = gray.astype(np.float32) * np.float32(1 / 255)
        ph, pw = -h % _MULTIPLE, -w % _MULTIPLE
        if ph or pw:
            mode: Literal["reflect", "edge"] = "reflect" if h > ph and w > pw else "edge"
            x = np.pad(x, ((0, ph), (0, pw)), mode=mode)
        with self._lock:  # one run at a time: each already uses every thread it was given
            (logits,) = self._session.run(None, {self._input: x[None, None]})
        z = logits[0, 0, :h, :w]
        return (1.0 / (1.0 + np.exp(-z))).astype(np.float32)


@lru_cache(maxsize=4)
def load_model(path: Path = MODEL_PATH, threads: int = 2) -> CrackModel:
    """The model at ``path``, loaded once per process."""
    return CrackModel(path, threads)


def crack_probability(
    gray: NDArray[np.uint8], params: LearnedParams = LearnedParams()
) -> NDArray[np.float32]:
    """(H, W) crack probability of an (H, W) uint8 image of any size, tile by tile."""
    model = load_model(params.model_path, params.threads)
    tiles = tile_cores(gray.shape, params.tile_px, params.overlap_px)
    if len(tiles) == 1:
        return model.probability(gray)
    out = np.empty(gray.shape, np.float32)
    for rows, cols, cr, cc in tiles:
        out[tile_core(rows, cols, cr, cc)] = model.probability(gray[rows, cols])[cr, cc]
    return out


def learned_cracks(
    gray: NDArray[np.uint8], params: LearnedParams = LearnedParams()
) -> NDArray[np.bool_]:
    """(H, W) bool crack mask: probability above the model's threshold (or
    ``params.threshold``)."""
    return crack_probability(gray, params) > crack_threshold(params)


def crack_threshold(params: LearnedParams = LearnedParams()) -> float:
    """The probability above which a pixel is crack: ``params.threshold``, else the one
    stored with the model."""
    model = load_model(params.model_path, params.threads)
    return model.threshold if params.threshold is None else params.threshold
