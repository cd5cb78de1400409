"""The code is kept to the project's lint rules and formatted at the declared line length."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _ruff(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ruff", *args], cwd=ROOT, capture_output=True, text=True, timeout=120
    )


def test_ruff_finds_nothing() -> None:
    out = _ruff("check", ".")
    assert out.returncode == 0, out.stdout + out.stderr


def test_the_code_is_formatted() -> None:
    out = _ruff("format", "--check", ".")
    assert out.returncode == 0, out.stdout + out.stderr


def test_the_dashboard_is_formatted_and_lint_clean() -> None:
    # Biome (web/biome.jsonc) formats and lints the dashboard's modules; npm ci installs it
    biome = ROOT / "web" / "node_modules" / ".bin" / "biome"
    assert biome.exists(), f"{biome} is missing: run scripts/setup.sh (npm ci in web/)"
    out = subprocess.run(
        [str(biome), "check", "--error-on-warnings", "--colors=off", "--max-diagnostics=none"],
        cwd=ROOT / "web",
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stdout + out.stderr
