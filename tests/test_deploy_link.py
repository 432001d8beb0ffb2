"""deploy/: the serial protocol, the mock firmware's state machine, and the host link over mock ports and a pty."""

import queue
import re
import threading
import time
from collections import deque
from contextlib import contextmanager

import numpy as np
import pytest
import serial
from cobs import cobs
from hypothesis import given, settings
from hypothesis import strategies as st

import warm_python
from conftest import ROOT, figures_stated, table_cells
from deploy import protocol as p
from deploy.link import HostLink
from deploy.mock_controller import MockController, PtyController, register_url_scheme

MESSAGES = [
    p.Message(p.HELLO, 0),
    p.Message(p.ARM, 1, (250, 600)),
    p.Message(p.DRIVE, 2, (-1000, 550)),
    p.Message(p.STOP, 3),
    p.Message(p.ESTOP, 4),
    p.Message(p.DISARM, 255),
    p.Message(p.INFO, 5, (1, 1, 0, 50, 2000)),
    p.Message(p.TELEMETRY, 6, (2, p.DRIVE, -1000, 550, p.STATUS_ARMED, 123456)),
    p.Message(p.NACK, 7, (2, p.DRIVE, p.NOT_ARMED)),
]


def test_every_message_round_trips_and_frames_have_one_delimiter():
    decoder = p.FrameDecoder()
    stream = b"".join(p.encode(m) for m in MESSAGES)
    assert stream.count(0) == len(MESSAGES)
    assert list(decoder.feed(stream)) == MESSAGES
    assert p.crc16(b"123456789") == 0x29B1  # CRC-16/CCITT-FALSE check value
    with pytest.raises(ValueError, match="bad fields for DRIVE"):
        p.encode(p.Message(p.DRIVE, 0, (40000, 0)))
    assert 0x7F not in p.PAYLOADS
    with pytest.raises(ValueError, match=r"^unknown message type 0x7f$"):  # a frame no controller could parse is never sent
        p.encode(p.Message(0x7F, 0, ()))


def test_the_documented_example_frame():
    assert p.encode(p.Message(p.DRIVE, 7, (-250, 500))) == bytes.fromhex("0b 01 03 07 04 06 ff f4 01 f6 c8 00")


def test_the_protocol_document_states_the_codes_layouts_and_limits_in_code():
    """docs/serial_protocol.md is the contract firmware is written from: its message tables (type, name,
    payload fields and widths), status bits, NACK reasons, frame limits, the reference controller's
    values and the host's defaults are those of deploy/protocol.py, mock_controller.py and link.py."""
    from deploy import jetracer, mock_controller

    text = (ROOT / "docs" / "serial_protocol.md").read_text()
    widths = {"u8": "B", "u16": "H", "i16": "h", "u32": "I"}
    documented = {}
    for section in ("## Messages, host to controller", "## Messages, controller to host"):
        for line in text.split(section, 1)[1].split("\n\n", 2)[1].splitlines()[2:]:  # the table, past its header
            code, name, payload, _ = table_cells(line)
            fields = re.findall(r"(\w+) ([ui]\d+)", payload)
            assert fields or payload == "none", line
            documented[int(code, 16)] = (name, "<" + "".join(widths[width] for _, width in fields))
    assert documented == {code: (p.NAMES[code], layout.format) for code, layout in p.PAYLOADS.items()}
    flat, link = " ".join(text.split()), HostLink("mockjetracer://")  # not started: its defaults
    bits = dict(re.findall(r"(0x0\d) (armed|e-stop latched|watchdog tripped)", flat.split("status** bits:", 1)[1][:80]))
    assert {int(bit, 16): name for bit, name in bits.items()} == {p.STATUS_ARMED: "armed", p.STATUS_ESTOP_LATCHED: "e-stop latched", p.STATUS_WATCHDOG_TRIPPED: "watchdog tripped"}
    reasons = re.findall(r"(\d) ([a-z -]+?)[,.]", flat.split("**reasons**:", 1)[1].split("## ", 1)[0])
    assert {int(code): reason for code, reason in reasons} == p.REASONS
    stated = [
        (r"payload length in bytes \(u8, at most (\d+)\)", (p.MAX_PAYLOAD,)),
        (r"longer than (\d+) bytes before decoding \(the COBS encoding of the longest body, (\d+) bytes; (\d+) with the 0x00\)",
         (len(cobs.encode(bytes(range(1, p.MAX_BODY + 1)))), p.MAX_BODY, p.MAX_BODY + 2)),
        (r"The reference values are version (\d+), firmware (\d+)\.(\d+), watchdog (\d+)–(\d+) ms",
         (p.VERSION, *mock_controller.FIRMWARE_VERSION, mock_controller.MIN_WATCHDOG_MS, mock_controller.MAX_WATCHDOG_MS)),
        (r"an unsolicited TELEMETRY at least every (\d+) ms", (round(1000 * mock_controller.TELEMETRY_PERIOD),)),
        (r"ARM with the configured watchdog period \(default (\d+) ms\)", (link.watchdog_ms,)),
        (r"default ([\d.]+) × the control rate, (\d+) Hz at (\d+) Hz control",
         (jetracer.SENDS_PER_PERIOD, jetracer.SENDS_PER_PERIOD * jetracer.Common().control_hz, jetracer.Common().control_hz)),
        (r"exponential back-off \((\d+) ms doubling to (\d+) s\)", (1000 * link.backoff[0], link.backoff[1])),
        (r"keeps the latest (\d+) NACKs", (link.nacks.maxlen,)),
    ]
    for pattern, expected in stated:
        assert figures_stated(text, pattern) == [expected], (pattern, figures_stated(text, pattern), expected)


def test_decoder_resynchronises_after_garbage_and_split_reads():
    decoder = p.FrameDecoder()
    # garbage glued to a frame spoils that frame (it is dropped, not misread); the next delimiter resynchronises
    stream = (b"\x17\x99garbage" + p.encode(MESSAGES[1]) + b"\x00" + p.encode(MESSAGES[2])
              + b"\xff" * 500 + b"\x00" + p.encode(MESSAGES[7]))  # fmt: skip
    got = []
    for i in range(0, len(stream), 3):  # three bytes per read
        got += list(decoder.feed(stream[i : i + 3]))
    assert got == [MESSAGES[2], MESSAGES[7]]
    assert sum(decoder.dropped.values()) >= 2


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=400))
def test_decoder_never_raises_on_random_bytes(data):
    decoder = p.FrameDecoder()
    for message in decoder.feed(data):  # a random frame with a valid CRC is possible, but must parse
        assert message.type in p.PAYLOADS


@settings(max_examples=300, deadline=None)
@given(st.lists(st.sampled_from(MESSAGES), min_size=1, max_size=8), st.data())
def test_corrupted_frames_are_dropped_never_misread(messages, data):
    stream = bytearray(b"".join(p.encode(m) for m in messages))
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, len(stream) - 1))
        stream[i] ^= data.draw(st.integers(1, 255))
    got = list(p.FrameDecoder().feed(bytes(stream)))
    assert len(got) <= len(messages)
    for message in got:  # whatever survives is one of the messages sent, intact
        assert message in messages


def frames(controller):
    return list(p.FrameDecoder().feed(controller.take_output()))


def send(controller, message, now):
    controller.receive(p.encode(message), now)
    return frames(controller)


def frame_body(body: bytes) -> bytes:
    """A raw body framed with a good CRC, whatever its header says (p.encode only writes valid ones)."""
    return p.cobs.encode(body + p.crc16(body).to_bytes(2, "little")) + p.DELIMITER


def send_body(controller, body: bytes, now):
    controller.receive(frame_body(body), now)
    return frames(controller)


def test_frames_shorter_or_longer_than_any_body_are_dropped_as_such():
    decoder = p.FrameDecoder()
    for n in range(4):  # less than a header and a CRC, with a good CRC: dropped before anything is indexed
        assert list(decoder.feed(frame_body(bytes(n)))) == []
    assert decoder.dropped == {"short": 4}
    longest = bytes([p.VERSION, 0x84, 0, p.MAX_PAYLOAD]) + bytes(p.MAX_PAYLOAD)  # the longest body, of a type unknown here
    assert list(decoder.feed(frame_body(longest))) == [] and decoder.dropped == {"short": 4, "type": 1}
    one_more = bytes([p.VERSION, 0x84, 0, p.MAX_PAYLOAD + 1]) + bytes(p.MAX_PAYLOAD + 1)
    assert list(decoder.feed(frame_body(one_more))) == [] and decoder.dropped == {"short": 4, "type": 1, "overlong": 1}
    assert list(decoder.feed(b"\x01" * (2 * p.MAX_BODY + 1))) == []  # no delimiter in sight: counted, and only a tail kept
    assert decoder.dropped["overlong"] == 2 and len(decoder._buffer) == p.MAX_BODY
    assert list(decoder.feed(b"\x00" + p.encode(MESSAGES[2]))) == [MESSAGES[2]]


def test_commands_are_rounded_and_clamped_to_thousandths():
    values = [0.7777, -0.7777, 0.0004, 0.0006, -0.0006, 1.5, -3.0, 1.0, -1.0, 0.0]
    assert [p.to_thousandths(v) for v in values] == [778, -778, 0, 1, -1, 1000, -1000, 1000, -1000, 0]


def test_watchdog_trips_exactly_after_the_armed_period():
    c = MockController(now=0.0)
    (ack,) = send(c, p.Message(p.ARM, 1, (250, 600)), 0.0)
    assert ack.type == p.TELEMETRY and ack.fields[4] & p.STATUS_ARMED
    send(c, p.Message(p.DRIVE, 2, (300, 500)), 0.1)
    assert (c.steering, c.throttle) == (0.3, 0.5)
    c.poll(0.349)
    assert c.armed and c.throttle == 0.5
    c.poll(0.351)
    assert not c.armed and c.throttle == 0.0 and c.watchdog_tripped
    unsolicited = [f for f in frames(c) if f.type == p.TELEMETRY and f.fields[1] == 0]
    assert [f.fields[4] for f in unsolicited] == [p.STATUS_ARMED, p.STATUS_WATCHDOG_TRIPPED]  # periodic, then the trip
    (nack,) = send(c, p.Message(p.DRIVE, 3, (0, 500)), 0.4)  # a late command does not revive it
    assert nack.type == p.NACK and nack.fields[2] == p.NOT_ARMED


def test_throttle_cap_estop_latch_and_nack_reasons():
    c = MockController()
    (nack,) = send(c, p.Message(p.DRIVE, 1, (0, 500)), 0.0)
    assert nack.fields == (1, p.DRIVE, p.NOT_ARMED)
    (nack,) = send(c, p.Message(p.ARM, 2, (10, 500)), 0.0)  # watchdog below 50 ms
    assert nack.fields == (2, p.ARM, p.OUT_OF_RANGE)
    send(c, p.Message(p.ARM, 3, (250, 400)), 0.0)
    send(c, p.Message(p.DRIVE, 4, (-200, 900)), 0.01)
    assert c.throttle == 0.4  # capped
    send(c, p.Message(p.ESTOP, 5), 0.02)
    assert c.estop_latched and not c.armed and c.throttle == 0.0
    (nack,) = send(c, p.Message(p.DRIVE, 6, (0, 100)), 0.03)
    assert nack.fields == (6, p.DRIVE, p.ESTOP_LATCHED)
    assert c.log[-1] == (0.03, "NACK DRIVE#6(0, 100) e-stop latched")  # logged when refused, not at the last command
    send(c, p.Message(p.ARM, 7, (250, 400)), 0.04)  # re-arming clears the latch
    assert c.armed and not c.estop_latched
    (nack,) = send(c, p.Message(p.TELEMETRY, 8, (0, 0, 0, 0, 0, 0)), 0.05)
    assert nack.fields == (8, p.TELEMETRY, p.UNKNOWN_TYPE)
    (nack,) = send_body(c, bytes([p.VERSION, p.DRIVE, 9, 1, 7]), 0.06)  # DRIVE with a 1-byte payload
    assert nack.fields == (9, p.DRIVE, p.BAD_LENGTH)
    assert c.log[-1] == (0.06, "NACK DRIVE#9() bad length")
    (info,) = send(c, p.Message(p.HELLO, 10), 0.07)
    assert info.type == p.INFO and info.fields[0] == p.VERSION


@pytest.mark.parametrize(
    "version, kind, length, payload, reason",
    [
        (2, p.DRIVE, 4, b"\x00\x00\xf4\x01", p.BAD_VERSION),  # a well-formed DRIVE from a newer host
        (p.VERSION, 0x7F, 0, b"", p.UNKNOWN_TYPE),  # a type the protocol does not define
        (p.VERSION, p.DRIVE, 3, b"\x00\x00\xf4\x01", p.BAD_LENGTH),  # the length byte disagrees with the payload
    ],
)
def test_a_frame_with_a_good_crc_but_a_bad_header_is_refused_and_changes_nothing(version, kind, length, payload, reason):
    c = MockController()
    send(c, p.Message(p.ARM, 1, (250, 600)), 0.0)
    send(c, p.Message(p.DRIVE, 2, (100, 300)), 0.01)
    (nack,) = send_body(c, bytes([version, kind, 9, length]) + payload, 0.02)
    assert nack.type == p.NACK and nack.fields == (9, kind, reason)
    assert c.armed and (c.steering, c.throttle) == (0.1, 0.3)


def test_the_mock_controller_keeps_each_rule_of_the_documented_state_machine():
    """docs/serial_protocol.md, "Controller behaviour", rule by rule: what firmware written to it must do too."""
    c = MockController(now=10.0)
    (info,) = send(c, p.Message(p.HELLO, 1), 10.0)
    assert (info.type, info.fields) == (p.INFO, (p.VERSION, 1, 0, 50, 2000))  # the reference values
    for seq, fields in ((2, (49, 500)), (3, (2001, 500)), (4, (250, 1001))):  # a watchdog outside 50-2000 ms, a cap over 1000
        (nack,) = send(c, p.Message(p.ARM, seq, fields), 10.0)
        assert nack.fields == (seq, p.ARM, p.OUT_OF_RANGE) and not c.armed
    (ack,) = send(c, p.Message(p.ARM, 5, (2000, 1000)), 10.0)  # both limits are allowed
    assert ack.fields[:2] == (5, p.ARM) and ack.fields[4] == p.STATUS_ARMED
    send(c, p.Message(p.ARM, 6, (250, 400)), 10.0)
    send(c, p.Message(p.DRIVE, 7, (300, -900)), 10.01)
    assert (c.steering, c.throttle) == (0.3, -0.4)  # the cap holds both ways
    (nack,) = send(c, p.Message(p.DRIVE, 8, (0, 1001)), 10.02)
    assert nack.fields == (8, p.DRIVE, p.OUT_OF_RANGE) and (c.steering, c.throttle) == (0.3, -0.4)
    (ack,) = send(c, p.Message(p.ARM, 9, (250, 400)), 10.03)  # re-arming while driving starts from neutral
    assert (c.steering, c.throttle) == (0.0, 0.0) and ack.fields[2:4] == (0, 0)
    # the watchdog is checked before a frame is acted on: a DRIVE 0.3 s after the last command finds it tripped
    (trip, nack) = send(c, p.Message(p.DRIVE, 10, (0, 300)), 10.33)
    assert trip.fields[1] == 0 and trip.fields[4] == p.STATUS_WATCHDOG_TRIPPED and nack.fields == (10, p.DRIVE, p.NOT_ARMED)
    (ack,) = send(c, p.Message(p.ARM, 11, (250, 400)), 10.4)
    assert ack.fields[4] == p.STATUS_ARMED, "ARM clears the watchdog flag"
    (ack,) = send(c, p.Message(p.ESTOP, 12), 10.41)
    assert ack.fields[4] == p.STATUS_ESTOP_LATCHED
    send(c, p.Message(p.ARM, 13, (250, 400)), 10.42)
    (ack,) = send(c, p.Message(p.DISARM, 14), 10.46)
    assert not c.armed and ack.fields[4] == 0 and ack.fields[5] == 460, "uptime counts from power-up, in ms"
    c.poll(13.5)
    assert frames(c) == [], "no unsolicited telemetry while disarmed"
    (nack,) = send(c, p.Message(p.DRIVE, 15, (0, 300)), 13.6)
    assert nack.fields == (15, p.DRIVE, p.NOT_ARMED)
    seqs = []
    for _ in range(300):
        seqs += [f.seq for f in send(c, p.Message(p.HELLO, 16), 14.0)]
    assert seqs == [(seqs[0] + i) % 256 for i in range(300)], "its own frames count up, wrapping at 256"


@pytest.fixture
def mock_link():
    register_url_scheme()
    link = HostLink("mockjetracer://", send_hz=100, command_timeout=0.05).start()
    yield link
    link.close()


def wait_until(predicate, timeout=1.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return False


@pytest.mark.parametrize("bad", [dict(send_hz=0.0), dict(command_timeout=-1.0), dict(watchdog_ms=0), dict(watchdog_ms=70_000), dict(throttle_cap=1.5), dict(send_hz=float("nan"))])
def test_link_refuses_settings_the_protocol_cannot_carry(bad):
    with pytest.raises(ValueError, match="HostLink needs"):
        HostLink("mockjetracer://", **bad)  # before any port is opened


def test_link_drives_while_fresh_and_stops_when_stale(mock_link):
    controller = mock_link._port.controller
    assert mock_link.hello().fields[0] == p.VERSION
    assert mock_link.arm()
    mock_link.drive(0.5, 0.55)
    assert wait_until(lambda: controller.throttle == 0.55 and controller.steering == 0.5)
    # no new command: after command_timeout the loop sends STOP, which keeps the watchdog fed
    assert wait_until(lambda: controller.throttle == 0.0, timeout=0.5)
    time.sleep(0.4)  # longer than the 250 ms watchdog
    assert controller.armed and not controller.watchdog_tripped
    assert mock_link.round_trip_stats()["p50"] < 0.05


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_a_non_finite_command_stops_the_car_and_is_never_sent(bad):
    with pytest.raises(ValueError, match="finite"):
        p.to_thousandths(bad)  # clamping alone would send NaN as a full command
    register_url_scheme()
    link = HostLink("mockjetracer://", send_hz=100, command_timeout=30.0).start()  # a command stays fresh all test
    controller = link._port.controller
    try:
        assert link.arm()
        link.drive(0.5, 0.55)
        assert wait_until(lambda: controller.throttle == 0.55)
        with pytest.raises(ValueError, match="told to stop"):
            link.drive(bad, 0.55)
        assert wait_until(lambda: controller.throttle == 0.0)  # the earlier command is not sent on
        with pytest.raises(ValueError, match="finite"):
            link.drive(0.0, bad)
        time.sleep(0.05)
        assert controller.throttle == 0.0 and controller.steering == 0.0 and controller.armed
        link.drive(-0.5, 0.5)  # a finite command drives again: only the bad ones were refused
        assert wait_until(lambda: controller.throttle == 0.5 and controller.steering == -0.5)
    finally:
        link.close()


def test_arm_waits_for_its_own_acknowledgement_after_the_sequence_numbers_wrap():
    register_url_scheme()
    link = HostLink("mockjetracer://", send_hz=500).start()
    controller = link._port.controller
    try:
        # every one of the 256 sequence numbers acknowledged (STOPs, unarmed) before the first ARM, as when
        # the camera takes more than 256 sends (5 s at the car's 50 Hz) to open
        assert wait_until(lambda: len(link._acks) == 256, timeout=5.0)
        assert link.arm() and link.armed and controller.armed
        link.drive(0.0, 0.5)
        assert wait_until(lambda: controller.throttle == 0.5)
        # then every number acknowledged again, armed, before an ARM the controller refuses
        assert wait_until(lambda: all(status & p.STATUS_ARMED for status in list(link._acks.values())) and len(link._acks) == 256, timeout=5.0)
        link.estop()
        link.watchdog_ms = 10  # below what the controller accepts: it refuses this ARM
        assert not link.arm(timeout=0.3) and not link.armed and not controller.armed
    finally:
        link.close()


def test_link_estop_is_immediate_and_close_sends_stop_then_estop(mock_link):
    controller = mock_link._port.controller
    assert mock_link.arm()
    mock_link.drive(0.0, 0.5)
    assert wait_until(lambda: controller.throttle == 0.5)
    mock_link.estop()
    assert controller.estop_latched and controller.throttle == 0.0  # synchronous: the write handled it
    mock_link.drive(0.0, 0.5)
    time.sleep(0.05)
    assert controller.throttle == 0.0, "the host no longer believes the controller armed"
    assert mock_link.arm()
    mock_link.close()
    assert controller.log[-1][1] == "e-stop" and not controller.armed


def test_a_link_used_in_a_with_block_is_started_and_closed_with_an_estop_even_when_the_block_raises():
    register_url_scheme()
    with pytest.raises(KeyboardInterrupt):  # Ctrl-C mid-drive
        with HostLink("mockjetracer://", send_hz=100, command_timeout=30.0) as link:
            controller = link._port.controller
            assert link.arm()
            link.drive(0.0, 0.5)
            assert wait_until(lambda: controller.throttle == 0.5)
            raise KeyboardInterrupt
    assert controller.log[-1][1] == "e-stop" and controller.estop_latched and not controller.armed and controller.throttle == 0.0
    assert link._port is None and not any(thread.is_alive() for thread in link._threads)


def test_a_refused_drive_tells_the_link_that_the_controller_restarted(mock_link):
    controller = mock_link._port.controller
    assert mock_link.arm() and mock_link.armed
    mock_link.drive(0.0, 0.5)
    assert wait_until(lambda: controller.throttle == 0.5)
    controller.armed, controller.throttle = False, 0.0  # a brown-out restart: unarmed, and no telemetry says so
    assert wait_until(lambda: not mock_link.armed)  # the next DRIVE was refused
    assert mock_link.nacks[-1].fields == (mock_link.nacks[-1].fields[0], p.DRIVE, p.NOT_ARMED)
    refused = len(mock_link.nacks)
    mock_link.drive(0.0, 0.5)
    time.sleep(0.1)
    assert len(mock_link.nacks) == refused, "no DRIVE is sent to a controller believed unarmed"
    assert mock_link.arm() and mock_link.armed


class FloodPort:
    """A controller that answers every read with a NACK and a frame of a type this host does not know
    (good CRC, as from newer firmware), `frames` times, then with one TELEMETRY, then nothing."""

    def __init__(self, frames):
        self.frames, self.reads = frames, 0

    def write(self, data):
        return len(data)

    def read(self, size):
        self.reads += 1
        if self.reads > self.frames + 1:
            time.sleep(0.001)
            return b""
        if self.reads == self.frames + 1:
            return p.encode(p.Message(p.TELEMETRY, 0, (0, 0, 0, 0, 0, 12345)))
        seq = (self.reads - 1) & 0xFF
        return frame_body(bytes([p.VERSION, 0x84, seq, 0])) + p.encode(p.Message(p.NACK, seq, (seq, p.DRIVE, p.BAD_LENGTH)))

    def close(self):
        pass


def test_a_link_refused_for_hours_keeps_a_bounded_history():
    port = FloodPort(frames=3000)
    link = HostLink("flood://", opener=lambda url, timeout: port).start()
    try:
        assert wait_until(lambda: link.telemetry is not None, timeout=10.0)  # the stream's last frame: all before it handled
        assert link.telemetry.uptime_ms == 12345
        assert len(link.nacks) == 256  # of 3,000: the deque's bound
        assert link.nacks[-1].fields == ((3000 - 1) & 0xFF, p.DRIVE, p.BAD_LENGTH)  # the latest are the ones kept
        assert link.decoder.dropped == {"type": 3000}  # every unknown frame counted, none kept
        assert link.decoder.refusable == []
    finally:
        link.close()


class ScriptedPort:
    """A controller the test plays: it keeps what the host writes, as messages, answers each ARM with an
    armed TELEMETRY acknowledging it, and otherwise says only what the test queues with send()."""

    def __init__(self):
        self.raw, self.written, self.decoder = bytearray(), [], p.FrameDecoder()
        self.incoming: "queue.Queue[bytes]" = queue.Queue()
        self.failure = None  # an exception the next read raises: the port unplugged

    def write(self, data):
        self.raw += data
        for message in self.decoder.feed(data):
            self.written.append(message)
            if message.type == p.ARM:
                self.send(p.encode(p.Message(p.TELEMETRY, 0, (message.seq, p.ARM, 0, 0, p.STATUS_ARMED, 0))))
        return len(data)

    def send(self, data: bytes):
        self.incoming.put(data)

    def read(self, size):
        if self.failure is not None:
            raise self.failure
        try:
            return self.incoming.get(timeout=0.005)
        except queue.Empty:
            return b""

    def close(self):
        pass

    def types_since(self, n: int) -> list:
        return [m.type for m in self.written[n:]]


def next_sends(port: ScriptedPort, count: int = 5) -> list:
    """The types of the send loop's next `count` writes, after one that may have been in flight when the
    link's state changed (telemetry is handled without waiting for a send)."""
    n = len(port.written)
    assert wait_until(lambda: len(port.written) >= n + 1 + count, timeout=5.0)
    return port.types_since(n + 1)[:count]


@contextmanager
def driving(*ports: ScriptedPort, **settings):
    """A link opening `ports` in turn (one new port by default), armed and driving (0.1, 0.5) with a
    command that stays fresh all test; closed at the end."""
    ports = ports or (ScriptedPort(),)
    opened = iter(ports)
    link = HostLink("scripted://", send_hz=200, command_timeout=30.0, opener=lambda url, timeout: next(opened), **settings).start()
    try:
        assert link.arm()
        link.drive(0.1, 0.5)
        assert wait_until(lambda: p.DRIVE in ports[0].types_since(0))
        yield link, ports[0]
    finally:
        link.close()


@pytest.mark.parametrize(
    "news, disarms",
    [
        (p.Message(p.TELEMETRY, 0, (0, 0, 0, 0, 0, 1)), True),  # unsolicited: no longer armed
        (p.Message(p.TELEMETRY, 0, (0, 0, 0, 0, p.STATUS_WATCHDOG_TRIPPED, 1)), True),
        (p.Message(p.TELEMETRY, 0, (0, 0, 0, 0, p.STATUS_ESTOP_LATCHED, 1)), True),
        (p.Message(p.NACK, 0, (9, p.DRIVE, p.NOT_ARMED)), True),  # a controller that restarted
        (p.Message(p.NACK, 0, (9, p.DRIVE, p.ESTOP_LATCHED)), True),  # e-stopped by another hand
        (p.Message(p.NACK, 0, (9, p.DRIVE, p.OUT_OF_RANGE)), False),  # a refusal that says nothing of arming
        (p.Message(p.TELEMETRY, 0, (0, 0, 0, 0, p.STATUS_ARMED, 1)), False),
    ],
)
def test_each_sign_of_an_unarmed_controller_alone_ends_the_drive_commands(news, disarms):
    with driving() as (link, port):
        port.send(p.encode(news))
        assert wait_until(lambda: news in link.nacks or (link.telemetry is not None and link.telemetry.uptime_ms == 1))  # handled
        assert wait_until(lambda: link.armed != disarms)
        assert set(next_sends(port)) == ({p.STOP} if disarms else {p.DRIVE})


def test_an_estop_forgets_the_command_so_a_rearmed_car_waits_for_a_new_one():
    with driving() as (link, port):
        n = len(port.written)
        assert link.estop() and p.ESTOP in port.types_since(n) and not link.armed  # no controller says so: the host knows
        assert set(next_sends(port)) == {p.STOP}
        assert link.arm()
        assert set(next_sends(port)) == {p.STOP}, "the command before the e-stop is not resumed"
        link.drive(0.0, 0.3)
        assert wait_until(lambda: port.written[-1].type == p.DRIVE and port.written[-1].fields == (0, 300))


@pytest.mark.parametrize("how", ["stop", "estop", "non-finite"])
def test_no_drive_is_written_once_stop_estop_or_a_non_finite_command_returns(how):
    """The send loop reads the command and writes it under the link's lock. Holding that lock, the test
    lets the loop come to its next send and wait there, and stops the car meanwhile: the loop, let go,
    sends STOP. Read outside the lock, the command it read before waiting was written after the ESTOP
    (7 times in 2,000 e-stops with a 1 us thread switch interval)."""
    with driving() as (link, port):
        with link._lock:
            time.sleep(0.05)  # ten send periods: the loop is waiting for the lock
            n = len(port.written)
            if how == "stop":
                link.stop()
            elif how == "estop":
                assert link.estop()
            else:
                with pytest.raises(ValueError, match="told to stop"):
                    link.drive(float("nan"), 0.5)
        assert wait_until(lambda: len(port.written) >= n + 3)
        assert p.DRIVE not in port.types_since(n)


def test_a_reconnected_link_starts_clean_unarmed_and_without_a_command():
    old, new = ScriptedPort(), ScriptedPort()
    with driving(old, new, backoff=(0.01, 0.01)) as (link, _):
        old.send(p.encode(p.Message(p.TELEMETRY, 0, (0, 0, 100, 500, p.STATUS_ARMED, 1)))[:6])  # half a frame, then the unplug
        assert wait_until(old.incoming.empty)  # read: the next read fails
        old.failure = OSError("unplugged")
        assert wait_until(lambda: link.connected.is_set() and link.reconnects == 1)
        assert new.raw[:1] == p.DELIMITER  # whatever partial frame the controller holds is ended first
        assert not link.armed and set(next_sends(new)) == {p.STOP}
        new.send(p.encode(p.Message(p.TELEMETRY, 0, (0, 0, 0, 0, 0, 777))))  # decoded alone, not glued to the old half frame
        assert wait_until(lambda: link.telemetry is not None and link.telemetry.uptime_ms == 777)
        assert link.arm()
        assert set(next_sends(new)) == {p.STOP}, "the command before the unplug is not resumed"


def test_close_sends_stop_before_estop():
    port = ScriptedPort()
    link = HostLink("scripted://", send_hz=0.5, opener=lambda url, timeout: port).start()  # the loop sends once, then waits 2 s
    assert wait_until(lambda: len(port.written) == 1)
    link.close()
    assert port.types_since(0) == [p.STOP, p.STOP, p.ESTOP]


def test_only_an_acknowledging_telemetry_answers_a_frame_and_times_it_once():
    link = HostLink("scripted://", clock=lambda: 10.0)  # not started: its handler is called directly
    link._sent[5] = 9.75
    link._handle(p.Message(p.TELEMETRY, 0, (5, 0, 0, 0, p.STATUS_ARMED, 1)))  # unsolicited, though its seq field reads 5
    assert 5 not in link._acks and list(link.round_trips) == []
    link._handle(p.Message(p.TELEMETRY, 0, (5, p.DRIVE, 0, 0, p.STATUS_ARMED, 2)))
    assert link._acks == {5: p.STATUS_ARMED} and list(link.round_trips) == [0.25]
    link._handle(p.Message(p.TELEMETRY, 0, (5, p.DRIVE, 0, 0, p.STATUS_ARMED, 3)))  # a duplicate: no second round trip
    assert list(link.round_trips) == [0.25]


def test_round_trip_statistics_are_the_median_and_the_99th_percentile():
    link = HostLink("scripted://")
    assert link.round_trip_stats() == {}
    link.round_trips = deque(float(t) for t in reversed(range(200)))
    assert link.round_trip_stats() == {"p50": 99.5, "p99": 198.0}  # the 199th of 200, not the largest


class RecordingEvent(threading.Event):
    """An event whose waits return at once and are recorded, each passed to `on_wait`: a loop's sleeps without the sleeping."""

    def __init__(self, on_wait=None):
        super().__init__()
        self.waits, self.on_wait = [], on_wait

    def wait(self, timeout=None):
        self.waits.append(timeout)
        if self.on_wait is not None:
            self.on_wait(timeout)
        return self.is_set()


def test_reopening_backs_off_exponentially_up_to_its_cap():
    failures, port = iter(range(6)), ScriptedPort()

    def opener(url, timeout):
        if next(failures, None) is not None:
            raise OSError("no such device")
        return port

    link = HostLink("scripted://", backoff=(0.01, 0.05), opener=opener)  # not started: _reconnect runs here
    link._armed, link._command = True, (0.2, 0.5, 0.0)  # armed and driving when the port went down
    down = []  # the link's armed flag (what link.armed tells a caller) and its command, at each wait while the port is down
    link._stop_event = RecordingEvent(on_wait=lambda timeout: down.append((link.armed, link._command)))
    link._reconnect()
    assert link._stop_event.waits == [0.01, 0.02, 0.04, 0.05, 0.05, 0.05]
    assert down == [(False, None)] * 6, "neither armed nor holding a command while the port is down"
    assert link.reconnects == 1 and link.connected.is_set() and link._port is port and not link.armed


def test_the_send_loop_keeps_its_rate_when_its_sends_take_time():
    now = [100.0]

    def clock():  # every reading of the clock comes 3 ms after the last: a slow port
        now[0] += 0.003
        return now[0]

    link = HostLink("scripted://", send_hz=50, clock=clock)  # not started: its send loop runs here
    link._port = port = ScriptedPort()
    link.connected.set()
    woke = []

    def sleep(seconds):
        now[0] += seconds
        woke.append(now[0])
        if len(woke) == 5:
            link._stop_event.set()

    link._stop_event = RecordingEvent(sleep)
    start = now[0] + 0.003  # the loop's first reading
    link._send_loop()
    assert port.types_since(0) == [p.STOP] * 5
    np.testing.assert_allclose(woke, [start + 0.02 * k for k in range(1, 6)])  # every 20 ms, not every 20 ms plus the sends


def test_pty_link_survives_an_unplug_and_never_rearms_itself():
    pty = PtyController()
    link = HostLink(pty.path, send_hz=100, command_timeout=0.05, backoff=(0.02, 0.1)).start()
    try:
        assert link.arm()
        link.drive(0.2, 0.5)
        assert wait_until(lambda: pty.controller.throttle == 0.5)
        old_path = pty.path
        pty.unplug()
        assert wait_until(lambda: not link.connected.is_set())
        link.url = old_path  # the device node may come back under the same name
        pty.replug()
        link.url = pty.path
        assert wait_until(lambda: link.connected.is_set(), timeout=3.0)
        assert link.reconnects >= 1
        link.drive(0.2, 0.5)
        time.sleep(0.1)
        assert not pty.controller.armed and pty.controller.throttle == 0.0, "no automatic re-arm"
        assert link.arm()
        link.drive(0.2, 0.5)
        assert wait_until(lambda: pty.controller.throttle == 0.5)
    finally:
        link.close()
        pty.close()


def test_the_pty_controller_runs_its_watchdog_and_telemetry_on_its_own_clock():
    pty = PtyController()
    port = serial.Serial(pty.path, timeout=0.05)
    try:
        port.write(p.encode(p.Message(p.ARM, 1, (50, 500))))  # and then silence from the host
        received, deadline = [], time.monotonic() + 2.0
        decoder = p.FrameDecoder()
        while time.monotonic() < deadline and not any(f.fields[4] & p.STATUS_WATCHDOG_TRIPPED for f in received):
            received += [f for f in decoder.feed(port.read(64)) if f.type == p.TELEMETRY]
        assert received[0].fields[:2] == (1, p.ARM)
        assert received[-1].fields[1] == 0 and received[-1].fields[4] == p.STATUS_WATCHDOG_TRIPPED, "it trips with no frame to wake it"
        assert not pty.controller.armed
    finally:
        port.close()
        pty.close()


def test_the_mock_url_port_drops_pending_output_on_reset_and_refuses_use_once_closed():
    register_url_scheme()
    port = serial.serial_for_url("mockjetracer://", timeout=0.05)
    port.write(p.encode(p.Message(p.HELLO, 1)))
    assert port.in_waiting > 0
    port.reset_input_buffer()
    assert port.in_waiting == 0 and port.read(64) == b""
    port.write(p.encode(p.Message(p.HELLO, 2)))
    assert [m.type for m in p.FrameDecoder().feed(port.read(64))] == [p.INFO]
    port.close()
    for use in (lambda: port.write(p.encode(p.Message(p.HELLO, 3))), lambda: port.read(1)):
        with pytest.raises(OSError, match="port closed"):
            use()


def test_estop_with_the_port_down_says_so_and_never_raises():
    pty = PtyController()
    link = HostLink(pty.path, send_hz=100, backoff=(5.0, 5.0)).start()  # stays down once unplugged
    try:
        assert link.arm() and link.estop()  # written
        assert link.arm()
        link.drive(0.2, 0.5)
        pty.unplug()
        assert wait_until(lambda: not link.connected.is_set(), timeout=3.0)
        assert link.estop() is False  # from a signal handler, an exception would end the run mid-step
        assert not link.armed and link._command is None
    finally:
        link.close()
        pty.close()


def test_spy_url_wraps_a_real_port(tmp_path):
    pty = PtyController()
    log = tmp_path / "spy.txt"
    port = serial.serial_for_url(f"spy://{pty.path}?file={log}", timeout=0.2)
    port.write(p.encode(p.Message(p.HELLO, 1)))
    reply = list(p.FrameDecoder().feed(port.read(64)))
    port.close()
    pty.close()
    assert reply and reply[0].type == p.INFO
    assert "TX" in log.read_text()


def test_a_second_host_cannot_open_the_port_a_link_holds(tmp_path):
    pty = PtyController()
    link = HostLink(pty.path, send_hz=100, command_timeout=0.05).start()
    try:
        with pytest.raises(OSError, match=f"Could not exclusively lock port {pty.path}"):
            HostLink(pty.path, send_hz=100, command_timeout=0.05).start()
        # nor can the CLI: one line, before anything is armed or logged
        out = warm_python.run(["-m", "deploy.jetracer", "baseline", "--steps", "5", "--port", pty.path, "--log-dir", str(tmp_path / "runs")],
                              cwd=ROOT, timeout=60)  # fmt: skip
        assert out.returncode != 0 and "Traceback" not in out.stderr, out.stderr
        last = out.stderr.strip().splitlines()[-1]  # the errno differs between systems (EAGAIN, EWOULDBLOCK)
        assert last.startswith("baseline: error: cannot open the motor controller: [Errno ") and f"Could not exclusively lock port {pty.path}" in last
        assert not (tmp_path / "runs").exists()
        assert link.arm()  # the first host still has the car, alone
        link.drive(0.2, 0.5)
        assert wait_until(lambda: pty.controller.throttle == 0.5)
    finally:
        link.close()
    second = HostLink(pty.path, send_hz=100, command_timeout=0.05).start()  # free once the first has closed it
    second.close()
    pty.unplug()
