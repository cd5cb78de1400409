"""The MCU emulator as a child process (``steelscan mcu-emulator``), its true states read as
they come, each with the monotonic time it arrived: for tests and benchmarks that judge a
robot from the outside, as an acceptance check does."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any


@dataclass
class EmulatorProcess:
    """A running emulator: its serial device, header, and the states so far."""

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
        """The first state from now on for which ``predicate`` holds; AssertionError after
        ``timeout_s``."""
        start = len(self.states)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for _, s in self.states[start:]:
                if predicate(s):
                    return s
            time.sleep(0.02)
        raise AssertionError(f"no such state within {timeout_s} s; last {self.latest()}")

    def signal(self, sig: int) -> None:
        """Send ``sig`` (SIGUSR1: fall silent or speak again, SIGUSR2: garble or stop)."""
        self.proc.send_signal(sig)

    def stop(self) -> None:
        """SIGTERM, then wait (kill after 10 s)."""
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def start_emulator(*args: str, timeout_s: float = 60.0) -> EmulatorProcess:
    """Start ``steelscan mcu-emulator ARGS`` and wait for its first state."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "server.cli", "mcu-emulator", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    assert proc.stdout is not None
    first = proc.stdout.readline()
    if not first.startswith("pty: "):
        proc.kill()
        raise RuntimeError(f"the MCU emulator did not start: {first!r}")
    emu = EmulatorProcess(proc, first.split(" ", 1)[1].strip(), json.loads(proc.stdout.readline()))

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            emu.states.append((time.monotonic(), json.loads(line)))

    threading.Thread(target=read, name="mcu-emulator-states", daemon=True).start()
    deadline = time.monotonic() + timeout_s
    while not emu.states and time.monotonic() < deadline:
        time.sleep(0.02)
    return emu
