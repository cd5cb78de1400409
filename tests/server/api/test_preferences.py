"""Each user's dashboard preferences over REST on the real server: kept per account,
merged key by key, bounded, and removed with the account."""

from __future__ import annotations

import httpx

from server.storage.models import Role
from tests.conftest import LiveServer
from tests.server.helpers import add_user, login


def test_preferences_are_kept_per_user_and_merged(live_server: LiveServer) -> None:
    url = f"{live_server.url}/api/auth/me/preferences"
    # the open station's anonymous user keeps preferences too
    assert httpx.get(url).json() == {}
    assert httpx.patch(url, json={"plot_fields": ["distance_m"]}).json() == {
        "plot_fields": ["distance_m"]
    }
    add_user(live_server, "ada", Role.admin)
    add_user(live_server, "otto", Role.viewer)
    assert httpx.get(url).status_code == 401  # accounts exist: sign in first
    ada, otto = login(live_server, "ada"), login(live_server, "otto")
    assert httpx.get(url, headers=ada).json() == {}  # not anonymous's
    fields = ["battery_v.main", "wheel_speed_mps[0]"]
    assert httpx.patch(url, json={"plot_fields": fields}, headers=ada).status_code == 200
    layout = {"video": "open", "plots": "closed"}
    merged = httpx.patch(url, json={"drive_panels": layout}, headers=ada).json()
    assert merged == {"plot_fields": fields, "drive_panels": layout}
    assert httpx.get(url, headers=otto).json() == {}  # a viewer keeps their own
    assert httpx.patch(url, json={"plot_fields": ["x"]}, headers=otto).status_code == 200
    assert httpx.get(url, headers=ada).json()["plot_fields"] == fields
    # null removes a key
    assert httpx.patch(url, json={"drive_panels": None}, headers=ada).json() == {
        "plot_fields": fields
    }
    # bounded, and a refused change changes nothing
    huge = {"plot_fields": ["f" * 1000] * 20}
    assert httpx.patch(url, json=huge, headers=ada).status_code == 413
    many = {f"k{i}": 1 for i in range(65)}
    assert httpx.patch(url, json=many, headers=ada).status_code == 422
    assert httpx.patch(url, json={"x" * 101: 1}, headers=ada).status_code == 422
    assert httpx.patch(url, json=[1, 2], headers=ada).status_code == 422
    nan = httpx.patch(
        url, content='{"a": NaN}', headers={**ada, "Content-Type": "application/json"}
    )
    assert nan.status_code == 422
    assert httpx.get(url, headers=ada).json() == {"plot_fields": fields}
    # an account removed takes its preferences along; a new one of that name starts empty
    users = f"{live_server.url}/api/users"
    assert httpx.delete(f"{users}/otto", headers=ada).status_code == 204
    add_user(live_server, "otto", Role.viewer)
    assert httpx.get(url, headers=login(live_server, "otto")).json() == {}
