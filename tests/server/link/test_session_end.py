"""A session's lifecycle: it ends once, nothing reopens it, and its results follow the data
it holds (data stored after its end is processed again), on the real server, SQLite and
PostgreSQL."""

import time
import uuid

import httpx
import pytest
from sqlalchemy import text
from sqlalchemy.exc import DBAPIError

from robot_link.protocol import MessageType
from server.storage.db import make_engine
from tests.conftest import LiveServer
from tests.server.helpers import end_message, frame, robot_ws, send_and_reply, session_json, start


def _stitch_jobs(server: LiveServer, sid: uuid.UUID) -> list[dict]:
    return [j for j in session_json(server, sid)["jobs"] if j["kind"] == "stitch"]


def test_data_stored_after_the_end_is_processed_again(live_server: LiveServer) -> None:
    """START, FRAME 2, END at 20, then FRAMEs 3-11 (resends from before the end): all
    stored, and the session's newest processing covers all ten frames."""
    sid = uuid.uuid4()
    with robot_ws(live_server) as ws:
        assert send_and_reply(ws, start(sid)).meta["status"] == "stored"
        assert send_and_reply(ws, frame(sid, 2)).meta["status"] == "stored"
        assert send_and_reply(ws, end_message(sid, 20)).meta["status"] == "stored"
        # the first processing fixed its inputs at the END: one frame
        deadline = time.monotonic() + 10
        while not _stitch_jobs(live_server, sid):
            assert time.monotonic() < deadline
            time.sleep(0.1)
        for seq in range(3, 12):
            assert send_and_reply(ws, frame(sid, seq)).meta["status"] == "stored"
    first = session_json(live_server, sid)
    assert first["frames"] == 10
    assert first["results_cover"]["frames"] == 1 and not first["results_cover"]["current"]
    deadline = time.monotonic() + 30
    while True:
        s = session_json(live_server, sid)
        cover = s["results_cover"]
        if cover["current"]:
            break
        assert time.monotonic() < deadline, s
        time.sleep(0.2)
    assert cover["frames"] == 10 and cover["clouds"] == 0
    stitches = _stitch_jobs(live_server, sid)
    assert len(stitches) == 2, stitches  # the nine late frames: one re-run, not nine


def test_a_session_ends_once_and_a_second_end_changes_nothing(live_server: LiveServer) -> None:
    sid = uuid.uuid4()
    with robot_ws(live_server) as ws:
        send_and_reply(ws, start(sid))
        send_and_reply(ws, frame(sid, 2))
        assert send_and_reply(ws, end_message(sid, 3)).meta["status"] == "stored"
        assert send_and_reply(ws, end_message(sid, 3)).meta["status"] == "duplicate"  # its resend
        for seq in range(100, 130):  # another END: refused for good, never reopens it
            reply = send_and_reply(ws, end_message(sid, seq))
            assert reply.type is MessageType.ERROR and not reply.meta["retry"]
            assert "second SESSION_END" in reply.meta["error"]
        reply = send_and_reply(ws, frame(sid, 99))
        assert reply.type is MessageType.ERROR and "after its end" in reply.meta["error"]
    time.sleep(1.0)
    s = session_json(live_server, sid)
    assert (s["status"], s["frames"]) == ("ended", 1)
    assert len(s["jobs"]) == 4  # one pipeline


def test_the_database_refuses_to_reopen_an_ended_session(live_server: LiveServer) -> None:
    sid = uuid.uuid4()
    with robot_ws(live_server) as ws:
        send_and_reply(ws, start(sid))
        send_and_reply(ws, end_message(sid, 2))
    engine = make_engine(live_server.settings.resolved_database_url())
    try:
        for change in ("status = 'live'", "end_seq = 50"):
            with pytest.raises(DBAPIError, match="cannot reopen"), engine.begin() as conn:
                conn.execute(
                    text(f"UPDATE inspection_sessions SET {change} WHERE id = :id"),
                    {"id": str(sid)},
                )
    finally:
        engine.dispose()
    assert httpx.get(f"{live_server.url}/api/sessions/{sid}").json()["status"] == "ended"


def test_a_re_run_lost_with_a_stop_is_caught_up_at_the_next_start(settings) -> None:  # type: ignore[no-untyped-def]
    from server.loopback import BackgroundServer, free_port
    from tests.conftest import make_token

    token = make_token(settings)
    sid = uuid.uuid4()
    server = BackgroundServer(settings, free_port())
    server.start()
    live = LiveServer(server.url, settings, token)
    try:
        with robot_ws(live) as ws:
            send_and_reply(ws, start(sid))
            send_and_reply(ws, frame(sid, 2))
            send_and_reply(ws, end_message(sid, 20))
            deadline = time.monotonic() + 10
            while not _stitch_jobs(live, sid):
                assert time.monotonic() < deadline
                time.sleep(0.1)
            assert send_and_reply(ws, frame(sid, 3)).meta["status"] == "stored"
    finally:
        server.stop()  # before the late frame's re-run settled
    server = BackgroundServer(settings, free_port())
    server.start()
    live = LiveServer(server.url, settings, token)
    try:
        deadline = time.monotonic() + 30
        while not (cover := session_json(live, sid)["results_cover"])["current"]:
            assert time.monotonic() < deadline, cover
            time.sleep(0.2)
        assert cover["frames"] == 2
    finally:
        server.stop()


def test_a_session_processed_before_inputs_were_recorded_is_left_as_it_is(settings) -> None:  # type: ignore[no-untyped-def]
    """The next start looks at every ended session, but does not process again one whose
    processing recorded no inputs (it cannot tell what that covered)."""
    from server.jobs.runner import JobRunner
    from server.storage.db import make_sessionmaker
    from server.storage.models import InspectionSession, Job, JobState, SessionStatus
    from tests.conftest import make_token

    make_token(settings)  # the database
    engine = make_engine(settings.resolved_database_url())
    factory = make_sessionmaker(engine)
    sid = str(uuid.uuid4())
    with factory() as db:
        db.add(InspectionSession(id=sid, structure="old", status=SessionStatus.ended))
        db.flush()
        db.add(Job(session_id=sid, kind="stitch", state=JobState.done, params={}))
        db.commit()
    runner = JobRunner(factory, settings.resolved_database_url(), str(settings.data_dir), 1)
    assert runner.refresh(sid) == []
    with factory() as db:  # a processing with recorded inputs is compared with the data
        db.add(Job(session_id=sid, kind="stitch", state=JobState.done, params={"inputs": {
            "frames": 0, "frames_upto": 0, "clouds": 0, "clouds_upto": 0, "telemetry": 0,
            "telemetry_upto": 0}}))  # fmt: skip
        db.commit()
    assert runner.refresh(sid) == []  # it covers what the session holds: nothing
    engine.dispose()
