"""Accounts, roles and tokens on the real server (contract: "Accounts and tokens")."""

import json
import subprocess
import sys
import time
import uuid

import httpx
import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from server.api.accounts import create_user
from server.storage.db import make_engine, make_sessionmaker, upgrade
from server.storage.models import Role
from tests.conftest import LiveServer
from tests.server.helpers import add_user, login, start, ws_url


def test_open_until_the_first_account_then_401_and_403(live_server: LiveServer) -> None:
    url = live_server.url
    sid = uuid.uuid4()
    with connect(
        ws_url(live_server), additional_headers={"Authorization": f"Bearer {live_server.token}"}
    ) as ws:
        ws.send(start(sid))
        ws.recv(timeout=10)
    assert httpx.get(f"{url}/api/sessions").status_code == 200  # no accounts yet: open
    add_user(live_server, "vera", Role.viewer)
    add_user(live_server, "otto", Role.operator)
    for path in (
        "/api/sessions",
        f"/api/sessions/{sid}",
        "/api/health",
        "/api/auth/me",
        "/api/jobs/1",
    ):
        r = httpx.get(url + path)
        assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer", path
    assert (
        httpx.get(f"{url}/api/sessions", headers={"Authorization": "Bearer forged"}).status_code
        == 401
    )
    assert (
        httpx.post(
            f"{url}/api/auth/token", data={"username": "vera", "password": "wrong"}
        ).status_code
        == 401
    )
    assert (
        httpx.post(
            f"{url}/api/auth/token", data={"username": "nobody", "password": "x"}
        ).status_code
        == 401
    )
    viewer, operator = login(live_server, "vera"), login(live_server, "otto")
    assert httpx.get(f"{url}/api/sessions/{sid}", headers=viewer).json()["frames"] == 0
    assert httpx.get(f"{url}/api/auth/me", headers=viewer).json() == {
        "name": "vera",
        "role": "viewer",
    }
    job = {"kind": "stitch"}
    assert httpx.post(f"{url}/api/sessions/{sid}/jobs", json=job, headers=viewer).status_code == 403
    assert (
        httpx.post(f"{url}/api/sessions/{sid}/jobs", json=job, headers=operator).status_code == 202
    )
    # viewers read reports but may not change what they say
    assert httpx.get(f"{url}/api/sessions/{sid}/report.json", headers=viewer).status_code == 200
    assert httpx.get(f"{url}/api/sessions/{sid}/defects.csv").status_code == 401
    assert (
        httpx.patch(f"{url}/api/sessions/{sid}", json={"location": "x"}, headers=viewer).status_code
        == 403
    )
    assert (
        httpx.patch(
            f"{url}/api/sessions/{sid}", json={"location": "x"}, headers=operator
        ).status_code
        == 200
    )
    assert (
        httpx.patch(
            f"{url}/api/sessions/{sid}/defects/1", json={"comment": "x"}, headers=viewer
        ).status_code
        == 403
    )
    # viewers download what exists but do not queue exports; they open a session's own 3D
    # view (it changes no one else's); without a token nobody does
    mcap = f"{url}/api/sessions/{sid}/export.mcap"
    assert httpx.get(mcap, headers=viewer).status_code == 403
    assert httpx.post(f"{url}/api/sessions/{sid}/view3d", headers=viewer).status_code == 200
    assert httpx.post(f"{url}/api/sessions/{sid}/view3d").status_code == 401
    assert httpx.get(mcap, headers=operator).status_code == 202
    # static pages and the OpenAPI document stay reachable, framed by no other site
    page = httpx.get(f"{url}/")
    assert page.status_code == 200 and page.headers["x-frame-options"] == "SAMEORIGIN"
    assert "script-src 'self'" in page.headers["content-security-policy"]
    assert page.headers["x-content-type-options"] == "nosniff"
    assert httpx.get(f"{url}/static/js/main.js").status_code == 200
    assert httpx.get(f"{url}/vendor/openseadragon/openseadragon.min.js").status_code == 200


def test_live_socket_needs_a_token_and_viewers_cannot_command(live_server: LiveServer) -> None:
    import json

    add_user(live_server, "vera", Role.viewer)
    live = live_server.url.replace("http://", "ws://") + "/ws/live"
    with pytest.raises(InvalidStatus), connect(live):
        pass
    token = login(live_server, "vera")["Authorization"].split()[1]
    with connect(f"{live}?token={token}") as ws:
        ws.send(json.dumps({"session_id": str(uuid.uuid4()), "cmd": "estop"}))
        while True:
            item = ws.recv(timeout=10)
            if isinstance(item, str) and json.loads(item).get("type") == "command_result":
                assert "operator role" in json.loads(item)["error"]
                break


def test_create_user_reads_the_password_from_stdin(tmp_path) -> None:
    cmd = [
        sys.executable,
        "-m",
        "server.cli",
        "admin",
        "create-user",
        "ana",
        "--role",
        "operator",
        "--data-dir",
        str(tmp_path),
    ]
    proc = subprocess.run(cmd, input="s3cret-pass\n", capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    again = subprocess.run(cmd, input="s3cret-pass\n", capture_output=True, text=True, timeout=120)
    assert (
        again.returncode != 0
        and "already exists" in again.stderr
        and "Traceback" not in again.stderr
    )
    short = subprocess.run(
        cmd[:5] + ["bo"] + cmd[6:], input="short\n", capture_output=True, text=True, timeout=120
    )
    assert short.returncode != 0 and "at least 8" in short.stderr


def test_password_guessing_is_throttled_and_the_right_password_still_works_later(
    live_server: LiveServer,
) -> None:
    add_user(live_server, "vera", Role.viewer)
    url = f"{live_server.url}/api/auth/token"
    live_server.app.state.steelscan.passwords.client_burst = 10  # the throttle, not the budget
    for _ in range(5):
        assert (
            httpx.post(
                url, data={"username": "vera", "password": f"guess-{uuid.uuid4()}"}
            ).status_code
            == 401
        )
    refused = httpx.post(url, data={"username": "vera", "password": "correct horse"})
    assert (
        refused.status_code == 429
        and int(refused.headers["retry-after"]) > 0
        and "try again" in refused.json()["detail"]
    )
    # other users unaffected
    assert httpx.post(url, data={"username": "otto", "password": "whatever"}).status_code == 401
    live_server.app.state.steelscan.logins.window_s = 0.2  # the window passes
    time.sleep(0.3)
    assert (
        httpx.post(url, data={"username": "vera", "password": "correct horse"}).status_code == 200
    )


def test_login_throttle_forgets_on_success_and_stays_bounded() -> None:
    from server.limits import LoginThrottle

    throttle = LoginThrottle(max_failures=2, window_s=60, max_keys=3)
    throttle.failed("a", "u")
    throttle.succeeded("a", "u")
    throttle.failed("a", "u")
    assert throttle.retry_after("a", "u") == 0
    throttle.failed("a", "u")
    assert 59 < throttle.retry_after("a", "u") <= 60 and throttle.retry_after("b", "u") == 0
    for k in range(10):
        throttle.failed(f"c{k}", "u")
    assert len(throttle._failures) <= 3


def test_another_sites_page_cannot_open_the_live_socket(live_server: LiveServer) -> None:
    live = live_server.url.replace("http://", "ws://") + "/ws/live"
    host = live_server.url.removeprefix("http://")
    with pytest.raises(InvalidStatus), connect(live, origin="http://evil.example"):  # type: ignore[arg-type]
        pass
    with connect(live, origin=f"http://{host}") as ws:  # type: ignore[arg-type]  # the dashboard's own page
        ws.send(json.dumps({"session_id": str(uuid.uuid4()), "cmd": "stop"}))
    with connect(live) as ws:  # no Origin: not a browser
        ws.send(json.dumps({"session_id": str(uuid.uuid4()), "cmd": "stop"}))


def test_a_browser_flooding_or_sending_huge_messages_is_refused_but_can_always_stop(
    live_server: LiveServer,
) -> None:
    live = live_server.url.replace("http://", "ws://") + "/ws/live"
    sid = str(uuid.uuid4())

    def results(ws, n: int) -> list[dict]:  # type: ignore[no-untyped-def]
        out: list[dict] = []
        while len(out) < n:
            item = ws.recv(timeout=10)
            if isinstance(item, str) and json.loads(item).get("type") == "command_result":
                out.append(json.loads(item))
        return out

    with connect(live, max_size=2**22) as ws:
        ws.send(json.dumps({"session_id": sid, "cmd": "drive", "args": {"pad": "x" * 20_000}}))
        assert "bytes is refused" in results(ws, 1)[0]["error"]
        for _ in range(200):
            ws.send(json.dumps({"session_id": sid, "cmd": "drive", "args": {}}))
        flood = results(ws, 200)
        limited = [r for r in flood if "too many messages" in r.get("error", "")]
        assert 50 <= len(limited) < 200
        # the bucket is empty: e-stop still goes through
        ws.send(json.dumps({"session_id": sid, "cmd": "estop"}))
        assert "too many" not in results(ws, 1)[0].get("error", "")


def test_guessing_over_many_user_names_is_throttled_per_client() -> None:
    from server.limits import LoginThrottle

    throttle = LoginThrottle(max_failures=5, window_s=60, max_client_failures=20)
    for k in range(20):
        assert throttle.retry_after("mallory", f"user-{k}") == 0
        throttle.failed("mallory", f"user-{k}")
    assert throttle.retry_after("mallory", "a-new-name") > 59
    assert throttle.retry_after("ana", "user-1") == 0  # another client is not affected
    throttle.succeeded("mallory", "user-3")  # one right password does not reset the client
    assert throttle.retry_after("mallory", "user-3") > 59


def test_password_checks_have_a_budget_per_address_and_for_the_station(
    live_server: LiveServer,
) -> None:
    """A login flood from one address (random user names) is answered 429 beyond that
    address's share, before any hashing: it can neither take the CPU ingest needs nor
    spend the station's budget, so an operator at another address still signs in."""
    from server.limits import PasswordBudget

    budget = PasswordBudget(rate=1.0, burst=3.0, client_rate=0.1, client_burst=2.0)
    assert [budget.take_for("a") for _ in range(3)] == [True, True, False]
    assert [budget.take_for("b") for _ in range(2)] == [True, False]  # the station's budget
    add_user(live_server, "vera", Role.viewer)
    url = f"{live_server.url}/api/auth/token"
    replies = [
        httpx.post(url, data={"username": f"u{uuid.uuid4()}", "password": "x"}) for _ in range(30)
    ]
    codes = [r.status_code for r in replies]
    assert codes.count(429) >= 20 and set(codes) <= {401, 429}  # the share, or the throttle
    assert all(
        r.json()["detail"].startswith(("too many wrong passwords", "too many sign-ins"))
        for r in replies
        if r.status_code == 429
    )
    elsewhere = httpx.Client(transport=httpx.HTTPTransport(local_address="127.0.0.2"))
    with elsewhere:
        for _ in range(3):
            ok = elsewhere.post(url, data={"username": "vera", "password": "correct horse"})
            assert ok.status_code == 200, ok.text


def test_signing_out_ends_that_token_only(live_server: LiveServer) -> None:
    url = live_server.url
    add_user(live_server, "otto", Role.operator)
    here, there = login(live_server, "otto"), login(live_server, "otto")
    assert httpx.get(f"{url}/api/auth/me", headers=here).status_code == 200
    assert httpx.delete(f"{url}/api/auth/token", headers=here).status_code == 204
    assert httpx.get(f"{url}/api/auth/me", headers=here).status_code == 401
    assert httpx.get(f"{url}/api/auth/me", headers=there).status_code == 200  # another browser
    assert httpx.delete(f"{url}/api/auth/token", headers=here).status_code == 401
    assert httpx.delete(f"{url}/api/auth/token").status_code == 401


def test_signing_in_works_while_the_storage_is_full(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """With the database unable to grow (SQLite's "database or disk is full"), a sign-in is
    kept in memory: the operator gets in to see the storage warning, and signs out again."""
    from sqlalchemy import event, text

    from server.api.accounts import issue_token, revoke_token, user_for_token
    from server.link.robots import hash_token
    from server.storage.models import AuthToken

    url = f"sqlite:///{tmp_path / 'full.db'}"
    upgrade(url)
    engine = make_engine(url)
    create_user(make_sessionmaker(engine), "ana", "correct horse", Role.operator)
    with engine.connect() as conn:
        pages = conn.execute(text("PRAGMA page_count")).scalar()
    engine.dispose()
    full = make_engine(url)

    @event.listens_for(full, "connect")
    def _no_room(dbapi_conn, _record) -> None:  # type: ignore[no-untyped-def]
        dbapi_conn.execute(f"PRAGMA max_page_count = {pages}")

    factory = make_sessionmaker(full)
    for _ in range(200):  # sign in until the tokens' pages are full
        issued = issue_token(factory, "ana", "correct horse")
        assert issued is not None
        token, _user = issued
        with factory() as db:
            if db.get(AuthToken, hash_token(token)) is None:
                break
    else:
        raise AssertionError("the database never filled up")
    with factory() as db:
        assert user_for_token(db, token).name == "ana"  # type: ignore[union-attr]
        assert revoke_token(db, token)
        assert user_for_token(db, token) is None
    full.dispose()
