"""robot.toml: the documented example loads; a misspelt key or a wrong value is refused
with its name before any device is opened."""

from __future__ import annotations

from pathlib import Path

import pytest

from robot_link.agent.config import ConfigError, load_config

EXAMPLE = Path(__file__).resolve().parents[3] / "docs" / "robot.toml"


def test_the_documented_example_loads() -> None:
    cfg = load_config(EXAMPLE)
    assert cfg.mcu.device and cfg.station.url.startswith("http")
    assert cfg.safety.deadman_s == pytest.approx(0.2)


@pytest.mark.parametrize(
    "text,words",
    [
        (
            "[station]\nurl='http://x'\ntoken='t'\n[mcu]\ndevice='/dev/x'\n[camera]\nsource=0\n"
            "[tof]\nsource='emulator'\n[safety]\ndeadman='0.2'\n",
            "safety.deadman",
        ),
        (
            "[station]\nurl='http://x'\n[mcu]\ndevice='/dev/x'\n[camera]\nsource=0\n"
            "[tof]\nsource='emulator'\n",
            "station.token",
        ),
        ("[station\n", "not valid TOML"),
    ],
)
def test_a_bad_config_names_its_problem(tmp_path: Path, text: str, words: str) -> None:
    path = tmp_path / "robot.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=words):
        load_config(path)
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.toml")
