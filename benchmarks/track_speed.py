"""Env steps per second of JetRacerTrack-v0 on one core, camera rendering and preprocessing included.

Steps per CPU-second of this process (what one dedicated core gives, whatever else shares the
machine) and per wall-clock second.

    python benchmarks/track_speed.py --steps 2000
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from envs import get_baseline, make_env  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    minimums = {"--steps": (args.steps, 1), "--repeats": (args.repeats, 1)}
    if too_small := [f"{flag} must be at least {low}" for flag, (value, low) in minimums.items() if not value >= low]:
        parser.error("; ".join(too_small))
    env = make_env("JetRacerTrack-v0")
    baseline = get_baseline("JetRacerTrack-v0")
    rates, cpu_rates = [], []
    for repeat in range(args.repeats):
        obs, _ = env.reset(seed=repeat)
        baseline.reset()
        start, cpu_start = time.perf_counter(), time.process_time()
        for _ in range(args.steps):
            obs, _, terminated, truncated, info = env.step(baseline(obs))
            if terminated or truncated:
                obs, _ = env.reset()
                baseline.reset()
        rates.append(args.steps / (time.perf_counter() - start))
        cpu_rates.append(args.steps / (time.process_time() - cpu_start))
    print(f"JetRacerTrack-v0, lane-follower actions, {args.steps} steps x {args.repeats} (medians): "
          f"{statistics.median(cpu_rates):.0f} steps per CPU-second, {statistics.median(rates):.0f} steps per wall-clock second")  # fmt: skip


if __name__ == "__main__":
    main()
