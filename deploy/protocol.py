"""The JetRacer motor-controller serial protocol (docs/serial_protocol.md): messages and framing.

A frame on the wire is COBS(body) followed by one 0x00 byte; body = version, type, sequence number,
payload length (one byte each), the payload, and a CRC-16/CCITT-FALSE (little-endian) over all of it.
`FrameDecoder` turns any byte stream into valid messages: garbage, truncated or corrupted frames are
counted and dropped, and decoding resynchronises at the next 0x00. Runs on Python 3.8.
"""

from __future__ import annotations

import binascii
import math
import struct
from dataclasses import dataclass
from typing import Dict, Iterator, List, Optional, Tuple

from cobs import cobs

VERSION = 1
DELIMITER = b"\x00"
MAX_PAYLOAD = 32
MAX_BODY = 4 + MAX_PAYLOAD + 2

# Host -> controller
HELLO, ARM, DRIVE, STOP, ESTOP, DISARM = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
# Controller -> host
INFO, TELEMETRY, NACK = 0x81, 0x82, 0x83

# payload layouts (little-endian) per message type
PAYLOADS: Dict[int, struct.Struct] = {
    HELLO: struct.Struct("<"),
    ARM: struct.Struct("<HH"),  # watchdog period ms, throttle cap (thousandths)
    DRIVE: struct.Struct("<hh"),  # steering, throttle (thousandths, -1000..1000)
    STOP: struct.Struct("<"),
    ESTOP: struct.Struct("<"),
    DISARM: struct.Struct("<"),
    INFO: struct.Struct("<BBBHH"),  # protocol version, firmware major, minor, min and max watchdog ms
    TELEMETRY: struct.Struct("<BBhhBI"),  # acked seq, acked type, applied steering, throttle, status, uptime ms
    NACK: struct.Struct("<BBB"),  # refused seq, refused type, reason
}
NAMES = {HELLO: "HELLO", ARM: "ARM", DRIVE: "DRIVE", STOP: "STOP", ESTOP: "ESTOP", DISARM: "DISARM",
         INFO: "INFO", TELEMETRY: "TELEMETRY", NACK: "NACK"}  # fmt: skip

# TELEMETRY status bits
STATUS_ARMED, STATUS_ESTOP_LATCHED, STATUS_WATCHDOG_TRIPPED = 0x01, 0x02, 0x04
# NACK reasons
UNKNOWN_TYPE, BAD_LENGTH, NOT_ARMED, ESTOP_LATCHED, OUT_OF_RANGE, BAD_VERSION = 1, 2, 3, 4, 5, 6
REASONS = {UNKNOWN_TYPE: "unknown type", BAD_LENGTH: "bad length", NOT_ARMED: "not armed",
           ESTOP_LATCHED: "e-stop latched", OUT_OF_RANGE: "out of range", BAD_VERSION: "bad version"}  # fmt: skip


@dataclass(frozen=True)
class Message:
    """One message: its type, the sender's sequence number (0-255), its payload fields as integers in the
    order and widths of PAYLOADS[type], and the protocol version."""

    type: int
    seq: int
    fields: Tuple[int, ...] = ()
    version: int = VERSION

    def __str__(self) -> str:
        return f"{NAMES.get(self.type, hex(self.type))}#{self.seq}{self.fields}"


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE: polynomial 0x1021, initial value 0xFFFF (check value 0x29B1 for b'123456789')."""
    return binascii.crc_hqx(data, 0xFFFF)


def encode(message: Message) -> bytes:
    """The frame for one message, delimiter included. ValueError for an unknown type or bad fields."""
    layout = PAYLOADS.get(message.type)
    if layout is None:
        raise ValueError(f"unknown message type {message.type:#x}")
    try:
        payload = layout.pack(*message.fields)
    except struct.error as err:
        raise ValueError(f"bad fields for {NAMES[message.type]}: {message.fields} ({err})") from None
    body = bytes([message.version, message.type, message.seq & 0xFF, len(payload)]) + payload
    return cobs.encode(body + struct.pack("<H", crc16(body))) + DELIMITER


def parse_body(body: bytes) -> Tuple[Optional[Message], str]:
    """A message from a decoded body, or (None, why) for a body that fails the CRC or the layout.

    A body with a good CRC whose type or length is wrong still yields a Message with empty fields
    and the reason, so that a controller can NACK it.
    """
    if len(body) < 6:
        return None, "short"
    if crc16(body[:-2]) != struct.unpack("<H", body[-2:])[0]:
        return None, "crc"
    version, kind, seq, length = body[0], body[1], body[2], body[3]
    payload = body[4:-2]
    if length != len(payload):
        return Message(kind, seq, (), version), "length"
    if version != VERSION:
        return Message(kind, seq, (), version), "version"
    layout = PAYLOADS.get(kind)
    if layout is None:
        return Message(kind, seq, (), version), "type"
    if layout.size != len(payload):
        return Message(kind, seq, (), version), "length"
    return Message(kind, seq, layout.unpack(payload), version), ""


class FrameDecoder:
    """Incremental decoder: feed() any bytes, get the messages of the complete, valid frames in them."""

    def __init__(self) -> None:
        self._buffer = bytearray()
        self.dropped: Dict[str, int] = {}  # why frames were dropped, counted
        self.refusable: List[Tuple[Message, str]] = []  # good-CRC frames with a bad type, length or version

    def _drop(self, why: str) -> None:
        self.dropped[why] = self.dropped.get(why, 0) + 1

    def feed(self, data: bytes) -> Iterator[Message]:
        """The messages of the frames `data` completes, in order; bytes of an unfinished frame wait for the next
        call. A dropped frame is counted in `dropped` by cause, and a refusable one added to `refusable`."""
        self._buffer.extend(data)
        while True:
            end = self._buffer.find(0)
            if end < 0:
                if len(self._buffer) > 2 * MAX_BODY:  # no delimiter in sight: garbage, keep only a tail
                    del self._buffer[: len(self._buffer) - MAX_BODY]
                    self._drop("overlong")
                return
            chunk = bytes(self._buffer[:end])
            del self._buffer[: end + 1]
            if not chunk:
                continue  # back-to-back delimiters, a common way to resynchronise
            if len(chunk) > MAX_BODY + 1:  # COBS adds one byte to a body this short
                self._drop("overlong")
                continue
            try:
                body = cobs.decode(chunk)
            except cobs.DecodeError:
                self._drop("cobs")
                continue
            message, why = parse_body(body)
            if message is None:
                self._drop(why)
            elif why:
                self._drop(why)
                self.refusable.append((message, why))
            else:
                yield message


def to_thousandths(value: float) -> int:
    """A command in [-1, 1] as the protocol's signed thousandths (clamped); ValueError if not finite
    (clamping would turn NaN into a full command: min(1.0, nan) is 1.0)."""
    if not math.isfinite(value):
        raise ValueError(f"a command must be a finite number, got {value}")
    return int(round(max(-1.0, min(1.0, value)) * 1000))
