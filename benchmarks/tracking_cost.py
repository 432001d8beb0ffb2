"""What `--track` costs a run in wall time, offline (WANDB_MODE=offline: no network in the figure).

Three forms of one `sac_continuous.py` run (Pendulum-v1, 16 units, --steps steps), each a fresh process:
- `plain`: without --track;
- `track`: with --track, as the script starts W&B (the TensorBoard folder named to wandb);
- `sync_tensorboard`: with --track, with CleanRL's `wandb.init(sync_tensorboard=True)` put in place of
  the named folder, with which wandb seeks the folder for 10 s from its start, and no run ends sooner.

side_by_side.measure runs the forms in turn within each repeat (their order rotating, the seed the
repeat's), so that a busy machine slows all three alike. Prints the median and range over the repeats
of each form's seconds, and of its ratio to `plain` and the seconds it adds to it in the same repeat
(W&B's start and exit, and whatever its process takes from the run while it reads the TensorBoard logs:
the second command shows how much of that grows with the run).

    python benchmarks/tracking_cost.py --repeats 5
    python benchmarks/tracking_cost.py --repeats 3 --steps 4000
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from side_by_side import measure, stop_children_on_sigterm

ROOT = Path(__file__).resolve().parent.parent
RUN = ["--learning-starts", "200", "--hidden-size", "16", "--batch-size", "16", "--baseline-eval-episodes", "1"]
NAMED = '    wandb.tensorboard.patch(root_logdir=f"runs/{run_name}")'
INIT = "config=vars(args), save_code=True)"


def with_sync_tensorboard(text: str) -> str:
    """sac_continuous.py's text with CleanRL's sync_tensorboard=True in place of the named folder."""
    assert text.count(NAMED) == 1 and text.count(INIT) == 1, "start_tracking changed: update this benchmark"
    return text.replace(NAMED, "    pass").replace(INIT, "config=vars(args), save_code=True, sync_tensorboard=True)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--steps", type=int, default=400, help="the run's --total-timesteps")
    args = parser.parse_args()
    stop_children_on_sigterm()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    print(f"commit {commit or 'unknown'}")
    forms = ("plain", "track", "sync_tensorboard")
    with tempfile.TemporaryDirectory() as folder:
        script = (ROOT / "sac_continuous.py").read_text()
        (Path(folder) / "sac_continuous.py").write_text(script)
        (Path(folder) / "sac_sync.py").write_text(with_sync_tensorboard(script))
        # the runs' environment: offline, a home of their own (no login, no cache), this repository's envs/
        os.environ.update(WANDB_MODE="offline", HOME=folder, PYTHONPATH=str(ROOT))

        def command(form: str, seed: int) -> list[str]:
            name = "sac_sync.py" if form == "sync_tensorboard" else "sac_continuous.py"
            return [sys.executable, name, *RUN, "--total-timesteps", str(args.steps), "--seed", str(seed)] + ([] if form == "plain" else ["--track"])

        sps, _ = measure(command, forms, args.steps, args.repeats, Path(folder))
        written = len(list(Path(folder).glob("wandb/offline-run-*/run-*.wandb")))
        if written != 2 * args.repeats:
            raise SystemExit(f"{written} W&B runs were written, not {2 * args.repeats}")
    seconds = {form: [args.steps / rate for rate in sps[form]] for form in forms}
    for form in forms:
        ratios = [s / p for s, p in zip(seconds[form], seconds["plain"])]
        added = [s - p for s, p in zip(seconds[form], seconds["plain"])]
        print(f"{form:>16}: {statistics.median(seconds[form]):5.1f} s ({min(seconds[form]):.1f} to {max(seconds[form]):.1f}),"
              f" {statistics.median(ratios):.2f}x plain ({min(ratios):.2f} to {max(ratios):.2f}),"
              f" +{statistics.median(added):.1f} s ({min(added):.1f} to {max(added):.1f})")  # fmt: skip


if __name__ == "__main__":
    main()
