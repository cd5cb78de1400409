"""A training run saved and resumed: the same model as one sitting, and no resuming with
other data or options."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.processing.helpers import textured_plate

torch = pytest.importorskip("torch")

from processing.learning.data import AugmentParams, Sample  # noqa: E402
from processing.learning.network import NetworkParams  # noqa: E402
from processing.learning.train import TrainParams, train  # noqa: E402

PARAMS = TrainParams(
    iterations=6,
    batch=2,
    threads=1,
    centre_weight=2.0,
    ema_decay=0.5,  # the average follows the weights closely: a broken resume shows
    augment=AugmentParams(crop_px=64),
    network=NetworkParams(channels=(4, 8, 8, 16, 16)),
)


def _sets(seed: int = 0) -> dict[str, list[Sample]]:
    out = {}
    for name, base in (("a", seed), ("b", seed + 100)):
        samples = []
        for i in range(10):
            gray, truth = textured_plate((96, 128), base + i, width=2, depth=50)
            samples.append(Sample(f"{i:03d}.png", gray, truth))
        out[name] = samples
    return out


def _weights(model: torch.nn.Module) -> list[np.ndarray]:
    return [v.detach().numpy().copy() for v in model.state_dict().values()]


def test_a_run_in_two_sittings_gives_the_model_of_one(tmp_path: Path) -> None:
    sets = _sets()
    whole_ckpt = tmp_path / "whole.pt"
    whole, whole_record = train(sets, PARAMS, checkpoint=whole_ckpt)
    ckpt = tmp_path / "run.pt"
    _, first = train(sets, PARAMS, checkpoint=ckpt, sitting_iterations=4)
    assert first["iterations_done"] == 4 and not first["complete"]
    resumed, second = train(sets, PARAMS, checkpoint=ckpt)
    assert second["iterations_done"] == 6 and second["complete"]
    assert [s["iterations"] for s in second["sittings"]] == [4, 2]
    assert second["data_hash"] == whole_record["data_hash"]
    for a, b in zip(_weights(whole), _weights(resumed), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    raw = [torch.load(p, weights_only=False)["modules"]["network"] for p in (whole_ckpt, ckpt)]
    for k, v in raw[0].items():  # the weights themselves, not only their average
        np.testing.assert_allclose(v.numpy(), raw[1][k].numpy(), rtol=1e-5, atol=1e-6)
    again, third = train(sets, PARAMS, checkpoint=ckpt)  # already complete: nothing more
    assert third["iterations_done"] == 6 and third["sittings"][-1]["iterations"] == 0


def test_resuming_with_other_data_or_options_is_refused(tmp_path: Path) -> None:
    ckpt = tmp_path / "run.pt"
    train(_sets(), PARAMS, checkpoint=ckpt, sitting_iterations=2)
    before = ckpt.read_bytes()
    with pytest.raises(ValueError, match="other data"):
        train(_sets(seed=1), PARAMS, checkpoint=ckpt)
    other = TrainParams(**{**PARAMS.__dict__, "learning_rate": 1e-3})
    with pytest.raises(ValueError, match="learning_rate"):
        train(_sets(), other, checkpoint=ckpt)
    assert ckpt.read_bytes() == before  # a refused resume leaves the run as it was
    # the thread count is the machine's, not the run's: resuming with another is fine
    _, record = train(_sets(), TrainParams(**{**PARAMS.__dict__, "threads": 2}), checkpoint=ckpt)
    assert record["complete"]


def test_a_file_that_is_not_a_checkpoint_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "run.pt"
    bad.write_bytes(b"\x00not a checkpoint")
    with pytest.raises(ValueError, match="not a readable training checkpoint"):
        train(_sets(), PARAMS, checkpoint=bad)
    torch.save({"format": "something else"}, bad)
    with pytest.raises(ValueError, match="not a steelscan training checkpoint"):
        train(_sets(), PARAMS, checkpoint=bad)
