"""``steelscan`` commands on the sessions of a data directory: ``import``, ``export`` and
``report``; and the settings every command reads from its arguments."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from server.config import Settings
from server.errors import CommandError


def settings_from_args(args: argparse.Namespace) -> Settings:
    """The settings, with the data directory and TLS files given on the command line."""
    overrides = {}
    if getattr(args, "data_dir", None):
        overrides["data_dir"] = Path(args.data_dir)
    for name in ("tls_cert", "tls_key"):
        if getattr(args, name, None):
            overrides[name] = Path(getattr(args, name))
    try:
        return Settings(**overrides)
    except ValueError as exc:
        raise CommandError(str(exc)) from None


def _database(args: argparse.Namespace) -> tuple[Any, Any]:
    """(sessionmaker, SessionFiles) of the data directory, migrated to head."""
    from server.storage.db import make_engine, make_sessionmaker, upgrade
    from server.storage.files import SessionFiles

    settings = settings_from_args(args)
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    url = settings.resolved_database_url()
    upgrade(url)
    return make_sessionmaker(make_engine(url)), SessionFiles(settings.data_dir)


def cmd_import(args: argparse.Namespace) -> int:
    """Import an MCAP session log into a new session; prints its id and counts as JSON."""
    from server.reports.mcap_import import McapImportError, import_session

    path = Path(args.file)
    if not path.is_file():
        raise CommandError(f"{path}: no such file")
    factory, files = _database(args)
    with factory() as db:
        try:
            result = import_session(db, files, path)
        except McapImportError as exc:
            raise CommandError(str(exc)) from None
    settings = settings_from_args(args)
    if settings.auto_process:  # queued as for a session that ends: the station runs them
        result["jobs"] = _job_runner(factory, settings).enqueue_pipeline(result["session_id"])
    print(json.dumps(result))
    return 0


def _job_runner(factory: Any, settings: Any) -> Any:
    """A job runner that only queues (the station's dispatcher runs what it queues)."""
    from server.jobs.runner import JobRunner

    return JobRunner(
        factory,
        settings.resolved_database_url(),
        str(settings.data_dir.resolve()),
        0,
        defaults={"detect": {"method": settings.detect_method}},
    )


def _session_id(factory: Any, session_id: str) -> str:
    from server.storage.models import InspectionSession

    with factory() as db:
        if db.get(InspectionSession, session_id) is None:
            raise CommandError(f"no session {session_id!r} in this data directory")
    return session_id


def cmd_export(args: argparse.Namespace) -> int:
    """Write a session as an MCAP file."""
    from server.reports.mcap_export import export_session

    factory, files = _database(args)
    sid = _session_id(factory, args.session_id)
    out = Path(args.out)
    tmp = out.with_name(f".{out.name}.tmp")
    try:
        with factory() as db, tmp.open("wb") as fh:
            counts = export_session(db, files, sid, fh)
        tmp.replace(out)
    except OSError as exc:
        raise CommandError(f"cannot write {out}: {exc}") from None
    finally:
        tmp.unlink(missing_ok=True)
    print(json.dumps({"session_id": sid, "mcap_path": str(out.resolve()), **counts}))
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    """Write a session's report.pdf, report.json and defects.csv into a folder."""
    from server.reports.content import build_report
    from server.reports.pdf import write_pdf
    from server.reports.tables import defects_csv
    from server.storage.files import write_atomic

    factory, files = _database(args)
    sid = _session_id(factory, args.session_id)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with factory() as db:
        report = build_report(db, files, sid)
        write_atomic(out / "report.json", json.dumps(report, indent=1).encode())
        write_atomic(out / "defects.csv", "".join(defects_csv(report["defects"])).encode("utf-8"))
        write_pdf(db, files, sid, out / "report.pdf")
    print(
        json.dumps(
            {
                name: str((out / name).resolve())
                for name in ("report.pdf", "report.json", "defects.csv")
            }
        )
    )
    return 0
