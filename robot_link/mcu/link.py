"""The host side of the MCU serial link: handshake, commands, sensor packets and the line's
health (silent or garbled lines raise a fault the on-board safety acts on).

One serial device, read by the event loop when bytes arrive (no polling thread); a
watchdog task notices silence and reopens a device that went away.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import serial

from robot_link.mcu.framing import Frame, FrameError, FrameReader, encode_frame
from robot_link.mcu.packets import (
    PROTOCOL_VERSION,
    Ack,
    Drive,
    FaultReport,
    HelloReply,
    Lift,
    PacketError,
    PacketType,
    Sensors,
    hello_body,
)

log = logging.getLogger(__name__)


class McuError(RuntimeError):
    """The MCU cannot be reached or does not speak the protocol."""


@dataclass
class LineHealth:
    """What the host measured of the serial line."""

    packets: int = 0
    bad_frames: int = 0
    bad_in_a_row: int = 0
    lost_packets: int = 0
    reopened: int = 0
    last_packet: float = float("-inf")  # monotonic time of the last good packet
    error: str | None = None  # why the line cannot be trusted now

    def as_meta(self) -> dict[str, object]:
        """The line's state for telemetry."""
        age = time.monotonic() - self.last_packet
        return {
            "packets": self.packets,
            "bad_frames": self.bad_frames,
            "lost_packets": self.lost_packets,
            "reopened": self.reopened,
            "last_packet_ms": round(age * 1000, 1) if age < 1e6 else None,
            "error": self.error,
        }


class McuLink:
    """A connection to the MCU over ``device``.

    ``silent_s``: no packet for this long is a fault; ``garbled_frames``: this many damaged
    frames in a row is a fault. Faults are reported through ``on_fault`` (its text; None once
    the line is healthy again).
    """

    def __init__(
        self,
        device: str,
        *,
        baud: int = 115200,
        silent_s: float = 0.3,
        garbled_frames: int = 5,
        on_sensors: Callable[[Sensors], None] | None = None,
        on_fault: Callable[[str | None], None] | None = None,
    ) -> None:
        self.device = device
        self.baud = baud
        self.silent_s = silent_s
        self.garbled_frames = garbled_frames
        self.on_sensors = on_sensors
        self.on_fault = on_fault
        self.health = LineHealth()
        self.info: HelloReply | None = None
        self.latest: Sensors | None = None
        self.faults: list[FaultReport] = []
        self._serial: serial.Serial | None = None
        self._reader = FrameReader()
        self._seq = 0
        self._mcu_seq: int | None = None
        self._acks: dict[int, asyncio.Future[Ack]] = {}
        self._hello: asyncio.Future[HelloReply] | None = None
        self._watchdog: asyncio.Task[None] | None = None

    async def open(self, timeout_s: float = 1.0) -> HelloReply:
        """Open the device and shake hands; McuError if it cannot be opened or is silent."""
        self._open_device()
        try:
            reply = await self._handshake(timeout_s)
        except McuError:
            self._close_device()
            raise
        self.health.last_packet = time.monotonic()
        self._watchdog = asyncio.create_task(self._watch())
        return reply

    async def close(self) -> None:
        """Stop the wheels (best effort) and close the device."""
        if self._watchdog is not None:
            self._watchdog.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._watchdog
        if self._serial is not None:
            with contextlib.suppress(OSError, serial.SerialException):
                self.send(PacketType.STOP)
        self._close_device()

    def send(self, ptype: PacketType, body: bytes = b"") -> int:
        """Send one command; its sequence number."""
        self._seq = (self._seq + 1) & 0xFF
        if self._serial is None:
            raise McuError(f"the MCU on {self.device} is not connected")
        try:
            self._serial.write(encode_frame(ptype, self._seq, body))
        except (OSError, serial.SerialException) as exc:
            self._lost(f"cannot write to {self.device}: {exc}")
            raise McuError(str(self.health.error)) from None
        return self._seq

    async def request(self, ptype: PacketType, body: bytes = b"", timeout_s: float = 0.2) -> Ack:
        """Send one command and wait for its ACK; McuError when none comes."""
        seq = self.send(ptype, body)
        future = asyncio.get_running_loop().create_future()
        self._acks[seq] = future
        try:
            return await asyncio.wait_for(future, timeout_s)
        except TimeoutError:
            raise McuError(
                f"the MCU did not acknowledge {ptype.name} within {timeout_s} s"
            ) from None
        finally:
            self._acks.pop(seq, None)

    def drive(self, left_mps: float, right_mps: float, hold_s: float) -> int:
        """Wheel speeds per side, held for ``hold_s`` (the MCU stops after that)."""
        return self.send(PacketType.DRIVE, Drive(left_mps, right_mps, hold_s).pack())

    def lift(self, axle: str, up: bool) -> int:
        """Raise or lower an axle's lift."""
        return self.send(PacketType.LIFT, Lift(axle, up).pack())

    @property
    def ok(self) -> bool:
        """Whether the line is healthy now."""
        return self._serial is not None and self.health.error is None

    def _open_device(self) -> None:
        try:
            self._serial = serial.Serial(
                self.device, self.baud, timeout=0, write_timeout=0.5, exclusive=True
            )
        except (OSError, ValueError, serial.SerialException) as exc:
            raise McuError(f"cannot open the MCU's serial device {self.device}: {exc}") from None
        self._reader = FrameReader()
        asyncio.get_running_loop().add_reader(self._serial.fileno(), self._readable)

    def _close_device(self) -> None:
        if self._serial is None:
            return
        with contextlib.suppress(Exception):
            asyncio.get_running_loop().remove_reader(self._serial.fileno())
        with contextlib.suppress(Exception):
            self._serial.close()
        self._serial = None

    async def _handshake(self, timeout_s: float) -> HelloReply:
        self._hello = asyncio.get_running_loop().create_future()
        self.send(PacketType.HELLO, hello_body())
        try:
            reply = await asyncio.wait_for(self._hello, timeout_s)
        except TimeoutError:
            raise McuError(
                f"the MCU on {self.device} did not answer within {timeout_s} s "
                "(check the wiring, the baud rate and that its firmware runs)"
            ) from None
        if reply.version != PROTOCOL_VERSION:
            raise McuError(
                f"the MCU speaks protocol version {reply.version}, this agent {PROTOCOL_VERSION}"
            )
        self.info = reply
        return reply

    def _readable(self) -> None:
        assert self._serial is not None
        try:
            data = self._serial.read(self._serial.in_waiting or 1)
        except (OSError, serial.SerialException) as exc:
            self._lost(f"the MCU's serial device {self.device} went away: {exc}")
            return
        for item in self._reader.feed(data):
            if isinstance(item, FrameError):
                self._bad(str(item))
            else:
                self._frame(item)

    def _frame(self, frame: Frame) -> None:
        try:
            self._dispatch(frame)
        except (PacketError, ValueError) as exc:
            self._bad(f"packet 0x{frame.type:02x}: {exc}")
            return
        h = self.health
        h.packets += 1
        h.bad_in_a_row = 0
        h.last_packet = time.monotonic()
        if self._mcu_seq is not None:
            h.lost_packets += (frame.seq - self._mcu_seq - 1) & 0xFF
        self._mcu_seq = frame.seq
        if h.error is not None and self._serial is not None:
            h.error = None
            self._fault(None)

    def _dispatch(self, frame: Frame) -> None:
        ptype = PacketType(frame.type)
        if ptype is PacketType.SENSORS:
            self.latest = Sensors.unpack(frame.body)
            if self.on_sensors is not None:
                self.on_sensors(self.latest)
        elif ptype is PacketType.ACK:
            ack = Ack.unpack(frame.body)
            future = self._acks.get(ack.seq)
            if future is not None and not future.done():
                future.set_result(ack)
        elif ptype is PacketType.HELLO_REPLY:
            reply = HelloReply.unpack(frame.body)
            if self._hello is not None and not self._hello.done():
                self._hello.set_result(reply)
        elif ptype is PacketType.FAULT:
            report = FaultReport.unpack(frame.body)
            self.faults = [*self.faults[-19:], report]
            log.warning("MCU fault %s: %s", report.faults, report.text)
        else:
            raise PacketError(f"type {ptype.name} does not come from an MCU")

    def _bad(self, why: str) -> None:
        h = self.health
        h.bad_frames += 1
        h.bad_in_a_row += 1
        if h.bad_in_a_row >= self.garbled_frames and h.error is None:
            h.error = f"the MCU line is garbled: {h.bad_in_a_row} damaged frames in a row ({why})"
            self._fault(h.error)

    def _lost(self, why: str) -> None:
        self._close_device()
        if self.health.error != why:
            self.health.error = why
            self._fault(why)

    def _fault(self, why: str | None) -> None:
        if why:
            log.error("MCU link: %s", why)
        if self.on_fault is not None:
            self.on_fault(why)

    async def _watch(self) -> None:
        """Notice a silent line; reopen a device that went away."""
        while True:
            await asyncio.sleep(min(0.05, self.silent_s / 4))
            h = self.health
            if self._serial is None:
                await self._reopen()
                continue
            silent = time.monotonic() - h.last_packet
            if silent > self.silent_s and h.error is None:
                h.error = f"the MCU has been silent for {silent * 1000:.0f} ms"
                self._fault(h.error)

    async def _reopen(self) -> None:
        await asyncio.sleep(0.5)
        try:
            self._open_device()
            await self._handshake(1.0)
        except McuError:
            self._close_device()
            return
        self.health.reopened += 1
        self.health.last_packet = time.monotonic()
