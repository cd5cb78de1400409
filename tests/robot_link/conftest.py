"""The MCU emulator as a process on its pseudo-terminal, its true states read as they come."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest


@dataclass
class EmulatorProcess:
    """A running ``steelscan mcu-emulator``: its device, header and the states so far, each
    with the monotonic time it was read."""

    proc: subprocess.Popen[str]
    device: str
    header: dict[str, Any]
    states: list[tuple[float, dict[str, Any]]] = field(default_factory=list)

    def latest(self) -> dict[str, Any]:
        """The newest state."""
        return self.states[-1][1]

    def wait_for(
        self, predicate: Callable[[dict[str, Any]], bool], timeout_s: float = 10.0
    ) -> dict[str, Any]:
        """The first state from now on for which ``predicate`` holds."""
        start = len(self.states)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for _, s in self.states[start:]:
                if predicate(s):
                    return s
            time.sleep(0.02)
        raise AssertionError(f"no such state within {timeout_s} s; last {self.latest()}")

    def signal(self, sig: int) -> None:
        """Send ``sig`` (SIGUSR1: fall silent/speak, SIGUSR2: garble/stop garbling)."""
        self.proc.send_signal(sig)


def start_emulator(*args: str) -> EmulatorProcess:
    """Start the emulator and read its first two lines."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "server.cli", "mcu-emulator", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    assert proc.stdout is not None
    first = proc.stdout.readline()
    assert first.startswith("pty: "), first
    emu = EmulatorProcess(proc, first.split(" ", 1)[1].strip(), json.loads(proc.stdout.readline()))

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            emu.states.append((time.monotonic(), json.loads(line)))

    threading.Thread(target=read, daemon=True).start()
    deadline = time.monotonic() + 10
    while not emu.states and time.monotonic() < deadline:
        time.sleep(0.02)
    return emu


@pytest.fixture
def emulator_factory() -> Iterator[Callable[..., EmulatorProcess]]:
    started: list[EmulatorProcess] = []

    def make(*args: str) -> EmulatorProcess:
        emu = start_emulator(*args)
        started.append(emu)
        return emu

    yield make
    for emu in started:
        emu.proc.send_signal(signal.SIGTERM)
        try:
            emu.proc.wait(10)
        except subprocess.TimeoutExpired:
            emu.proc.kill()


@pytest.fixture
def emulator(emulator_factory: Callable[..., EmulatorProcess]) -> EmulatorProcess:
    return emulator_factory("--seed", "5", "--plate", "0.9x0.7")
