"""benchmarks/paper_window.py: the end of the paper's Table I window, on curves whose answer is known."""

import os
import sys
import time

import pytest
from torch.utils.tensorboard import SummaryWriter

from conftest import ROOT

sys.path.insert(0, str(ROOT / "benchmarks"))
import paper_window  # noqa: E402


def test_value_at_reads_a_cumulative_series():
    series = [(10, 1.0), (20, 3.0), (30, 6.0)]
    assert paper_window.value_at(series, 5) == 0.0  # nothing accumulated before the first log
    assert paper_window.value_at(series, 20) == 3.0
    assert paper_window.value_at(series, 29) == 3.0
    assert paper_window.value_at(series, 10**6) == 6.0


def test_full_control_and_trailing_mean():
    assert paper_window.first_full_control([(100, 0.2), (200, 0.99), (300, 1.0), (400, 0.7), (500, 1.0)]) == 300
    assert paper_window.first_full_control([(100, 0.2)]) is None
    returns = [(200, -400.0), (400, -300.0), (600, -200.0)]
    assert paper_window.trailing_mean(returns, 599, 2) == pytest.approx(-350.0)
    assert paper_window.trailing_mean(returns, 600, 2) == pytest.approx(-250.0)
    assert paper_window.trailing_mean(returns, 100, 2) != paper_window.trailing_mean(returns, 100, 2)  # NaN: none ended


# SAC at -200 throughout; JIRL climbs 10 per episode from -300 and ends an episode every 200 steps
SAC = [(200 * i, -200.0) for i in range(1, 31)]
JIRL = [(200 * i, -300.0 + 10.0 * i) for i in range(1, 31)]


def test_the_window_ends_where_jirl_catches_up():
    # trailing mean of 2 episodes ending at episode i: -300 + 10 i - 5; >= -200 first at i = 11 (-195)
    assert paper_window.window_end(JIRL, SAC, t_100=0, episodes=2, tolerance=0.0) == 200 * 11
    # 10 % of |SAC's| is 20: -300 + 10 i - 5 >= -220 first at i = 9
    assert paper_window.window_end(JIRL, SAC, t_100=0, episodes=2, tolerance=0.1) == 200 * 9
    # a full hand-over later than the catch-up: the window ends at the first episode after it
    assert paper_window.window_end(JIRL, SAC, t_100=3_050, episodes=2, tolerance=0.0) == 3_200
    assert paper_window.window_end(JIRL, SAC, t_100=None, episodes=2, tolerance=0.0) is None
    assert paper_window.window_end([(s, -500.0) for s, _ in JIRL], SAC, t_100=0, episodes=2, tolerance=0.1) is None
    # "at least SAC's mean less the tolerance": a tie counts, at either tolerance
    assert paper_window.window_end([(s, -200.0) for s, _ in JIRL], SAC, t_100=0, episodes=2, tolerance=0.0) == 200
    assert paper_window.window_end([(s, -300.0) for s, _ in JIRL], SAC, t_100=0, episodes=2, tolerance=0.5) == 200
    # an episode that ends at T_100's step is at or after the hand-over
    assert paper_window.window_end(JIRL, SAC, t_100=3_000, episodes=2, tolerance=0.0) == 3_000


def test_a_sustained_window_ends_where_jirl_stays_similar():
    # JIRL above SAC, then 5 episodes below, then above again to the end
    jirl = [(200 * i, r) for i, r in enumerate([-100.0] * 5 + [-300.0] * 5 + [-150.0] * 5, 1)]
    assert paper_window.window_end(jirl, SAC, t_100=0, episodes=1, tolerance=0.0) == 200
    assert paper_window.window_end(jirl, SAC, t_100=0, episodes=1, tolerance=0.0, sustained=True) == 200 * 11
    # 2-episode means: episode 11 still averages -225 with episode 10, so it ends one episode later
    assert paper_window.window_end(jirl, SAC, t_100=0, episodes=2, tolerance=0.0, sustained=True) == 200 * 12
    # a hand-over after the recovery: the window ends at the first episode after it, as without
    assert paper_window.window_end(jirl, SAC, t_100=2_500, episodes=1, tolerance=0.0, sustained=True) == 2_600
    # the run's last episode falls short: never
    assert paper_window.window_end([*jirl, (3_200, -400.0)], SAC, t_100=0, episodes=1, tolerance=0.0, sustained=True) is None


def scalars(returns, control, regret, phases=None):
    """Tag -> series as read_scalars returns them; regret per step is the episode form times 3."""
    out = {
        "charts/episodic_return": returns,
        "charts/rl_control_fraction": control,
        "charts/baseline_regret": regret,
        "charts/baseline_regret_per_step": [(s, 3.0 * v) for s, v in regret],
    }
    for name, series in (phases or {}).items():
        out[f"phases/baseline_regret_{name}"] = series
        out[f"phases/baseline_regret_per_step_{name}"] = [(s, 3.0 * v) for s, v in series]
    return out


def test_measure_splits_the_window_into_table_one_phases():
    steps = [s for s, _ in JIRL]
    jirl_regret = [(s, 10.0 * i) for i, s in enumerate(steps, 1)]  # 10 per episode
    phases = {
        "0_50": [(s, 10.0 * min(i, 5)) for i, s in enumerate(steps, 1)],
        "50_100": [(s, 10.0 * max(0, i - 5)) for i, s in enumerate(steps, 1)],
        "100": [(s, 0.0) for s in steps],
    }
    jirl = scalars(JIRL, [(1_000, 0.5), (2_000, 1.0)], jirl_regret, phases)
    sac = scalars(SAC, [], [(s, 100.0 * i) for i, s in enumerate(steps, 1)])  # 100 per episode
    w = paper_window.measure(4, jirl, sac, episodes=2, tolerance=0.0)
    assert (w.t_100, w.t_end, w.last_step) == (2_000, 2_200, 6_000)
    assert w.jirl == (110.0, 330.0) and w.sac == (1_100.0, 3_300.0)
    assert w.jirl_phases == {"0_50": (50.0, 150.0), "50_100": (60.0, 180.0), "100": (0.0, 0.0)}
    assert sum(v[0] for v in w.jirl_phases.values()) == w.jirl[0]
    assert w.sac_whole == (3_000.0, 9_000.0) and w.jirl_whole == (300.0, 900.0)


def write_run(workdir, name, data):
    writer = SummaryWriter(str(workdir / "runs" / name))
    for tag, series in data.items():
        for step, value in series:
            writer.add_scalar(tag, value, step)
    writer.close()


def test_the_command_reads_the_logs_and_pairs_the_seeds(tmp_path, capsys):
    steps = [s for s, _ in JIRL]
    jirl = scalars(JIRL, [(2_000, 1.0)], [(s, 10.0 * i) for i, s in enumerate(steps, 1)], {"100": [(s, 10.0 * i) for i, s in enumerate(steps, 1)]})
    sac = scalars(SAC, [], [(s, 100.0 * i) for i, s in enumerate(steps, 1)])
    write_run(tmp_path / "jirl", "Pendulum-v1__jirl__1__100", jirl)
    write_run(tmp_path / "jirl", "Pendulum-v1__jirl__2__100", jirl)  # no SAC run on seed 2: left out
    write_run(tmp_path / "sac", "Pendulum-v1__sac__1__100", sac)
    paper_window.main(["--jirl", str(tmp_path / "jirl"), "--sac", str(tmp_path / "sac"), "--episodes", "2", "--tolerance", "0"])
    out = capsys.readouterr().out
    # T_end 2,200 (episode 11): JIRL 110, SAC 1,100 over the same steps, 3,000 over its run
    assert "| 1 | 2,000 | 2,200 | 0 | 0 | 110 | 110 | 1,100 | 3,000 | 10.0× | 27.3× | 300 | 10.0× |" in out
    assert "| 1 | 2,000 | 2,200 | 0 | 0 | 330 | 330 | 3,300 | 9,000 | 10.0× | 27.3× | 900 | 10.0× |" in out
    assert "| median | | | | | | 110 | 1,100 | 3,000 | 10.0× | 27.3× | 300 | 10.0× |" in out  # one seed: its own figures
    assert "| 2 |" not in out
    write_run(tmp_path / "sac", "Pendulum-v1__sac__2__100", sac)
    paper_window.main(["--jirl", str(tmp_path / "jirl"), "--sac", str(tmp_path / "sac"), "--episodes", "2", "--seeds", "2"])
    out = capsys.readouterr().out
    assert "| 2 | 2,000 |" in out and "| 1 |" not in out
    # JIRL stays similar from episode 11 on, so the sustained window ends where the first one does
    paper_window.main(["--jirl", str(tmp_path / "jirl"), "--sac", str(tmp_path / "sac"), "--episodes", "2", "--tolerance", "0", "--seeds", "1", "--sustained"])
    out = capsys.readouterr().out
    assert "to the end of the run" in out and "| 1 | 2,000 | 2,200 | 0 | 0 | 110 | 110 | 1,100 |" in out


def test_a_seed_run_twice_is_read_from_its_newest_run(tmp_path):
    now = time.time()
    for name, age in (("Pendulum-v1__jirl__1__200", 100), ("Pendulum-v1__jirl__1__100", 0), ("Pendulum-v1__jirl__2__300", 50)):
        (tmp_path / "runs" / name).mkdir(parents=True)
        os.utime(tmp_path / "runs" / name, (now - age, now - age))
    runs = paper_window.runs_by_seed(tmp_path)
    assert {seed: run.name for seed, run in runs.items()} == {1: "Pendulum-v1__jirl__1__100", 2: "Pendulum-v1__jirl__2__300"}


def test_the_command_refuses_bad_input(tmp_path, capsys):
    with pytest.raises(SystemExit, match="no runs under"):
        paper_window.main(["--jirl", str(tmp_path), "--sac", str(tmp_path)])
    for option, message in ((["--tolerance", "-1"], "--tolerance must be >= 0, got -1.0"), (["--episodes", "0"], "--episodes must be >= 1, got 0")):
        with pytest.raises(SystemExit):
            paper_window.main(["--jirl", str(tmp_path), "--sac", str(tmp_path), *option])
        assert message in capsys.readouterr().err  # refused as parsed, not for the runs it then lacks
    returns = [(200, -200.0)]
    write_run(tmp_path / "jirl", "Pendulum-v1__jirl__1__100", scalars(returns, [(200, 1.0)], [(200, 1.0)]))
    write_run(tmp_path / "sac", "Pendulum-v1__sac__1__100", {"charts/episodic_return": returns})  # --regret-estimator off
    with pytest.raises(SystemExit, match="logged no charts/baseline_regret, charts/baseline_regret_per_step"):
        paper_window.main(["--jirl", str(tmp_path / "jirl"), "--sac", str(tmp_path / "sac")])
