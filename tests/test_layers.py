"""Imports go one way: no stage of the data flow imports a later one (docs/architecture.md),
checked over every module, imports inside functions included."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# what each part may import of the project (its own modules always)
ALLOWED = {
    "processing": set(),
    "robot_link": {"processing"},
    "server.storage": {"server.config", "server.errors"},
    "server.process": set(),
    "server.link": {"server.storage", "server.errors", "server.limits", "server.tokens"},
    "server.reports": {"server.storage", "server.errors", "processing", "robot_link"},
    "server.jobs": {
        "server.storage",
        "server.config",
        "server.process",
        "server.reports",
        "server.link",
    },
    "server.live": {"server.link", "server.storage", "server.process", "server.reports"},
    "server.limits": set(),
}
STAGES = {"server.storage", "server.link", "server.jobs", "server.live", "server.reports"}


def _imports(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
        elif isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
    return names


def _part(module: str) -> str | None:
    for part in sorted(ALLOWED, key=len, reverse=True):
        if module == part or module.startswith(part + "."):
            return part
    return None


def test_no_stage_imports_a_later_one() -> None:
    wrong = []
    for folder in ("processing", "robot_link", "server"):
        for path in (ROOT / folder).rglob("*.py"):
            module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            part = _part(module)
            if part is None:
                continue
            for name in _imports(path):
                if name.split(".")[0] not in ("processing", "robot_link", "server", "bench"):
                    continue
                target = _part(name) or ".".join(name.split(".")[:2])
                if target == part or name == part or name.startswith(part + "."):
                    continue
                allowed = ALLOWED[part] | (
                    {"processing", "robot_link", "server.config", "server.errors"}
                    if part in STAGES
                    else set()
                )
                if not any(name == a or name.startswith(a + ".") for a in allowed):
                    wrong.append(f"{module} imports {name}")
    assert wrong == [], "\n".join(sorted(wrong))


def test_the_station_never_imports_the_benchmarks() -> None:
    for path in (ROOT / "server").rglob("*.py"):
        assert not any(n.split(".")[0] == "bench" for n in _imports(path)), path
