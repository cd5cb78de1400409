"""Training of the crack network and its export to ONNX (``steelscan train-detector``).

The pipeline: crops drawn evenly from every training set and augmented
(:mod:`processing.learning.data`), Dice + binary cross-entropy (a loss that does not let
the 97 % background drown a one-pixel crack; the crack's centre line, faint stretches most,
weighted up), AdamW under a one-cycle schedule, fixed seeds, an exponential moving average
of the weights as the model (usable at any iteration); a run saved to a checkpoint and
resumed across sittings (:mod:`processing.learning.checkpoint`); then the probability
threshold that maximises the pooled 2-px-tolerant DSC on
images held back from every training set; then ONNX export with the threshold and the
training record stored in the model's metadata.
"""

from __future__ import annotations

import json
import logging
import time
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import NDArray
from torch.optim.swa_utils import AveragedModel

from processing.learning.calibration import calibrate_exported
from processing.learning.checkpoint import (
    RunState,
    data_hash,
    load_checkpoint,
    save_checkpoint,
)
from processing.learning.data import (
    AugmentParams,
    Sample,
    balanced_batch,
    load_dataset,
    split_holdout,
)
from processing.learning.network import CrackNet, NetworkParams, parameter_count
from processing.learning.quantize import calibration_crops, quantize_int8
from processing.metrics import PooledCounts

log = logging.getLogger(__name__)

MODEL_FORMAT = "steelscan-crack-net/1"


@dataclass(frozen=True)
class TrainParams:
    """Options of one training run."""

    iterations: int = 11000
    batch: int = 12
    learning_rate: float = 4e-3
    weight_decay: float = 1e-4
    dice_weight: float = 1.0
    centre_weight: float = 2.0
    ema_decay: float = 0.999
    seed: int = 0
    threads: int = 2
    augment: AugmentParams = field(default_factory=AugmentParams)
    network: NetworkParams = field(default_factory=NetworkParams)
    thresholds: tuple[float, ...] = tuple(np.round(np.arange(0.2, 0.81, 0.05), 2))
    tolerance_px: int = 2


def loss_fn(
    logits: torch.Tensor,
    truth: torch.Tensor,
    dice_weight: float,
    weight: torch.Tensor | None = None,
) -> torch.Tensor:
    """Binary cross-entropy (per-pixel ``weight``, default 1) plus ``dice_weight`` × (1 −
    soft Dice), the Dice taken per crop and averaged, so that a crop with a hairline weighs
    as much as one with a wide crack."""
    bce = F.binary_cross_entropy_with_logits(logits, truth, weight=weight)
    p = torch.sigmoid(logits)
    inter = (p * truth).sum(dim=(1, 2, 3))
    dice = (2 * inter + 1.0) / (p.sum(dim=(1, 2, 3)) + truth.sum(dim=(1, 2, 3)) + 1.0)
    return bce + dice_weight * (1.0 - dice.mean())


def _ema(decay: float) -> Callable[[torch.Tensor, torch.Tensor, torch.Tensor | int], torch.Tensor]:
    """The moving average's update with its decay warmed up, min(decay, (1 + n) / (10 + n))
    after n updates, so the first weights, still random, are soon forgotten."""

    def update(average: torch.Tensor, current: torch.Tensor, n: torch.Tensor | int) -> torch.Tensor:
        k = float(n)
        d = min(decay, (1.0 + k) / (10.0 + k))
        return average + (current - average) * (1.0 - d)

    return update


def predict(model: CrackNet, gray: NDArray[np.uint8]) -> NDArray[np.float32]:
    """(H, W) crack probability of an (H, W) uint8 image by the PyTorch model, padded by
    mirroring to a multiple of 32."""
    h, w = gray.shape
    ph, pw = -h % 32, -w % 32
    x = np.pad(gray.astype(np.float32) / 255.0, ((0, ph), (0, pw)), mode="reflect")
    with torch.no_grad():
        y = torch.sigmoid(model(torch.from_numpy(x)[None, None]))
    return y[0, 0, :h, :w].numpy()


def choose_threshold(
    model: CrackNet, holdout: dict[str, list[Sample]], params: TrainParams
) -> tuple[float, float]:
    """The probability threshold with the best tolerant DSC on ``holdout`` (pooled per set,
    then averaged over the sets, so that each set counts once), and that mean DSC."""
    counts = {
        (name, t): PooledCounts(params.tolerance_px) for name in holdout for t in params.thresholds
    }
    for name, samples in holdout.items():
        for s in samples:
            prob = predict(model, s.gray)
            for t in params.thresholds:
                counts[name, t].add(prob > t, s.truth)

    def mean_dsc(t: float) -> float:
        return float(np.mean([counts[name, t].scores().dsc for name in holdout]))

    best = max(params.thresholds, key=mean_dsc)
    return float(best), round(mean_dsc(best), 4)


def train(
    datasets: dict[str, list[Sample]],
    params: TrainParams = TrainParams(),
    *,
    checkpoint: Path | None = None,
    budget_s: float | None = None,
    sitting_iterations: int | None = None,
    checkpoint_every_s: float = 300.0,
) -> tuple[CrackNet, dict[str, Any]]:
    """Train a :class:`CrackNet` on ``datasets`` (name → samples); returns the model (the
    moving average of the weights, in eval mode) and its training record.

    With ``checkpoint``, the run resumes from that file when it exists and saves to it
    every ``checkpoint_every_s`` seconds and when it stops; ``budget_s`` stops this sitting
    after that many seconds of training (the record says ``complete: false`` until all
    ``params.iterations`` are done), ``sitting_iterations`` after that many iterations.
    The same iterations give the same model whether run in one sitting or several.
    """
    torch.manual_seed(params.seed)
    torch.set_num_threads(params.threads)
    rng = np.random.default_rng(params.seed)
    fit, hold = {}, {}
    for name, samples in datasets.items():
        if not samples:
            raise ValueError(f"dataset {name!r} has no images")
        f, h = split_holdout(samples)
        fit[name] = f or samples
        if h:
            hold[name] = h
    model = CrackNet(params.network)
    average = AveragedModel(model, avg_fn=_ema(params.ema_decay), use_buffers=True)
    opt = torch.optim.AdamW(
        model.parameters(), lr=params.learning_rate, weight_decay=params.weight_decay
    )
    sched = torch.optim.lr_scheduler.OneCycleLR(
        opt, max_lr=params.learning_rate, total_steps=max(params.iterations, 1), pct_start=0.1
    )
    modules = {"network": model, "average": average, "optimizer": opt, "schedule": sched}
    everything = _jsonable(asdict(params))
    assert isinstance(everything, dict)
    options = {k: v for k, v in everything.items() if k != "threads"}
    data = data_hash(datasets)
    state = RunState()
    if checkpoint is not None and checkpoint.exists():
        state = load_checkpoint(checkpoint, modules=modules, data=data, options=options)
        rng.bit_generator.state = state.rng_state
        log.info("resuming %s at iteration %d", checkpoint, state.iteration)
    segment = state.begin(params.threads)
    sets = list(fit.values())
    t0 = last_save = time.perf_counter()
    recent: list[float] = []

    def save() -> None:
        segment.seconds = round(time.perf_counter() - t0, 1)
        state.rng_state = dict(rng.bit_generator.state)
        if checkpoint is not None:
            save_checkpoint(checkpoint, modules=modules, state=state, data=data, options=options)

    model.train()
    while state.iteration < params.iterations:
        if budget_s is not None and time.perf_counter() - t0 >= budget_s:
            break
        if sitting_iterations is not None and segment.iterations >= sitting_iterations:
            break
        x, y, w = balanced_batch(sets, params.batch, rng, params.augment, params.centre_weight)
        loss = loss_fn(
            model(torch.from_numpy(x)),
            torch.from_numpy(y),
            params.dice_weight,
            torch.from_numpy(w),
        )
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        average.update_parameters(model)
        state.iteration += 1
        segment.iterations += 1
        recent = (recent + [loss.item()])[-100:]
        if state.iteration % 100 == 0:
            log.info(
                "iteration %d/%d loss %.4f (%.0f s)",
                state.iteration,
                params.iterations,
                float(np.mean(recent)),
                time.perf_counter() - t0,
            )
        if time.perf_counter() - last_save >= checkpoint_every_s:
            save()
            last_save = time.perf_counter()
    save()
    shipped = average.module
    assert isinstance(shipped, CrackNet)
    shipped.eval()
    threshold, holdout_dsc = choose_threshold(shipped, hold, params) if hold else (0.5, 0.0)
    record = {
        "format": MODEL_FORMAT,
        "datasets": {k: len(v) for k, v in datasets.items()},
        "data_hash": data,
        "holdout_images": {k: len(v) for k, v in hold.items()},
        "threshold": threshold,
        "holdout_dsc_tol": holdout_dsc,
        "final_loss": round(float(np.mean(recent)), 4) if recent else None,
        "parameters": parameter_count(shipped),
        "iterations_done": state.iteration,
        "complete": state.iteration >= params.iterations,
        "train_seconds": round(state.seconds, 1),
        "sittings": [vars(s) for s in state.segments],
        "params": _jsonable(asdict(params)),
        "torch": torch.__version__,
    }
    return shipped, record


def _jsonable(value: object) -> object:
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def export_onnx(model: CrackNet, record: dict[str, Any], path: Path) -> None:
    """Write ``model`` as ONNX (opset 17, any even height and width) with ``record`` as
    JSON in the metadata key ``steelscan``."""
    import onnx

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.onnx")
    with warnings.catch_warnings():  # the exporter's notices of its own deprecations
        warnings.simplefilter("ignore")
        torch.onnx.export(
            model.eval(),
            (torch.zeros(1, 1, 64, 64),),
            str(tmp),
            input_names=["image"],
            output_names=["logits"],
            dynamic_axes={"image": {0: "batch", 2: "height", 3: "width"}, "logits": {0: "batch"}},
            opset_version=17,
            dynamo=False,
        )
    proto = onnx.load(str(tmp))
    entry = proto.metadata_props.add()
    entry.key, entry.value = "steelscan", json.dumps(record)
    onnx.save(proto, str(path))
    tmp.unlink()


def export_model(
    model: CrackNet,
    record: dict[str, Any],
    path: Path,
    datasets: dict[str, list[Sample]],
    int8: bool,
) -> None:
    """Export as ONNX; with ``int8``, quantized (calibrated on crops of up to eight images
    of each dataset) — what the station ships."""
    if not int8:
        export_onnx(model, record, path)
        return
    float_path = path.with_suffix(".float.onnx")
    try:
        export_onnx(model, record, float_path)
        images = [s.gray for samples in datasets.values() for s in samples[:8]]
        quantize_int8(float_path, path, calibration_crops(images))
    finally:
        float_path.unlink(missing_ok=True)


def train_from_folders(
    roots: list[Path],
    out: Path,
    params: TrainParams = TrainParams(),
    limit: int | None = None,
    int8: bool = True,
    *,
    extra: dict[str, list[Sample]] | None = None,
    checkpoint: Path | None = None,
    budget_s: float | None = None,
) -> dict[str, Any]:
    """Load each dataset folder (and the ``extra`` sets, e.g. rendered ones), train (see
    :func:`train` for ``checkpoint`` and ``budget_s``), export to ``out`` (int8 unless not
    ``int8``); returns the training record."""
    datasets = {r.name: load_dataset(r, limit) for r in roots} | (extra or {})
    model, record = train(datasets, params, checkpoint=checkpoint, budget_s=budget_s)
    export_model(model, record, out, datasets, int8)
    record["calibration"] = calibrate_exported(out, datasets)
    return record


def leave_one_out(
    roots: list[Path],
    out_dir: Path,
    params: TrainParams = TrainParams(),
    limit: int | None = None,
    int8: bool = True,
) -> dict[str, dict[str, Any]]:
    """One model per dataset, trained on all the others: ``out_dir/<left-out name>.onnx``
    (for scoring each set with a model that never saw it). Returns the records by name."""
    if len(roots) < 2:
        raise ValueError("leave-one-out needs at least two datasets")
    datasets = {r.name: load_dataset(r, limit) for r in roots}
    records = {}
    for left in datasets:
        log.info("training without %s", left)
        model, record = train({k: v for k, v in datasets.items() if k != left}, params)
        record["left_out"] = left
        kept = {k: v for k, v in datasets.items() if k != left}
        export_model(model, record, out_dir / f"{left}.onnx", kept, int8)
        record["calibration"] = calibrate_exported(out_dir / f"{left}.onnx", kept)
        records[left] = record
    return records
