"""Where one SAC training step's time goes (issue: speed): torch.profiler over acting + update.

    python benchmarks/profile_sac.py --width 256 --steps 300
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from update_speed import training_step

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=256)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--rows", type=int, default=12)
    args = parser.parse_args()
    minimums = {"--width": (args.width, 1), "--steps": (args.steps, 1), "--rows": (args.rows, 1)}
    if too_small := [f"{flag} must be at least {low}" for flag, (value, low) in minimums.items() if not value >= low]:
        parser.error("; ".join(too_small))
    # the script's default delayed actor update (policy_frequency 2), as in training
    step = training_step(str(ROOT / "sac_continuous.py"), args.width, policy_frequency=2)

    for i in range(30):
        step(i)
    start = time.perf_counter()
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as profiler:
        for i in range(args.steps):
            step(i)
    elapsed = time.perf_counter() - start
    print(f"width {args.width}: {1000 * elapsed / args.steps:.2f} ms per step under the profiler")
    print(profiler.key_averages().table(sort_by="self_cpu_time_total", row_limit=args.rows))


if __name__ == "__main__":
    main()
