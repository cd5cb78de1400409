"""The 3D view through the ground station's /viser/ proxy, on the real server."""

import logging
import uuid

import httpx
import pytest
import viser
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from robot_link.protocol import MessageType, decode_message
from server.api.accounts import create_user
from server.storage.db import make_engine, make_sessionmaker
from server.storage.models import Role
from tests.conftest import LiveServer
from tests.server.helpers import empty_session, msg, start, ws_url


def view_ws(server: LiveServer) -> str:
    return server.url.replace("http://", "ws://") + "/viser/"


def add_user(server: LiveServer) -> str:
    engine = make_engine(server.settings.resolved_database_url())
    create_user(make_sessionmaker(engine), "ada", "correct horse", Role.viewer)
    engine.dispose()
    r = httpx.post(
        f"{server.url}/api/auth/token", data={"username": "ada", "password": "correct horse"}
    )
    return r.raise_for_status().json()["access_token"]


def test_view_needs_a_token_and_then_keeps_a_cookie(live_server: LiveServer) -> None:
    token = add_user(live_server)
    assert httpx.get(f"{live_server.url}/viser/").status_code == 401
    with httpx.Client() as client:
        page = client.get(f"{live_server.url}/viser/", params={"token": token})
        assert page.status_code == 200 and "<title>Viser</title>" in page.text
        cookie = page.headers["set-cookie"]
        assert (
            "httponly" in cookie.lower()
            and "samesite=strict" in cookie.lower()
            and "path=/viser" in cookie.lower()
        )
        # the cookie is enough now
        assert client.get(f"{live_server.url}/viser/").status_code == 200
    with pytest.raises(InvalidStatus):
        connect(view_ws(live_server), subprotocols=[f"viser-v{viser.__version__}"])  # type: ignore[list-item]


def test_view_websocket_passes_through_to_viser(live_server: LiveServer) -> None:
    token = add_user(live_server)
    with connect(
        f"{view_ws(live_server)}?token={token}", subprotocols=[f"viser-v{viser.__version__}"]
    ) as ws:  # type: ignore[list-item]
        assert ws.subprotocol == f"viser-v{viser.__version__}"
        first = ws.recv(timeout=10)
        assert isinstance(first, bytes) and len(first) > 0  # viser's scene state, msgpack
    assert live_server.app.state.steelscan.scenes.live.port != int(
        live_server.url.rsplit(":", 1)[1]
    )


def test_live_poses_move_the_robot_and_sessions_can_be_shown(live_server: LiveServer) -> None:
    sid = uuid.uuid4()
    with connect(
        ws_url(live_server), additional_headers={"Authorization": f"Bearer {live_server.token}"}
    ) as ws:
        ws.send(start(sid))
        ws.send(msg(sid, 2, MessageType.TELEMETRY, {"pose": {"x": 0.3, "y": 0.4, "yaw": 0.1}}))
        for _ in range(2):
            decode_message(ws.recv(timeout=10))
    scenes = live_server.app.state.steelscan.scenes
    assert scenes.live.session_id == str(sid)  # the live session took over the live view
    shown = httpx.post(f"{live_server.url}/api/sessions/{sid}/view3d").raise_for_status().json()
    assert shown == {
        "session_id": str(sid),
        "points": 0,
        "trajectory_poses": 0,
        "defects": 0,
        "url": f"/viser/session/{sid}/",
    }
    assert httpx.post(f"{live_server.url}/api/sessions/{uuid.uuid4()}/view3d").status_code == 404


def test_each_session_has_its_own_view_and_live_poses_do_not_take_it_over(
    live_server: LiveServer,
) -> None:
    """A finished session's view keeps its scene while another robot is live; the page and
    the websocket of each view reach their own viser server; a browser that leaves a view
    leaves no error in the station's log."""
    import time

    done, live = uuid.uuid4(), uuid.uuid4()
    with connect(
        ws_url(live_server), additional_headers={"Authorization": f"Bearer {live_server.token}"}
    ) as ws:
        ws.send(start(done))
        decode_message(ws.recv(timeout=10))
    shown = httpx.post(f"{live_server.url}/api/sessions/{done}/view3d").raise_for_status().json()
    scenes = live_server.app.state.steelscan.scenes
    own = scenes.get(str(done))
    assert own is not None and own is not scenes.live and own.session_id == str(done)
    with connect(
        ws_url(live_server), additional_headers={"Authorization": f"Bearer {live_server.token}"}
    ) as ws:
        ws.send(start(live))
        ws.send(msg(live, 2, MessageType.TELEMETRY, {"pose": {"x": 0.3, "y": 0.4, "yaw": 0.1}}))
        for _ in range(2):
            decode_message(ws.recv(timeout=10))
    assert scenes.live.session_id == str(live) and own.session_id == str(done)
    page = httpx.get(live_server.url + shown["url"])
    assert page.status_code == 200 and "<title>Viser</title>" in page.text
    assert httpx.get(f"{live_server.url}/viser/session/{uuid.uuid4()}/").status_code == 404
    protocol = [f"viser-v{viser.__version__}"]
    errors: list[str] = []
    handler = logging.Handler(logging.ERROR)
    handler.emit = lambda record: errors.append(record.getMessage())  # type: ignore[method-assign]
    for name in ("uvicorn.error", "server"):
        logging.getLogger(name).addHandler(handler)
    ws_view = live_server.url.replace("http://", "ws://") + shown["url"].removesuffix("/")
    for _ in range(3):  # browsers open the view and leave abruptly
        sock = connect(ws_view, subprotocols=protocol)  # type: ignore[arg-type]
        assert isinstance(sock.recv(timeout=10), bytes)  # the session's scene, msgpack
        sock.socket.close()  # no closing handshake: the peer is just gone
    time.sleep(0.5)
    for name in ("uvicorn.error", "server"):
        logging.getLogger(name).removeHandler(handler)
    assert errors == []


def test_the_map_grows_live_during_a_session(live_server: LiveServer) -> None:
    """Clouds placed by ICP in a worker process while the robot inspects, shown in the view."""
    import asyncio
    import time

    from robot_link.client import RobotLink
    from robot_link.sim.inspection import InspectionSim, SimConfig

    async def run() -> None:
        link = RobotLink(live_server.url, live_server.token)
        await link.start()
        sim = InspectionSim(link, SimConfig(seed=4, lanes=1, time_scale=6.0))
        try:
            await sim.run()
        finally:
            await link.close()

    asyncio.run(run())
    scene = live_server.app.state.steelscan.scenes.live
    deadline = time.monotonic() + 60
    # with the pose graph's trajectory
    while scene.live_map_points == 0 or scene.live_trajectory_poses < 2:
        assert time.monotonic() < deadline, "the live map never showed"
        time.sleep(0.2)
    assert scene.live_map_points > 1000
    assert "map of" in scene._title.content
    # titled by the robot's name, not the session's id
    robot = httpx.get(f"{live_server.url}/api/sessions/{scene.session_id}").json()["robot_name"]
    assert robot and scene._title.content.startswith(f"**Live: {robot}**")
    assert scene.session_id not in scene._title.content


def test_a_defects_3d_text_gives_its_one_position_and_its_box(live_server: LiveServer) -> None:
    """The view's text gives the position the table, PDF and CSV give (world_x_m, world_y_m:
    the box's corner nearest the origin), then the box; the sphere sits in the box's middle."""
    from server.storage.models import Defect

    sid = empty_session(live_server)
    engine = make_engine(live_server.settings.resolved_database_url())
    with make_sessionmaker(engine)() as db:
        d = Defect(
            session_id=str(sid),
            number=8,
            defect_class="crack",
            **dict.fromkeys(("bbox_x", "bbox_y", "bbox_w", "bbox_h", "area_px"), 10),
            **dict.fromkeys(("length_px", "max_width_px", "mean_width_px"), 1.0),
            orientation_deg=0.0,
            length_mm=52.0,
            max_width_mm=0.8,
            world_x_m=0.544,
            world_y_m=0.465,
            world_w_m=0.076,
            world_h_m=0.084,
        )
        db.add(d)
        db.commit()
        defect_id = d.id
    engine.dispose()
    httpx.post(f"{live_server.url}/api/sessions/{sid}/view3d").raise_for_status()
    marker = live_server.app.state.steelscan.scenes.get(str(sid)).markers[defect_id]
    assert "**Defect 8**" in marker.text
    assert "at x 0.544 m, y 0.465 m (the corner of the defect's box nearest" in marker.text
    assert "box x 0.544–0.620 m, y 0.465–0.549 m" in marker.text
    assert "0.582" not in marker.text and "0.507" not in marker.text
    assert (marker.x, marker.y) == pytest.approx((0.582, 0.507))


def test_a_moment_of_the_timeline_moves_the_robot_in_the_sessions_view(
    live_server: LiveServer,
) -> None:
    """The timeline puts the robot at the pose of the moment scrubbed to, in the session's
    own view only; a moment without a view open, or with a pose that is not a number, is
    refused."""
    sid, other = uuid.uuid4(), uuid.uuid4()
    with connect(
        ws_url(live_server), additional_headers={"Authorization": f"Bearer {live_server.token}"}
    ) as ws:
        ws.send(start(sid))
        decode_message(ws.recv(timeout=10))
    url = f"{live_server.url}/api/sessions/{sid}/view3d/moment"
    body = {"x": 0.42, "y": -0.1, "yaw": 1.5, "label": "frame 12 · +00:31"}
    assert httpx.post(url, json=body).status_code == 404  # no view of it open yet
    httpx.post(f"{live_server.url}/api/sessions/{sid}/view3d").raise_for_status()
    assert httpx.post(url, json=body).raise_for_status().json()["yaw"] == 1.5
    scenes = live_server.app.state.steelscan.scenes
    view = scenes.get(str(sid))
    assert view is not None and view.moment == (0.42, -0.1, 1.5)
    assert scenes.live.moment is None  # the live robots' view is not moved
    assert view._moment_text.content == "Robot at frame 12 · +00:31"
    assert "frame 12" not in view._info.content  # the defect's text stays
    for bad in (
        {"x": 0.1, "y": 0.2},
        {**body, "yaw": 1e9},
        {**body, "speed": 3},
        {**body, "label": "x" * 201},
    ):
        assert httpx.post(url, json=bad).status_code == 422, bad
    raw = '{"x": NaN, "y": 0, "yaw": 0}'
    r = httpx.post(url, content=raw, headers={"Content-Type": "application/json"})
    assert r.status_code == 422 and view.moment == (0.42, -0.1, 1.5)
    assert (
        httpx.post(f"{live_server.url}/api/sessions/{other}/view3d/moment", json=body).status_code
        == 404
    )
