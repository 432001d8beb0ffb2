"""benchmarks/reproduce.py: the table and figures on synthetic logs with known answers, and both launchers."""

import math
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy import stats
from torch.utils.tensorboard import SummaryWriter

from conftest import ROOT, table_cells

sys.path.insert(0, str(ROOT / "benchmarks"))
import reproduce  # noqa: E402

JIRL_PHASES = {1: (100.0, 50.0, 0.0), 2: (120.0, 30.0, 10.0), 3: (80.0, 40.0, 5.0)}
TOTALS = {"sac": {1: 2000.0, 2: 2400.0, 3: 1900.0}, "ppo_il": {1: 900.0, 2: 800.0, 3: 1000.0}, "trpo_il": {1: 1500.0, 2: 1600.0, 3: 1400.0}}


def write_run(workdir, env, method, seed, total, phases=None, rollout=None, evaluated=True):
    folder = reproduce.run_dir(workdir, env, method, seed)
    writer = SummaryWriter(str(folder / "runs" / f"{env}__{method}__{seed}"))
    if rollout is not None:  # PPO/TRPO+IL log SPS at the end of each whole rollout
        for step in range(rollout, 1001, rollout):
            writer.add_scalar("charts/SPS", 300, step)
    for step in range(1, 11):  # episodes of 100 steps earning -1 per step at first, then -0.5
        writer.add_scalar("charts/episodic_return", -100.0 if step < 6 else -50.0, step * 100)
        writer.add_scalar("charts/episodic_length", 100, step * 100)
        writer.add_scalar("charts/rl_control_fraction", step / 10, step * 100)
    for step, share in ((500, 0.25), (1000, 1.0)):  # logged as it accumulates: the report takes the last value
        writer.add_scalar("charts/baseline_regret_per_step", share * total, step)
        writer.add_scalar("charts/baseline_regret", share * total / 2, step)
        for name, value in zip(("0_50", "50_100", "100"), phases or ()):
            writer.add_scalar(f"phases/baseline_regret_per_step_{name}", share * value, step)
            writer.add_scalar(f"phases/baseline_regret_{name}", share * value / 2, step)
    writer.add_scalar("charts/baseline_return", -80.0 - seed, 0)  # measured once per seed, alike for every method
    writer.add_scalar("charts/baseline_reward_per_step", -0.8, 0)
    for i, value in enumerate([-40.0 - seed, -60.0 - seed] if evaluated else []):
        writer.add_scalar("eval/episodic_return", value, i)
    writer.close()
    (folder / "DONE").write_text("synthetic\n")


def test_table_and_figures_on_synthetic_logs(tmp_path):
    for seed, phases in JIRL_PHASES.items():
        write_run(tmp_path, "Pendulum-v1", "jirl", seed, sum(phases), phases)
        for method, totals in TOTALS.items():
            write_run(tmp_path, "Pendulum-v1", method, seed, totals[seed])
    results = reproduce.collect(tmp_path, ["Pendulum-v1"], list(reproduce.SCRIPTS), [1, 2, 3])
    text = reproduce.table(results)
    row = next(line for line in text.splitlines() if line.startswith("| Pendulum-v1") and "×" in line)
    cells = table_cells(row)
    # phase 0-50 %: mean 100, 95 % CI half-width t(0.975, 2) * sd / sqrt(3)
    half = stats.t.ppf(0.975, 2) * np.std([100, 120, 80], ddof=1) / math.sqrt(3)
    assert cells[1] == f"100 ± {half:,.0f}"
    jirl_total = np.mean([sum(p) for p in JIRL_PHASES.values()])  # 145
    assert cells[4].startswith(f"{jirl_total:,.0f} ±")
    assert cells[6].startswith("900 ±") and "PPO+IL" in cells[6]  # the better of the two IL methods
    assert cells[7] == f"{np.mean(list(TOTALS['sac'].values())) / jirl_total:.1f}×"
    assert cells[8] == f"{900 / jirl_total:.1f}×"
    p_value = stats.ttest_rel([sum(JIRL_PHASES[s]) for s in (1, 2, 3)], [TOTALS["ppo_il"][s] for s in (1, 2, 3)], alternative="less").pvalue
    assert f"p = {p_value:.3g}" in cells[9]
    assert "### Accumulated baseline regret, per episode" in text
    eval_row = [line for line in text.splitlines() if line.startswith("| Pendulum-v1")][-1]
    # seeds' means -51, -52, -53 for every method and the baseline's -81, -82, -83: one value per seed, not one per run
    assert eval_row.count("-52 ± 2") == 4 and eval_row.strip().endswith(f"-82 ± {stats.t.ppf(0.975, 2) / math.sqrt(3):,.0f} |")
    paths = reproduce.figures(results, tmp_path)
    assert paths[0].exists() and paths[0].stat().st_size > 10_000
    curve = reproduce.reward_per_step_curve(results["Pendulum-v1"]["sac"][1], np.array([150.0, 950.0]), window=1)
    np.testing.assert_allclose(curve, [-1.0, -0.5])


def test_the_curves_average_the_episodes_there_are_and_their_bands_are_student_t():
    """Episodes of -1 per step then of -0.5, five each. Averaged over 3 episodes, the first and last
    are means of two (they were padded with a zero: -0.67 and -0.33, a run's ends bent towards 0)."""
    scalars = {"charts/episodic_return": [(100 * i, -100.0 if i < 6 else -50.0) for i in range(1, 11)],
               "charts/episodic_length": [(100 * i, 100) for i in range(1, 11)]}  # fmt: skip
    curve = reproduce.reward_per_step_curve(scalars, np.array([100.0, 500.0, 600.0, 1000.0, 1100.0]), window=3)
    np.testing.assert_allclose(curve, [-1.0, (-1 - 1 - 0.5) / 3, (-1 - 0.5 - 0.5) / 3, -0.5, np.nan])
    # three seeds' curves, one with no value at the third point, two none at the fourth (their runs had
    # ended), and a run that logged no episode: mean and band only where all three have a value
    curves = np.array([[1.0, 2.0, np.nan, np.nan], [3.0, 4.0, 5.0, np.nan], [5.0, 9.0, 7.0, 8.0], [np.nan] * 4])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mean, half = reproduce.mean_band(curves)
        one_mean, one_half = reproduce.mean_band(curves[2:])
    np.testing.assert_allclose(mean, [3.0, 5.0, np.nan, np.nan])  # a mean of 6 then 8 there would jump where the runs end
    t = stats.t.ppf(0.975, 2)  # 4.30; 1.96 made the bands less than half as wide
    np.testing.assert_allclose(half, [t * 2 / math.sqrt(3), t * math.sqrt(13) / math.sqrt(3), np.nan, np.nan])
    np.testing.assert_allclose(one_mean, curves[2])  # a single seed: its curve, with no band
    assert np.isnan(one_half).all()


def test_a_report_of_two_seeds_leaves_out_unfinished_runs_and_missing_values(tmp_path):
    """A workdir partly done: two seeds of every method, a third JIRL seed killed (its logs stay, its DONE
    never came), one SAC run that was not evaluated, and an env on which JIRL's regret is 0."""
    for env in ("Pendulum-v1", "LunarLanderContinuous-v3"):
        for seed in (1, 2):
            phases = JIRL_PHASES[seed] if env == "Pendulum-v1" else (0.0, 0.0, 0.0)
            write_run(tmp_path, env, "jirl", seed, sum(phases), phases)
            for method, totals in TOTALS.items():
                write_run(tmp_path, env, method, seed, totals[seed], evaluated=(env, method, seed) != ("Pendulum-v1", "sac", 2))
    write_run(tmp_path, "Pendulum-v1", "jirl", 3, 10_000.0, (10_000.0, 0.0, 0.0))
    (reproduce.run_dir(tmp_path, "Pendulum-v1", "jirl", 3) / "DONE").unlink()
    results = reproduce.collect(tmp_path, ["Pendulum-v1", "LunarLanderContinuous-v3"], list(reproduce.SCRIPTS), [1, 2, 3])
    assert sorted(results["Pendulum-v1"]["jirl"]) == [1, 2]  # the killed run is not read
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # one value is reported without an interval, not with numpy's warnings
        text = reproduce.table(results)
    rows = [table_cells(line) for line in text.splitlines() if line.startswith(("| Pendulum", "| Lunar"))]
    pendulum, lander = rows[0], rows[1]  # the per-step form

    def ci(values):  # mean ± t(0.975, n - 1) sd / sqrt(n), as the table rounds
        return f"{np.mean(values):,.0f} ± {stats.t.ppf(0.975, len(values) - 1) * np.std(values, ddof=1) / math.sqrt(len(values)):,.0f}"

    assert pendulum[1:5] == [ci([100, 120]), ci([50, 30]), ci([0, 10]), ci([150, 160])]
    assert pendulum[5:7] == [ci([2000, 2400]), f"{ci([900, 800])} (PPO+IL)"]
    assert pendulum[7:9] == [f"{2200 / 155:.1f}×", f"{850 / 155:.1f}×"]
    p_value = stats.ttest_rel([150, 160], [900, 800], alternative="less").pvalue
    assert pendulum[9] == f"p = {p_value:.3g} (PPO+IL, 2 seeds)"  # two seeds are enough for a paired test
    assert lander[4] == "0 ± 0" and lander[7:9] == ["–", "–"]  # no ratio to a regret of 0
    evaluation = rows[4]
    assert evaluation[0] == "Pendulum-v1" and evaluation[2] == "-51"  # SAC: seed 1's mean alone, without an interval
    assert evaluation[1] == ci([-51, -52]) and evaluation[5] == ci([-81, -82])
    assert text.strip().endswith("Mean ± 95 % confidence interval over seeds [1, 2].")


def test_a_training_asked_for_after_a_stop_never_starts(tmp_path):
    """A worker that reaches its run after Ctrl-C or SIGTERM has stopped the others (the pool had already
    handed it out) must not start a training that nothing would end."""
    import signal

    trainings, mark = reproduce.Trainings(), tmp_path / "started"
    trainings.stop()
    code = reproduce.run_one([sys.executable, "-c", f"open({str(mark)!r}, 'w').close()"], str(tmp_path / "run"), trainings)
    assert code == -signal.SIGTERM and not mark.exists() and not (tmp_path / "run" / "DONE").exists()
    assert reproduce.run_one([sys.executable, "-c", f"open({str(mark)!r}, 'w').close()"], str(tmp_path / "run"), reproduce.Trainings()) == 0
    assert mark.exists() and (tmp_path / "run" / "DONE").exists()  # the same run, not stopped


def test_budget_names_the_steps_ppo_and_trpo_ran_in_whole_rollouts(tmp_path):
    for method, rollout in (("jirl", None), ("sac", None), ("ppo_il", 400), ("trpo_il", 250)):
        for seed in (1, 2):
            write_run(tmp_path, "Pendulum-v1", method, seed, 100.0, rollout=rollout)
            command = f"python {method}.py --env-id Pendulum-v1 --total-timesteps 1000\n"
            (reproduce.run_dir(tmp_path, "Pendulum-v1", method, seed) / "DONE").write_text(command)
    results = reproduce.collect(tmp_path, ["Pendulum-v1"], list(reproduce.SCRIPTS), [1, 2])
    assert reproduce.budgets(tmp_path, results) == (  # 1000 steps are two whole rollouts of 400, four of 250
        "Budgets: Pendulum-v1: 1,000 env steps per run (PPO+IL 800: whole rollouts), 2/2/2/2 seeds (JIRL (SAC)/SAC/PPO+IL/TRPO+IL)."
    )
    for seed in (1, 2):  # a budget shorter than a rollout still runs one, and the sentence names its longer length
        for scalars in (results["Pendulum-v1"]["ppo_il"][seed], results["Pendulum-v1"]["trpo_il"][seed]):
            scalars["charts/SPS"] = [(1200, 300.0)]
    assert "1,000 env steps per run (PPO+IL 1,200; TRPO+IL 1,200: whole rollouts)" in reproduce.budgets(tmp_path, results)


def test_quick_preset_end_to_end_and_resume(tmp_path, capsys):
    args = reproduce.Args(envs=("Pendulum-v1",), seeds=(1,), preset="quick", workdir=str(tmp_path / "work"),
                          output=str(tmp_path / "out"), workers=2)  # fmt: skip
    reproduce.main(args)
    table = (tmp_path / "out" / "table.md").read_text()
    assert "| Pendulum-v1 |" in table and (tmp_path / "out" / "fig_Pendulum-v1.png").exists()
    capsys.readouterr()
    reproduce.main(args)  # everything is done: nothing runs again
    assert "4 already done, 0 to run" in capsys.readouterr().out
    assert "Budgets: Pendulum-v1: 600 env steps per run, 1/1/1/1 seeds" in table
    with pytest.raises(SystemExit, match="4 finished runs used other arguments"):  # another budget, same workdir
        reproduce.main(reproduce.Args(**{**vars(args), "steps": 700}))


def test_submitit_local_executor(tmp_path):
    args = reproduce.Args(envs=("Pendulum-v1",), methods=("sac",), seeds=(2,), preset="quick", launcher="submitit-local",
                          workdir=str(tmp_path / "work"), output=str(tmp_path / "out"))  # fmt: skip
    reproduce.main(args)
    assert (reproduce.run_dir(tmp_path / "work", "Pendulum-v1", "sac", 2) / "DONE").exists()


def test_submitted_runs_are_reported_as_they_end(tmp_path, monkeypatch, capsys):
    def command(preset, env, method, seed, steps=None):  # seed 1 trains longest
        return [sys.executable, "-c", f"import time; time.sleep({6 if seed == 1 else 0})", str(seed)]

    monkeypatch.setattr(reproduce, "command", command)
    args = reproduce.Args(envs=("Pendulum-v1",), methods=("sac",), seeds=(1, 2), preset="quick", launcher="submitit-local", workdir=str(tmp_path / "work"))
    reproduce.launch(args)
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("[")]
    # before: in the order submitted, so a run that failed in a minute was named only after one that trained for hours
    assert [Path(line.split()[1]).name for line in lines] == ["seed2", "seed1"], lines
    assert lines[0].startswith("[1/2] ") and " done (job " in lines[0] and "ETA" in lines[0]


def test_ctrl_c_while_waiting_for_slurm_says_the_jobs_go_on(tmp_path, monkeypatch):
    import submitit

    monkeypatch.setattr(reproduce, "command", lambda preset, env, method, seed, steps=None: [sys.executable, "-c", "pass"])
    monkeypatch.setattr(reproduce.shutil, "which", lambda name: f"/usr/bin/{name}")
    monkeypatch.setattr(submitit, "AutoExecutor", lambda folder, cluster=None: submitit.LocalExecutor(folder=folder))  # Slurm's stand-in

    def interrupted(jobs, poll_frequency):
        for job in jobs:
            job.result()  # the jobs end, in Slurm, after the user stopped waiting
        raise KeyboardInterrupt

    monkeypatch.setattr(submitit.helpers, "as_completed", interrupted)
    args = reproduce.Args(envs=("Pendulum-v1",), methods=("sac",), seeds=(1,), preset="quick", launcher="slurm", workdir=str(tmp_path / "work"))
    with pytest.raises(SystemExit, match=r"^reproduce: stopped waiting; the jobs submitted go on in Slurm, each writing its DONE as it ends"):
        reproduce.launch(args)  # before: a KeyboardInterrupt traceback
    assert (reproduce.run_dir(tmp_path / "work", "Pendulum-v1", "sac", 1) / "DONE").exists()


def test_unknown_method_is_an_error(tmp_path):
    with pytest.raises(SystemExit, match="unknown methods or envs"):
        reproduce.main(reproduce.Args(methods=("dqn",), workdir=str(tmp_path)))


def test_learning_summary_skips_what_a_script_does_not_log():
    import learning

    values = [-170.0, -180.0, -200.0]
    half = stats.t.ppf(0.975, 2) * np.std(values, ddof=1) / math.sqrt(3)
    assert learning.mean_ci(values) == f"{np.mean(values):.1f} ± {half:.1f}"
    assert learning.mean_ci([*values, math.nan]) == learning.mean_ci(values)  # one seed without the tag
    assert learning.mean_ci([math.nan] * 3) == "–"  # SAC's RL-control fraction
    assert learning.mean_ci([5.0, math.nan]) == "5.0"


def test_every_preset_command_parses_and_the_paper_preset_bounds_sac_buffers(monkeypatch):
    """Each preset's command is accepted by its script's own Args; the paper preset gives JIRL and SAC
    the authors' replay buffers (Pendulum 50k, Lunar Lander 100k) and leaves the rest at 1e6."""
    import importlib.util

    import tyro

    modules = {}
    for method, script in reproduce.SCRIPTS.items():
        spec = importlib.util.spec_from_file_location(f"_preset_{method}", ROOT / script)
        modules[method] = importlib.util.module_from_spec(spec)
        monkeypatch.setitem(sys.modules, spec.name, modules[method])  # dataclasses look their module up
        spec.loader.exec_module(modules[method])
    parsed = {}
    for name, preset in reproduce.PRESETS.items():
        for env in preset:
            for method in reproduce.SCRIPTS:
                cmd = reproduce.command(preset, env, method, seed=3)
                assert cmd[1] == str(ROOT / reproduce.SCRIPTS[method])
                parsed[name, env, method] = tyro.cli(modules[method].Args, args=cmd[2:])
    paper = {env: {m: parsed["paper", env, m] for m in ("jirl", "sac")} for env in reproduce.PRESETS["paper"]}
    assert paper["Pendulum-v1"]["jirl"].buffer_size == paper["Pendulum-v1"]["sac"].buffer_size == 50_000
    assert paper["LunarLanderContinuous-v3"]["jirl"].buffer_size == paper["LunarLanderContinuous-v3"]["sac"].buffer_size == 100_000
    assert paper["Walker2DBulletEnv-v0"]["sac"].buffer_size == 1_000_000
    assert paper["Pendulum-v1"]["jirl"].gate_k == 1 and paper["Pendulum-v1"]["jirl"].penalty_sigma2 == 0.01
    assert parsed["local", "Pendulum-v1", "jirl"].buffer_size == parsed["local", "Pendulum-v1", "sac"].buffer_size == 1_000_000
    assert parsed["paper", "Pendulum-v1", "sac"].total_timesteps == 280_000 and parsed["paper", "Pendulum-v1", "sac"].seed == 3


@pytest.mark.parametrize("launcher", ["local", "submitit-local"])
def test_a_failed_run_is_named_and_the_others_finish(tmp_path, monkeypatch, launcher):
    def command(preset, env, method, seed, steps=None):  # seed 2 fails the way a script refusing its arguments does
        code = "import sys; print('boom'); sys.exit(2)" if seed == 2 else "print('fine')"
        return [sys.executable, "-c", code, env, method, str(seed)]

    monkeypatch.setattr(reproduce, "command", command)
    args = reproduce.Args(envs=("Pendulum-v1",), methods=("sac",), seeds=(1, 2, 3), preset="quick", launcher=launcher,
                          workdir=str(tmp_path / "work"), output=str(tmp_path / "out"), workers=2)  # fmt: skip
    with pytest.raises(SystemExit, match=r"1 of 3 runs failed; see log.txt in .*seed2$"):
        reproduce.launch(args)
    folder = {seed: reproduce.run_dir(tmp_path / "work", "Pendulum-v1", "sac", seed) for seed in (1, 2, 3)}
    assert (folder[1] / "DONE").exists() and (folder[3] / "DONE").exists() and not (folder[2] / "DONE").exists()
    assert "boom" in (folder[2] / "log.txt").read_text()


def test_a_finished_run_is_recognised_when_a_path_in_its_command_has_a_space(tmp_path, monkeypatch, capsys):
    script = tmp_path / "my projects" / "train.py"  # e.g. a clone under "My Projects"
    script.parent.mkdir()
    script.write_text("print('fine')\n")
    monkeypatch.setattr(reproduce, "command", lambda preset, env, method, seed, steps=None: [sys.executable, str(script), "--seed", str(seed)])
    args = reproduce.Args(envs=("Pendulum-v1",), methods=("sac",), seeds=(1, 2), preset="quick", workdir=str(tmp_path / "work"), workers=2)
    reproduce.launch(args)
    assert reproduce.done_arguments(reproduce.run_dir(tmp_path / "work", "Pendulum-v1", "sac", 2)) == ["--seed", "2"]
    capsys.readouterr()
    reproduce.launch(args)  # before, the DONE marker split the path: every finished run "used other arguments"
    assert "2 already done, 0 to run" in capsys.readouterr().out


def test_arguments_out_of_range_are_refused():
    for bad in (dict(workers=0), dict(steps=0), dict(seeds=()), dict(seeds=(1, -1))):
        with pytest.raises(ValueError, match=f"--{next(iter(bad))} must be"):
            reproduce.Args(**bad)


WRITE_ONE_LOG = """
import sys, time
from torch.utils.tensorboard import SummaryWriter
writer = SummaryWriter(f"runs/attempt_{time.time_ns()}")  # as a script names its run: a new directory each attempt
writer.add_scalar("charts/baseline_regret", float(sys.argv[1]), 1)
writer.close()
"""


@pytest.mark.parametrize("launcher", ["local", "submitit-local"])
def test_a_run_killed_earlier_is_trained_again_from_scratch_and_reported_once(tmp_path, monkeypatch, launcher):
    script = tmp_path / "train.py"
    script.write_text(WRITE_ONE_LOG)
    monkeypatch.setattr(reproduce, "command", lambda preset, env, method, seed, steps=None: [sys.executable, str(script), "7"])
    folder = reproduce.run_dir(tmp_path / "work", "Pendulum-v1", "sac", 1)
    killed = SummaryWriter(str(folder / "runs" / "attempt_0"))  # the logs of an attempt killed with the session: no DONE
    killed.add_scalar("charts/baseline_regret", 99.0, 1)
    killed.close()
    args = reproduce.Args(envs=("Pendulum-v1",), methods=("sac",), seeds=(1,), preset="quick", launcher=launcher, workdir=str(tmp_path / "work"))
    reproduce.launch(args)  # before, the folder then held two runs and the report ended in "too many values to unpack"
    assert (folder / "DONE").exists() and [p.name for p in (folder / "runs").iterdir()] != ["attempt_0"]
    assert len(list((folder / "runs").iterdir())) == 1
    results = reproduce.collect(tmp_path / "work", ["Pendulum-v1"], ["sac"], [1])
    assert reproduce.last(results["Pendulum-v1"]["sac"][1], "charts/baseline_regret") == 7.0


def test_a_workdir_from_before_reports_the_attempt_that_finished(tmp_path):
    folder = reproduce.run_dir(tmp_path, "Pendulum-v1", "sac", 1)
    for name, value, age in (("killed", 99.0, 3600), ("finished", 7.0, 0)):  # "killed" ran an hour earlier (and sorts last by name)
        writer = SummaryWriter(str(folder / "runs" / name))
        writer.add_scalar("charts/baseline_regret", value, 1)
        writer.close()
        for log in (folder / "runs" / name).iterdir():  # set, not slept for: some file systems keep whole seconds
            os.utime(log, (time.time() - age, time.time() - age))
    (folder / "DONE").write_text("synthetic\n")
    assert reproduce.last(reproduce.read_scalars(folder), "charts/baseline_regret") == 7.0
    (folder / "runs" / "finished").rename(folder / "elsewhere")
    (folder / "runs" / "killed").rename(folder / "elsewhere_too")
    with pytest.raises(SystemExit, match="is marked DONE but holds no TensorBoard log; delete its DONE to train it again$"):
        reproduce.read_scalars(folder)


def test_a_second_reproduce_on_one_workdir_is_refused_while_the_first_trains(tmp_path, monkeypatch):
    started = []
    monkeypatch.setattr(reproduce, "command", lambda preset, env, method, seed, steps=None: started.append(seed) or [sys.executable, "-c", "pass"])
    args = reproduce.Args(envs=("Pendulum-v1",), methods=("sac",), seeds=(1,), preset="quick", workdir=str(tmp_path / "work"))
    with reproduce.holding(tmp_path / "work"):  # as a first reproduce.py in another terminal holds it
        with pytest.raises(SystemExit, match=r"^reproduce: error: another reproduce.py is training in .*work; wait for it to end, or use another --workdir$"):
            reproduce.launch(args)
        assert started == [] and not (tmp_path / "work" / "Pendulum-v1").exists()  # nothing started, nothing cleared
    reproduce.launch(args)  # released
    assert started == [1] and (reproduce.run_dir(tmp_path / "work", "Pendulum-v1", "sac", 1) / "DONE").exists()


def test_a_workdir_that_cannot_be_locked_still_runs_with_a_warning(tmp_path, monkeypatch, capsys):
    import errno
    import fcntl

    def no_locks(fd, operation):  # a file system without locks
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_locks)
    with reproduce.holding(tmp_path):
        ran = True
    assert ran and "reproduce: warning: cannot lock" in capsys.readouterr().err


@pytest.mark.parametrize("flag", ["workdir", "output"])
def test_a_file_in_the_way_of_a_folder_is_refused_before_anything_trains(tmp_path, monkeypatch, flag):
    started = []
    monkeypatch.setattr(reproduce, "command", lambda preset, env, method, seed, steps=None: started.append(seed) or [sys.executable, "-c", "pass"])
    (tmp_path / "afile").write_text("a user's notes")
    folders = {"workdir": str(tmp_path / "work"), "output": str(tmp_path / "out"), flag: str(tmp_path / "afile" / "sub")}
    args = reproduce.Args(envs=("Pendulum-v1",), methods=("sac",), seeds=(1,), preset="quick", **folders)
    # before: a FileExistsError or NotADirectoryError traceback, for --output only once every run had trained
    with pytest.raises(SystemExit, match=rf"^reproduce: error: --{flag} .*sub cannot be a folder: .*afile is a file$"):
        reproduce.main(args)
    assert started == [] and not (tmp_path / "work").exists() and (tmp_path / "afile").read_text() == "a user's notes"


def test_the_slurm_launcher_without_slurm_is_refused_instead_of_running_every_run_here(tmp_path, monkeypatch):
    import submitit

    started = []
    monkeypatch.setattr(reproduce, "command", lambda preset, env, method, seed, steps=None: started.append(seed) or [sys.executable, "-c", "pass"])
    args = reproduce.Args(envs=("Pendulum-v1",), methods=("sac",), seeds=(1, 2), preset="quick", launcher="slurm",
                          workdir=str(tmp_path / "work"), output=str(tmp_path / "out"))  # fmt: skip
    monkeypatch.setattr(reproduce.shutil, "which", lambda name: None)  # a machine without Slurm
    # before: submitit's AutoExecutor fell back to its local executor and started both runs here at once
    with pytest.raises(SystemExit, match=r"^reproduce: error: --launcher slurm needs Slurm \(no sbatch here\)"):
        reproduce.main(args)
    assert started == [] and not (tmp_path / "work").exists()

    class Asked(Exception):
        pass

    def executor(folder, cluster=None, **kwargs):  # where sbatch exists: the executor is Slurm's, never a fallback
        raise Asked(cluster)

    monkeypatch.setattr(reproduce.shutil, "which", lambda name: f"/usr/bin/{name}")
    monkeypatch.setattr(submitit, "AutoExecutor", executor)
    with pytest.raises(Asked, match="^slurm$"):
        reproduce.main(args)


LAUNCHER = """
import sys
sys.path.insert(0, sys.argv[1])
import reproduce
# each run notes its process id in the marks folder, then trains for 60 s
train = "import os, sys, time; open(os.path.join(sys.argv[1], str(os.getpid())), 'w').close(); time.sleep(60)"
reproduce.command = lambda preset, env, method, seed, steps=None: [sys.executable, "-c", train, sys.argv[3]]
reproduce.launch(reproduce.Args(envs=("Pendulum-v1",), methods=("sac",), seeds=(1, 2, 3), preset="quick", workers=2, workdir=sys.argv[2]))
"""


def test_sigterm_ends_the_local_launchers_trainings_and_starts_no_queued_one(tmp_path):
    """`kill` or `timeout` sends SIGTERM to reproduce.py alone: it used to die at once, leaving its
    trainings to run on unrecorded (no DONE) and unseen."""
    import signal
    import subprocess

    marks = tmp_path / "marks"
    marks.mkdir()
    launcher = subprocess.Popen([sys.executable, "-c", LAUNCHER, str(ROOT / "benchmarks"), str(tmp_path / "work"), str(marks)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    deadline = time.time() + 60
    while len(list(marks.iterdir())) < 2 and time.time() < deadline:  # both workers' runs have started
        time.sleep(0.05)
    launcher.send_signal(signal.SIGTERM)
    out, err = launcher.communicate(timeout=30)
    assert launcher.returncode == 1 and err.strip().splitlines()[-1] == "reproduce: interrupted; the same command trains again what has no DONE, from scratch", err
    pids = [int(mark.name) for mark in marks.iterdir()]
    assert len(pids) == 2  # the queued third run never started
    time.sleep(0.5)
    for pid in pids:  # before: both trained on for their 60 s
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)
    assert not list((tmp_path / "work").rglob("DONE"))


TRAIN_4S = "import time; time.sleep(4); print('trained')"
WATCHER = f"""
import sys
sys.path.insert(0, sys.argv[1])
import reproduce
reproduce.command = lambda preset, env, method, seed, steps=None: [sys.executable, "-c", {TRAIN_4S!r}]
reproduce.launch(reproduce.Args(envs=("Pendulum-v1",), methods=("sac",), seeds=(1,), preset="quick", launcher="submitit-local", workdir=sys.argv[2]))
"""


def test_a_submitted_run_that_ends_after_its_watcher_has_gone_is_done(tmp_path, monkeypatch, capsys):
    """The job writes its own DONE: a reproduce.py killed while it waits (a closed terminal on a Slurm
    login node) loses no run that goes on to finish."""
    import subprocess

    folder = reproduce.run_dir(tmp_path / "work", "Pendulum-v1", "sac", 1)
    watcher = subprocess.Popen([sys.executable, "-c", WATCHER, str(ROOT / "benchmarks"), str(tmp_path / "work")])
    deadline = time.time() + 60
    while not (folder / "JOB").exists() and watcher.poll() is None and time.time() < deadline:  # written once the job is submitted
        time.sleep(0.05)
    watcher.kill()  # as the job starts: it sleeps 4 s before it prints
    watcher.wait()
    assert not (folder / "DONE").exists()
    while not (folder / "DONE").exists() and time.time() < deadline:  # before: never, the watcher wrote it
        time.sleep(0.1)
    assert (folder / "DONE").exists() and (folder / "log.txt").read_text() == "trained\n"
    assert (folder / "JOB").read_text().strip().isdigit()  # the job's id, for a later call to ask Slurm about
    monkeypatch.setattr(reproduce, "command", lambda preset, env, method, seed, steps=None: [sys.executable, "-c", TRAIN_4S])
    reproduce.launch(reproduce.Args(envs=("Pendulum-v1",), methods=("sac",), seeds=(1,), preset="quick", launcher="submitit-local",
                                    workdir=str(tmp_path / "work")))  # fmt: skip
    assert "1 runs, 1 already done, 0 to run" in capsys.readouterr().out


def test_runs_whose_earlier_slurm_jobs_are_still_queued_are_not_submitted_again(tmp_path, monkeypatch):
    import submitit

    monkeypatch.setattr(reproduce, "command", lambda preset, env, method, seed, steps=None: [sys.executable, "-c", "pass", str(seed)])
    args = reproduce.Args(envs=("Pendulum-v1",), methods=("sac",), seeds=(1, 2), preset="quick", launcher="slurm",
                          workdir=str(tmp_path / "work"), output=str(tmp_path / "out"))  # fmt: skip
    for seed, job in ((1, "4242"), (2, "4343")):  # what an earlier call, whose reproduce.py has gone, submitted
        folder = reproduce.run_dir(tmp_path / "work", "Pendulum-v1", "sac", seed)
        folder.mkdir(parents=True)
        (folder / "JOB").write_text(f"{job}\n")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    squeue = bin_dir / "squeue"
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setattr(reproduce.shutil, "which", lambda name: f"/usr/bin/{name}")

    class Submitted(Exception):
        pass

    def executor(folder, cluster=None, **kwargs):
        raise Submitted(cluster)

    monkeypatch.setattr(submitit, "AutoExecutor", executor)
    squeue.write_text("#!/bin/sh\necho 4242\necho 999_3\n")  # seed 1's job still runs
    squeue.chmod(0o755)
    with pytest.raises(SystemExit, match=r"^reproduce: error: 1 runs submitted by an earlier call are still in Slurm's queue \(e\.g\. .*seed1, job 4242\);"):
        reproduce.main(args)  # before: submitted again, two jobs training seed 1 in one folder
    squeue.write_text("#!/bin/sh\necho 999_3\n")  # both have left the queue: submitted
    with pytest.raises(Submitted):
        reproduce.main(args)
    squeue.write_text("#!/bin/sh\necho 'slurm_load_jobs error: Unable to contact slurm controller' >&2\nexit 1\n")
    with pytest.raises(SystemExit, match=r"cannot ask Slurm whether the jobs of an earlier call still run \(squeue: slurm_load_jobs error: Unable"):
        reproduce.main(args)


def test_ctrl_c_starts_no_queued_run(tmp_path, monkeypatch):
    monkeypatch.setattr(reproduce, "command", lambda preset, env, method, seed, steps=None: [sys.executable, "-c", "import time; time.sleep(0.3)"])
    real_as_completed = reproduce.as_completed

    def interrupted(futures):  # Ctrl-C as the first run finishes
        yield next(real_as_completed(futures))
        raise KeyboardInterrupt

    monkeypatch.setattr(reproduce, "as_completed", interrupted)
    args = reproduce.Args(envs=("Pendulum-v1",), methods=("sac",), seeds=(1, 2, 3), preset="quick", workdir=str(tmp_path / "work"), workers=1)
    try:
        with pytest.raises(SystemExit, match="^reproduce: interrupted; the same command trains again what has no DONE, from scratch$"):
            reproduce.launch(args)
    except KeyboardInterrupt:  # caught here, or it would end the whole test session
        pytest.fail("the Ctrl-C escaped launch (after the pool had run every queued run)")
    folder = {seed: reproduce.run_dir(tmp_path / "work", "Pendulum-v1", "sac", seed) for seed in (1, 2, 3)}
    assert (folder[1] / "DONE").exists()
    assert not folder[3].exists()  # before: the pool went on to start every queued run, one Ctrl-C each
