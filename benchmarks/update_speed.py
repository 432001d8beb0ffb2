"""Milliseconds per SAC training step, ours against Stable-Baselines3's, without env or startup costs.

One training step = one stochastic action for a single observation + one gradient step (critics, actor,
entropy coefficient, targets) on a batch of 256 from a filled replay buffer: `SoftActorCritic.update`
here, `SAC.train(gradient_steps=1)` in SB3, with the same hyperparameters as benchmarks/sps_vs_sb3.py
(one actor update per step). Each measurement is a fresh process on one torch thread; the order rotates
every repetition; `--before REV` adds sac_continuous.py at git revision REV. Prints a markdown table of
medians and per-repetition ratios.

    python benchmarks/update_speed.py --widths 256 64 --repeats 5 --before 66f0bdb
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

from side_by_side import checked, load_module, require, script_at, stop_children_on_sigterm

ROOT = Path(__file__).resolve().parent.parent


def training_step(script: str, width: int, policy_frequency: int = 1) -> Callable[[int], None]:
    """step(i) for the SAC script at `script`: one sampled action for a single observation and one
    update (batch 256) from a buffer of 10,000 random Pendulum-shaped transitions."""
    import numpy as np
    import torch

    sac = load_module(script)
    torch.set_num_threads(1)
    torch.manual_seed(0)
    args = sac.Args(hidden_size=width, batch_size=256, policy_lr=3e-4, q_lr=3e-4, policy_frequency=policy_frequency)
    agent = sac.SoftActorCritic(3, 1, args)
    rb = sac.ReplayBuffer(100_000, 3, 1, 0)
    rng = np.random.default_rng(0)
    for _ in range(10_000):
        rb.add(rng.normal(size=3), rng.uniform(-1, 1, 1), -1.0, rng.normal(size=3), False)
    obs = torch.zeros(1, 3)

    def step(i: int) -> None:
        with torch.inference_mode():
            agent.actor.get_action(obs)
        agent.update(rb.sample(256), i)

    return step


def ours_worker(script: str, width: int, steps: int) -> float:
    step = training_step(script, width)
    for i in range(50):
        step(i)
    start = time.perf_counter()
    for i in range(steps):
        step(i)
    return (time.perf_counter() - start) / steps


def sb3_worker(width: int, steps: int) -> float:
    import numpy as np
    import torch
    from stable_baselines3 import SAC

    torch.set_num_threads(1)
    model = SAC("MlpPolicy", "Pendulum-v1", learning_rate=3e-4, learning_starts=100, batch_size=256, train_freq=1, gradient_steps=1,
                ent_coef="auto_0.2", policy_kwargs={"net_arch": [width, width]}, seed=0, device="cpu")  # fmt: skip
    model.learn(1000)  # fills the buffer past learning_starts and runs the first updates
    obs = np.zeros(3, dtype=np.float32)
    for _ in range(50):
        model.predict(obs)
        model.train(gradient_steps=1, batch_size=256)
    start = time.perf_counter()
    for _ in range(steps):
        model.predict(obs)  # SB3's acting call (deterministic=False samples, as in training)
        model.train(gradient_steps=1, batch_size=256)
    return (time.perf_counter() - start) / steps


def run(impl: str, width: int, steps: int, workdir: Path) -> float:
    script = {"sac": str(ROOT / "sac_continuous.py"), "sac_before": str(workdir / "sac_before.py")}.get(impl, "")
    out = checked(subprocess.run([sys.executable, __file__, "--worker", impl, script, str(width), str(steps)],
                                 capture_output=True, text=True)).stdout  # fmt: skip
    return float(out.strip().splitlines()[-1]) * 1000.0


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        impl, script, width, steps = sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5])
        print(sb3_worker(width, steps) if impl == "sb3" else ours_worker(script, width, steps))
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--widths", type=int, nargs="+", default=[256, 64])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--before", default="", help="git revision of an earlier sac_continuous.py to time too")
    parser.add_argument("--workdir", type=Path, default=ROOT / "benchmarks" / "results" / "update_speed")
    args = parser.parse_args()
    minimums = {"--widths": (min(args.widths), 1), "--steps": (args.steps, 1), "--repeats": (args.repeats, 1)}
    if too_small := [f"{flag} must be at least {low}" for flag, (value, low) in minimums.items() if not value >= low]:
        parser.error("; ".join(too_small))
    require(parser, "stable_baselines3")
    args.workdir.mkdir(parents=True, exist_ok=True)
    names = ["sac", "sb3"]
    if args.before:
        script_at(args.before, args.workdir)
        names.append("sac_before")
    print(f"ms per training step (acting + one update, batch 256), {args.steps} steps per process, 1 thread")
    header = "| width | ours | SB3 | SB3/ours |" + (f" ours at {args.before} | before/now |" if args.before else "")
    print(header + " reps |")
    print("|---" * (header.count("|") - 1) + "|---|")
    for width in args.widths:
        ms: dict[str, list[float]] = {name: [] for name in names}
        for rep in range(args.repeats):
            shift = rep % len(names)
            for name in names[shift:] + names[:shift]:
                ms[name].append(run(name, width, args.steps, args.workdir))

        def ratio(slow: str) -> str:
            ratios = [s / f for s, f in zip(ms[slow], ms["sac"])]
            return f"{statistics.median(ratios):.2f} (range {min(ratios):.2f}-{max(ratios):.2f})"

        row = f"| {width} | {statistics.median(ms['sac']):.2f} | {statistics.median(ms['sb3']):.2f} | {ratio('sb3')} |"
        if args.before:
            row += f" {statistics.median(ms['sac_before']):.2f} | {ratio('sac_before')} |"
        print(row + f" {args.repeats} |", flush=True)


if __name__ == "__main__":
    stop_children_on_sigterm()
    main()
