"""What the per-step checks of a user's env and baseline cost, against the calls they wrap.

- `CheckedEnv.step` (make_env's wrapper: an env's exception, NaN or malformed return ends the run
  keeping its model) against the bare step: everything the wrapper adds, `flaw`'s checks included.
- `ask_baseline` (a baseline's exception ends the run keeping its model) against the bare call.

Pendulum-v1 from `jirl_sac_continuous.py` (the four scripts share both definitions, a test checks).
Each repeat times both sides back to back (which first alternates), the best of 3 runs of `--calls` calls each; prints the
median and range over the repeats of the time added per call.

    python benchmarks/step_checks.py --repeats 9
"""

from __future__ import annotations

import argparse
import statistics
import sys
import timeit
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parent.parent


def added(new: Callable[[], object], old: Callable[[], object], calls: int, repeats: int) -> tuple[float, list[float]]:
    """Seconds per call of `old`, and the seconds `new` adds per call in each repeat."""
    olds, diffs = [], []
    for i in range(repeats):
        order = (old, new) if i % 2 == 0 else (new, old)  # alternate which side runs first
        times = {f: min(timeit.repeat(f, number=calls, repeat=3)) / calls for f in order}
        t_old, t_new = times[old], times[new]
        olds.append(t_old)
        diffs.append(t_new - t_old)
    return statistics.median(olds), diffs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--calls", type=int, default=100_000)
    args = parser.parse_args()

    sys.path.insert(0, str(ROOT))
    import gymnasium as gym
    import numpy as np

    import jirl_sac_continuous as jirl

    bare, checked = gym.make("Pendulum-v1"), jirl.CheckedEnv(gym.make("Pendulum-v1"), "Pendulum-v1")
    bare.reset(seed=0)
    checked.reset(seed=0)  # Pendulum never terminates, and its time limit only flags truncation
    action = np.array([0.3], dtype=np.float32)

    def baseline(obs: np.ndarray) -> np.ndarray:
        return action

    obs = np.zeros(3, dtype=np.float32)
    rows = [
        ("CheckedEnv.step vs the bare step", lambda: checked.step(action), lambda: bare.step(action)),
        ("ask_baseline vs the bare call", lambda: jirl.ask_baseline(baseline, obs), lambda: baseline(obs)),
    ]
    print("| check | the call it wraps | added per call: median | range |")
    print("|---|---|---|---|")
    for name, new, old in rows:
        before, diffs = added(new, old, args.calls, args.repeats)
        print(f"| {name} | {before * 1e6:.2f} µs | {statistics.median(diffs) * 1e9:.0f} ns | {min(diffs) * 1e9:.0f} to {max(diffs) * 1e9:.0f} ns |")


if __name__ == "__main__":
    main()
