"""What JIRL's per-step work (baseline query, gate, fabricated transitions) costs: JIRL against SAC.

Both scripts train Pendulum-v1 with the same SAC settings, one torch thread, alternating which runs
first; SPS is env steps over the process's whole wall time. JIRL's gate, penalty and extra transitions
are all it adds (regret estimation runs in both).

    python benchmarks/sps_jirl_vs_sac.py --widths 64 256 --repeats 3
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from side_by_side import compare, stop_children_on_sigterm

ROOT = Path(__file__).resolve().parent.parent


def command(script: str, width: int, steps: int, learning_starts: int, seed: int) -> list[str]:
    return [sys.executable, str(ROOT / f"{script}.py"), "--env-id", "Pendulum-v1", "--seed", str(seed),
            "--total-timesteps", str(steps), "--learning-starts", str(learning_starts), "--hidden-size", str(width),
            "--torch-threads", "1"]  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--widths", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--learning-starts", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workdir", type=Path, default=ROOT / "benchmarks" / "results" / "sps_jirl_vs_sac")
    args = parser.parse_args()
    minimums = {"--widths": (min(args.widths), 1), "--steps": (args.steps, 1), "--repeats": (args.repeats, 1), "--learning-starts": (args.learning_starts, 0)}
    if too_small := [f"{flag} must be at least {low}" for flag, (value, low) in minimums.items() if not value >= low]:
        parser.error("; ".join(too_small))
    args.workdir.mkdir(parents=True, exist_ok=True)
    print(f"Pendulum-v1, {args.steps} steps, learning starts {args.learning_starts}, batch 256, 1 thread")
    print("| width | JIRL SPS (median) | SAC SPS (median) | ratio JIRL/SAC (median of pairs) | pairs |")
    print("|---|---|---|---|---|")
    for width in args.widths:
        row = compare(lambda script, seed: command(script, width, args.steps, args.learning_starts, seed),
                      args.steps, args.repeats, args.workdir, names=("jirl_sac_continuous", "sac_continuous"))  # fmt: skip
        print(f"| {width} | {row}", flush=True)


if __name__ == "__main__":
    stop_children_on_sigterm()
    main()
