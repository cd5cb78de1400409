"""The MCU emulator as a process on its pseudo-terminal (:mod:`robot_link.emulator.process`)."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest

from robot_link.emulator.process import EmulatorProcess, start_emulator


@pytest.fixture
def emulator_factory() -> Iterator[Callable[..., EmulatorProcess]]:
    started: list[EmulatorProcess] = []

    def make(*args: str) -> EmulatorProcess:
        emu = start_emulator(*args)
        started.append(emu)
        return emu

    yield make
    for emu in started:
        emu.stop()


@pytest.fixture
def emulator(emulator_factory: Callable[..., EmulatorProcess]) -> EmulatorProcess:
    return emulator_factory("--seed", "5", "--plate", "0.9x0.7")
