"""Crafted MCAP files are refused with 422 and a reason, before anything large is decoded or
decompressed, and leave nothing behind."""

from __future__ import annotations

import io
import struct
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from mcap.writer import CompressionType, Writer

from tests.conftest import LiveServer
from tests.media import jpeg


def _mcap(
    messages: list[tuple[str, bytes]], compression: CompressionType = CompressionType.NONE
) -> bytes:
    buf = io.BytesIO()
    writer = Writer(buf, compression=compression)
    writer.start()
    schema = writer.register_schema("steelscan.Json", "jsonschema", b"{}")
    channels: dict[str, int] = {}
    for i, (topic, data) in enumerate(messages):
        if topic not in channels:
            channels[topic] = writer.register_channel(topic, "json", schema)
        writer.add_message(channels[topic], log_time=i, publish_time=i, data=data, sequence=i)
    writer.finish()
    return buf.getvalue()


def _huge_jpeg() -> bytes:
    """A small JPEG whose frame header declares 20000×20000 pixels."""
    data = bytearray(jpeg(64, 48))
    sof = data.index(b"\xff\xc0")
    struct.pack_into(">HH", data, sof + 5, 20000, 20000)
    return bytes(data)


def _bomb() -> bytes:
    """A compressed chunk whose header says it decompresses to 2 GiB."""
    data = bytearray(
        _mcap([("/robot/telemetry", b'{"a": 1}')] * 50, compression=CompressionType.ZSTD)
    )
    at = 8  # past the magic: the Header record, then the first Chunk
    (header_len,) = struct.unpack_from("<Q", data, at + 1)
    at += 9 + header_len
    assert data[at] == 0x06  # a Chunk: opcode, length, start and end time, uncompressed size
    struct.pack_into("<Q", data, at + 1 + 8 + 16, 2**31)
    return bytes(data)


def _understated(compression: CompressionType) -> bytes:
    """A chunk of 64 MiB of telemetry that says it holds 1,000 bytes (it inflates from a few
    kilobytes: a decompression bomb its header does not announce)."""
    padding = b" " * (64 * 2**20)
    data = bytearray(_mcap([("/robot/telemetry", b'{"a": 1' + padding + b"}")], compression))
    at = 8
    (header_len,) = struct.unpack_from("<Q", data, at + 1)
    at += 9 + header_len
    assert data[at] == 0x06 and len(data) < 2**20
    struct.pack_into("<Q", data, at + 1 + 8 + 16, 1000)
    return bytes(data)


TELEMETRY = "/robot/telemetry"
CASES = {
    "magic only": b"\x89MCAP0\r\n",
    "telemetry that is not JSON": _mcap([(TELEMETRY, b"{not json")]),
    "a text timestamp": _mcap([(TELEMETRY, b'{"timestamp": "soon"}')]),
    "a NaN timestamp": _mcap([(TELEMETRY, b'{"timestamp": NaN}')]),
    "JSON nested too deeply": _mcap(
        [(TELEMETRY, b'{"a":' + b"[" * 100_000 + b"]" * 100_000 + b"}")]
    ),
    "an image declaring 400 megapixels": _mcap(
        [("/camera/image", CompressedImage(format="jpeg", data=_huge_jpeg()).SerializeToString())]
    ),
    "a decompression bomb": _bomb(),
    "a zstd chunk that understates its size": _understated(CompressionType.ZSTD),
    "an lz4 chunk that understates its size": _understated(CompressionType.LZ4),
}


def test_byte_flipped_files_are_refused_with_422_never_500(live_server: LiveServer) -> None:
    import random

    messages = [
        ("/camera/image", CompressedImage(format="jpeg", data=jpeg(64, 48)).SerializeToString()),
        *[(TELEMETRY, b'{"battery_v": {"main": %d}}' % k) for k in range(40)],
    ]
    url = f"{live_server.url}/api/sessions"
    rng = random.Random(7)
    for compression in (CompressionType.ZSTD, CompressionType.LZ4):
        good = _mcap(messages, compression)
        for _ in range(15):
            bad = bytearray(good)
            for _ in range(3):
                bad[rng.randrange(8, len(bad) - 8)] ^= 1 << rng.randrange(8)
            r = httpx.post(f"{url}/import", files={"file": ("flipped.mcap", bytes(bad))})
            assert r.status_code in (201, 422), r.text


@pytest.mark.parametrize("case", list(CASES))
def test_crafted_files_are_refused_with_422(live_server: LiveServer, case: str) -> None:
    url = f"{live_server.url}/api/sessions"
    r = httpx.post(f"{url}/import", files={"file": ("crafted.mcap", CASES[case])}, timeout=60)
    assert r.status_code == 422, r.text
    assert r.json()["detail"]
    assert httpx.get(url).json()["count"] == 0


def test_import_refuses_a_file_that_is_not_an_mcap_session(tmp_path: Path) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"\x89MCAP0\r\n" + b"garbage" * 100)
    data = tmp_path / "data"
    for target in (bad, tmp_path / "missing.mcap"):
        out = subprocess.run(
            [sys.executable, "-m", "server.cli", "import", str(target), "--data-dir", str(data)],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert out.returncode != 0 and out.stderr.strip().splitlines()[-1].startswith("error: ")
        assert "Traceback" not in out.stderr
    # nothing left behind
    assert not (data / "sessions").exists() or not list((data / "sessions").glob("*"))
