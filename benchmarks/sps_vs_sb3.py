"""Training speed of sac_continuous.py against Stable-Baselines3's SAC, side by side.

Both train Pendulum-v1 with the same hyperparameters (one learning rate for actor, critics and
entropy coefficient, one actor update per env step, batch 256, the same warm-up), one torch
thread each, alternating which runs first, for every network width asked. Each run is a fresh
process; the reported SPS is env steps over the process's whole wall time (imports included,
for both). Prints a markdown table with medians and the median of the per-repetition ratios.

    python benchmarks/sps_vs_sb3.py --widths 256 64 --repeats 3
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from side_by_side import compare

ROOT = Path(__file__).resolve().parent.parent


def sb3_worker(width: int, steps: int, learning_starts: int, seed: int) -> None:
    import torch
    from stable_baselines3 import SAC

    torch.set_num_threads(1)
    model = SAC(
        "MlpPolicy",
        "Pendulum-v1",
        learning_rate=3e-4,
        buffer_size=1_000_000,
        learning_starts=learning_starts,
        batch_size=256,
        tau=0.005,
        gamma=0.99,
        train_freq=1,
        gradient_steps=1,
        policy_kwargs={"net_arch": [width, width]},
        seed=seed,
        device="cpu",
    )
    model.learn(total_timesteps=steps)


def command(impl: str, width: int, steps: int, learning_starts: int, seed: int) -> list[str]:
    if impl == "sb3":
        return [sys.executable, __file__, "--worker", str(width), str(steps), str(learning_starts), str(seed)]
    return [
        sys.executable, str(ROOT / "sac_continuous.py"), "--env-id", "Pendulum-v1", "--seed", str(seed),
        "--total-timesteps", str(steps), "--learning-starts", str(learning_starts), "--batch-size", "256",
        "--hidden-size", str(width), "--policy-lr", "3e-4", "--q-lr", "3e-4", "--policy-frequency", "1",
        "--regret-estimator", "off", "--torch-threads", "1",
    ]  # fmt: skip


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        sb3_worker(*(int(v) for v in sys.argv[2:6]))
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--widths", type=int, nargs="+", default=[256, 64])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--learning-starts", type=int, default=500)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workdir", type=Path, default=ROOT / "benchmarks" / "results" / "sps_vs_sb3")
    args = parser.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    print(f"Pendulum-v1, {args.steps} steps, learning starts {args.learning_starts}, batch 256, 1 thread")
    print("| width | ours SPS (median) | SB3 SPS (median) | ratio ours/SB3 (median of pairs) | pairs |")
    print("|---|---|---|---|---|")
    for width in args.widths:
        row = compare(lambda impl, seed: command(impl, width, args.steps, args.learning_starts, seed), args.steps, args.repeats, args.workdir)
        print(f"| {width} | {row}", flush=True)

if __name__ == "__main__":
    main()
