"""Secrets never reach the logs: the station's own log of a session with accounts, a robot
and the browser's token-carrying URLs holds no password, token or bearer credential."""

import logging
import subprocess
import uuid
from pathlib import Path

import httpx
from websockets.sync.client import connect

from server.api.accounts import create_user
from server.config import Settings
from server.logs import MASK, RedactSecrets, redact
from server.loopback import free_port, serve_process
from server.storage.db import make_engine, make_sessionmaker
from server.storage.models import Role
from tests.conftest import make_token
from tests.server.helpers import frame, start


def test_redact_masks_tokens_passwords_and_bearer_credentials() -> None:
    assert (
        redact('"GET /viser/?token=eyJ.a-b_c HTTP/1.1" 200')
        == f'"GET /viser/?token={MASK} HTTP/1.1" 200'
    )
    assert redact("/api/x?a=1&access_token=abc&b=2") == f"/api/x?a=1&access_token={MASK}&b=2"
    assert redact("login ?password=hunter2") == f"login ?password={MASK}"
    assert redact("Authorization: Bearer abc.def-ghi") == f"Authorization: Bearer {MASK}"
    assert redact("robot token ssr_Zx9-_q was revoked") == f"robot token ssr_{MASK} was revoked"
    assert redact("GET /api/sessions/3?limit=5 200") == "GET /api/sessions/3?limit=5 200"


def test_the_filter_keeps_uvicorn_style_arguments_and_masks_them() -> None:
    record = logging.LogRecord(
        "uvicorn.access",
        logging.INFO,
        __file__,
        1,
        '%s - "%s %s HTTP/%s" %d',
        ("127.0.0.1:5", "GET", "/viser/?token=s3cret", "1.1", 200),
        None,
    )
    assert RedactSecrets().filter(record)
    assert (
        isinstance(record.args, tuple)
        and "s3cret" not in record.getMessage()
        and f"token={MASK}" in record.getMessage()
    )
    record = logging.LogRecord("server", logging.INFO, __file__, 1, "token=%s", ("s3cret",), None)
    RedactSecrets().filter(record)
    assert record.getMessage() == f"token={MASK}"


def test_a_session_with_accounts_logs_no_secret(tmp_path: Path, database_url: str) -> None:
    data, log = tmp_path / "data", tmp_path / "serve.log"
    robot_token = make_token(Settings(data_dir=data, database_url=database_url))
    password, wrong = "correct horse battery", "hunter2-wrong"
    engine = make_engine(database_url)
    try:
        create_user(make_sessionmaker(engine), "ada", password, Role.admin)
    finally:
        engine.dispose()
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    proc = serve_process(
        data,
        port,
        log=log,
        STEELSCAN_AUTO_PROCESS="false",
        STEELSCAN_VIEW3D="false",
        STEELSCAN_DATABASE_URL=database_url,
    )
    try:
        assert (
            httpx.post(
                f"{url}/api/auth/token", data={"username": "ada", "password": wrong}
            ).status_code
            == 401
        )
        bearer = httpx.post(
            f"{url}/api/auth/token", data={"username": "ada", "password": password}
        ).json()["access_token"]
        assert (
            httpx.get(
                f"{url}/api/sessions", headers={"Authorization": f"Bearer {bearer}"}
            ).status_code
            == 200
        )
        assert httpx.get(f"{url}/api/sessions?token={bearer}").status_code in (200, 401)
        httpx.get(f"{url}/viser/?token={bearer}")
        sid = uuid.uuid4()
        with connect(
            f"ws://127.0.0.1:{port}/ws/robot",
            additional_headers={"Authorization": f"Bearer {robot_token}"},
        ) as ws:
            ws.send(start(sid))
            ws.send(frame(sid, 2))
            ws.recv(timeout=10)
            ws.recv(timeout=10)
        with connect(f"ws://127.0.0.1:{port}/ws/live?token={bearer}") as ws:
            ws.recv(timeout=10)
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
    text = log.read_text()
    assert f"token={MASK}" in text  # the access log was written, masked
    for secret in (password, wrong, bearer, robot_token, robot_token.split("_", 1)[1]):
        assert secret not in text
