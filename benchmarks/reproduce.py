"""Reproduce the JIRL paper's Table I and Fig. 1: train every method on every env and seed, then report.

    python benchmarks/reproduce.py --preset quick                      # a smoke check, minutes
    python benchmarks/reproduce.py --preset local --envs Pendulum-v1    # this machine's budgets
    python benchmarks/reproduce.py --preset paper --launcher slurm --slurm-partition cpu

Each run (method, env, seed) trains in its own folder under --workdir and leaves a DONE marker when it
finishes, so a second call runs only what is missing (resumable). Then the TensorBoard logs of all
finished runs are read and written to --output:
- `table.md`: the paper's Table I (JIRL's baseline regret in the 0-50 %, 50-<100 % and 100 % RL-control
  phases, JIRL's total, SAC's, the best of PPO/TRPO+IL), for both paired estimators, as mean ± 95 % CI
  over seeds, with the ratios and a paired t-test; then the final evaluation returns of every method
  and of the baseline;
- `fig_{env}.png`: smoothed reward per step with 95 % CI bands per method, the baseline's level, and
  JIRL's RL-control fraction on a second axis.
Launchers: a local pool of processes (one per core, with progress and ETA), or Slurm through submitit.
"""

from __future__ import annotations

import contextlib
import math
import os
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
import warnings
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Literal, Optional, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SCRIPTS = {"jirl": "jirl_sac_continuous.py", "sac": "sac_continuous.py", "ppo_il": "ppo_il.py", "trpo_il": "trpo_il.py"}
LABELS = {"jirl": "JIRL (SAC)", "sac": "SAC", "ppo_il": "PPO+IL", "trpo_il": "TRPO+IL"}

# On the track an early agent leaves the lane within tens of steps while the paired shadow env drives
# the baseline's full 2000: the shadow rollouts would dominate the run (README, Baseline regret).
TRACK_REGRET = ["--regret-estimator", "unpaired"]
# The authors' SAC replay buffers (their report, Table III) for the SAC-based methods: Pendulum and
# Lunar Lander; Walker2D's was our default 1e6, and the paper has no track trained step by step.
PAPER_BUFFER = {"Pendulum-v1": ["--buffer-size", "50000"], "LunarLanderContinuous-v3": ["--buffer-size", "100000"]}
# Budgets per preset and env: env steps for every method, then extra arguments per method.
PRESETS: dict[str, dict[str, dict]] = {
    "quick": {
        env: {"steps": 600, "all": ["--hidden-size", "16"], "jirl": ["--learning-starts", "200", "--batch-size", "32"],
              "sac": ["--learning-starts", "200", "--batch-size", "32"],
              "ppo_il": ["--num-steps", "200", "--num-minibatches", "4", "--il-steps", "400", "--il-max-epochs", "5"],
              "trpo_il": ["--num-steps", "200", "--il-steps", "400", "--il-max-epochs", "5"]}  # fmt: skip
        for env in ("Pendulum-v1", "LunarLanderContinuous-v3", "JetRacerTrack-v0", "Walker2DBulletEnv-v0")
    },
    "local": {  # what one 2-core machine finishes in hours (BENCHMARKS.md)
        "Pendulum-v1": {"steps": 40_000, "all": ["--hidden-size", "64"], "jirl": ["--learning-starts", "1000"], "sac": ["--learning-starts", "1000"]},
        "LunarLanderContinuous-v3": {"steps": 100_000, "all": ["--hidden-size", "64"]},
        "JetRacerTrack-v0": {"steps": 54_000, "all": ["--hidden-size", "64", *TRACK_REGRET]},
        "Walker2DBulletEnv-v0": {"steps": 100_000, "all": ["--hidden-size", "256"]},
    },
    # The paper's training lengths (its figures' x axes), 64 units (256 for Walker2D), its JIRL K and
    # sigma^2, and its SAC replay buffers where they differ from our 1e6: a bounded buffer is how the
    # paper forgets the fabricated transitions after the hand-over (BENCHMARKS.md, Pendulum at 280k).
    "paper": {
        "Pendulum-v1": {"steps": 280_000, "all": ["--hidden-size", "64"], "jirl": ["--gate-k", "1", "--penalty-sigma2", "0.01", *PAPER_BUFFER["Pendulum-v1"]],
                        "sac": PAPER_BUFFER["Pendulum-v1"]},
        "LunarLanderContinuous-v3": {"steps": 550_000, "all": ["--hidden-size", "64"],
                                     "jirl": ["--gate-k", "1", "--penalty-sigma2", "0.1", *PAPER_BUFFER["LunarLanderContinuous-v3"]],
                                     "sac": PAPER_BUFFER["LunarLanderContinuous-v3"]},
        "JetRacerTrack-v0": {"steps": 54_000, "all": ["--hidden-size", "64", *TRACK_REGRET], "jirl": ["--gate-k", "10", "--penalty-sigma2", "0.01"]},
        "Walker2DBulletEnv-v0": {"steps": 4_000_000, "all": ["--hidden-size", "256"], "jirl": ["--gate-k", "1", "--penalty-sigma2", "0.01"]},
    },
}


@dataclass
class Args:
    envs: tuple[str, ...] = ("Pendulum-v1", "LunarLanderContinuous-v3")
    """environments"""
    methods: tuple[str, ...] = ("jirl", "sac", "ppo_il", "trpo_il")
    """methods: jirl, sac, ppo_il, trpo_il"""
    seeds: tuple[int, ...] = (1, 2, 3)
    """seeds of every method"""
    preset: Literal["quick", "local", "paper"] = "local"
    """budgets: quick (smoke check), local (this machine), paper (the paper's lengths)"""
    steps: Optional[int] = None
    """env steps of every run instead of the preset's (the report states each env's budget)"""
    workdir: str = "benchmarks/results/reproduce"
    """where runs train; a run with a DONE marker is not run again"""
    output: str = "docs/reproduction"
    """where table.md and the figures go"""
    launcher: Literal["local", "slurm", "submitit-local"] = "local"
    """local process pool, Slurm through submitit, or submitit's local executor (for testing)"""
    workers: int = os.cpu_count() or 1
    """parallel runs with the local launcher (each uses one torch thread)"""
    slurm_partition: str = ""
    """Slurm partition"""
    slurm_timeout_min: int = 24 * 60
    """Slurm time limit per run, minutes"""
    report_only: bool = False
    """skip training; only read the finished runs and write the report"""

    def __post_init__(self) -> None:
        """Out-of-range values end the parse with a message naming each flag (tyro prints it)."""
        rules = [
            ("envs", len(self.envs) >= 1, "at least one env"),
            ("methods", len(self.methods) >= 1, "at least one method"),
            ("seeds", len(self.seeds) >= 1 and all(0 <= seed < 2**32 for seed in self.seeds), "at least one seed, each in [0, 2**32)"),
            ("steps", self.steps is None or self.steps >= 1, ">= 1"),
            ("workers", self.workers >= 1, ">= 1"),
            ("slurm_timeout_min", self.slurm_timeout_min >= 1, ">= 1"),
        ]
        problems = [f"--{name.replace('_', '-')} must be {rule}, got {getattr(self, name)}" for name, ok, rule in rules if not ok]
        if problems:
            raise ValueError("; ".join(problems))


# -- running ------------------------------------------------------------------------------------
def run_dir(workdir: Path, env: str, method: str, seed: int) -> Path:
    return workdir / env / method / f"seed{seed}"


def command(preset: dict, env: str, method: str, seed: int, steps: Optional[int] = None) -> list[str]:
    budget = preset[env]
    return [sys.executable, str(ROOT / SCRIPTS[method]), "--env-id", env, "--seed", str(seed), "--total-timesteps",
            str(steps or budget["steps"]), "--exp-name", method, "--save-model", *budget.get("all", []), *budget.get(method, [])]  # fmt: skip


def done_arguments(folder: Path) -> Optional[list[str]]:
    """The arguments a finished run was trained with (after interpreter and script), or None if unfinished."""
    marker = folder / "DONE"
    return shlex.split(marker.read_text())[2:] if marker.exists() else None


def fresh(folder: Path) -> Path:
    """folder, made, without the logs of an earlier attempt that did not finish (killed with the session,
    Ctrl-C, failed): beside the new run's, they would leave two runs to read in one folder."""
    folder.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(folder / "runs", ignore_errors=True)
    return folder


@contextlib.contextmanager
def holding(workdir: Path) -> Iterator[None]:
    """Hold {workdir}/.lock while runs train: a second reproduce.py on the same --workdir would train the
    same runs in the same folders, each clearing the other's. The lock goes with the process."""
    workdir.mkdir(parents=True, exist_ok=True)
    with open(workdir / ".lock", "w") as lock:
        try:
            import fcntl
        except ImportError:  # not POSIX: no lock
            yield
            return
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise SystemExit(f"reproduce: error: another reproduce.py is training in {workdir}; wait for it to end, or use another --workdir") from None
        except OSError as err:  # a file system without locks (some network and FUSE ones): run, saying what is not guarded
            print(f"reproduce: warning: cannot lock {workdir / '.lock'} ({err}); nothing keeps a second reproduce.py off this workdir", file=sys.stderr)
        yield


class Terminated(Exception):
    """SIGTERM, raised where the local launcher waits."""


@contextlib.contextmanager
def terminable() -> Iterator[None]:
    """Inside, SIGTERM raises Terminated in the main thread instead of ending the process at once, which
    left its trainings running on, and their DONE never written."""
    if threading.current_thread() is not threading.main_thread():  # only the main thread may set a handler
        yield
        return

    def terminated(signum, frame) -> None:
        raise Terminated

    previous = signal.signal(signal.SIGTERM, terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class Trainings:
    """The local launcher's running trainings, so that a stop reaches them: a SIGTERM (`kill`, `timeout`)
    reaches this process alone, where Ctrl-C's SIGINT reaches the whole process group."""

    def __init__(self) -> None:
        self.lock, self.stopped = threading.Lock(), False
        self.running: set[subprocess.Popen] = set()

    def run(self, cmd: list[str], cwd: Path, log) -> int:
        """Run cmd to its end and return its exit code; after stop(), start nothing (-SIGTERM)."""
        with self.lock:
            if self.stopped:
                return -signal.SIGTERM
            process = subprocess.Popen(cmd, cwd=cwd, stdout=log, stderr=subprocess.STDOUT)
            self.running.add(process)
        try:
            return process.wait()
        finally:
            with self.lock:
                self.running.discard(process)

    def stop(self) -> None:
        with self.lock:
            self.stopped = True
            for process in self.running:
                process.terminate()


def run_one(cmd: list[str], folder: str, trainings: Optional[Trainings] = None) -> int:
    """Train one run in `folder`, its output in log.txt; write DONE on success. Returns the exit code.

    A submitted job runs this too (JOB_COMMAND), so that its DONE is written where it trains: a run that
    finishes after the reproduce.py waiting for it has gone (a closed terminal, Ctrl-C) is not lost."""
    path = fresh(Path(folder))
    with open(path / "log.txt", "w") as log:
        code = (trainings or Trainings()).run(cmd, path, log)
    if code == 0:
        (path / "DONE").write_text(shlex.join(cmd) + "\n")  # quoted: a path with a space stays one argument
    return code


# What a submitit job runs: run_one, imported by path (the job's Python has no benchmarks/ on its path);
# then the arguments: benchmarks/, the run's folder, the run's command.
JOB_COMMAND = [sys.executable, "-c", "import sys; sys.path.insert(0, sys.argv[1]); import reproduce; sys.exit(reproduce.run_one(sys.argv[3:], sys.argv[2]))"]


def still_queued(folders: list[str]) -> list[tuple[str, str]]:
    """(folder, job id) of each run whose job, submitted by an earlier call, is still in Slurm's queue."""
    jobs = {folder: (Path(folder) / "JOB").read_text().strip() for folder in folders if (Path(folder) / "JOB").exists()}
    if not jobs:
        return []
    import getpass

    try:
        out = subprocess.run(["squeue", "--noheader", "--format", "%i", "--user", getpass.getuser()], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as err:
        raise SystemExit(f"reproduce: error: cannot ask Slurm whether the jobs of an earlier call still run (squeue: {err})") from None
    if out.returncode != 0:
        raise SystemExit(f"reproduce: error: cannot ask Slurm whether the jobs of an earlier call still run (squeue: {out.stderr.strip()})")
    queued = set(out.stdout.split())
    return [(folder, job) for folder, job in jobs.items() if job in queued]


def report_failures(failed: list[str], total: int) -> None:
    """After every run has ended: one line naming the failed runs, whose log.txt says why."""
    if failed:
        raise SystemExit(f"reproduce: error: {len(failed)} of {total} runs failed; see log.txt in {', '.join(failed)}")


def launch(args: Args) -> None:
    with holding(Path(args.workdir)):
        launch_holding(args)


def launch_locally(todo: list[tuple[list[str], str]], workers: int) -> None:
    """The local launcher: `workers` runs at a time, with progress and ETA; Ctrl-C or SIGTERM ends them all."""
    start, finished, failed, trainings = time.time(), 0, [], Trainings()
    with terminable(), ThreadPoolExecutor(max_workers=workers) as pool:
        try:
            futures = {pool.submit(run_one, cmd, folder, trainings): folder for cmd, folder in todo}
            for future in as_completed(futures):
                code = future.result()
                if code != 0:  # the other runs go on; their results are not lost to one failure
                    failed.append(futures[future])
                finished += 1
                elapsed = time.time() - start
                eta = elapsed / finished * (len(todo) - finished)
                outcome = "done" if code == 0 else f"FAILED (exit {code})"
                print(f"[{finished}/{len(todo)}] {futures[future]} {outcome}; elapsed {elapsed / 60:.1f} min, ETA {eta / 60:.1f} min", flush=True)
        except (KeyboardInterrupt, Terminated):  # start no queued run (the pool would), and end the running ones
            trainings.stop()
            pool.shutdown(wait=False, cancel_futures=True)
            raise SystemExit("reproduce: interrupted; the same command trains again what has no DONE, from scratch") from None
    report_failures(failed, len(todo))


def launch_holding(args: Args) -> None:
    workdir, preset = Path(args.workdir), PRESETS[args.preset]
    jobs = [(command(preset, env, method, seed, args.steps), str(run_dir(workdir, env, method, seed)))
            for env in args.envs for method in args.methods for seed in args.seeds]  # fmt: skip
    clashes = [folder for cmd, folder in jobs if done_arguments(Path(folder)) not in (None, cmd[2:])]
    if clashes:  # a finished run made with another budget or other arguments is not silently reused
        raise SystemExit(f"reproduce: error: {len(clashes)} finished runs used other arguments (e.g. {clashes[0]}); use another --workdir")
    todo = [job for job in jobs if done_arguments(Path(job[1])) is None]
    print(f"{len(jobs)} runs, {len(jobs) - len(todo)} already done, {len(todo)} to run")
    if not todo:
        return
    if args.launcher == "local":
        launch_locally(todo, args.workers)
    else:
        launch_submitit(todo, args)


def launch_submitit(todo: list[tuple[list[str], str]], args: Args) -> None:
    """Slurm, or submitit's local executor: every run is a job, which writes its own DONE; progress as they end."""
    import submitit

    if args.launcher == "slurm":
        queued = still_queued([folder for _, folder in todo])
        if queued:  # submitted again, two jobs would train one run in one folder
            raise SystemExit(f"reproduce: error: {len(queued)} runs submitted by an earlier call are still in Slurm's queue (e.g. {queued[0][0]},"
                             f" job {queued[0][1]}); each writes its DONE as it ends: run this again once they have, or scancel them first")
        executor: submitit.Executor = submitit.AutoExecutor(folder=str(Path(args.workdir) / "slurm"), cluster="slurm")  # never its fallback: every run at once, here
        executor.update_parameters(timeout_min=args.slurm_timeout_min, cpus_per_task=1, slurm_partition=args.slurm_partition or None)
    else:
        executor = submitit.LocalExecutor(folder=str(Path(args.workdir) / "submitit"))
        executor.update_parameters(timeout_min=args.slurm_timeout_min)
    folders, failed = {}, []  # the run's folder of each submitted job
    poll = 10.0 if args.launcher == "slurm" else 0.5  # seconds between asking for the jobs' states
    try:
        for cmd, folder in todo:
            Path(folder).mkdir(parents=True, exist_ok=True)  # the job clears an earlier attempt's logs as it starts (run_one)
            job = executor.submit(submitit.helpers.CommandFunction([*JOB_COMMAND, str(Path(__file__).resolve().parent), str(Path(folder).resolve()), *cmd]))
            job_file = Path(folder) / "JOB"  # a later call asks Slurm whether it still runs
            job_file.with_name("JOB.tmp").write_text(f"{job.job_id}\n")
            os.replace(job_file.with_name("JOB.tmp"), job_file)  # whole or absent: a reproduce.py killed here leaves no empty id
            folders[job] = folder
        start = time.time()
        for i, job in enumerate(submitit.helpers.as_completed(list(folders), poll_frequency=poll), 1):
            folder, elapsed = folders[job], time.time() - start
            try:
                job.result()
                outcome = "done"
            except Exception as err:  # the run failed (its log.txt says why), or its job did (a time limit, a lost node): add submitit's account
                with open(Path(folder) / "log.txt", "a") as log:
                    log.write(f"\n{err}\n")
                failed.append(folder)
                outcome = "FAILED"
            eta = elapsed / i * (len(folders) - i)
            print(f"[{i}/{len(folders)}] {folder} {outcome} (job {job.job_id}); elapsed {elapsed / 60:.1f} min, ETA {eta / 60:.1f} min", flush=True)
    except KeyboardInterrupt:
        if args.launcher == "slurm":  # the jobs are Slurm's now
            raise SystemExit("reproduce: stopped waiting; the jobs submitted go on in Slurm, each writing its DONE as it ends:"
                             " run the same command again once they have, or scancel them") from None
        raise SystemExit("reproduce: interrupted; the same command trains again what has no DONE, from scratch") from None
    report_failures(failed, len(folders))


# -- reading and reporting ----------------------------------------------------------------------
def read_scalars(folder: Path) -> dict[str, list[tuple[int, float]]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    logs = sorted((folder / "runs").glob("*/events.out.tfevents.*"), key=lambda p: p.stat().st_mtime)
    if not logs:
        raise SystemExit(f"reproduce: error: {folder} is marked DONE but holds no TensorBoard log; delete its DONE to train it again")
    events_dir = logs[-1].parent  # a workdir from before fresh() may hold a killed attempt's logs too: the finished run wrote last
    accumulator = EventAccumulator(str(events_dir), size_guidance={"scalars": 0})
    accumulator.Reload()
    return {tag: [(e.step, e.value) for e in accumulator.Scalars(tag)] for tag in accumulator.Tags()["scalars"]}


def last(scalars: dict, tag: str) -> float:
    return scalars[tag][-1][1] if scalars.get(tag) else math.nan


def mean_ci(values: list[float]) -> tuple[float, float]:
    """Mean and the half-width of its 95 % confidence interval (Student t)."""
    from scipy import stats

    values = [v for v in values if not math.isnan(v)]
    if not values:
        return math.nan, math.nan
    if len(values) == 1:
        return values[0], math.nan
    return float(np.mean(values)), float(stats.t.ppf(0.975, len(values) - 1) * np.std(values, ddof=1) / math.sqrt(len(values)))


def fmt(mean: float, half: float) -> str:
    if math.isnan(mean):
        return "–"
    return f"{mean:,.0f}" if math.isnan(half) else f"{mean:,.0f} ± {half:,.0f}"


def collect(workdir: Path, envs: Sequence[str], methods: Sequence[str], seeds: Sequence[int]) -> dict:
    """results[env][method][seed] = scalars of the finished runs."""
    results: dict = {}
    for env in envs:
        for method in methods:
            for seed in seeds:
                folder = run_dir(workdir, env, method, seed)
                if (folder / "DONE").exists():
                    results.setdefault(env, {}).setdefault(method, {})[seed] = read_scalars(folder)
    return results


def budgets(workdir: Path, results: dict) -> str:
    """One sentence: each env's env steps per run and seeds per method, read from the runs themselves.
    PPO/TRPO+IL run whole rollouts (the budget rounded down, at least one): where theirs differ, they are named."""
    parts = []
    for env, methods in results.items():
        steps: set[int] = set()
        rollouts: dict[str, set[int]] = {}
        for method, runs in methods.items():
            for seed, scalars in runs.items():
                arguments = done_arguments(run_dir(workdir, env, method, seed)) or []
                if "--total-timesteps" in arguments:
                    steps.add(int(arguments[arguments.index("--total-timesteps") + 1]))
                if method in ("ppo_il", "trpo_il") and scalars.get("charts/SPS"):  # logged at the end of each rollout
                    rollouts.setdefault(method, set()).add(int(scalars["charts/SPS"][-1][0]))
        other = [f"{LABELS[m]} {', '.join(f'{n:,}' for n in sorted(ran))}" for m, ran in rollouts.items() if ran != steps]
        seeds = "/".join(str(len(runs)) for runs in methods.values())
        parts.append(f"{env}: {', '.join(f'{n:,}' for n in sorted(steps))} env steps per run"
                     + (f" ({'; '.join(other)}: whole rollouts)" if other else "")
                     + f", {seeds} seeds ({'/'.join(LABELS[m] for m in methods)})")  # fmt: skip
    return "Budgets: " + "; ".join(parts) + "."


def table(results: dict) -> str:
    from scipy import stats

    lines = []
    for form, tag in (("per step (the paper's Definition 1)", "baseline_regret_per_step"), ("per episode", "baseline_regret")):
        lines += [f"### Accumulated baseline regret, {form}", "",
                  "| env | JIRL 0–50 % RL | JIRL 50–<100 % | JIRL 100 % RL | JIRL total | SAC total | best PPO/TRPO+IL total | SAC / JIRL | best IL / JIRL | paired t-test JIRL < best IL |",
                  "|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
        for env, methods in results.items():
            jirl = methods.get("jirl", {})
            phases = [fmt(*mean_ci([last(s, f"phases/{tag}_{p}") for s in jirl.values()])) for p in ("0_50", "50_100", "100")]
            totals = {m: {seed: last(s, f"charts/{tag}") for seed, s in runs.items()} for m, runs in methods.items()}
            il = [m for m in ("ppo_il", "trpo_il") if m in totals]
            best = min(il, key=lambda m: np.mean(list(totals[m].values()))) if il else None
            j_mean = np.mean(list(totals["jirl"].values())) if "jirl" in totals else math.nan
            ratio = lambda m: f"{np.mean(list(totals[m].values())) / j_mean:.1f}×" if m in totals and j_mean > 0 else "–"  # noqa: E731
            test = "–"
            if best is not None and "jirl" in totals:
                common = sorted(set(totals["jirl"]) & set(totals[best]))
                if len(common) >= 2:
                    result = stats.ttest_rel([totals["jirl"][s] for s in common], [totals[best][s] for s in common], alternative="less")
                    test = f"p = {result.pvalue:.3g} ({LABELS[best]}, {len(common)} seeds)"
            cells = [env, *phases, *(fmt(*mean_ci(list(totals[m].values()))) if m in totals else "–" for m in ("jirl", "sac")),
                     f"{fmt(*mean_ci(list(totals[best].values())))} ({LABELS[best]})" if best else "–",
                     ratio("sac"), ratio(best) if best else "–", test]  # fmt: skip
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    lines += ["### Final deterministic evaluation return", "", "| env | " + " | ".join(LABELS.values()) + " | baseline |",
              "|---" * (len(LABELS) + 2) + "|"]  # fmt: skip
    for env, methods in results.items():
        cells = [fmt(*mean_ci([_mean(s.get("eval/episodic_return", [])) for s in methods[m].values()])) if m in methods else "–"
                 for m in LABELS]  # fmt: skip
        per_seed = {seed: last(s, "charts/baseline_return") for runs in methods.values() for seed, s in runs.items()}
        baseline = mean_ci(list(per_seed.values()))  # one value per seed: every method met the same seeds
        lines.append(f"| {env} | " + " | ".join(cells) + f" | {fmt(*baseline)} |")
    seeds = sorted({seed for methods in results.values() for runs in methods.values() for seed in runs})
    lines += ["", f"Mean ± 95 % confidence interval over seeds {seeds}."]
    return "\n".join(lines) + "\n"


def _mean(points: list) -> float:
    return float(np.mean([v for _, v in points])) if points else math.nan


def reward_per_step_curve(scalars: dict, grid: np.ndarray, window: int = 5) -> np.ndarray:
    """Each episode's reward per step, averaged over the `window` episodes centred on it, interpolated
    onto `grid` steps. Near a run's first and last episodes the average is over the episodes there are;
    convolve's "same" alone pads with zeros, which bent a run's ends towards 0."""
    returns, lengths = scalars.get("charts/episodic_return", []), scalars.get("charts/episodic_length", [])
    if not returns:
        return np.full(len(grid), np.nan)
    steps = np.array([s for s, _ in returns], dtype=float)
    per_step = np.array([r / max(length, 1.0) for (_, r), (_, length) in zip(returns, lengths)])
    kernel = np.ones(min(window, len(per_step)))
    smooth = np.convolve(per_step, kernel, mode="same") / np.convolve(np.ones(len(per_step)), kernel, mode="same")
    return np.interp(grid, steps, smooth, left=np.nan, right=np.nan)


def mean_band(curves: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per grid point, the mean of the seeds' curves and the half-width of its 95 % confidence interval
    (Student t, as in the table: 1.96 would be an 81 % band with 3 seeds). Both are NaN wherever a seed
    has no value yet or any more: a mean over the seeds that have one jumps where a run ends, and a t
    band over two of three seeds is 3.6 times as wide for the same spread. With one seed, no band."""
    from scipy import stats

    seeds = curves[~np.isnan(curves).all(1)]  # a run that logged no episode has no curve to average
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # no seed, or one: NaN, which draws nothing
        mean = seeds.mean(0)
        half = stats.t.ppf(0.975, len(seeds) - 1) * seeds.std(0, ddof=1) / np.sqrt(len(seeds))
    return mean, half


def figures(results: dict, output: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for env, methods in results.items():
        horizon = max(s["charts/episodic_return"][-1][0] for runs in methods.values() for s in runs.values() if s.get("charts/episodic_return"))
        grid = np.linspace(0, horizon, 200)
        fig, ax = plt.subplots(figsize=(7, 4))
        for method, runs in methods.items():
            mean, half = mean_band(np.array([reward_per_step_curve(s, grid) for s in runs.values()]))
            (line,) = ax.plot(grid, mean, label=LABELS[method])
            ax.fill_between(grid, mean - half, mean + half, alpha=0.2, color=line.get_color())  # none where NaN
        level = np.nanmean([last(s, "charts/baseline_reward_per_step") for runs in methods.values() for s in runs.values()])
        ax.axhline(float(level), color="k", linestyle="--", label="baseline")
        ax.set_xlabel("environment steps (PPO/TRPO+IL: after their imitation phase)")
        ax.set_ylabel("reward per step (smoothed)")
        if "jirl" in methods:
            ax2 = ax.twinx()
            fractions = [np.interp(grid, *np.array(s["charts/rl_control_fraction"]).T) for s in methods["jirl"].values() if s.get("charts/rl_control_fraction")]
            if fractions:
                ax2.plot(grid, 100 * np.mean(fractions, 0), color="tab:gray", linestyle=":", label="JIRL RL control")
                ax2.set_ylabel("JIRL RL control (%)")
                ax2.set_ylim(0, 105)
        handles = [h for a in fig.axes for h in a.get_legend_handles_labels()[0]]
        ax.legend(handles=handles, loc="lower right", fontsize=8)
        ax.set_title(env)
        fig.tight_layout()
        path = output / f"fig_{env}.png"
        fig.savefig(path, dpi=120)
        plt.close(fig)
        paths.append(path)
    return paths


def file_in_the_way(folder: str) -> Optional[Path]:
    """The file where folder, or a folder above it, would have to be made; None if there is none."""
    path = Path(folder).absolute()
    return next((p for p in (path, *path.parents) if p.exists() and not p.is_dir()), None)


def main(args: Args) -> None:
    unknown = [m for m in args.methods if m not in SCRIPTS] + [e for e in args.envs if e not in PRESETS[args.preset]]
    if unknown:
        raise SystemExit(f"reproduce: error: unknown methods or envs {unknown}")
    if args.launcher == "slurm" and not args.report_only and shutil.which("sbatch") is None:
        # submitit's AutoExecutor would fall back to starting every run at once on this machine
        raise SystemExit("reproduce: error: --launcher slurm needs Slurm (no sbatch here): run it where jobs are submitted, or use --launcher local")
    for flag, folder in (("--workdir", args.workdir), ("--output", args.output)):  # checked now, not after hours of training
        if (file := file_in_the_way(folder)) is not None:
            raise SystemExit(f"reproduce: error: {flag} {folder} cannot be a folder: {file} is a file")
    if not args.report_only:
        launch(args)
    results = collect(Path(args.workdir), args.envs, args.methods, args.seeds)
    if not results:
        raise SystemExit("reproduce: no finished runs to report")
    output = Path(args.output)
    output.mkdir(parents=True, exist_ok=True)
    (output / "table.md").write_text(f"Preset `{args.preset}`. {budgets(Path(args.workdir), results)}\n\n" + table(results))
    for path in figures(results, output):
        print(f"wrote {path}")
    print(f"wrote {output / 'table.md'}")


if __name__ == "__main__":
    import tyro

    main(tyro.cli(Args))
