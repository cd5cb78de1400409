"""``steelscan admin``: accounts and robots, in the data directory's database (migrated
first, so the commands work on a fresh station)."""

from __future__ import annotations

import argparse
import sys

from server.cli.session_commands import settings_from_args
from server.errors import CommandError


def cmd_create_robot(args: argparse.Namespace) -> int:
    """Register a robot and print its token."""
    from server.errors import Conflict
    from server.link.robots import create_robot
    from server.storage.db import make_engine, make_sessionmaker, upgrade

    settings = settings_from_args(args)
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    url = settings.resolved_database_url()
    upgrade(url)
    try:
        token = create_robot(make_sessionmaker(make_engine(url)), args.name)
    except (Conflict, ValueError) as exc:
        raise CommandError(str(exc)) from None
    print(token)
    return 0


def _read_password() -> str:
    if sys.stdin.isatty():
        import getpass

        first = getpass.getpass("Password: ")
        if getpass.getpass("Again: ") != first:
            raise CommandError("the two passwords differ")
        return first
    line = sys.stdin.readline()
    return line.rstrip("\r\n")


def cmd_create_user(args: argparse.Namespace) -> int:
    """Create an operator account; the password comes from stdin."""
    from server.api.accounts import create_user
    from server.errors import Conflict
    from server.storage.db import make_engine, make_sessionmaker, upgrade
    from server.storage.models import Role

    settings = settings_from_args(args)
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    url = settings.resolved_database_url()
    upgrade(url)
    password = _read_password()
    try:
        create_user(make_sessionmaker(make_engine(url)), args.name, password, Role(args.role))
    except (Conflict, ValueError) as exc:
        raise CommandError(str(exc)) from None
    print(f"created {args.role} {args.name}", file=sys.stderr)
    return 0
