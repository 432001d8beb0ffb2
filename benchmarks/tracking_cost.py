"""What `--track` costs a run in wall time, offline (WANDB_MODE=offline: no network in the figure).

Three forms of one short `sac_continuous.py` run (Pendulum-v1, 16 units, --steps steps), each in a fresh
folder holding its own copy of the script:
- `plain`: without --track;
- `track`: with --track, as the script starts W&B (the TensorBoard folder named to wandb);
- `sync_tensorboard`: with --track, with CleanRL's `wandb.init(sync_tensorboard=True)` put in place of
  the named folder, with which wandb seeks the folder for 10 s from its start, and no run ends sooner.

The forms run in turn within each repeat (their order rotating), so that a busy machine slows all
three alike; prints the median and range over the repeats of each form's seconds, and of its ratio to
`plain` and the seconds it adds to it in the same repeat (W&B's start and exit, and whatever its
process takes from the run while it reads the TensorBoard logs: the second command shows how much of
that grows with the run).

    python benchmarks/tracking_cost.py --repeats 5
    python benchmarks/tracking_cost.py --repeats 3 --steps 4000
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RUN = ["--learning-starts", "200", "--hidden-size", "16", "--batch-size", "16", "--baseline-eval-episodes", "1"]
NAMED = '    wandb.tensorboard.patch(root_logdir=f"runs/{run_name}")'
INIT = "config=vars(args), save_code=True)"


def script_text(form: str) -> str:
    text = (ROOT / "sac_continuous.py").read_text()
    if form == "sync_tensorboard":
        assert text.count(NAMED) == 1 and text.count(INIT) == 1, "start_tracking changed: update this benchmark"
        text = text.replace(NAMED, "    pass").replace(INIT, "config=vars(args), save_code=True, sync_tensorboard=True)")
    return text


def timed(form: str, steps: int) -> float:
    with tempfile.TemporaryDirectory() as folder:
        (Path(folder) / "sac_continuous.py").write_text(script_text(form))
        env = {k: v for k, v in os.environ.items() if not k.startswith("WANDB_")} | {"WANDB_MODE": "offline", "HOME": folder, "PYTHONPATH": str(ROOT)}
        args = RUN + ["--total-timesteps", str(steps)] + ([] if form == "plain" else ["--track"])
        start = time.perf_counter()
        out = subprocess.run([sys.executable, "sac_continuous.py", *args], cwd=folder, env=env, capture_output=True, text=True)
        seconds = time.perf_counter() - start
        if out.returncode != 0:
            raise SystemExit(f"{form}: the run failed:\n{out.stderr}")
        if form != "plain" and not list(Path(folder).glob("wandb/offline-run-*/run-*.wandb")):
            raise SystemExit(f"{form}: no W&B run was written")
        return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--steps", type=int, default=400, help="the run's --total-timesteps")
    args = parser.parse_args()
    if shutil.which("git"):
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
        print(f"commit {commit}")
    forms = ["plain", "track", "sync_tensorboard"]
    seconds: dict[str, list[float]] = {form: [] for form in forms}
    for i in range(args.repeats):
        for form in forms[i % 3 :] + forms[: i % 3]:
            seconds[form].append(timed(form, args.steps))
        print(f"repeat {i + 1}: " + ", ".join(f"{form} {seconds[form][-1]:.1f} s" for form in forms), flush=True)
    for form in forms:
        ratios = [s / p for s, p in zip(seconds[form], seconds["plain"])]
        added = [s - p for s, p in zip(seconds[form], seconds["plain"])]
        print(f"{form:>16}: {statistics.median(seconds[form]):5.1f} s ({min(seconds[form]):.1f} to {max(seconds[form]):.1f}),"
              f" {statistics.median(ratios):.2f}x plain ({min(ratios):.2f} to {max(ratios):.2f}),"
              f" +{statistics.median(added):.1f} s ({min(added):.1f} to {max(added):.1f})")  # fmt: skip


if __name__ == "__main__":
    main()
