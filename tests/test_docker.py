"""The container files, checked without a Docker engine: the compose file against the
Compose specification's schema, and everything the files run against the project itself
(the commands exist, the settings are ours, the copied paths are there)."""

from __future__ import annotations

import json
import re
import shlex
from importlib import resources
from pathlib import Path

import jsonschema
import yaml

from bench.scale import POSTGRES_REALTIME, STATION_REALTIME
from server.cli.main import build_parser
from server.config import Settings

ROOT = Path(__file__).resolve().parent.parent
COMPOSE = ROOT / "docker" / "compose.yaml"
DOCKERFILE = ROOT / "docker" / "Dockerfile"


def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def test_the_compose_file_follows_the_compose_specification() -> None:
    schema = json.loads(
        resources.files("check_jsonschema")
        .joinpath("builtin_schemas/vendor/compose-spec.json")
        .read_text()
    )
    jsonschema.validate(compose(), schema)


def test_station_workers_and_services_with_health_checks_and_named_volumes() -> None:
    c = compose()
    services = c["services"]
    assert set(services) == {"station", "worker", "postgres", "redis"}
    assert all("healthcheck" in s for s in services.values())
    for s in services.values():
        for volume in s.get("volumes", []):
            assert volume.split(":")[0] in c["volumes"], volume  # named, not host folders
    assert services["worker"]["volumes"] == services["station"]["volumes"]  # one data dir
    assert services["worker"]["deploy"]["replicas"] >= 2
    assert services["worker"]["depends_on"]["station"]["condition"] == "service_healthy"
    assert services["station"]["image"] == services["worker"]["image"]  # one image


def test_the_station_and_its_database_run_at_the_priorities_the_benchmark_measured() -> None:
    services = compose()["services"]
    station, postgres = services["station"], services["postgres"]
    assert station["environment"]["STEELSCAN_REALTIME_PRIORITY"] == str(STATION_REALTIME)
    assert postgres["entrypoint"][:3] == ["chrt", "--rr", str(POSTGRES_REALTIME)]
    assert postgres["command"] == ["postgres"]  # an entrypoint given clears the image's command
    assert 0 < POSTGRES_REALTIME < STATION_REALTIME
    for s in (station, postgres):
        assert "SYS_NICE" in s["cap_add"]
    assert "cap_add" not in services["worker"]  # workers stay below both


def test_what_the_containers_run_is_ours() -> None:
    c = compose()
    fields = set(Settings.model_fields)
    parser = build_parser()
    for name in ("station", "worker"):
        s = c["services"][name]
        env = s["environment"]
        for key in env:
            assert key.startswith("STEELSCAN_") and key.removeprefix("STEELSCAN_").lower() in fields
        assert env["STEELSCAN_JOB_BACKEND"] == "celery"
        assert env["STEELSCAN_DATABASE_URL"].startswith("postgresql+psycopg://")
        Settings(**{k.removeprefix("STEELSCAN_").lower(): v for k, v in env.items()})
        for command in (s["command"], s["healthcheck"]["test"][1:]):
            if command[0] == "steelscan":
                parser.parse_args(command[1:])  # exits on an unknown command or option
    cmd = re.search(r"^CMD (\[.*\])$", DOCKERFILE.read_text(), re.M)
    assert cmd is not None
    parser.parse_args(json.loads(cmd.group(1))[1:])


def test_the_dockerfile_copies_what_exists() -> None:
    for line in DOCKERFILE.read_text().splitlines():
        if line.startswith("COPY ") and "--from" not in line:
            for src in shlex.split(line)[1:-1]:
                assert (ROOT / src).exists(), src
    readme = (ROOT / "README.md").read_text()
    for command in ("up -d --build", "create-user", "create-robot"):
        assert "docker compose -f docker/compose.yaml" in readme and command in readme
