"""Host side of the motor-controller link: a receive thread, a fixed-rate send loop, e-stop, reconnects.

The send loop sends the latest DRIVE command only while it is fresh (younger than
`command_timeout`) and the host believes the controller armed; otherwise it sends STOP, which keeps
the controller's watchdog fed with neutral outputs. A lost port is reopened with exponential
back-off, and a reopened link is never re-armed by itself: arming is always the caller's decision.
`close()` sends STOP, then ESTOP. Works with any `serial.serial_for_url` URL (a device path,
`mockjetracer://`, `spy://...`); a device is opened exclusively. Runs on Python 3.8.
"""

from __future__ import annotations

import math
import statistics
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Deque, Dict, List, Optional, Tuple

from deploy import protocol as p

if TYPE_CHECKING:  # for the annotation only: pyserial is imported where a port is opened
    import serial


@dataclass
class Telemetry:
    """The controller's latest TELEMETRY: the steering and throttle it applies (in [-1, 1]), its status bits,
    its uptime (ms), and when the host received it (s, on the link's clock)."""

    steering: float
    throttle: float
    status: int
    uptime_ms: int
    received_at: float

    @property
    def armed(self) -> bool:
        return bool(self.status & p.STATUS_ARMED)

    @property
    def estop_latched(self) -> bool:
        return bool(self.status & p.STATUS_ESTOP_LATCHED)

    @property
    def watchdog_tripped(self) -> bool:
        return bool(self.status & p.STATUS_WATCHDOG_TRIPPED)


def _open_url(url: str, timeout: float) -> serial.SerialBase:
    import serial

    from deploy.mock_controller import register_url_scheme

    register_url_scheme()
    # exclusive (a flock on POSIX; Windows ports always are): a second host on the same car, a `run` left
    # open in another terminal, is refused when it opens the port instead of interleaving its commands and stealing replies
    return serial.serial_for_url(url, baudrate=115200, timeout=timeout, exclusive=True)


class HostLink:
    """The host's link to one motor controller (module docstring): `start()`, then `hello()`, `arm()`,
    `drive()` at the control rate, `stop()` or `estop()`; `close()` at the end."""

    def __init__(
        self,
        url: str,
        send_hz: float = 50.0,
        command_timeout: float = 0.1,
        watchdog_ms: int = 250,
        throttle_cap: float = 0.6,
        backoff: Tuple[float, float] = (0.05, 2.0),
        opener: Callable = _open_url,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not (0 < send_hz < math.inf and command_timeout > 0 and 0 < watchdog_ms <= 65535 and 0 <= throttle_cap <= 1):
            raise ValueError(f"HostLink needs send_hz > 0, command_timeout > 0, watchdog_ms in (0, 65535] and throttle_cap in [0, 1];"
                             f" got {send_hz}, {command_timeout}, {watchdog_ms}, {throttle_cap}")
        self.url, self.send_period, self.command_timeout = url, 1.0 / send_hz, command_timeout
        self.watchdog_ms, self.throttle_cap, self.backoff = watchdog_ms, throttle_cap, backoff
        self._opener, self._clock = opener, clock
        self._port: Any = None  # what the opener returned: a pyserial port, or the tests' stand-in; None while closed
        self._lock = threading.RLock()  # guards the port and the sequence number
        self._seq = 0
        self._command: Optional[Tuple[float, float, float]] = None  # steering, throttle, time set
        self._armed = False  # what the host believes; set only by arm() and telemetry
        self._stop_event = threading.Event()
        self._threads: List[threading.Thread] = []
        self._sent: Dict[int, float] = {}  # seq -> send time, for round-trip times
        self.round_trips: Deque[float] = deque(maxlen=1000)
        self.telemetry: Optional[Telemetry] = None
        self.info: Optional[p.Message] = None
        self.nacks: Deque[p.Message] = deque(maxlen=256)  # the latest refusals, for diagnostics
        self.decoder = p.FrameDecoder()  # its `dropped` counts the frames lost since the port was last opened
        self.reconnects = 0
        self._acks: Dict[int, int] = {}  # acknowledged seq -> status in its telemetry (seq numbers wrap at 256)
        self.connected = threading.Event()
        self._reply = threading.Condition()

    # -- lifecycle -----------------------------------------------------------------------------
    def start(self) -> "HostLink":
        """Open the port (OSError if it cannot be) and start the receive and send threads."""
        self._connect()
        for target in (self._receive_loop, self._send_loop):
            thread = threading.Thread(target=target, daemon=True)
            thread.start()
            self._threads.append(thread)
        return self

    def _connect(self) -> None:
        self._port = self._opener(self.url, 0.01)
        self._port.write(p.DELIMITER)  # ends whatever partial frame the controller holds
        self._armed = False
        self.connected.set()

    def _reconnect(self) -> None:
        """Reopen the port with exponential back-off until it opens or the link closes; never re-arms."""
        self.connected.clear()
        with self._lock:
            self._armed, self._command = False, None
            try:
                if self._port is not None:
                    self._port.close()
            except Exception:
                pass
            self._port = None
        delay = self.backoff[0]
        while not self._stop_event.is_set():
            try:
                with self._lock:
                    self._connect()
                self.reconnects += 1
                return
            except Exception:
                self._stop_event.wait(delay)
                delay = min(delay * 2.0, self.backoff[1])

    def close(self) -> None:
        """STOP, then ESTOP, then close the port and end the threads."""
        self._command = None
        for kind in (p.STOP, p.ESTOP):
            try:
                self._send(kind)
            except Exception:
                pass
        self._stop_event.set()
        for thread in self._threads:
            thread.join(timeout=1.0)
        with self._lock:
            if self._port is not None:
                self._port.close()
                self._port = None

    def __enter__(self) -> "HostLink":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- commands ------------------------------------------------------------------------------
    def _send(self, kind: int, fields: tuple = ()) -> int:
        with self._lock:
            if self._port is None:
                raise OSError("not connected")
            seq = self._seq
            self._seq = (self._seq + 1) & 0xFF
            self._acks.pop(seq, None)  # the acknowledgement of the frame 256 sends ago must not answer this one
            self._sent[seq] = self._clock()
            self._port.write(p.encode(p.Message(kind, seq, fields)))
            return seq

    def _wait_for(self, predicate: Callable[[], bool], timeout: float) -> bool:
        with self._reply:
            return self._reply.wait_for(predicate, timeout)

    def hello(self, timeout: float = 1.0) -> Optional[p.Message]:
        """The controller's INFO (protocol and firmware versions, watchdog range), or None if none came within `timeout` s."""
        self.info = None
        self._send(p.HELLO)
        self._wait_for(lambda: self.info is not None, timeout)
        return self.info

    def arm(self, timeout: float = 1.0) -> bool:
        """Arm the controller with this link's watchdog period and throttle cap; True once telemetry says armed."""
        seq = self._send(p.ARM, (self.watchdog_ms, int(round(self.throttle_cap * 1000))))
        self._wait_for(lambda: seq in self._acks, timeout)
        status = self._acks.pop(seq, 0)
        self._armed = bool(status & p.STATUS_ARMED)
        return self._armed

    @property
    def armed(self) -> bool:
        """Whether the host believes the controller armed: False after an e-stop, a reconnect, telemetry
        saying otherwise (a tripped watchdog, a latched e-stop) or a DRIVE refused as not armed or
        e-stopped (a controller that restarted); only arm() sets it again."""
        return self._armed

    def drive(self, steering: float, throttle: float) -> None:
        """Set the command the send loop will send while it is fresh. A non-finite value stops the car
        (STOP from the next send) and raises ValueError: no earlier command is sent after it."""
        steering, throttle = float(steering), float(throttle)
        if not (math.isfinite(steering) and math.isfinite(throttle)):
            self._command = None
            raise ValueError(f"drive needs finite steering and throttle, got {steering}, {throttle}; the car was told to stop")
        self._command = (steering, throttle, self._clock())

    def stop(self) -> None:
        """Drop the command: STOP from the next send, the controller still armed."""
        self._command = None

    def estop(self) -> bool:
        """Immediate, outside the send loop. A port that is down is no exception here, as this runs from
        signal handlers: False says the ESTOP was not written, and the controller's watchdog then stops the
        car within its period (a reopened link is not armed)."""
        self._command = None
        self._armed = False
        try:
            self._send(p.ESTOP)
        except OSError:  # serial.SerialException is one
            return False
        return True

    # -- loops ---------------------------------------------------------------------------------
    def _send_loop(self) -> None:
        next_time = self._clock()
        while not self._stop_event.is_set():
            try:
                if self.connected.is_set():
                    with self._lock:  # read where it is written: a command stopped while this send waited for the port is not sent
                        command = self._command
                        if command is not None and self._armed and self._clock() - command[2] <= self.command_timeout:
                            self._send(p.DRIVE, (p.to_thousandths(command[0]), p.to_thousandths(command[1])))
                        else:
                            self._send(p.STOP)
            except Exception:
                pass  # the receive loop notices a dead port and reconnects
            next_time += self.send_period
            self._stop_event.wait(max(0.0, next_time - self._clock()))

    def _receive_loop(self) -> None:
        while not self._stop_event.is_set():
            try:
                port = self._port
                if port is None:
                    raise OSError("not connected")
                data = port.read(256)
            except Exception:
                if self._stop_event.is_set():
                    return
                self._reconnect()
                self.decoder = p.FrameDecoder()
                continue
            if data:
                for message in self.decoder.feed(data):
                    self._handle(message)
                self.decoder.refusable.clear()  # only a controller answers those; `dropped` still counts them

    def _handle(self, message: p.Message) -> None:
        now = self._clock()
        with self._reply:
            if message.type == p.TELEMETRY:
                acked_seq, acked_type, steering, throttle, status, uptime = message.fields
                self.telemetry = Telemetry(steering / 1000.0, throttle / 1000.0, status, uptime, now)
                if acked_type:
                    self._acks[acked_seq] = status
                    sent = self._sent.pop(acked_seq, None)
                    if sent is not None:
                        self.round_trips.append(now - sent)
                if not self.telemetry.armed:
                    self._armed = False
            elif message.type == p.INFO:
                self.info = message
            elif message.type == p.NACK:
                self.nacks.append(message)
                if message.fields[2] in (p.NOT_ARMED, p.ESTOP_LATCHED):  # e.g. a controller that restarted, unarmed
                    self._armed = False
            self._reply.notify_all()

    def round_trip_stats(self) -> Dict[str, float]:
        """Median and 99th percentile of the command round-trip times, s."""
        times = sorted(self.round_trips)
        if not times:
            return {}
        return {"p50": statistics.median(times), "p99": times[min(len(times) - 1, int(0.99 * len(times)))]}
