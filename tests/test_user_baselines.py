"""A user's baseline (--baseline module:function) that returns the wrong thing is a clear error, in every script."""

import os

import gymnasium as gym
import numpy as np
import pytest

from conftest import ROOT, load_script
from test_sac_script import run_script

SCRIPTS = ["sac_continuous", "jirl_sac_continuous", "ppo_il", "trpo_il"]
USER_BASELINES = """
import numpy as np

def bare_number(obs):  # Pendulum's one torque as a plain float, not an array
    return -1.0 * float(obs[2])

def nan(obs):
    return np.array([np.nan])

def two_values(obs):
    return np.zeros(2)

not_a_function = 3.14
"""


@pytest.mark.parametrize("script", SCRIPTS)
def test_check_baseline_action(script):
    check = load_script(script).check_baseline_action
    space = gym.spaces.Box(-2.0, 2.0, shape=(1,), dtype=np.float32)
    assert check(0.5, space).shape == (1,) and check(0.5, space)[0] == 0.5  # a bare number for a 1-D space
    action = np.array([0.25], dtype=np.float32)
    assert check(action, space).dtype == np.float32 and check(action, space)[0] == action[0]  # values and dtype kept
    for bad in (np.array([np.inf]), np.zeros(2), "left", [None]):
        with pytest.raises(ValueError, match="expected 1 finite number"):
            check(bad, space)
    assert check([[1.0, 2.0]], gym.spaces.Box(-5, 5, shape=(2,))).shape == (2,)


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_baseline_that_is_not_callable_is_refused_when_loaded(script, tmp_path, monkeypatch):
    (tmp_path / "user_baselines.py").write_text(USER_BASELINES)
    monkeypatch.syspath_prepend(str(tmp_path))
    module = load_script(script)
    with pytest.raises(ValueError, match="'user_baselines:not_a_function' is a float, not a function or class"):
        module.load_baseline("user_baselines:not_a_function", "Pendulum-v1")
    assert np.isnan(module.load_baseline("user_baselines:nan", "Pendulum-v1")(np.zeros(3))[0])  # loads; fails when used


@pytest.mark.parametrize(
    "script, baseline, message",
    [
        ("jirl_sac_continuous", "nan", "the baseline returned array([nan]); expected 1 finite number(s) in env units"),
        ("sac_continuous", "two_values", "the baseline returned array([0., 0.]); expected 1 finite number(s)"),
        ("ppo_il", "nan", "the baseline returned array([nan])"),  # the imitation phase's rollouts
    ],
)
def test_a_wrong_action_ends_the_run_with_one_line(script, baseline, message, tmp_path):
    (tmp_path / "user_baselines.py").write_text(USER_BASELINES)
    env = dict(os.environ, PYTHONPATH=f"{tmp_path}{os.pathsep}{ROOT}")
    out = run_script(ROOT / f"{script}.py", ["--baseline", f"user_baselines:{baseline}", "--total-timesteps", "10"], tmp_path, env)
    assert out.returncode != 0 and message in out.stderr, out.stderr
    assert len(out.stderr.strip().splitlines()) == 1, out.stderr


def test_a_bare_number_is_a_pendulum_action(tmp_path):
    (tmp_path / "user_baselines.py").write_text(USER_BASELINES)
    env = dict(os.environ, PYTHONPATH=f"{tmp_path}{os.pathsep}{ROOT}")
    args = ["--baseline", "user_baselines:bare_number", "--total-timesteps", "250", "--learning-starts", "200",
            "--hidden-size", "16", "--batch-size", "16", "--baseline-eval-episodes", "1"]  # fmt: skip
    out = run_script(ROOT / "jirl_sac_continuous.py", args, tmp_path, env)
    assert out.returncode == 0, out.stderr
    assert "baseline regret estimator: paired" in out.stdout
