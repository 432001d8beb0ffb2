"""Train an algorithm script on several seeds and summarise what its TensorBoard logs say.

Runs the seeds one after another (one torch thread each; start two of these side by side on a
2-core machine, not one with two threads), each with --save-model so the final deterministic
evaluation is logged, then prints one markdown row per seed and the median:
final evaluation return, the baseline's return, accumulated baseline regret (both paired
forms), wall time and SPS, then the median and the mean with its 95 % confidence interval. Extra arguments after `--` go to the script unchanged.

    python benchmarks/learning.py --script sac_continuous.py --env-id Pendulum-v1 \
        --seeds 1 2 3 --total-timesteps 20000 -- --learning-starts 1000
"""

from __future__ import annotations

import argparse
import math
import statistics
import subprocess
import sys
import time
from pathlib import Path

from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from side_by_side import stop_children_on_sigterm

ROOT = Path(__file__).resolve().parent.parent


def read_scalars(run_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """All scalars of one run directory: tag -> [(step, value), ...]."""
    events = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})
    events.Reload()
    return {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def last(scalars: dict, tag: str) -> float:
    return scalars[tag][-1][1] if tag in scalars else float("nan")


def summarise(scalars: dict) -> dict[str, float]:
    evals = [v for _, v in scalars.get("eval/episodic_return", [])]
    return {
        "eval_return": statistics.mean(evals) if evals else float("nan"),
        "baseline_return": last(scalars, "charts/baseline_return"),
        "baseline_regret": last(scalars, "charts/baseline_regret"),
        "baseline_regret_per_step": last(scalars, "charts/baseline_regret_per_step"),
        "rl_control_fraction": last(scalars, "charts/rl_control_fraction"),
        "sps": last(scalars, "charts/SPS"),
    }


def main() -> None:
    argv = sys.argv[1:]
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    argv = argv[: argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--script", default="sac_continuous.py")
    parser.add_argument("--env-id", default="Pendulum-v1")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--total-timesteps", type=int, default=20_000)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--workdir", type=Path, default=ROOT / "benchmarks" / "results" / "learning")
    args = parser.parse_args(argv)
    args.workdir.mkdir(parents=True, exist_ok=True)
    exp_name = f"{Path(args.script).stem}_bench"
    rows = []
    for seed in args.seeds:
        cmd = [
            sys.executable, str(ROOT / args.script), "--env-id", args.env_id, "--seed", str(seed),
            "--total-timesteps", str(args.total_timesteps), "--save-model",
            "--eval-episodes", str(args.eval_episodes), "--exp-name", exp_name, *extra,
        ]  # fmt: skip
        start = time.perf_counter()
        if subprocess.run(cmd, cwd=args.workdir, stdout=subprocess.DEVNULL).returncode != 0:  # its error is on stderr above
            raise SystemExit(f"learning: error: seed {seed} failed; the rows above are the seeds that finished")
        wall = time.perf_counter() - start
        run_dir = max((args.workdir / "runs").glob(f"{args.env_id}__{exp_name}__{seed}__*"), key=lambda p: p.stat().st_mtime)
        row = summarise(read_scalars(run_dir)) | {"seed": seed, "wall_s": wall}
        rows.append(row)
        print(f"seed {seed}: {row}", flush=True)
    keys = ["eval_return", "baseline_return", "baseline_regret", "baseline_regret_per_step", "rl_control_fraction", "sps", "wall_s"]
    print(f"\n{args.script} on {args.env_id}, {args.total_timesteps} steps, extra args: {' '.join(extra) or '(none)'}")
    print("| seed | " + " | ".join(keys) + " |")
    print("|---" * (len(keys) + 1) + "|")
    for row in rows:
        print(f"| {row['seed']} | " + " | ".join(f"{row[k]:.1f}" for k in keys) + " |")
    print("| median | " + " | ".join(f"{statistics.median(r[k] for r in rows):.1f}" for k in keys) + " |")
    if len(rows) > 1:
        print("| mean ± 95 % CI | " + " | ".join(mean_ci([r[k] for r in rows]) for k in keys) + " |")


def mean_ci(values: list[float]) -> str:
    """Mean ± the half-width of its 95 % confidence interval (Student's t over the seeds); NaNs (a
    quantity the script does not log, such as SAC's RL-control fraction) are left out."""
    from scipy import stats

    values = [v for v in values if not math.isnan(v)]
    if len(values) < 2:
        return f"{values[0]:.1f}" if values else "–"
    half = stats.t.ppf(0.975, len(values) - 1) * statistics.stdev(values) / len(values) ** 0.5
    return f"{statistics.mean(values):.1f} ± {half:.1f}"


if __name__ == "__main__":
    stop_children_on_sigterm()
    main()
