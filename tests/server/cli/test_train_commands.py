"""``steelscan train-detector`` in sittings (checkpoint, time budget, rendered steel) and
``steelscan calibrate-detector``, through the command line."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from processing.detection.learned import MODEL_PATH, CrackModel
from tests.processing.helpers import crack_dataset
from tests.server.helpers import steelscan

pytest.importorskip("torch")

TINY = ("--iterations", "3", "--batch", "2", "--channels", "4", "8", "8", "16", "16")


def test_a_run_resumes_from_its_checkpoint_and_refuses_other_options(tmp_path: Path) -> None:
    data = crack_dataset(tmp_path / "set", 6, 3)
    out, ckpt = tmp_path / "m.onnx", tmp_path / "run.pt"
    args = ("train-detector", str(data), "--out", str(out), "--checkpoint", str(ckpt))
    first = steelscan(*args, *TINY, "--synthetic-steel", "4", "--float")
    assert first.returncode == 0, first.stderr
    done = json.loads(first.stdout.splitlines()[-1])
    assert done["iterations_done"] == 3 and done["complete"] and ckpt.is_file()
    record = CrackModel(out).record
    assert record["datasets"] == {"set": 6, "steel-synthetic": 4}
    assert len(record["sittings"]) == 1 and record["data_hash"]
    again = steelscan(*args, *TINY, "--synthetic-steel", "4", "--float")
    assert again.returncode == 0, again.stderr
    assert len(CrackModel(out).record["sittings"]) == 2  # resumed: nothing left to do
    other = steelscan(*args, *TINY, "--float")  # without the rendered steel: other data
    assert other.returncode == 2 and "other data" in other.stderr
    assert "Traceback" not in other.stderr


def test_calibrating_a_model_with_too_little_data_is_a_clear_error(tmp_path: Path) -> None:
    model = tmp_path / "m.onnx"
    shutil.copy(MODEL_PATH, model)
    before = model.read_bytes()
    small = crack_dataset(tmp_path / "small", 4, 9)  # no image held back
    proc = steelscan("calibrate-detector", str(small), "--model", str(model))
    assert proc.returncode == 2 and "held-back images" in proc.stderr
    data = crack_dataset(tmp_path / "set", 12, 9)  # one image held back: a crack or two
    proc = steelscan("calibrate-detector", str(data), "--model", str(model))
    assert proc.returncode == 2 and "ten or more components" in proc.stderr
    assert model.read_bytes() == before  # the model is left as it was
    missing = steelscan("calibrate-detector", str(data), "--model", str(tmp_path / "no.onnx"))
    assert missing.returncode == 2 and "no such model file" in missing.stderr
