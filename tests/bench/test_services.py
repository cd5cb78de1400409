"""The benchmark's PostgreSQL at real-time priority: the server and the backends it starts
for new connections, as the compose file runs it beside a station and workers."""

from __future__ import annotations

import os

import psycopg
import pytest

from bench.services import Postgres, may_raise

PRIORITY = 5


@pytest.mark.skipif(not may_raise(PRIORITY), reason="real-time priority is refused here")
def test_every_backend_of_a_realtime_server_runs_at_its_priority() -> None:
    pg = Postgres(realtime=PRIORITY)
    try:
        assert pg.realtime == PRIORITY
        for _ in range(2):  # each connection is a backend forked anew
            with psycopg.connect(
                f"host=127.0.0.1 port={pg.port} user={pg.user} dbname=postgres"
            ) as conn:
                pid = conn.execute("SELECT pg_backend_pid()").fetchone()[0]
                assert os.sched_getscheduler(pid) == os.SCHED_RR
                assert os.sched_getparam(pid).sched_priority == PRIORITY
    finally:
        pg.stop()


def test_a_server_without_priority_runs_at_normal_priority(postgres: Postgres) -> None:
    assert postgres.realtime == 0
    with psycopg.connect(
        f"host=127.0.0.1 port={postgres.port} user={postgres.user} dbname=postgres"
    ) as conn:
        pid = conn.execute("SELECT pg_backend_pid()").fetchone()[0]
        assert os.sched_getscheduler(pid) == os.SCHED_OTHER


def test_a_priority_out_of_range_or_zero_is_not_taken() -> None:
    assert not may_raise(0)
    assert not may_raise(100)
