"""Real PostgreSQL and Redis servers from Debian's packages, started in temporary
directories on free loopback ports, for the test suite and the scale benchmark.

PostgreSQL refuses to run as root: as root, its folder is handed to the ``postgres`` system
user (created by Debian's package) and its programs run as that user.
"""

from __future__ import annotations

import glob
import os
import shutil
import subprocess
import tempfile
import time
import uuid
from pathlib import Path

from server.loopback import free_port

STARTUP_S = 30.0


class ServiceMissing(RuntimeError):
    """The service's programs are not installed (scripts/setup.sh installs them)."""


def _pg_bin(name: str) -> str:
    found = shutil.which(name)
    if found is None:  # Debian keeps the server's programs out of PATH
        candidates = sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"))
        if not candidates:
            raise ServiceMissing(f"{name} not found: install Debian's postgresql package")
        found = candidates[-1]
    return found


def may_raise(priority: int) -> bool:
    """Whether this process may start programs at real-time priority ``priority``
    (``CAP_SYS_NICE``, or an ``RLIMIT_RTPRIO`` of it)."""
    chrt = shutil.which("chrt")
    if chrt is None or priority <= 0:
        return False
    done = subprocess.run([chrt, "--rr", str(priority), "true"], capture_output=True, check=False)
    return done.returncode == 0


class Postgres:
    """A PostgreSQL cluster of its own; :meth:`new_database` gives a fresh empty database.

    With ``realtime`` (1-99, where :func:`may_raise`), the server and every backend it
    starts run at real-time round-robin priority, as ``docker/compose.yaml`` starts it
    beside a station and workers on one machine; ``realtime`` is 0 where that is refused."""

    user = "steelscan"

    def __init__(self, realtime: int = 0) -> None:
        self.dir = Path(tempfile.mkdtemp(prefix="steelscan-pg-"))
        self.port = free_port()
        self.realtime = realtime if may_raise(realtime) else 0
        self._as: list[str] = []
        if os.geteuid() == 0:
            shutil.chown(self.dir, "postgres", "postgres")
            self._as = ["runuser", "-u", "postgres", "--"]
        data = self.dir / "data"
        self._run(
            [_pg_bin("initdb"), "-D", str(data), "-U", self.user, "-A", "trust", "-E", "UTF8"]
        )
        options = (
            f"-p {self.port} -k {self.dir} -c listen_addresses=127.0.0.1 -c fsync=off "
            "-c synchronous_commit=off -c full_page_writes=off -c max_connections=200"
        )
        self._run(
            [
                _pg_bin("pg_ctl"),
                "-D",
                str(data),
                "-o",
                options,
                "-l",
                str(self.dir / "log"),
                "-w",
                "-t",
                str(int(STARTUP_S)),
                "start",
            ],  # fmt: skip
            raised=["chrt", "--rr", str(self.realtime)] if self.realtime else [],
        )
        self._data = data

    def _run(self, cmd: list[str], raised: list[str] | None = None) -> None:
        """``cmd`` as the server's user, started by ``raised`` (a priority's command) first."""
        done = subprocess.run(
            (raised or []) + self._as + cmd, capture_output=True, text=True, check=False
        )
        if done.returncode != 0:
            raise RuntimeError(f"{Path(cmd[0]).name} failed: {done.stderr or done.stdout}")

    def url(self, database: str = "postgres") -> str:
        """SQLAlchemy URL of one of its databases."""
        return f"postgresql+psycopg://{self.user}@127.0.0.1:{self.port}/{database}"

    def new_database(self) -> str:
        """Create an empty database and return its URL."""
        import psycopg

        name = f"t_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(
            f"host=127.0.0.1 port={self.port} user={self.user} dbname=postgres", autocommit=True
        ) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def stop(self) -> None:
        """Stop the server at once and remove its folder."""
        try:
            self._run([_pg_bin("pg_ctl"), "-D", str(self._data), "-m", "immediate", "-w", "stop"])
        finally:
            shutil.rmtree(self.dir, ignore_errors=True)


class Redis:
    """A Redis server of its own, nothing persisted."""

    def __init__(self) -> None:
        exe = shutil.which("redis-server")
        if exe is None:
            raise ServiceMissing("redis-server not found: install Debian's redis-server package")
        self.dir = Path(tempfile.mkdtemp(prefix="steelscan-redis-"))
        self.port = free_port()
        self.proc = subprocess.Popen(
            [exe, "--port", str(self.port), "--bind", "127.0.0.1", "--dir", str(self.dir),
             "--save", "", "--appendonly", "no", "--daemonize", "no", "--loglevel", "warning"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        deadline = time.monotonic() + STARTUP_S
        import redis

        client = redis.Redis(host="127.0.0.1", port=self.port)
        while True:
            try:
                client.ping()
                break
            except redis.ConnectionError:
                if time.monotonic() > deadline or self.proc.poll() is not None:
                    self.stop()
                    raise RuntimeError("redis-server did not start") from None
                time.sleep(0.05)
        client.close()

    @property
    def url(self) -> str:
        """Its broker URL."""
        return f"redis://127.0.0.1:{self.port}/0"

    def stop(self) -> None:
        """Stop the server and remove its folder."""
        self.proc.terminate()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
        shutil.rmtree(self.dir, ignore_errors=True)


def start_worker(env: dict[str, str], log: Path) -> subprocess.Popen[bytes]:
    """``steelscan worker`` with one job process, in a process group of its own (stopped or
    killed whole), its settings from ``env``, its output appended to ``log``."""
    import sys

    with log.open("ab") as out:
        return subprocess.Popen(
            [sys.executable, "-m", "server.cli", "worker", "--concurrency", "1"],
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )


def stop_workers(workers: list[subprocess.Popen[bytes]], grace_s: float = 30.0) -> None:
    """SIGTERM each worker's group (a warm shutdown), SIGKILL what is left after ``grace_s``."""
    import signal

    for w in workers:
        if w.poll() is None:
            os.killpg(w.pid, signal.SIGTERM)
    for w in workers:
        try:
            w.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            os.killpg(w.pid, signal.SIGKILL)
            w.wait()
