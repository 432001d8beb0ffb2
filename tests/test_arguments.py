"""Out-of-range arguments end the parse with a message naming the flag, before anything runs or is written."""

import dataclasses
import math
import os
import subprocess
import sys
import typing

import pytest

from conftest import ROOT, load_script

SCRIPTS = ["sac_continuous", "jirl_sac_continuous", "ppo_il", "trpo_il"]
jetracer = pytest.importorskip("deploy.jetracer")


def numeric_fields(cls) -> list[tuple[str, type]]:
    """(name, int or float) of every int or float field, Optional ones included; bools are not numbers here."""
    hints = typing.get_type_hints(cls)
    fields = []
    for f in dataclasses.fields(cls):
        kinds = [t for t in typing.get_args(hints[f.name]) or (hints[f.name],) if t is not type(None)]
        if kinds in ([int], [float]):
            fields.append((f.name, kinds[0]))
    return fields


ARG_CLASSES = {name: load_script(name).Args for name in SCRIPTS} | {f"deploy {c}": getattr(jetracer, c) for c in ("Run", "Baseline", "Train")}


@pytest.mark.parametrize("label", list(ARG_CLASSES))
def test_every_number_has_a_range(label):
    """-1 for every int field and NaN for every float field is refused, each by its own flag; defaults pass."""
    cls = ARG_CLASSES[label]
    cls()  # the defaults are valid
    fields = numeric_fields(cls)
    assert len(fields) >= 8, fields
    for name, kind in fields:
        bad = -1 if kind is int else math.nan
        with pytest.raises(ValueError, match=f"--{name.replace('_', '-')} must be"):
            cls(**{name: bad})


@pytest.mark.parametrize(
    "script, field, value",
    [
        ("sac_continuous", "exp_name", "ablations/sigma"),  # the run trained, then its model could not be saved
        ("jirl_sac_continuous", "exp_name", ""),
        ("ppo_il", "exp_name", "a/b"),
        ("trpo_il", "exp_name", "a/b"),
        ("sac_continuous", "buffer_size", 0),  # was an IndexError in the first buffer write
        ("sac_continuous", "tau", 1.5),
        ("sac_continuous", "gamma", 1.01),
        ("sac_continuous", "seed", 2**32),  # numpy's global seed
        ("jirl_sac_continuous", "penalty_sigma2", 0.0),
        ("jirl_sac_continuous", "switch_penalty", math.inf),
        ("jirl_sac_continuous", "rl_control_window", 0),  # was a ZeroDivisionError at the first log
        ("ppo_il", "num_minibatches", 0),
        ("ppo_il", "il_value_epochs", 0),  # was a NameError after imitation
        ("trpo_il", "max_kl", 0.0),
        ("trpo_il", "line_search_shrinking_factor", 1.0),
        ("trpo_il", "num_steps", 1),  # one step's advantage has no std: the policy never moved
    ],
)
def test_edges_of_the_ranges(script, field, value):
    with pytest.raises(ValueError, match=f"--{field.replace('_', '-')} must be"):
        load_script(script).Args(**{field: value})


def test_every_problem_is_named_at_once():
    sac = load_script("sac_continuous")
    with pytest.raises(ValueError) as err:
        sac.Args(batch_size=0, q_lr=-1.0, policy_frequency=0)
    assert str(err.value).count("must be") == 3


def test_valid_values_at_the_edges_pass():
    load_script("sac_continuous").Args(gamma=1.0, tau=1.0, learning_starts=0, seed=0)
    load_script("jirl_sac_continuous").Args(gate_c=0.0, gate_k=0, guidance_steps=0, handover_tolerance=0.0)
    load_script("ppo_il").Args(target_kl=None, ent_coef=0.0)
    load_script("trpo_il").Args(num_steps=1, norm_adv=False)


def test_deploy_checks_the_car_safety_settings():
    with pytest.raises(ValueError, match="--max-steering-rate must be > 0"):
        jetracer.Run(max_steering_rate=-1.0)  # once drove: a negative rate limit turned the wheels by itself
    with pytest.raises(ValueError, match="steering change per step must be > 0"):
        jetracer.SafetyFilter(jetracer.ActionMapping(), max_steering_rate=-1.0, period=0.05)
    with pytest.raises(ValueError, match="--min-throttle must be in"):
        jetracer.Baseline(min_throttle=0.7, max_throttle=0.6)
    with pytest.raises(ValueError, match=r"--watchdog-ms must be longer than the link's send period \(20 ms\)"):
        jetracer.Baseline(watchdog_ms=20)  # 20 Hz control, 2.5 frames per period: one frame every 20 ms
    jetracer.Baseline(watchdog_ms=21)


@pytest.mark.parametrize(
    "cls, field, bad, good",
    [
        ("Baseline", "control_hz", math.inf, 100.0),  # a period of 0: no rate limit on the steering
        ("Baseline", "max_throttle", 1.01, 1.0),
        ("Baseline", "max_steering_rate", 0.0, 0.1),  # the wheel could never turn
        ("Baseline", "watchdog_ms", 65536, 65535),  # the protocol's field is 16 bits
        ("Baseline", "seed", 2**32, 2**32 - 1),
        ("Run", "steps", 0, 1),
        ("Baseline", "steps", 0, 1),
        ("Train", "total_steps", 0, 1),
        ("Train", "gradient_steps", 0, 1),
    ],
)
def test_deploy_ranges_at_their_edges(cls, field, bad, good):
    with pytest.raises(ValueError, match=f"--{field.replace('_', '-')} must be"):
        getattr(jetracer, cls)(**{field: bad})
    getattr(jetracer, cls)(**{field: good})


def test_the_safety_filter_refuses_a_steering_step_of_zero_or_infinity():
    for rate, period in ((0.0, 0.05), (8.0, 0.0), (math.inf, 0.05)):
        with pytest.raises(ValueError, match="steering change per step must be > 0"):
            jetracer.SafetyFilter(jetracer.ActionMapping(), max_steering_rate=rate, period=period)


def test_deploy_train_refuses_a_checkpoint_that_is_no_file_path(tmp_path):
    for bad in ("", str(tmp_path), f"{tmp_path / 'new'}/"):  # before: "... holds an earlier training", or a failed first save
        with pytest.raises(ValueError, match=r"--checkpoint must be a file's path \(not empty, not a directory\)"):
            jetracer.Train(checkpoint=bad)
    jetracer.Train(checkpoint=str(tmp_path / "train.pt"))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "command, message",
    [
        (["sac_continuous.py", "--buffer-size", "0"], "--buffer-size must be >= 1, got 0"),
        (["jirl_sac_continuous.py", "--penalty-sigma2", "-0.1"], "--penalty-sigma2 must be > 0, got -0.1"),
        (["ppo_il.py", "--total-timesteps", "-5"], "--total-timesteps must be >= 1, got -5"),
        (["trpo_il.py", "--max-kl", "0"], "--max-kl must be > 0, got 0.0"),
        (["-m", "deploy.jetracer", "train", "--train-every", "0"], "--train-every must be >= 1, got 0"),
        (["-m", "deploy.jetracer", "train", "--jirl.tau", "nan"], "--tau must be in (0, 1], got nan"),
    ],
)
def test_the_command_line_reports_and_writes_nothing(tmp_path, command, message):
    command = [str(ROOT / command[0]), *command[1:]] if command[0].endswith(".py") else command
    env = dict(os.environ, PYTHONPATH=str(ROOT), COLUMNS="300")  # one line of tyro's box holds the message
    out = subprocess.run([sys.executable, *command], cwd=tmp_path, capture_output=True, text=True, timeout=60, env=env)
    assert out.returncode == 2, out.stderr
    assert message in out.stderr and "Traceback" not in out.stderr, out.stderr
    assert list(tmp_path.iterdir()) == [], "nothing is written before the arguments are checked"
    if command[:2] == ["-m", "deploy.jetracer"]:  # the help it points to is a command to run, not the module's file
        assert "see python -m deploy.jetracer --help" in out.stderr and str(ROOT) not in out.stderr, out.stderr


def test_a_controller_that_refuses_to_arm_is_a_one_line_error(tmp_path):
    """The mock controller accepts watchdog periods of 50-2000 ms; the host's own rule lets 30 through."""
    command = ["-m", "deploy.jetracer", "baseline", "--watchdog-ms", "30", "--log-dir", str(tmp_path / "runs")]
    out = subprocess.run([sys.executable, *command], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode != 0
    assert "did not arm with --watchdog-ms 30; it accepts 50-2000 ms" in out.stderr and "Traceback" not in out.stderr, out.stderr
    assert not (tmp_path / "runs").exists(), "no log of a session that never armed"
