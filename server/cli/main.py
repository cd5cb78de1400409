"""The ``steelscan`` command: ``demo``, ``serve``, ``worker``, ``sim``, ``detect``, ``stitch``, ``map``, ``bench``,
``report``, ``export``, ``import`` and ``admin`` (``steelscan --help``)."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Callable, Sequence
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

from server.cli.robot_commands import add_robot_commands
from server.cli.train_commands import add_train_commands
from server.errors import CommandError
from server.logs import RedactSecrets, uvicorn_log_config
from server.process.allocator import keep_arrays_on_heap

Command = Callable[[argparse.Namespace], int]


def _imported_when_run(module: str, name: str) -> Command:
    """The command ``module.name``, imported only when it runs (the settings and database
    imports behind the session and admin commands stay out of the other commands' start-up)."""

    def run(args: argparse.Namespace) -> int:
        import importlib

        return getattr(importlib.import_module(module), name)(args)

    run.__name__ = name
    return run


def cmd_serve(args: argparse.Namespace) -> int:
    """Run the ground station until interrupted."""
    import uvicorn

    from server.cli.session_commands import settings_from_args
    from server.main import create_app

    settings = settings_from_args(args)
    host = args.host or settings.host
    port = args.port if args.port is not None else settings.port
    uvicorn.run(
        create_app(settings),
        host=host,
        port=port,
        log_level="info",
        log_config=uvicorn_log_config(),
        **settings.uvicorn_options(),
    )
    return 0


def cmd_worker(args: argparse.Namespace) -> int:
    """Run a Celery job worker until stopped (its settings from STEELSCAN_*)."""
    if args.data_dir:
        os.environ["STEELSCAN_DATA_DIR"] = args.data_dir
    if args.broker:
        os.environ["STEELSCAN_BROKER_URL"] = args.broker
    from server.jobs.queue import ping_worker, run_worker

    if args.ping:
        return 0 if ping_worker() else 1
    run_worker(args.concurrency or os.cpu_count() or 1)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """Run the ground station, the simulated robot and the jobs; print the summary."""
    from server.cli.demo import run_demo
    from server.cli.session_commands import settings_from_args

    settings = settings_from_args(args)
    return run_demo(
        settings,
        port=args.port,
        exit_when_done=args.exit_when_done,
        keep_serving=args.keep_serving,
        time_scale=args.time_scale,
        lanes=args.lanes,
        seed=args.seed,
    )


def cmd_detect(args: argparse.Namespace) -> int:
    """Segment defects in images."""
    from server.cli.commands import detect_images

    detect_images(
        [Path(p) for p in args.images], Path(args.out), method=args.method, px_per_mm=args.px_per_mm
    )
    return 0


def cmd_changes(args: argparse.Namespace) -> int:
    """Align two visits' images and match their defects."""
    from server.cli.changes_command import changes

    changes(
        Path(args.before),
        Path(args.after),
        Path(args.out),
        method=args.method,
        px_per_mm=args.px_per_mm,
    )
    return 0


def cmd_stitch(args: argparse.Namespace) -> int:
    """Stitch a folder of frames."""
    from server.cli.commands import stitch_folder

    stitch_folder(
        Path(args.frames_dir),
        Path(args.out),
        odometry=Path(args.odometry) if args.odometry else None,
        px_per_m=args.px_per_m,
    )
    return 0


def cmd_map(args: argparse.Namespace) -> int:
    """Register a folder of point clouds into a map."""
    from server.cli.map_command import map_folder

    map_folder(
        Path(args.clouds_dir),
        Path(args.out),
        odometry=Path(args.odometry) if args.odometry else None,
        units=args.units,
        frames=Path(args.frames) if args.frames else None,
    )
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every sub-command."""
    p = argparse.ArgumentParser(
        prog="steelscan", description="Ground station for steel-inspection climbing robots."
    )
    p.add_argument("-v", "--verbose", action="store_true", help="log more")
    sub = p.add_subparsers(dest="command", required=True)

    _add_station_commands(sub)
    _add_processing_commands(sub)
    _add_session_commands(sub)
    _add_admin_commands(sub)
    add_robot_commands(sub)
    for plugin in entry_points(group="steelscan.commands"):  # the benchmarks: bench.cli
        plugin.load()(sub)

    return p


def _add_station_commands(sub: Any) -> None:
    """``serve``, ``worker``, ``demo`` and ``sim``: the station, its workers and a robot."""
    s = sub.add_parser("serve", help="run the ground station")
    s.add_argument("--data-dir")
    s.add_argument("--host")
    s.add_argument("--port", type=int)
    s.add_argument("--tls-cert", help="PEM certificate: serve HTTPS, robots connect over wss://")
    s.add_argument("--tls-key", help="PEM private key of --tls-cert")
    s.set_defaults(func=cmd_serve)

    s = sub.add_parser("worker", help="run a job worker (STEELSCAN_JOB_BACKEND=celery)")
    s.add_argument("--data-dir", help="the data directory the station and every worker mount")
    s.add_argument("--broker", help="Celery broker URL (default STEELSCAN_BROKER_URL)")
    s.add_argument("--concurrency", type=int, help="job processes (default: one per core)")
    s.add_argument(
        "--ping", action="store_true", help="exit 0 if a worker on this host answers (health check)"
    )
    s.set_defaults(func=cmd_worker)

    s = sub.add_parser("demo", help="ground station + simulated robot + processing, end to end")
    s.add_argument("--data-dir")
    s.add_argument("--port", type=int, default=0, help="0 = a free port")
    s.add_argument("--exit-when-done", action="store_true")
    s.add_argument(
        "--keep-serving",
        action="store_true",
        help="with --exit-when-done: keep the server up after the summary",
    )
    s.add_argument(
        "--time-scale",
        type=float,
        default=20.0,
        help="simulated seconds per wall second (0 = flat out)",
    )
    s.add_argument("--lanes", type=int, default=5)
    s.add_argument("--seed", type=int, default=7)
    s.set_defaults(func=cmd_demo)

    _add_sim_command(sub)


def _add_sim_command(sub: Any) -> None:
    """``sim``: the simulated robot alone, against a station."""
    s = sub.add_parser("sim", help="the simulated robot alone")
    s.add_argument("--server", required=True, help="ground station base URL, http://host:port")
    s.add_argument("--token")
    s.add_argument("--exit-when-done", action="store_true")
    s.add_argument(
        "--spool", help="durable spool folder: unacknowledged messages survive outages and restarts"
    )
    s.add_argument("--spool-max-mb", type=float, default=2048.0, help="size bound of the spool")
    s.add_argument(
        "--ca-file", help="PEM certificate(s) to trust for an https:// station (self-signed)"
    )
    s.add_argument(
        "--flush-timeout",
        type=float,
        default=120.0,
        help="seconds to wait at the end for every acknowledgement (unacknowledged: exit 2, "
        "the spool keeps them)",
    )
    s.add_argument("--time-scale", type=float, default=20.0)
    s.add_argument("--lanes", type=int, default=5)
    s.add_argument("--seed", type=int, default=7)
    s.add_argument(
        "--teleop",
        action="store_true",
        help="drive as the operator commands (live video, dead-man stop) instead of the route",
    )
    s.add_argument(
        "--duration",
        type=float,
        help="with --teleop: end the session after this many seconds (default: on the operator's end_session)",
    )
    s.set_defaults(func=_imported_when_run("server.cli.sim_command", "cmd_sim"))


def _add_processing_commands(sub: Any) -> None:
    """``detect``, ``train-detector``, ``stitch`` and ``map``: the algorithms on files."""
    s = sub.add_parser("detect", help="crack/defect segmentation of images")
    s.add_argument("images", nargs="+")
    s.add_argument("--out", required=True)
    s.add_argument(
        "--method", default="proposed", choices=["proposed", "learned", "paper", "otsu", "sauvola"]
    )
    s.add_argument("--px-per-mm", type=float)
    s.set_defaults(func=cmd_detect, image_work=True)

    s = sub.add_parser(
        "changes", help="a surface's history: two visits' images aligned, defects matched, growth"
    )
    s.add_argument("before", help="the earlier visit's image")
    s.add_argument("after", help="the later visit's image")
    s.add_argument("--out", required=True)
    s.add_argument(
        "--method", default="learned", choices=["proposed", "learned", "paper", "otsu", "sauvola"]
    )
    s.add_argument("--px-per-mm", type=float, help="AFTER's scale")
    s.set_defaults(func=cmd_changes, image_work=True)

    add_train_commands(sub)

    s = sub.add_parser("stitch", help="stitch a folder of downward-camera frames")
    s.add_argument("frames_dir")
    s.add_argument("--out", required=True)
    s.add_argument("--odometry")
    s.add_argument("--px-per-m", type=float)
    s.set_defaults(func=cmd_stitch, image_work=True)

    s = sub.add_parser("map", help="register a folder of point clouds into a 3D map")
    s.add_argument("clouds_dir")
    s.add_argument("--out", required=True)
    s.add_argument("--odometry")
    s.add_argument(
        "--units",
        choices=("auto", "m", "mm"),
        default="auto",
        help="the clouds' unit: auto (metres; millimetres are recognised and refused), m, or mm (converted)",
    )
    s.add_argument(
        "--frames",
        help="the downward camera's images and camera.json: their motion joins the clouds'",
    )
    s.set_defaults(func=cmd_map, image_work=True)


def _add_session_commands(sub: Any) -> None:
    """``import``, ``export`` and ``report``: a stored session in and out."""
    s = sub.add_parser(
        "import", help="import a session's MCAP log (as exported) into a new session"
    )
    s.add_argument("file")
    s.add_argument("--data-dir")
    s.set_defaults(func=_imported_when_run("server.cli.session_commands", "cmd_import"))

    s = sub.add_parser("export", help="write a session as an MCAP log that opens in Foxglove")
    s.add_argument("session_id")
    s.add_argument("--out", required=True)
    s.add_argument("--data-dir")
    s.set_defaults(func=_imported_when_run("server.cli.session_commands", "cmd_export"))

    s = sub.add_parser(
        "report", help="write a session's inspection report (PDF, JSON, CSV) into a folder"
    )
    s.add_argument("session_id")
    s.add_argument("--out", required=True)
    s.add_argument("--data-dir")
    s.set_defaults(func=_imported_when_run("server.cli.session_commands", "cmd_report"))


def _add_admin_commands(sub: Any) -> None:
    """``admin``: accounts and robots."""
    admin = sub.add_parser("admin", help="accounts and robots")
    asub = admin.add_subparsers(dest="admin_command", required=True)
    s = asub.add_parser("create-user", help="create an account; the password is read from stdin")
    s.add_argument("name")
    s.add_argument("--role", required=True, choices=["admin", "operator", "viewer"])
    s.add_argument("--data-dir")
    s.set_defaults(func=_imported_when_run("server.cli.admin_commands", "cmd_create_user"))
    s = asub.add_parser("create-robot", help="register a robot and print its token")
    s.add_argument("name")
    s.add_argument("--data-dir")
    s.set_defaults(func=_imported_when_run("server.cli.admin_commands", "cmd_create_robot"))


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``steelscan`` console script."""
    args = build_parser().parse_args(argv)
    handler = logging.StreamHandler(sys.stderr)
    handler.addFilter(RedactSecrets())
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        handlers=[handler],
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    for noisy in ("alembic", "httpx", "pyvips"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    func: Command = args.func
    if getattr(args, "image_work", False):
        keep_arrays_on_heap()
    try:
        return func(args)
    except CommandError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
