"""Baseline regret over the paper's Table I window: up to where JIRL performs like SAC.

The paper's Table I counts JIRL's regret in three phases, and its last phase, "Full RL", "starts when
JIRL assigns 100 % RL control and ends when the average performance of JIRL is similar to that of
SAC" (Sec. V). What the agent pays after that is not in the table. The scripts' own
`charts/baseline_regret*` count to the end of the budget. This tool reads the TensorBoard logs of
JIRL runs and of SAC runs on the same seeds (the `--workdir`s of benchmarks/learning.py) and finds,
for each seed, the end of that window:

- T_100: the first logged step with `charts/rl_control_fraction` at 1 (the agent acted on every one
  of the last --rl-control-window steps);
- T_end: the first JIRL episode end at or after T_100 where the mean return of JIRL's last
  `--episodes` episodes is at least SAC's over its last `--episodes` episodes ended by then, less
  `--tolerance` of |SAC's|. "Never" when that does not happen within the run; the window is then the
  whole run. Where JIRL starts above SAC (its guided returns are at the baseline's level while SAC's
  are still poor), that first episode can come at the hand-over itself; `--sustained` reads "similar" as the
  first episode from which JIRL stays similar to SAC to the end of the run.

It prints JIRL's regret at T_end split into Table I's phases, SAC's regret over the same steps and
over its whole run, and the ratios, per seed and as medians, in both regret forms.

    python benchmarks/paper_window.py --jirl benchmarks/results/window/pend280k_jirl \
        --sac benchmarks/results/window/pend280k_sac
"""

from __future__ import annotations

import argparse
import bisect
import math
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Optional

sys.path.insert(0, str(Path(__file__).resolve().parent))

from learning import read_scalars  # noqa: E402

Series = list[tuple[int, float]]  # (step, value), steps increasing, as TensorBoard logs them
PHASES = ("0_50", "50_100", "100")  # Table I's phases: RL control 0-50 %, 50-<100 %, 100 %
FORMS = {"episode": "", "per_step": "_per_step"}  # the scripts' tag suffix for each regret form
SAC_TAGS = ["charts/episodic_return", "charts/baseline_regret", "charts/baseline_regret_per_step"]
JIRL_TAGS = [*SAC_TAGS, "charts/rl_control_fraction"]


def value_at(series: Series, step: int) -> float:
    """The last value logged at or before `step` (a cumulative sum), 0 before the first."""
    i = bisect.bisect_right([s for s, _ in series], step)
    return series[i - 1][1] if i else 0.0


def first_full_control(rl_control: Series) -> Optional[int]:
    """T_100: the first step where the RL-control fraction is 1, None if it never is."""
    return next((step for step, fraction in rl_control if fraction >= 1.0), None)


def trailing_mean(returns: Series, step: int, episodes: int) -> float:
    """Mean return of the last `episodes` episodes ended at or before `step` (NaN if none ended)."""
    i = bisect.bisect_right([s for s, _ in returns], step)
    window = [r for _, r in returns[max(0, i - episodes) : i]]
    return statistics.fmean(window) if window else math.nan


def window_end(
    jirl_returns: Series, sac_returns: Series, t_100: Optional[int], episodes: int, tolerance: float, sustained: bool = False
) -> Optional[int]:
    """T_end: the first JIRL episode end at or after T_100 where JIRL's recent mean return is within
    `tolerance` of |SAC's| below SAC's recent mean (or above it); None if it never is, or if the agent
    never held full control. With `sustained`, the first such episode from which JIRL stays similar to
    the end of the run (None if its last episode falls short)."""
    if t_100 is None:
        return None

    def similar(step: int) -> bool:
        sac_mean = trailing_mean(sac_returns, step, episodes)  # NaN before SAC's first episode: not similar
        return trailing_mean(jirl_returns, step, episodes) >= sac_mean - tolerance * abs(sac_mean)

    steps = [step for step, _ in jirl_returns if step >= t_100]
    if not sustained:
        return next((step for step in steps if similar(step)), None)
    end = None
    for step in reversed(steps):  # back from the run's end to the last episode that fell short
        if not similar(step):
            break
        end = step
    return end


@dataclass(frozen=True)
class Window:
    seed: int
    last_step: int  # of the JIRL run
    t_100: Optional[int]
    t_end: Optional[int]  # None: never similar; the window is then the whole run
    jirl_phases: dict[str, tuple[float, float]]  # phase -> (episode form, per step) at the window's end
    jirl: tuple[float, float]  # JIRL's regret over the window, both forms
    sac: tuple[float, float]  # SAC's over the same steps
    sac_whole: tuple[float, float]  # SAC's over its whole run
    jirl_whole: tuple[float, float]


def measure(seed: int, jirl: dict[str, Series], sac: dict[str, Series], episodes: int, tolerance: float, sustained: bool = False) -> Window:
    """The window of one seed from the two runs' scalars (tag -> series)."""
    t_100 = first_full_control(jirl["charts/rl_control_fraction"])
    t_end = window_end(jirl["charts/episodic_return"], sac["charts/episodic_return"], t_100, episodes, tolerance, sustained)
    last_step = jirl["charts/episodic_return"][-1][0]
    end = last_step if t_end is None else t_end
    forms = FORMS.values()
    return Window(
        seed=seed,
        last_step=last_step,
        t_100=t_100,
        t_end=t_end,
        jirl_phases={p: pair(value_at(jirl.get(f"phases/baseline_regret{f}_{p}", []), end) for f in forms) for p in PHASES},
        jirl=pair(value_at(jirl[f"charts/baseline_regret{f}"], end) for f in forms),
        sac=pair(value_at(sac[f"charts/baseline_regret{f}"], end) for f in forms),
        sac_whole=pair(sac[f"charts/baseline_regret{f}"][-1][1] for f in forms),
        jirl_whole=pair(jirl[f"charts/baseline_regret{f}"][-1][1] for f in forms),
    )


def pair(regrets: Iterable[float]) -> tuple[float, float]:
    """(episode form, per step) from the regrets read for FORMS' two tag suffixes, in order."""
    episode, per_step = regrets
    return episode, per_step


def runs_by_seed(workdir: Path, tool: str = "paper_window") -> dict[int, Path]:
    """The run directories under workdir/runs, by seed (the newest run of a seed if there are several);
    `tool` names the command in the error for a workdir without runs."""
    runs: dict[int, Path] = {}
    for run in sorted((workdir / "runs").glob("*__*__*__*"), key=lambda p: p.stat().st_mtime):
        runs[int(run.name.split("__")[2])] = run
    if not runs:
        raise SystemExit(f"{tool}: error: no runs under {workdir / 'runs'}")
    return runs


def newest_runs(workdirs: Iterable[Path], tool: str) -> dict[int, Path]:
    """The newest run of each seed across workdirs: a seed in two workdirs counts as one seeded twice in one."""
    runs: dict[int, Path] = {}
    for workdir in workdirs:
        for seed, run in runs_by_seed(workdir, tool).items():
            if seed not in runs or run.stat().st_mtime > runs[seed].stat().st_mtime:
                runs[seed] = run
    return runs


def ratio(sac: float, jirl: float) -> str:
    return f"{sac / jirl:.1f}×" if jirl > 0 else "∞"


def report(windows: list[Window]) -> str:
    lines = []
    for form_index, form in enumerate(FORMS):
        lines += [
            f"\nregret, {form.replace('_', ' ')} form",
            "| seed | T_100 | T_end | JIRL 0-50 % | JIRL 50-<100 % | JIRL 100 % | JIRL to T_end | SAC to T_end | SAC whole run"
            " | SAC/JIRL, same steps | SAC whole / JIRL to T_end | JIRL whole run | SAC/JIRL, whole runs |",
            "|---" * 13 + "|",
        ]
        for w in windows:
            phases = " | ".join(f"{w.jirl_phases[p][form_index]:,.0f}" for p in PHASES)
            t_end = "never" if w.t_end is None else f"{w.t_end:,}"
            t_100 = "never" if w.t_100 is None else f"{w.t_100:,}"
            j, s, sw, jw = w.jirl[form_index], w.sac[form_index], w.sac_whole[form_index], w.jirl_whole[form_index]
            lines.append(f"| {w.seed} | {t_100} | {t_end} | {phases} | {j:,.0f} | {s:,.0f} | {sw:,.0f} | {ratio(s, j)} | {ratio(sw, j)} | {jw:,.0f} | {ratio(sw, jw)} |")
        med = {name: statistics.median(getattr(w, name)[form_index] for w in windows) for name in ("jirl", "sac", "sac_whole", "jirl_whole")}
        lines.append(
            f"| median | | | | | | {med['jirl']:,.0f} | {med['sac']:,.0f} | {med['sac_whole']:,.0f} | {ratio(med['sac'], med['jirl'])}"
            f" | {ratio(med['sac_whole'], med['jirl'])} | {med['jirl_whole']:,.0f} | {ratio(med['sac_whole'], med['jirl_whole'])} |"
        )
    return "\n".join(lines)


def main(argv: Optional[list[str]] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jirl", type=Path, required=True, help="workdir of the JIRL runs (benchmarks/learning.py --workdir)")
    parser.add_argument("--sac", type=Path, required=True, help="workdir of the SAC runs on the same seeds")
    parser.add_argument("--seeds", type=int, nargs="+", help="only these seeds (default: every seed with runs on both sides)")
    parser.add_argument("--episodes", type=int, default=20, help="episodes in each side's trailing mean return")
    parser.add_argument("--tolerance", type=float, default=0.05, help="JIRL's mean may fall this fraction of |SAC's| short")
    parser.add_argument("--sustained", action="store_true", help="the window ends where JIRL becomes similar to SAC for the rest of the run")
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    if not 0.0 <= args.tolerance < math.inf:
        parser.error(f"--tolerance must be >= 0, got {args.tolerance}")
    jirl_runs, sac_runs = runs_by_seed(args.jirl), runs_by_seed(args.sac)
    seeds = sorted(set(jirl_runs) & set(sac_runs) & set(args.seeds or jirl_runs))
    if not seeds:
        raise SystemExit(f"paper_window: error: no seed has both a JIRL run ({sorted(jirl_runs)}) and a SAC run ({sorted(sac_runs)})")
    windows = []
    for seed in seeds:
        jirl, sac = read_scalars(jirl_runs[seed]), read_scalars(sac_runs[seed])
        for run, scalars, tags in ((jirl_runs[seed], jirl, JIRL_TAGS), (sac_runs[seed], sac, SAC_TAGS)):
            missing = [tag for tag in tags if not scalars.get(tag)]
            if missing:
                raise SystemExit(f"paper_window: error: {run} logged no {', '.join(missing)} (a run with the regret estimator off, or not finished?)")
        windows.append(measure(seed, jirl, sac, args.episodes, args.tolerance, args.sustained))
    until = ", from T_end to the end of the run" if args.sustained else ""
    print(f"similar: JIRL's mean return over its last {args.episodes} episodes >= SAC's less {args.tolerance:.0%} of |SAC's|{until}")
    print(report(windows))


if __name__ == "__main__":
    main()
