"""A training run that outlives one sitting: its state saved every few minutes and resumed.

A checkpoint holds everything the next iteration depends on — the network, its moving
average, the optimiser and schedule, both random generators, the iteration — together
with the hash of the training data and the run's options. Resuming with other data or
other options is an error that names what differs, so that the hours spent on one run add
up to one model. Each sitting appends a segment (machine, threads, iterations, seconds) to
the run's record.
"""

from __future__ import annotations

import hashlib
import os
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from processing.learning.data import Sample

CHECKPOINT_FORMAT = "steelscan-crack-train/1"


def data_hash(datasets: dict[str, list[Sample]]) -> str:
    """SHA-256 (hex) of every set's name and every image's name, size, pixels and truth,
    in the order training draws from them: two runs with the same hash saw the same data
    in the same order."""
    h = hashlib.sha256()
    for name, samples in datasets.items():
        h.update(repr((name, len(samples))).encode())
        for s in samples:
            h.update(repr((s.name, s.gray.shape, s.truth.shape)).encode())
            h.update(np.ascontiguousarray(s.gray).tobytes())
            h.update(np.packbits(s.truth).tobytes())
    return h.hexdigest()


def machine() -> str:
    """The processor and system this sitting runs on, in one line."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    device = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    return f"{cpu}, {os.cpu_count()} logical CPUs, {device}, {platform.system()}"


@dataclass
class Segment:
    """One sitting of a run: where, how, how much."""

    machine: str
    threads: int
    started: str
    first_iteration: int
    iterations: int = 0
    seconds: float = 0.0


@dataclass
class RunState:
    """What a checkpoint restores besides the modules' own state dicts."""

    iteration: int = 0
    rng_state: dict[str, Any] = field(default_factory=dict)
    segments: list[Segment] = field(default_factory=list)

    @property
    def seconds(self) -> float:
        """Training time over all sittings."""
        return sum(s.seconds for s in self.segments)

    def begin(self, threads: int) -> Segment:
        """Start this sitting's segment."""
        seg = Segment(
            machine(), threads, time.strftime("%Y-%m-%dT%H:%M:%S%z"), first_iteration=self.iteration
        )
        self.segments.append(seg)
        return seg


def save_checkpoint(
    path: Path,
    *,
    modules: dict[str, Any],
    state: RunState,
    data: str,
    options: dict[str, Any],
) -> None:
    """Write the run atomically (a half-written file never replaces a good one).

    ``modules`` maps names to objects with ``state_dict()`` (network, average, optimiser,
    schedule); ``data`` is :func:`data_hash`; ``options`` the run's options as JSON values.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": CHECKPOINT_FORMAT,
        "data_hash": data,
        "options": options,
        "iteration": state.iteration,
        "rng_state": state.rng_state,
        "torch_rng": torch.get_rng_state(),
        "segments": [vars(s) for s in state.segments],
        "modules": {k: m.state_dict() for k, m in modules.items()},
    }
    tmp = path.with_name(path.name + ".partial")
    torch.save(payload, tmp)
    os.replace(tmp, path)


def load_checkpoint(
    path: Path, *, modules: dict[str, Any], data: str, options: dict[str, Any]
) -> RunState:
    """Restore ``modules`` from ``path`` and return the run's state.

    Raises
    ------
    ValueError
        The file is not a training checkpoint, or was made with other data or options
        (the message names them).
    """
    try:
        payload = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the same error to a user
        raise ValueError(f"{path}: not a readable training checkpoint ({exc})") from exc
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: not a steelscan training checkpoint")
    if payload["data_hash"] != data:
        raise ValueError(
            f"{path} was trained on other data (hash {payload['data_hash'][:12]}…, "
            f"these datasets {data[:12]}…): resume with the same datasets and --limit"
        )
    differ = sorted(
        k
        for k in set(options) | set(payload["options"])
        if options.get(k) != payload["options"].get(k)
    )
    if differ:
        raise ValueError(f"{path} was made with other options: {', '.join(differ)}")
    missing = sorted(set(modules) - set(payload.get("modules", {})))
    if missing:
        raise ValueError(f"{path} lacks the state of: {', '.join(missing)}")
    for name, module in modules.items():
        module.load_state_dict(payload["modules"][name])
    torch.set_rng_state(payload["torch_rng"])
    return RunState(
        iteration=int(payload["iteration"]),
        rng_state=payload["rng_state"],
        segments=[Segment(**s) for s in payload["segments"]],
    )
