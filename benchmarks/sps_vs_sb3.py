"""Training speed of sac_continuous.py and jirl_sac_continuous.py against Stable-Baselines3's SAC.

All train Pendulum-v1 with the same hyperparameters (one learning rate for actor, critics and entropy
coefficient, one actor update per env step, batch 256, the same warm-up), one torch thread each, in
fresh processes whose order rotates every repetition, for every network width asked. SPS is env steps
over the process's whole wall time (imports included, for all), and as each reports it for its
training loop alone (setup and imports excluded; SB3's from learn()'s own start time). `--before REV` adds sac_continuous.py
as it was at git revision REV (copied out alone, so it runs without envs/), for a before/after ratio
measured in the same run. Prints a markdown table: median SPS and the median of per-repetition ratios.

    python benchmarks/sps_vs_sb3.py --widths 256 64 --repeats 3 --before 66f0bdb
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

from side_by_side import measure, ratio_cell, require, script_at, stop_children_on_sigterm

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
        ent_coef="auto_0.2",  # tuned from 0.2, as our scripts' --alpha starts it (SB3 starts from 1)
        train_freq=1,
        gradient_steps=1,
        policy_kwargs={"net_arch": [width, width]},
        seed=seed,
        device="cpu",
    )
    model.learn(total_timesteps=steps)
    print(f"SPS: {steps / ((time.time_ns() - model.start_time) / 1e9):.1f}")  # learn()'s own clock, as our scripts report


def command(impl: str, width: int, steps: int, learning_starts: int, seed: int, workdir: Path) -> list[str]:
    if impl == "sb3":
        return [sys.executable, __file__, "--worker", str(width), str(steps), str(learning_starts), str(seed)]
    script = workdir / "sac_before.py" if impl == "sac_before" else ROOT / f"{impl}.py"
    return [
        sys.executable, str(script), "--env-id", "Pendulum-v1", "--seed", str(seed),
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
    parser.add_argument("--steps", type=int, default=5000)
    parser.add_argument("--learning-starts", type=int, default=500)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--before", default="", help="git revision of an earlier sac_continuous.py to time too")
    parser.add_argument("--workdir", type=Path, default=ROOT / "benchmarks" / "results" / "sps_vs_sb3")
    args = parser.parse_args()
    minimums = {"--widths": (min(args.widths), 1), "--steps": (args.steps, 1), "--repeats": (args.repeats, 1), "--learning-starts": (args.learning_starts, 0)}
    if too_small := [f"{flag} must be at least {low}" for flag, (value, low) in minimums.items() if not value >= low]:
        parser.error("; ".join(too_small))
    require(parser, "stable_baselines3")
    args.workdir.mkdir(parents=True, exist_ok=True)
    names = ["sac_continuous", "jirl_sac_continuous", "sb3"]
    if args.before:
        script_at(args.before, args.workdir)
        names.append("sac_before")
    print(f"Pendulum-v1, {args.steps} steps, learning starts {args.learning_starts}, batch 256, 1 thread")
    header = "| width | SPS | SAC | JIRL | SB3 | SAC/SB3 | JIRL/SB3 |"
    if args.before:
        header += f" SAC at {args.before} | SAC now/before |"
    print(header + " reps |")
    print("|---" * (header.count("|") - 1) + "|---|")
    for width in args.widths:
        sps_pair = measure(lambda impl, seed: command(impl, width, args.steps, args.learning_starts, seed, args.workdir), names, args.steps, args.repeats, args.workdir)
        for label, sps in zip(("whole process", "training loop"), sps_pair):
            row = f"| {width} | {label} | " + " | ".join(f"{statistics.median(sps[n]):.1f}" for n in names[:3])
            row += f" | {ratio_cell(sps, 'sac_continuous', 'sb3')} | {ratio_cell(sps, 'jirl_sac_continuous', 'sb3')} |"
            if args.before:
                row += f" {statistics.median(sps['sac_before']):.1f} | {ratio_cell(sps, 'sac_continuous', 'sac_before')} |"
            print(row + f" {args.repeats} |", flush=True)


if __name__ == "__main__":
    stop_children_on_sigterm()
    main()
