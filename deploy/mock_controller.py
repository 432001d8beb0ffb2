"""A fake motor-controller firmware implementing docs/serial_protocol.md, for tests and simulation.

`MockController` is a pure state machine: bytes in with `receive(data, now)`, time passes with
`poll(now)`, bytes out from `take_output()`. The clock is whatever the caller passes (seconds), so
tests drive it with a fake clock. It is reachable three ways:
- `serial.serial_for_url("mockjetracer://")` (this module registers the scheme), a fast in-process
  port on a real clock;
- `PtyController`, a thread serving the controller on a pseudo-terminal, so the real `serial.Serial`
  path is exercised, unplugging included;
- read by `deploy.io.SimWorld`, whose car drives with the applied outputs. Runs on Python 3.8.
"""

from __future__ import annotations

import os
import threading
import time
from typing import List, Optional, Tuple

from deploy import protocol as p

FIRMWARE_VERSION = (1, 0)
MIN_WATCHDOG_MS, MAX_WATCHDOG_MS = 50, 2000
TELEMETRY_PERIOD = 0.05  # s between unsolicited telemetry frames while armed


class MockController:
    """The controller's state machine of docs/serial_protocol.md, on the caller's clock: `receive(data, now)`
    takes the host's bytes, `poll(now)` runs the watchdog and the telemetry, `take_output()` gives the frames sent."""

    def __init__(self, now: float = 0.0) -> None:
        self.decoder = p.FrameDecoder()
        self.armed = False
        self.estop_latched = False
        self.watchdog_tripped = False
        self.watchdog_period = 0.25  # s, set by ARM
        self.throttle_cap = 0.0
        self.steering = 0.0  # applied outputs, in [-1, 1]
        self.throttle = 0.0
        self.last_command_time = now
        self.boot_time = now
        self.last_telemetry = now
        self.seq = 0
        self._output = bytearray()
        self.log: List[Tuple[float, str]] = []  # (time, event), for tests and debugging

    # -- outputs -------------------------------------------------------------------------------
    def _send(self, kind: int, fields: tuple) -> None:
        self._output += p.encode(p.Message(kind, self.seq, fields))
        self.seq = (self.seq + 1) & 0xFF

    def status(self) -> int:
        return (
            (p.STATUS_ARMED if self.armed else 0)
            | (p.STATUS_ESTOP_LATCHED if self.estop_latched else 0)
            | (p.STATUS_WATCHDOG_TRIPPED if self.watchdog_tripped else 0)
        )

    def _telemetry(self, now: float, acked: Optional[p.Message] = None) -> None:
        seq, kind = (acked.seq, acked.type) if acked is not None else (0, 0)
        uptime = int((now - self.boot_time) * 1000) & 0xFFFFFFFF
        self._send(p.TELEMETRY, (seq, kind, p.to_thousandths(self.steering), p.to_thousandths(self.throttle), self.status(), uptime))
        self.last_telemetry = now

    def _nack(self, message: p.Message, reason: int, now: float) -> None:
        self._send(p.NACK, (message.seq, message.type, reason))
        self.log.append((now, f"NACK {message} {p.REASONS[reason]}"))

    def _neutral(self) -> None:
        self.steering = self.throttle = 0.0

    def take_output(self) -> bytes:
        data, self._output = bytes(self._output), bytearray()
        return data

    # -- inputs --------------------------------------------------------------------------------
    def receive(self, data: bytes, now: float) -> None:
        self.poll(now)  # a late frame must not revive a watchdog that has already tripped
        for message in self.decoder.feed(data):
            self._handle(message, now)
        for message, why in self.decoder.refusable:
            reason = {"type": p.UNKNOWN_TYPE, "version": p.BAD_VERSION}.get(why, p.BAD_LENGTH)
            self._nack(message, reason, now)
        self.decoder.refusable.clear()

    def _handle(self, message: p.Message, now: float) -> None:
        kind = message.type
        if kind == p.HELLO:
            self._send(p.INFO, (p.VERSION, *FIRMWARE_VERSION, MIN_WATCHDOG_MS, MAX_WATCHDOG_MS))
        elif kind == p.ARM:
            watchdog_ms, cap = message.fields
            if not (MIN_WATCHDOG_MS <= watchdog_ms <= MAX_WATCHDOG_MS and cap <= 1000):
                return self._nack(message, p.OUT_OF_RANGE, now)
            self.armed, self.estop_latched, self.watchdog_tripped = True, False, False  # re-arming clears the latch
            self.watchdog_period, self.throttle_cap = watchdog_ms / 1000.0, cap / 1000.0
            self.last_command_time = now
            self._neutral()
            self.log.append((now, "armed"))
            self._telemetry(now, message)
        elif kind == p.DRIVE:
            if self.estop_latched:
                return self._nack(message, p.ESTOP_LATCHED, now)
            if not self.armed:
                return self._nack(message, p.NOT_ARMED, now)
            steering, throttle = message.fields
            if abs(steering) > 1000 or abs(throttle) > 1000:
                return self._nack(message, p.OUT_OF_RANGE, now)
            self.steering = steering / 1000.0
            self.throttle = max(-self.throttle_cap, min(self.throttle_cap, throttle / 1000.0))
            self.last_command_time = now
            self._telemetry(now, message)
        elif kind == p.STOP:
            self._neutral()
            if self.armed:
                self.last_command_time = now
            self._telemetry(now, message)
        elif kind == p.ESTOP:
            self._neutral()
            self.armed, self.estop_latched = False, True
            self.log.append((now, "e-stop"))
            self._telemetry(now, message)
        elif kind == p.DISARM:
            self._neutral()
            self.armed = False
            self.log.append((now, "disarmed"))
            self._telemetry(now, message)
        else:  # a controller-to-host type sent to the controller
            self._nack(message, p.UNKNOWN_TYPE, now)

    def poll(self, now: float) -> None:
        """Advance time: the watchdog, and unsolicited telemetry while armed."""
        if self.armed and now - self.last_command_time > self.watchdog_period:
            self._neutral()
            self.armed, self.watchdog_tripped = False, True
            self.log.append((now, "watchdog"))
            self._telemetry(now)
        elif self.armed and now - self.last_telemetry >= TELEMETRY_PERIOD:
            self._telemetry(now)


class Serial:
    """pyserial port for `serial_for_url("mockjetracer://")`: an in-process MockController on the real clock."""

    def __init__(self, url: Optional[str] = None, timeout: Optional[float] = None, **_ignored: object) -> None:
        self.port, self.timeout = url, timeout
        self.controller = MockController(time.monotonic())
        self.is_open = False
        self._lock = threading.Lock()
        if url is not None:
            self.open()

    def open(self) -> None:
        self.is_open = True

    def write(self, data: bytes) -> int:
        if not self.is_open:
            raise OSError("port closed")
        with self._lock:
            self.controller.receive(bytes(data), time.monotonic())
        return len(data)

    def read(self, size: int = 1) -> bytes:
        deadline = time.monotonic() + (self.timeout if self.timeout is not None else 1e9)
        while True:
            if not self.is_open:
                raise OSError("port closed")
            with self._lock:
                self.controller.poll(time.monotonic())
                data = self.controller.take_output()
            if data or time.monotonic() >= deadline:
                if len(data) > size:  # keep the rest for the next read
                    with self._lock:
                        self.controller._output[:0] = data[size:]
                    data = data[:size]
                return data
            time.sleep(0.001)

    @property
    def in_waiting(self) -> int:
        with self._lock:
            return len(self.controller._output)

    def reset_input_buffer(self) -> None:
        with self._lock:
            self.controller.take_output()

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.is_open = False


class PtyController:
    """Serve a MockController on a pseudo-terminal; `path` is the device the host opens.

    `unplug()` closes the controller's side, as pulling the USB cable would; `replug()` serves a fresh
    controller (powered up, disarmed) on a new pty, whose path replaces `path`.
    """

    def __init__(self) -> None:
        self.controller: MockController
        self.path = ""
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self.replug()

    def replug(self) -> None:
        import pty
        import tty

        self.unplug()
        self._master, slave = pty.openpty()
        tty.setraw(slave)
        self.path = os.ttyname(slave)
        self._slave = slave
        self.controller = MockController(time.monotonic())
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        import select

        master, stop = self._master, self._stop
        while not stop.is_set():
            ready, _, _ = select.select([master], [], [], 0.002)
            now = time.monotonic()
            try:
                if ready:
                    self.controller.receive(os.read(master, 4096), now)
                self.controller.poll(now)
                out = self.controller.take_output()
                if out:
                    os.write(master, out)
            except OSError:
                return

    def unplug(self) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join(timeout=1.0)
            self._thread = None
            for fd in (self._master, self._slave):
                try:
                    os.close(fd)
                except OSError:
                    pass

    def close(self) -> None:
        self.unplug()


def register_url_scheme() -> None:
    """Make `serial.serial_for_url("mockjetracer://")` return a `Serial` of this module."""
    import serial

    if "deploy" not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append("deploy")
