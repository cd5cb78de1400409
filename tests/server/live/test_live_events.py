"""The browser events are defined once: the dashboard's constants are generated from the
models and documented in the protocol, and a drift fails here."""

from pathlib import Path

from server.live.events import EVENTS, CommandAck, FrameHeader, Hello, event_type, javascript

ROOT = Path(__file__).resolve().parents[3]


def test_the_dashboards_event_constants_are_generated_from_the_models() -> None:
    written = (ROOT / "web" / "js" / "events.js").read_text()
    assert written == javascript(), "run: python -m server.live.events > web/js/events.js"


def test_every_event_is_documented_with_its_fields() -> None:
    doc = (ROOT / "docs" / "protocol.md").read_text()
    section = doc[doc.index("## Browsers: `/ws/live`") :]
    for model in EVENTS:
        row = next(
            (
                line
                for line in section.splitlines()
                if line.startswith(f"| `{event_type(model)}` |")
            ),
            None,
        )
        assert row is not None, f"{event_type(model)} is not in docs/protocol.md"
        for name in model.model_fields:
            if name != "type":
                assert f"`{name}`" in row, f"{event_type(model)}.{name} is not documented"


def test_the_dashboard_matches_on_the_generated_constants_only() -> None:
    for js in (ROOT / "web" / "js").glob("*.js"):
        text = js.read_text()
        for model in EVENTS:
            assert f'type === "{event_type(model)}"' not in text, (js.name, event_type(model))


def test_events_serialise_as_the_dashboard_reads_them() -> None:
    import json
    import struct

    assert json.loads(Hello(watcher_id=3).text()) == {"type": "hello", "watcher_id": 3}
    ack = json.loads(CommandAck(session_id="s", seq=4, cmd="stop", reason="estopped").text())
    assert ack["type"] == "command_ack" and ack["reason"] == "estopped"
    data = FrameHeader(session_id="s", seq=2, t=1.5).pack(b"\xff\xd8jpeg")
    (size,) = struct.unpack_from("<I", data)
    assert json.loads(data[4 : 4 + size])["seq"] == 2 and data[4 + size :] == b"\xff\xd8jpeg"
