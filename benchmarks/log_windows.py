"""What runs logged, window by window of steps: medians of some scalars, and what running totals grew by.

Reads the newest run of each seed under the workdirs given as arguments (each the `--workdir` of a
benchmarks/learning.py run) and prints one table per seed, a row per --window steps from step 0:

- for each --medians tag, the median of the points logged in the window (– where none was): by
  default the RL-control fraction, the critic's value of the sampled pairs and the entropy coefficient,
  which tell whether an agent kept the control and whether its critic stayed bounded;
- for each --totals tag, what it grew by in the window: its last value logged before the window's end
  less its last before the window's start (0 before its first point). By default the two forms of the
  baseline regret, which the scripts log as running totals at episode ends.

    python benchmarks/log_windows.py --window 20000 benchmarks/results/tol25_walker200k_s4
"""

from __future__ import annotations

import argparse
import bisect
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

sys.path.insert(0, str(Path(__file__).resolve().parent))

from learning import read_scalars  # noqa: E402
from paper_window import Series, newest_runs, value_at  # noqa: E402

MEDIANS = ["charts/rl_control_fraction", "losses/qf1_values", "losses/alpha"]
TOTALS = ["charts/baseline_regret", "charts/baseline_regret_per_step"]


def window_median(series: Series, start: int, end: int) -> Optional[float]:
    """The median of the values logged at steps in [start, end) (series sorted by step); None where none was."""
    first, stop = (bisect.bisect_left(series, step, key=lambda point: point[0]) for step in (start, end))
    return statistics.median(value for _, value in series[first:stop]) if stop > first else None


@dataclass
class Row:
    """One window: its first step, the medians of the median tags and the growths of the totals, in order."""

    start: int
    medians: list[Optional[float]]
    growths: list[float]


def windows(scalars: dict[str, Series], medians: list[str], totals: list[str], window: int) -> list[Row]:
    """One row per window of `window` steps, from step 0 to the last step any of the tags logged."""
    last = max(step for tag in medians + totals for step, _ in scalars[tag])
    return [
        Row(
            start,
            [window_median(scalars[tag], start, start + window) for tag in medians],
            # steps are integers: the last value logged before step n is the last at or before n - 1
            [value_at(scalars[tag], start + window - 1) - value_at(scalars[tag], start - 1) for tag in totals],
        )
        for start in range(0, last + 1, window)
    ]


def report(seed: int, rows: list[Row], medians: list[str], totals: list[str], window: int) -> str:
    head = ["steps"] + [f"{tag}, median" for tag in medians] + [f"{tag}, grew by" for tag in totals]
    lines = [f"seed {seed}", "| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for row in rows:
        cells = [f"{row.start:,}–{row.start + window:,}"]
        cells += ["–" if value is None else f"{value:.4g}" for value in row.medians]
        cells += [f"{value:,.0f}" for value in row.growths]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: Optional[list[str]] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workdirs", type=Path, nargs="+", help="workdirs of the runs (benchmarks/learning.py --workdir)")
    parser.add_argument("--window", type=int, default=20_000, help="steps per row (> 0)")
    parser.add_argument("--medians", nargs="*", default=MEDIANS, help="tags whose median over each window is printed")
    parser.add_argument("--totals", nargs="*", default=TOTALS, help="running totals whose growth in each window is printed")
    args = parser.parse_args(argv)
    if args.window <= 0:
        parser.error(f"--window must be > 0, got {args.window}")
    if not args.medians and not args.totals:
        parser.error("nothing to print: give --medians or --totals a tag")
    tables = []
    for seed, run in sorted(newest_runs(args.workdirs, "log_windows").items()):
        scalars = read_scalars(run)
        missing = [tag for tag in args.medians + args.totals if not scalars.get(tag)]
        if missing:
            raise SystemExit(f"log_windows: error: {run} logged no {', '.join(missing)}")
        tables.append(report(seed, windows(scalars, args.medians, args.totals, args.window), args.medians, args.totals, args.window))
    print("\n\n".join(tables))


if __name__ == "__main__":
    main()
