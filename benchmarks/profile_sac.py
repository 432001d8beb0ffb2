"""Where one SAC training step's time goes (issue: speed): torch.profiler over acting + update.

    python benchmarks/profile_sac.py --width 256 --steps 300
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=256)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--rows", type=int, default=12)
    args = parser.parse_args()
    import importlib.util

    spec = importlib.util.spec_from_file_location("sac_continuous", ROOT / "sac_continuous.py")
    sac = importlib.util.module_from_spec(spec)
    sys.modules["sac_continuous"] = sac
    spec.loader.exec_module(sac)
    torch.set_num_threads(1)
    agent = sac.SoftActorCritic(3, 1, sac.Args(hidden_size=args.width))
    rb = sac.ReplayBuffer(100_000, 3, 1, 0)
    rng = np.random.default_rng(0)
    for _ in range(10_000):
        rb.add(rng.normal(size=3), rng.uniform(-1, 1, 1), -1.0, rng.normal(size=3), False)
    obs = torch.zeros(1, 3)

    def step(i: int) -> None:
        with torch.inference_mode():
            agent.actor.get_action(obs)
        agent.update(rb.sample(256), i)

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
