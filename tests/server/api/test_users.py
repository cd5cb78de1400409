"""Accounts over REST (admin role) on the real server: add, change role and password,
remove; never the last admin, never yourself; viewers and operators may not."""

from __future__ import annotations

import httpx

from server.storage.models import Role
from tests.conftest import LiveServer
from tests.server.helpers import add_user, login


def test_admins_manage_accounts(live_server: LiveServer) -> None:
    url = f"{live_server.url}/api/users"
    # no account yet: the open station's anonymous admin adds the first, and sign-in starts
    first = httpx.post(url, json={"name": "ada", "password": "correct horse", "role": "admin"})
    assert first.status_code == 201 and first.json()["role"] == "admin"
    assert httpx.get(url).status_code == 401
    admin = login(live_server, "ada")
    assert (
        httpx.post(url, json={"name": "otto", "password": "short"}, headers=admin).status_code
        == 422
    )
    assert (
        httpx.post(url, json={"name": "otto", "password": "long enough"}, headers=admin).status_code
        == 201
    )
    assert (
        httpx.post(url, json={"name": "otto", "password": "long enough"}, headers=admin).status_code
        == 409
    )
    assert [u["name"] for u in httpx.get(url, headers=admin).json()] == ["ada", "otto"]
    otto = login(live_server, "otto", "long enough")
    assert httpx.get(url, headers=otto).status_code == 403  # a viewer
    r = httpx.patch(f"{url}/otto", json={"role": "operator"}, headers=admin)
    assert r.status_code == 200 and r.json()["role"] == "operator"
    assert httpx.get(url, headers=otto).status_code == 403  # an operator still may not
    # a new password signs the account out everywhere
    assert (
        httpx.patch(f"{url}/otto", json={"password": "another one"}, headers=admin).status_code
        == 200
    )
    assert httpx.get(f"{live_server.url}/api/auth/me", headers=otto).status_code == 401
    login(live_server, "otto", "another one")
    # never without an admin, never yourself
    assert httpx.patch(f"{url}/ada", json={"role": "viewer"}, headers=admin).status_code == 409
    assert httpx.delete(f"{url}/ada", headers=admin).status_code == 409
    assert httpx.delete(f"{url}/nobody", headers=admin).status_code == 404
    assert httpx.delete(f"{url}/otto", headers=admin).status_code == 204
    assert (
        httpx.post(
            f"{live_server.url}/api/auth/token",
            data={"username": "otto", "password": "another one"},
        ).status_code
        == 401
    )


def test_an_operator_cannot_add_an_admin(live_server: LiveServer) -> None:
    add_user(live_server, "otto", Role.operator)
    otto = login(live_server, "otto")
    body = {"name": "mallory", "password": "correct horse", "role": "admin"}
    assert httpx.post(f"{live_server.url}/api/users", json=body, headers=otto).status_code == 403
