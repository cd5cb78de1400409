"""The shipped crack network: what it is, that ONNX Runtime runs it as PyTorch does, that
tiles leave no seams, that it finds hairlines, and that the training script makes a model."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from processing.detection.learned import (
    MODEL_PATH,
    CrackModel,
    LearnedParams,
    crack_probability,
    load_model,
)
from tests.processing.helpers import crack_dataset, textured_plate
from tests.server.helpers import steelscan


def test_shipped_model_is_small_and_carries_its_threshold_and_training_record() -> None:
    assert MODEL_PATH.is_file()
    assert MODEL_PATH.stat().st_size <= 10 * 1024 * 1024
    record = load_model().record
    assert record["format"] == "steelscan-crack-net/1"
    assert record["parameters"] <= 10_000_000
    assert 0.0 < record["threshold"] < 1.0
    assert len(record["datasets"]) >= 2  # trained on more than one kind of surface
    from processing.detection.confidence import Calibration

    assert Calibration.from_record(record) is not None  # each defect gets a confidence


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_hairline_cracks_on_textured_paint_are_found(seed: int) -> None:
    from processing.detection import detect_cracks

    gray, truth = textured_plate((320, 480), seed, width=1, depth=35)
    mask = detect_cracks(gray, method="learned")
    near = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    recall = (near & truth).sum() / truth.sum()
    near_truth = cv2.dilate(truth.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    precision = (mask & near_truth).sum() / max(mask.sum(), 1)
    assert recall > 0.6, recall
    assert precision > 0.5, precision


def test_a_plain_plate_has_no_cracks() -> None:
    rng = np.random.default_rng(2)
    gray = np.clip(rng.normal(140, 4, (256, 384)), 0, 255).astype(np.uint8)
    from processing.detection import detect_cracks

    assert detect_cracks(gray, method="learned").sum() < 0.001 * gray.size


def test_tiles_leave_no_seams() -> None:
    gray, _ = textured_plate((700, 900), 5, width=2, depth=40)
    whole = crack_probability(gray, LearnedParams(tile_px=4096))
    tiled = crack_probability(gray, LearnedParams(tile_px=320, overlap_px=64))
    assert np.abs(whole - tiled).max() < 0.1
    t = load_model().threshold
    assert ((whole > t) ^ (tiled > t)).sum() <= 0.01 * max((whole > t).sum(), 1)


def test_odd_and_tiny_images_keep_their_shape() -> None:
    for shape in [(5, 7), (33, 65), (384, 545)]:
        gray = np.full(shape, 120, np.uint8)
        assert crack_probability(gray).shape == shape


def test_a_missing_model_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="train-detector"):
        CrackModel(tmp_path / "none.onnx")


def test_training_script_makes_a_model_onnx_runtime_runs_as_pytorch_does(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    from processing.learning.data import AugmentParams, load_dataset
    from processing.learning.network import NetworkParams
    from processing.learning.train import TrainParams, export_onnx, predict, train

    sets = {
        name: load_dataset(crack_dataset(tmp_path / name, 12, seed))
        for name, seed in (("a", 0), ("b", 100))
    }
    params = TrainParams(
        iterations=4,
        batch=2,
        augment=AugmentParams(crop_px=64),
        network=NetworkParams(channels=(4, 8, 8, 16, 16)),
    )
    model, record = train(sets, params)
    assert record["datasets"] == {"a": 12, "b": 12}
    assert record["threshold"] in params.thresholds
    out = tmp_path / "m.onnx"
    export_onnx(model, record, out)
    onnx_model = CrackModel(out, threads=1)
    assert onnx_model.record["threshold"] == record["threshold"]
    gray = sets["a"][0].gray
    torch.manual_seed(0)
    np.testing.assert_allclose(onnx_model.probability(gray), predict(model, gray), atol=1e-4)
    from processing.learning.quantize import calibration_crops, quantize_int8

    quantize_int8(out, tmp_path / "q.onnx", calibration_crops([s.gray for s in sets["b"]]))
    int8 = CrackModel(tmp_path / "q.onnx", threads=1)
    assert int8.record["threshold"] == record["threshold"] and "quantized" in int8.record
    np.testing.assert_allclose(int8.probability(gray), onnx_model.probability(gray), atol=0.05)


def test_train_detector_command_trains_and_detect_uses_the_result(tmp_path: Path) -> None:
    pytest.importorskip("torch")

    data = crack_dataset(tmp_path / "set", 6, 7)
    out = tmp_path / "model.onnx"
    proc = steelscan(
        "train-detector", str(data), "--out", str(out), "--iterations", "2", "--batch", "2"
    )
    assert proc.returncode == 0, proc.stderr
    assert "threshold" in json.loads(proc.stdout.splitlines()[-1])
    assert CrackModel(out).record["datasets"] == {"set": 6}
    assert CrackModel(out).record["quantized"]["calibration_crops"] == 6  # shipped as int8
    bad = steelscan("train-detector", str(tmp_path), "--out", str(out))
    assert bad.returncode == 2 and "not a dataset folder" in bad.stderr


SHARED = Path(__file__).resolve().parents[4] / "shared" / "datasets"


@pytest.mark.parametrize(
    "name",
    [
        pytest.param(n, marks=pytest.mark.skipif(not (SHARED / n).is_dir(), reason="set absent"))
        for n in ("cracksc", "uav75")
    ],
)
def test_thin_crack_photographs_get_masks_that_beat_sauvola(name: str) -> None:
    from processing.detection import detect_cracks
    from processing.learning.data import load_dataset
    from processing.metrics import PooledCounts

    samples = load_dataset(SHARED / name)[::10]
    ours, sauvola, empty = PooledCounts(2), PooledCounts(2), 0
    for s in samples:
        mask = detect_cracks(s.gray, method="learned")
        empty += int(s.truth.any() and not mask.any())
        ours.add(mask, s.truth)
        sauvola.add(detect_cracks(s.gray, method="sauvola"), s.truth)
    assert empty <= len(samples) // 10
    assert ours.scores().si > 0.4
    assert ours.scores().dsc > 1.5 * sauvola.scores().dsc
