"""The figures BENCHMARKS.md quotes for an on-car training, read from the run's TensorBoard log.

`python -m deploy.jetracer train` logs every `--jirl.log-every` steps: the RL-control fraction, the
control switches, the fabricated transitions, both baseline regrets per step, the loop's period and
the link's round trip; and, sim-in-the-loop, each completed lap's time at the first log after it.
This tool prints, as markdown:

- laps and the median lap time in each window of steps (`--windows`, edges in steps);
- the RL-control fraction at the first log at or after `--control-at`, and the first logged step from
  which it stays at 100 %;
- the last logged counters and regrets per step (the run's own final line prints them at its last step);
- the medians over the logs of the loop period's p50 and p99, of the round trip's p50 and p99, and the
  frames dropped.

    python benchmarks/car_run.py benchmarks/results/car_1204/runs/train__*
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

COUNTERS = ("control_switches", "fabricated_transitions", "baseline_regret_per_step", "paired_regret_per_step")
TIMING = ("loop/period_p50_ms", "loop/period_p99_ms", "link/rtt_p50_ms", "link/rtt_p99_ms")


def read(run_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar of the run, as (step, value) in the order logged."""
    if not any(run_dir.glob("events.out.tfevents.*")):
        raise ValueError(f"{run_dir} holds no TensorBoard events")
    events = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})
    events.Reload()
    return {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def summarize(logged: dict[str, list[tuple[int, float]]], windows: list[int], control_at: int) -> dict:
    """The figures of one run; a figure the log lacks is None."""
    laps = logged.get("charts/lap_time", [])
    per_window = []
    for start, end in zip(windows, windows[1:]):
        times = [t for step, t in laps if start <= step < end or (end == windows[-1] and step == end)]
        per_window.append({"steps": (start, end), "laps": len(times), "median_lap_s": statistics.median(times) if times else None})
    control = logged.get("charts/rl_control_fraction", [])
    at = next(((step, value) for step, value in control if step >= control_at), None)
    full_from = None  # the first step of the last run of 100 % logs, if the log ends in one
    for step, value in control:
        if value < 1.0:
            full_from = None
        elif full_from is None:
            full_from = step
    last = {key: logged[f"charts/{key}"][-1] if f"charts/{key}" in logged else None for key in COUNTERS}
    timing = {tag: statistics.median(v for _, v in logged[tag]) if logged.get(tag) else None for tag in TIMING}
    dropped = logged["loop/frames_dropped"][-1][1] if logged.get("loop/frames_dropped") else None
    return {"windows": per_window, "control_at": at, "full_control_from": full_from, "last": last, "timing": timing, "frames_dropped": dropped}


def report(figures: dict) -> str:
    def number(x: float | None, digits: int) -> str:
        return "–" if x is None else f"{x:,.{digits}f}"

    edges = [f"{w['steps'][0] // 1000}k–{w['steps'][1] // 1000}k" for w in figures["windows"]]
    lines = ["| | " + " | ".join(edges) + " |", "|---" * (len(edges) + 1) + "|",
             "| median lap time (s) | " + " | ".join(number(w["median_lap_s"], 2) for w in figures["windows"]) + " |",
             "| laps | " + " | ".join(str(w["laps"]) for w in figures["windows"]) + " |", ""]  # fmt: skip
    if figures["control_at"] is not None:
        step, value = figures["control_at"]
        lines.append(f"RL control {100 * value:.0f} % at step {step:,}; 100 % from step {number(figures['full_control_from'], 0)} on")
    for key, entry in figures["last"].items():
        lines.append(f"{key} at step {entry[0]:,}: {number(entry[1], 1 if 'regret' in key else 0)}" if entry else f"{key}: not logged")
    lines.append("medians over the logs: " + ", ".join(f"{tag} {number(value, 2)}" for tag, value in figures["timing"].items()))
    lines.append(f"frames dropped: {number(figures['frames_dropped'], 0)}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a train run's log directory (under --log-dir)")
    parser.add_argument("--windows", type=int, nargs="+", default=[0, 5000, 20000, 40000, 54000], help="window edges, in steps")
    parser.add_argument("--control-at", type=int, default=5000, help="report the RL-control fraction at the first log at or after this step")
    args = parser.parse_args(argv)
    if len(args.windows) < 2 or args.windows != sorted(set(args.windows)):
        parser.error(f"--windows needs two or more increasing edges, got {args.windows}")
    try:
        logged = read(args.run_dir)
    except ValueError as err:
        parser.error(str(err))
    print(report(summarize(logged, args.windows, args.control_at)))


if __name__ == "__main__":
    main()
