"""Measurements of the serial link (docs/serial_protocol.md) against the mock controller.

1. Watchdog: the host drives at the link's send rate, then its send loop dies without a word (as a
   crashed process would). The controller must go neutral within its watchdog period plus one send
   interval of the last command; the trip latency is measured from the last command's arrival.
2. Decoder: throughput and crashes on frames with random corruptions and random garbage between them.

    python benchmarks/deploy_link.py --trials 1000 --frames 100000
"""

from __future__ import annotations

import argparse
import random
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from deploy import protocol as p  # noqa: E402
from deploy.link import HostLink  # noqa: E402
from deploy.mock_controller import register_url_scheme  # noqa: E402


def watchdog_trials(trials: int, watchdog_ms: int, send_hz: float) -> list[float]:
    register_url_scheme()
    latencies = []
    for _ in range(trials):
        link = HostLink("mockjetracer://", send_hz=send_hz, command_timeout=1.0, watchdog_ms=watchdog_ms).start()
        controller = link._port.controller
        assert link.arm()
        link.drive(0.1, 0.5)
        time.sleep(3.0 / send_hz)
        link._stop_event.set()  # the host dies: no STOP, no ESTOP, nothing more on the wire
        for thread in link._threads:
            thread.join()
        while controller.armed:  # the port's owner is gone; time still passes for the controller
            controller.poll(time.monotonic())
            time.sleep(0.0002)
        trip_time = next(t for t, event in reversed(controller.log) if event == "watchdog")
        latencies.append(trip_time - controller.last_command_time)
        link._port.close()
    return latencies


def decoder_throughput(frames: int, seed: int = 0) -> tuple[float, int, int]:
    rng = random.Random(seed)
    messages = [p.Message(p.DRIVE, i & 0xFF, (rng.randint(-1000, 1000), rng.randint(0, 1000))) for i in range(256)]
    stream = bytearray()
    for i in range(frames):
        frame = bytearray(p.encode(messages[i % 256]))
        if rng.random() < 0.3:  # corrupt 30 % of the frames
            frame[rng.randrange(len(frame) - 1)] ^= rng.randint(1, 255)
        if rng.random() < 0.05:  # and put garbage between some
            stream += bytes(rng.randrange(256) for _ in range(rng.randint(1, 20)))
        stream += frame
    decoder = p.FrameDecoder()
    start = time.perf_counter()
    decoded = 0
    for i in range(0, len(stream), 4096):  # serial reads come in chunks
        decoded += sum(1 for _ in decoder.feed(bytes(stream[i : i + 4096])))
    return frames / (time.perf_counter() - start), decoded, sum(decoder.dropped.values())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=1000)
    parser.add_argument("--watchdog-ms", type=int, default=250)
    parser.add_argument("--send-hz", type=float, default=50.0)
    parser.add_argument("--frames", type=int, default=100_000)
    args = parser.parse_args()
    minimums = {"--trials": (args.trials, 1), "--frames": (args.frames, 1), "--watchdog-ms": (args.watchdog_ms, 1), "--send-hz": (args.send_hz, 1)}
    if too_small := [f"{flag} must be at least {low}" for flag, (value, low) in minimums.items() if not value >= low]:
        parser.error("; ".join(too_small))
    latencies = sorted(watchdog_trials(args.trials, args.watchdog_ms, args.send_hz))
    bound = args.watchdog_ms / 1000 + 1 / args.send_hz
    within = sum(latency <= bound for latency in latencies)
    p99 = latencies[min(len(latencies) - 1, int(0.99 * len(latencies)))]  # as HostLink.round_trip_stats and the car's loop timing count it
    print(f"watchdog {args.watchdog_ms} ms, send interval {1000 / args.send_hz:.0f} ms, {args.trials} trials:")
    print(f"  trip latency after the last command: median {1000 * statistics.median(latencies):.1f} ms, "
          f"p99 {1000 * p99:.1f} ms, max {1000 * latencies[-1]:.1f} ms; "
          f"within {1000 * bound:.0f} ms: {within}/{len(latencies)}")  # fmt: skip
    rate, decoded, dropped = decoder_throughput(args.frames)
    print(f"decoder: {args.frames} frames (30 % corrupted, 5 % behind garbage): {rate:,.0f} frames/s, "
          f"{decoded} decoded, {dropped} dropped, 0 crashes")  # fmt: skip


if __name__ == "__main__":
    main()
