"""When JIRL handed control to its agent, per seed, read from the TensorBoard logs of its runs.

Reads the JIRL runs under the workdirs given as arguments (each the `--workdir` of a
benchmarks/learning.py run; the newest run of each seed) and prints one row per seed and the medians,
from what the script logs every --log-every steps:

- C = 0 from: the first logged step where the gate's C (`gate/c`) is 0: the guidance is over;
- 100 % from: the first logged step where `charts/rl_control_fraction` is 1, the agent having acted
  on every one of the last --rl-control-window steps (T_100 of benchmarks/paper_window.py);
- C > 0 again: the share of the points logged from "C = 0 from" on where C is above 0 again (the
  earned schedule handing control back after episodes that fell behind the baseline's);
- C and the RL-control fraction at the last point logged.

    python benchmarks/handover.py benchmarks/results/earned40k_ten
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path
from typing import Optional

sys.path.insert(0, str(Path(__file__).resolve().parent))

from learning import read_scalars  # noqa: E402
from paper_window import Series, first_full_control, newest_runs  # noqa: E402

TAGS = ("gate/c", "charts/rl_control_fraction")


def handover(c: Series, rl_control: Series) -> dict[str, Optional[float]]:
    """One run's hand-over from its logged C and RL-control fraction (None where it never came)."""
    c_zero = next((step for step, value in c if value == 0.0), None)
    after = [value for step, value in c if c_zero is not None and step >= c_zero]
    return {
        "c_zero": c_zero,
        "full_control": first_full_control(rl_control),
        "c_back": sum(value > 0.0 for value in after) / len(after) if after else None,
        "c_end": c[-1][1],
        "control_end": rl_control[-1][1],
    }


def cell(value: Optional[float], form: str) -> str:
    return "never" if value is None else form.format(value).replace("%", " %")


def report(rows: dict[int, dict[str, Optional[float]]]) -> str:
    lines = ["| seed | C = 0 from | 100 % from | C > 0 again | C at the end | RL control at the end |", "|---" * 6 + "|"]
    forms = {"c_zero": "{:,.0f}", "full_control": "{:,.0f}", "c_back": "{:.0%}", "c_end": "{:.3g}", "control_end": "{:.1%}"}
    for seed, row in sorted(rows.items()):
        lines.append(f"| {seed} | " + " | ".join(cell(row[key], form) for key, form in forms.items()) + " |")
    medians = []
    for key, form in forms.items():
        values = [row[key] for row in rows.values()]
        reached = [value for value in values if value is not None]
        # a median over runs of which some never got there would be no step of any run
        medians.append(cell(statistics.median(reached), form) if len(reached) == len(values) else "–")
    lines.append("| median | " + " | ".join(medians) + " |")
    return "\n".join(lines)


def main(argv: Optional[list[str]] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workdirs", type=Path, nargs="+", help="workdirs of the JIRL runs (benchmarks/learning.py --workdir)")
    args = parser.parse_args(argv)
    rows = {}
    for seed, run in newest_runs(args.workdirs, "handover").items():
        scalars = read_scalars(run)
        missing = [tag for tag in TAGS if not scalars.get(tag)]
        if missing:
            raise SystemExit(f"handover: error: {run} logged no {', '.join(missing)} (not a JIRL run, or not started?)")
        rows[seed] = handover(scalars["gate/c"], scalars["charts/rl_control_fraction"])
    print(report(rows))


if __name__ == "__main__":
    main()
