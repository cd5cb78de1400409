"""A file upload streamed from the request into the data directory: after the route's
dependencies have authenticated the caller (the route declares no body parameter, so
nothing is read before), each chunk claimed from the disk reserve before it is written,
within the route's size cap. A ``multipart/form-data`` body (its ``file`` field, as a
browser's form sends it) or the raw file as the body."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

import anyio
from fastapi import HTTPException, Request, status
from python_multipart.multipart import MultipartParseError, MultipartParser, parse_options_header

from server.errors import IngestError

Claim = Callable[[int], None]  # raises IngestError when the bytes would not fit


async def receive_upload(
    request: Request, dest: Path, max_bytes: int, claim: Claim, field: str = "file"
) -> str:
    """Write the uploaded file to ``dest``; its name as the client gave it. 413 past
    ``max_bytes``, 507 when the disk reserve refuses, 400 for a malformed form."""
    content_type, options = parse_options_header(request.headers.get("content-type", ""))
    with dest.open("wb") as fh:
        sink = _Sink(fh, max_bytes, claim)
        if content_type == b"multipart/form-data":
            boundary = options.get(b"boundary")
            if not boundary:
                raise HTTPException(400, "a multipart body needs a boundary")
            form = _FileField(sink, field)
            parser = MultipartParser(boundary, form.callbacks())
            try:
                async for chunk in request.stream():
                    await anyio.to_thread.run_sync(parser.write, chunk)
                parser.finalize()
            except MultipartParseError as exc:
                raise HTTPException(400, f"malformed form: {exc}") from None
            if not form.found:
                raise HTTPException(422, f"the form has no '{field}' file")
            return form.filename or "upload"
        async for chunk in request.stream():
            await anyio.to_thread.run_sync(sink.write, chunk)
    return request.headers.get("x-filename", "upload")


class _Sink:
    """Bytes into the file, counted against the cap and claimed from the reserve."""

    def __init__(self, fh: BinaryIO, max_bytes: int, claim: Claim) -> None:
        self.fh, self.max_bytes, self.claim, self.size = fh, max_bytes, claim, 0

    def write(self, data: bytes) -> None:
        self.size += len(data)
        if self.size > self.max_bytes:
            raise HTTPException(
                status.HTTP_413_REQUEST_ENTITY_TOO_LARGE,
                f"the file is larger than the import limit of {self.max_bytes} bytes",
            )
        try:
            self.claim(len(data))
        except IngestError as exc:
            raise HTTPException(status.HTTP_507_INSUFFICIENT_STORAGE, str(exc)) from None
        self.fh.write(data)


class _FileField:
    """The callbacks that pick one file field out of a multipart stream."""

    def __init__(self, sink: _Sink, field: str) -> None:
        self.sink, self.field = sink, field
        self.found, self.filename = False, ""
        self._header, self._value = b"", b""
        self._headers: dict[bytes, bytes] = {}
        self._writing = False

    def callbacks(self) -> Any:
        def header_field(data: bytes, start: int, end: int) -> None:
            self._header += data[start:end]

        def header_value(data: bytes, start: int, end: int) -> None:
            self._value += data[start:end]

        def header_end() -> None:
            self._headers[self._header.lower()] = self._value
            self._header, self._value = b"", b""

        def headers_finished() -> None:
            _, params = parse_options_header(self._headers.get(b"content-disposition", b""))
            name = params.get(b"name", b"").decode("utf-8", "replace")
            self._writing = name == self.field and not self.found
            if self._writing:
                self.found = True
                self.filename = params.get(b"filename", b"").decode("utf-8", "replace")

        def part_data(data: bytes, start: int, end: int) -> None:
            if self._writing:
                self.sink.write(data[start:end])

        def part_end() -> None:
            self._writing = False
            self._headers = {}

        return {
            "on_header_field": header_field,
            "on_header_value": header_value,
            "on_header_end": header_end,
            "on_headers_finished": headers_finished,
            "on_part_data": part_data,
            "on_part_end": part_end,
        }
