"""benchmarks/handover.py: when JIRL handed control over, on logs whose answer is known."""

import os
import sys
import time

import pytest

from conftest import ROOT
from test_paper_window import write_run

sys.path.insert(0, str(ROOT / "benchmarks"))
import handover  # noqa: E402

# C falls to 0 at 300, is back above 0 at 400 and 500, and 0 again from 600: 2 of the 5 points from 300
C = [(100, 10.0), (200, 0.5), (300, 0.0), (400, 1e-6), (500, 2e-6), (600, 0.0), (700, 0.0)]
CONTROL = [(100, 0.1), (200, 0.999), (300, 0.9), (400, 1.0), (500, 0.95), (600, 1.0), (700, 0.75)]


def test_the_handover_of_one_run():
    assert handover.handover(C, CONTROL) == {"c_zero": 300, "full_control": 400, "c_back": 2 / 5, "c_end": 0.0, "control_end": 0.75}


def test_a_run_whose_guidance_never_ended():
    row = handover.handover([(100, 10.0), (200, 5.0)], [(100, 0.2), (200, 0.6)])
    assert row == {"c_zero": None, "full_control": None, "c_back": None, "c_end": 5.0, "control_end": 0.6}
    assert "| 1 | never | never | never | 5 | 60.0 % |" in handover.report({1: row})


def test_the_command_reads_the_newest_run_of_each_seed_across_workdirs(tmp_path, capsys):
    now = time.time()
    late = [(step + 1_000, value) for step, value in C]  # the same run, 1,000 steps later
    runs = [
        ("a", "Pendulum-v1__jirl__1__100", {"gate/c": C, "charts/rl_control_fraction": CONTROL}, 200),
        ("b", "Pendulum-v1__jirl__1__200", {"gate/c": late, "charts/rl_control_fraction": CONTROL}, 100),  # seed 1 again, newer
        ("b", "Pendulum-v1__jirl__3__100", {"gate/c": [(50, 0.0), (100, 0.0)], "charts/rl_control_fraction": [(50, 1.0), (100, 1.0)]}, 300),
    ]
    for workdir, name, data, age in runs:
        write_run(tmp_path / workdir, name, data)
        os.utime(tmp_path / workdir / "runs" / name, (now - age, now - age))
    handover.main([str(tmp_path / "a"), str(tmp_path / "b")])
    out = capsys.readouterr().out
    assert "| 1 | 1,300 | 400 | 40 % | 0 | 75.0 % |" in out  # seed 1's newer run, in the second workdir
    assert "| 3 | 50 | 50 | 0 % | 0 | 100.0 % |" in out
    # medians of two: (1,300 + 50) / 2, (400 + 50) / 2, (40 % + 0 %) / 2, and RL control (75 % + 100 %) / 2
    assert "| median | 675 | 225 | 20 % | 0 | 87.5 % |" in out
    assert len(out.splitlines()) == 5  # header, rule, two seeds, median


def test_a_median_over_a_run_that_never_got_there_is_not_given():
    never = handover.handover([(100, 10.0)], [(100, 0.2)])
    table = handover.report({1: handover.handover(C, CONTROL), 2: never})
    assert "| median | – | – | – | 5 | 47.5 % |" in table


def test_the_command_refuses_what_is_no_jirl_run(tmp_path):
    with pytest.raises(SystemExit, match="handover: error: no runs under"):
        handover.main([str(tmp_path)])
    write_run(tmp_path, "Pendulum-v1__sac__1__100", {"charts/episodic_return": [(200, -300.0)]})
    with pytest.raises(SystemExit, match="logged no gate/c, charts/rl_control_fraction"):
        handover.main([str(tmp_path)])
