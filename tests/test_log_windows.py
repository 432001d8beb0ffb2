"""benchmarks/log_windows.py: window medians and growths of running totals, on logs whose answer is known."""

import os
import sys
import time

import numpy as np
import pytest

from conftest import ROOT
from test_paper_window import write_run

sys.path.insert(0, str(ROOT / "benchmarks"))
import log_windows  # noqa: E402

# the RL-control fraction every 50 steps, and a running total logged at episode ends
CONTROL = [(0, 0.2), (50, 0.4), (100, 0.5), (150, 0.9), (200, 0.7), (250, 1.0), (350, 1.0)]
REGRET = [(30, 10.0), (99, 25.0), (160, 40.0), (200, 55.0), (340, 100.0)]  # on a window's last and first steps


def test_medians_and_growths_window_by_window():
    rows = log_windows.windows({"control": CONTROL, "regret": REGRET}, ["control"], ["regret"], 100)
    assert [row.start for row in rows] == [0, 100, 200, 300]  # up to the last step logged, 350
    assert [row.start for row in log_windows.windows({"t": [(0, 1.0), (200, 2.0)]}, ["t"], [], 100)] == [0, 100, 200]
    # medians of (0.2, 0.4), (0.5, 0.9), (0.7, 1.0) and (1.0,): the points in [start, start + 100)
    assert [row.medians[0] for row in rows] == pytest.approx([0.3, 0.7, 0.85, 1.0])
    # the total's last value before each window's end less its last before the start (0 before the first):
    # the point at 200 counts in [200, 300), not in [100, 200)
    assert [row.growths for row in rows] == [[25.0], [15.0], [15.0], [45.0]]


def test_a_window_without_points_has_no_median_and_the_growths_sum_to_the_total():
    rows = log_windows.windows({"control": [(0, 0.5), (250, 1.0)], "regret": REGRET}, ["control"], ["regret"], 100)
    assert [row.medians for row in rows] == [[0.5], [None], [1.0], [None]]
    assert sum(row.growths[0] for row in rows) == REGRET[-1][1]
    table = log_windows.report(4, rows, ["control"], ["regret"], 100)
    assert table.splitlines()[:3] == ["seed 4", "| steps | control, median | regret, grew by |", "|---|---|---|"]
    assert table.splitlines()[4] == "| 100–200 | – | 15 |"


def test_the_command_reads_the_newest_run_of_each_seed_across_workdirs(tmp_path, capsys):
    now = time.time()
    runs = [
        ("a", "Walker2DBulletEnv-v0__jirl__4__100", {"charts/rl_control_fraction": CONTROL, "charts/baseline_regret": REGRET}, 200),
        # seed 4 again, newer, in the other workdir: its totals doubled
        ("b", "Walker2DBulletEnv-v0__jirl__4__200", {"charts/rl_control_fraction": CONTROL, "charts/baseline_regret": [(s, 2 * v) for s, v in REGRET]}, 100),
        ("b", "Walker2DBulletEnv-v0__jirl__5__100", {"charts/rl_control_fraction": [(10, 1.0)], "charts/baseline_regret": [(10, 7.0)]}, 300),
    ]
    for workdir, name, data, age in runs:
        write_run(tmp_path / workdir, name, data)
        os.utime(tmp_path / workdir / "runs" / name, (now - age, now - age))
    tags = ["--medians", "charts/rl_control_fraction", "--totals", "charts/baseline_regret"]
    log_windows.main([str(tmp_path / "a"), str(tmp_path / "b"), "--window", "200", *tags])
    out = capsys.readouterr().out
    seed4, seed5 = out.split("\n\n")
    # windows [0, 200) and [200, 400): medians of (0.2, 0.4, 0.5, 0.9) and (0.7, 1.0, 1.0); growths 2 x 40 and 2 x 60
    assert seed4.splitlines()[3:] == ["| 0–200 | 0.45 | 80 |", "| 200–400 | 1 | 120 |"]
    assert seed5.splitlines() == ["seed 5", "| steps | charts/rl_control_fraction, median | charts/baseline_regret, grew by |", "|---|---|---|", "| 0–200 | 1 | 7 |"]
    log_windows.main([str(tmp_path / "b"), "--window", "200", "--medians", "--totals", "charts/baseline_regret"])  # totals only
    assert capsys.readouterr().out.splitlines()[:4] == ["seed 4", "| steps | charts/baseline_regret, grew by |", "|---|---|", "| 0–200 | 80 |"]


def test_the_command_refuses_what_it_cannot_read(tmp_path, capsys):
    with pytest.raises(SystemExit, match="log_windows: error: no runs under"):
        log_windows.main([str(tmp_path)])
    write_run(tmp_path, "Pendulum-v1__sac__1__100", {"charts/episodic_return": [(200, -300.0)]})
    with pytest.raises(SystemExit, match="logged no charts/rl_control_fraction, losses/qf1_values, losses/alpha, charts/baseline_regret"):
        log_windows.main([str(tmp_path)])
    for bad, said in [(["--window", "0"], "--window must be > 0, got 0"), (["--medians", "--totals"], "nothing to print")]:
        with pytest.raises(SystemExit):
            log_windows.main([str(tmp_path), *bad])
        assert said in capsys.readouterr().err


def test_window_medians_and_growths_agree_with_numpy_on_uneven_steps():
    rng = np.random.default_rng(0)
    steps = np.sort(rng.choice(10_000, size=700, replace=False))
    values = rng.random(700)
    series = [(int(s), float(v)) for s, v in zip(steps, values)]
    totals = [(int(s), float(v)) for s, v in zip(steps, np.cumsum(values))]
    rows = log_windows.windows({"v": series, "t": totals}, ["v"], ["t"], 1_000)
    assert len(rows) == 10
    for row in rows:
        inside = (steps >= row.start) & (steps < row.start + 1_000)
        assert row.medians[0] == pytest.approx(np.median(values[inside]))
        assert row.growths[0] == pytest.approx(values[inside].sum())  # a running total grows by what was added in the window
