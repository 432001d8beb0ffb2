"""A user's own baseline and env (`--baseline module:function`, `--env-id module:Env-v0`) in every script: what runs, and the one-line errors for what cannot."""

import os
import shutil
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.envs.classic_control.pendulum import PendulumEnv

import warm_python
from conftest import ROOT, load_script
from test_sac_script import run_script, scalars

SCRIPTS = ["sac_continuous", "jirl_sac_continuous", "ppo_il", "trpo_il"]
# a few hundred steps each: two whole 200-step training episodes, with updates (SAC's and JIRL's from step 300)
BUDGETS = {"sac_continuous": ["--total-timesteps", "450", "--learning-starts", "300", "--batch-size", "16"],
           "jirl_sac_continuous": ["--total-timesteps", "450", "--learning-starts", "300", "--batch-size", "16"],
           "ppo_il": ["--num-steps", "256", "--total-timesteps", "512", "--il-steps", "400", "--il-max-epochs", "5"],
           "trpo_il": ["--num-steps", "256", "--total-timesteps", "512", "--il-steps", "400", "--il-max-epochs", "5"]}  # fmt: skip
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
    with pytest.raises(ValueError, match="expected 2 finite number"):  # one dimension's NaN is enough
        check([1.0, np.nan], gym.spaces.Box(-5, 5, shape=(2,)))
    # beyond the bounds: clipped to them, as the agent's action always is
    assert check(3.0, space)[0] == 2.0 and check(np.array([-7.0], dtype=np.float32), space).tolist() == [-2.0]
    assert check(np.array([-7.0], dtype=np.float32), space).dtype == np.float32
    asymmetric = gym.spaces.Box(np.array([0.0, -5.0], np.float32), np.array([2.0, 1.0], np.float32))
    assert check([5.0, -2.0], asymmetric).tolist() == [2.0, -2.0] and check([-1.0, 9.0], asymmetric).tolist() == [0.0, 1.0]


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_baseline_that_is_not_callable_is_refused_when_loaded(script, tmp_path, monkeypatch):
    (tmp_path / "user_baselines.py").write_text(USER_BASELINES)
    monkeypatch.syspath_prepend(str(tmp_path))
    module = load_script(script)
    with pytest.raises(ValueError, match="'user_baselines:not_a_function' is a float, not a function or class"):
        module.load_baseline("user_baselines:not_a_function", "Pendulum-v1")
    assert np.isnan(module.load_baseline("user_baselines:nan", "Pendulum-v1")(np.zeros(3))[0])  # loads; fails when used


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_baseline_that_refuses_its_settings_is_named_and_a_bug_in_it_keeps_its_traceback(script, tmp_path, monkeypatch):
    (tmp_path / "refusing_module.py").write_text('raise ValueError("set BASELINE_GAIN first")\n')
    (tmp_path / "user_controllers.py").write_text(
        "class Refusing:\n    def __init__(self):\n        raise ValueError('gain must be positive')\n\n"
        "class Buggy:\n    def __init__(self):\n        self.gain = self.gian\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    load = load_script(script).load_baseline
    with pytest.raises(ValueError, match=r"^cannot load baseline 'refusing_module:act': set BASELINE_GAIN first$"):
        load("refusing_module:act", "Pendulum-v1")
    with pytest.raises(ValueError, match=r"^cannot load baseline 'user_controllers:Refusing': gain must be positive$"):
        load("user_controllers:Refusing", "Pendulum-v1")
    with pytest.raises(AttributeError, match="gian"):  # the user's own bug: not dressed up as a bad --baseline
        load("user_controllers:Buggy", "Pendulum-v1")
    from envs.baselines import load_baseline  # python -m envs.baselines --baseline ...

    with pytest.raises(ValueError, match=r"^cannot import baseline module 'refusing_module': set BASELINE_GAIN first$"):
        load_baseline("refusing_module:act")
    with pytest.raises(ValueError, match=r"^cannot make baseline 'user_controllers:Refusing': gain must be positive$"):
        load_baseline("user_controllers:Refusing")
    with pytest.raises(AttributeError, match="gian"):
        load_baseline("user_controllers:Buggy")


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


@pytest.mark.parametrize("script", ["jirl_sac_continuous", "ppo_il", "trpo_il"])
def test_a_dimension_with_equal_bounds_is_0_in_policy_units_and_the_rest_unchanged(script):
    module = load_script(script)
    low, high = np.array([-2.0, 0.5], dtype=np.float32), np.array([2.0, 0.5], dtype=np.float32)
    for action in ([1.0, 0.5], [1.0, 7.0]):  # the fixed dimension holds one value, whatever the baseline says
        policy = module.to_policy_units(np.array(action), low, high)
        np.testing.assert_array_equal(policy, [0.5, 0.0])
        np.testing.assert_array_equal(module.to_env_units(policy, low, high), [1.0, 0.5])
    rng = np.random.default_rng(0)
    for _ in range(200):  # elsewhere bit for bit the formula the benchmarks ran with
        low = rng.uniform(-5, 0, size=3).astype(np.float32)
        high = low + rng.uniform(0.01, 5, size=3).astype(np.float32)
        action = rng.uniform(low - 1, high + 1)
        np.testing.assert_array_equal(module.to_policy_units(action, low, high), np.clip(2.0 * (action - low) / (high - low) - 1.0, -1.0, 1.0))


FIXED_DIMENSION_ENV = """
import gymnasium as gym
import numpy as np


class PendulumWithAFixedInput(gym.Env):
    '''Pendulum with a second action input fixed by its bounds; no render_mode argument, as in many users' envs.'''

    def __init__(self):
        self.pendulum = gym.make("Pendulum-v1").unwrapped
        self.observation_space = self.pendulum.observation_space
        self.action_space = gym.spaces.Box(np.array([-2.0, 0.5], np.float32), np.array([2.0, 0.5], np.float32))

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self.pendulum.reset(seed=seed)

    def step(self, action):
        if not np.all(np.isfinite(action)):
            raise RuntimeError(f"a non-finite action reached the env: {action}")
        return self.pendulum.step(np.asarray(action[:1]))


gym.register("FixedInput-v0", entry_point=PendulumWithAFixedInput, max_episode_steps=200)


def baseline(obs):  # damping only: no import of this project, so a script copied alone runs it too
    return np.array([-float(obs[2]), 0.5])
"""


@pytest.mark.parametrize("script, alone", [*((script, False) for script in SCRIPTS), ("jirl_sac_continuous", True)])
def test_every_script_runs_an_env_without_render_mode_and_with_a_fixed_action_dimension(script, alone, tmp_path):
    (tmp_path / "fixed_input.py").write_text(FIXED_DIMENSION_ENV)
    # no PYTHONPATH: the user's module is found in the current directory, the script run by its path from elsewhere
    env = {key: value for key, value in os.environ.items() if key != "PYTHONPATH"}
    path = ROOT / f"{script}.py"
    if alone:  # without envs/, the script makes the env with gymnasium itself
        path = Path(shutil.copy(path, tmp_path))
    if script in ("ppo_il", "trpo_il"):
        budget = ["--num-steps", "256", "--total-timesteps", "256", "--il-steps", "400", "--il-max-epochs", "5"]
    else:
        budget = ["--total-timesteps", "300", "--learning-starts", "100", "--batch-size", "16"]
    args = ["--env-id", "fixed_input:FixedInput-v0", "--baseline", "fixed_input:baseline", "--hidden-size", "16",
            "--baseline-eval-episodes", "1", *budget]  # fmt: skip
    out = run_script(path, args, tmp_path, env)
    assert out.returncode == 0, out.stderr
    assert "baseline regret estimator: paired" in out.stdout


STATEFUL_BASELINE = """
import os

import numpy as np


class Stateful:
    '''Writes, at each call, 1 if reset() came since its last call, else 0.'''

    def __init__(self):
        self.fresh, self.log = False, open(os.environ["BASELINE_LOG"], "a")

    def reset(self):
        self.fresh = True

    def __call__(self, obs):
        self.log.write("1" if self.fresh else "0")
        self.log.flush()
        self.fresh = False
        return np.array([-float(obs[2])])
"""


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_stateful_baseline_is_reset_before_every_episode_it_acts_in_and_at_no_other_call(script, tmp_path):
    # every episode the baseline acts in (measured, paired, imitated, or in JIRL's loop) lasts Pendulum-v1's 200 steps, so its
    # calls fall in blocks of 200 (JIRL's last episode cut short by the budget), each of which must start clean
    (tmp_path / "stateful_baseline.py").write_text(STATEFUL_BASELINE)
    log = tmp_path / "calls.txt"
    env = dict(os.environ, PYTHONPATH=f"{tmp_path}{os.pathsep}{ROOT}", BASELINE_LOG=str(log))
    args = ["--baseline", "stateful_baseline:Stateful", "--hidden-size", "16", "--baseline-eval-episodes", "2", *BUDGETS[script]]
    out = run_script(ROOT / f"{script}.py", args, tmp_path, env)
    assert out.returncode == 0, out.stderr
    calls = log.read_text()
    # the 2 measured episodes, the first paired one and one paired to each episode end (2 in each script); SAC's loop never asks
    # the baseline, JIRL's asks it at each of its 450 steps, PPO+IL's and TRPO+IL's imitation phase runs it for 2 episodes
    expected = {"sac_continuous": 400 + 200 + 400, "jirl_sac_continuous": 400 + 200 + 400 + 450, "ppo_il": 400 + 200 + 400 + 400, "trpo_il": 1400}
    assert len(calls) == expected[script]
    assert [i for i, fresh in enumerate(calls) if fresh == "1"] == list(range(0, len(calls), 200))


@pytest.mark.parametrize("script", SCRIPTS)
def test_the_baseline_is_measured_on_the_evaluation_seeds_and_the_unpaired_regret_is_against_it(script, tmp_path):
    # the same reset seeds as eval/episodic_return's, so the two returns compare; none of them a training episode's
    from envs import BASELINES, make_env
    from envs.baselines import rollout

    offset = load_script(script).EVAL_SEED_OFFSET
    assert offset == 1_000_000
    traces = [rollout(make_env("Pendulum-v1"), BASELINES["Pendulum-v1"], 1 + offset + i) for i in range(3)]
    args = ["--regret-estimator", "unpaired", "--baseline-eval-episodes", "3", "--hidden-size", "16", *BUDGETS[script]]
    out = run_script(ROOT / f"{script}.py", args, tmp_path)
    assert out.returncode == 0, out.stderr
    (run_dir,) = (tmp_path / "runs").iterdir()
    logged = scalars(run_dir)
    per_step = sum(t.sum() for t in traces) / sum(len(t) for t in traces)
    assert logged["charts/baseline_return"] == [pytest.approx(np.mean([t.sum() for t in traces]), rel=1e-6)]
    assert logged["charts/baseline_reward_per_step"] == [pytest.approx(per_step, rel=1e-6)]
    returns, lengths = np.array(logged["charts/episodic_return"]), np.array(logged["charts/episodic_length"])
    assert len(returns) == 2 and lengths.tolist() == [200, 200]
    # each episode's regret against a baseline earning its measured reward per step: max(0, b L - R)
    np.testing.assert_allclose(logged["charts/baseline_regret"], np.cumsum(np.maximum(0.0, per_step * lengths - returns)), rtol=1e-5)
    assert logged["charts/baseline_regret"][-1] > 0


UNCLIPPED_ENV = """
import gymnasium as gym
import numpy as np


class Unclipped(gym.Env):
    '''Applies whatever action it is given, as many users' envs do: reward -|a|^2 a step, 20 steps.'''

    def __init__(self):
        self.observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.action_space = gym.spaces.Box(np.array([-1.0, 0.0], np.float32), np.array([1.0, 4.0], np.float32))

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(2, np.float32), {}

    def step(self, action):
        return np.zeros(2, np.float32), -float(np.sum(np.square(action))), False, False, {}


gym.register("Unclipped-v0", entry_point=Unclipped, max_episode_steps=20)


def saturating(obs):  # beyond both bounds: clipped to (1, 0) it earns -1 a step; as given, -25
    return np.array([3.0, -4.0])
"""


@pytest.mark.parametrize("script", SCRIPTS)
def test_the_baseline_is_measured_as_it_acts_under_jirl_clipped_to_the_bounds(script, tmp_path, monkeypatch):
    (tmp_path / "unclipped_env.py").write_text(UNCLIPPED_ENV)
    monkeypatch.syspath_prepend(str(tmp_path))
    import unclipped_env

    _, rewards = load_script(script).baseline_rollout(gym.make("unclipped_env:Unclipped-v0"), unclipped_env.saturating, seed=0)
    assert rewards.tolist() == [-1.0] * 20


def test_jirl_logs_the_return_of_the_baseline_it_hands_control_to(tmp_path):
    (tmp_path / "unclipped_env.py").write_text(UNCLIPPED_ENV)
    env = {key: value for key, value in os.environ.items() if key != "PYTHONPATH"}
    args = ["--env-id", "unclipped_env:Unclipped-v0", "--baseline", "unclipped_env:saturating", "--hidden-size", "16",
            "--batch-size", "16", "--total-timesteps", "200", "--learning-starts", "100", "--baseline-eval-episodes", "2"]  # fmt: skip
    out = run_script(ROOT / "jirl_sac_continuous.py", args, tmp_path, env)
    assert out.returncode == 0, out.stderr
    (run_dir,) = (tmp_path / "runs").iterdir()
    logged = scalars(run_dir)
    assert logged["charts/baseline_return"] == [-20.0]  # 20 steps of -1: clipped, not the -25 a step asked for
    returns = np.array(logged["charts/episodic_return"])
    assert list(returns[:5]) == [-20.0] * 5  # the episodes the baseline drove earned that too
    # the paired regret is against that baseline: max(0, -20 - R) an episode (against -500, the agent's worse episodes were free)
    np.testing.assert_allclose(logged["charts/baseline_regret"], np.cumsum(np.maximum(0.0, -20.0 - returns)), rtol=1e-5)
    assert logged["charts/baseline_regret"][-1] > 1.0  # the agent acted and did worse than the baseline


SEEDED_ONCE_ENV = """
import gymnasium as gym
from gymnasium.envs.classic_control.pendulum import PendulumEnv


class SeededOnce(PendulumEnv):
    '''Pendulum seeded once, when made, as a simulator configured by a file is: reset ignores its seed, and
    the n-th env a process makes starts from seed n.'''

    made = 0

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        SeededOnce.made += 1
        self.own_seed = SeededOnce.made

    def reset(self, *, seed=None, options=None):
        seed, self.own_seed = self.own_seed, None
        return super().reset(seed=seed, options=options)


gym.register("SeededOnce-v0", entry_point=SeededOnce, max_episode_steps=200)
"""


@pytest.mark.parametrize("script", SCRIPTS)
def test_an_env_that_ignores_its_reset_seed_is_refused_by_the_paired_estimator_and_measured_unpaired_by_auto(script, tmp_path):
    """The paired estimator runs the baseline from each training episode's reset seed; an env that
    ignores it would compare episodes from different states. The scripts see it at the first episode."""
    (tmp_path / "seeded_once.py").write_text(SEEDED_ONCE_ENV)
    args = ["--env-id", "seeded_once:SeededOnce-v0", "--baseline", "envs.pendulum:pendulum_swing_up", "--hidden-size", "16",
            "--baseline-eval-episodes", "2", *BUDGETS[script]]  # fmt: skip
    refused = run_script(ROOT / f"{script}.py", [*args, "--regret-estimator", "paired"], tmp_path)
    assert refused.returncode == 1
    assert refused.stderr.strip().splitlines() == [f"{script}: error: seeded_once:SeededOnce-v0 does not reproduce a seeded reset;"
                                                   " use --regret-estimator unpaired"], refused.stderr  # fmt: skip
    (run_dir,) = (tmp_path / "runs").iterdir()
    assert "charts/episodic_return" not in scalars(run_dir), "refused before any training step"
    shutil.rmtree(tmp_path / "runs")

    out = run_script(ROOT / f"{script}.py", args, tmp_path)  # --regret-estimator auto
    assert out.returncode == 0, out.stderr
    assert "baseline regret estimator: unpaired" in out.stdout
    (run_dir,) = (tmp_path / "runs").iterdir()
    logged = scalars(run_dir)
    per_step = logged["charts/baseline_reward_per_step"][0]
    returns, lengths = np.array(logged["charts/episodic_return"]), np.array(logged["charts/episodic_length"])
    assert lengths.tolist() == [200, 200]
    # each episode's regret against a baseline earning its measured reward per step: max(0, b L - R)
    np.testing.assert_allclose(logged["charts/baseline_regret"], np.cumsum(np.maximum(0.0, per_step * lengths - returns)), rtol=1e-5)


SCENARIO_ENV = """
import os

import gymnasium as gym
from gymnasium.envs.classic_control.pendulum import PendulumEnv


class ScenarioPendulum(PendulumEnv):
    '''Pendulum served by a scenario server that goes away during the run: from the FAIL_AT-th reset from
    seed 1,000,001 (the first evaluation episode's at --seed 1) on, that reset raises.'''

    resets = 0

    def reset(self, *, seed=None, options=None):
        if seed == 1_000_001:
            ScenarioPendulum.resets += 1
            if ScenarioPendulum.resets >= int(os.environ["FAIL_AT"]):
                raise ConnectionError("the scenario server is gone")
        return super().reset(seed=seed, options=options)


gym.register("Scenario-v0", entry_point=ScenarioPendulum, max_episode_steps=200)
"""
# seed 1,000,001 is reset by the baseline's measurement, then by each evaluation: PPO+IL's and TRPO+IL's of
# the cloned policy first, and last every script's of the trained one
FINAL_EVALUATION = {"sac_continuous": 2, "jirl_sac_continuous": 2, "ppo_il": 3, "trpo_il": 3}


@pytest.mark.parametrize("script", SCRIPTS)
def test_an_env_failing_in_the_final_evaluation_ends_the_run_with_its_model_and_logs_kept(script, tmp_path):
    (tmp_path / "scenario.py").write_text(SCENARIO_ENV)
    line = SCENARIO_ENV.splitlines().index('                raise ConnectionError("the scenario server is gone")') + 1
    args = ["--env-id", "scenario:Scenario-v0", "--baseline", "envs.pendulum:pendulum_swing_up", "--hidden-size", "16",
            "--baseline-eval-episodes", "1", "--eval-episodes", "1", "--save-model", *BUDGETS[script]]  # fmt: skip
    out = run_script(ROOT / f"{script}.py", args, tmp_path, dict(os.environ, FAIL_AT=str(FINAL_EVALUATION[script])))
    assert out.returncode == 1
    assert out.stderr.strip().splitlines()[-1] == (f"{script}: error: scenario:Scenario-v0 raised ConnectionError (scenario.py, line {line})"
                                                   " at reset seed 1000001: the scenario server is gone"), out.stderr  # fmt: skip
    assert "ConnectionError: the scenario server is gone" in out.stderr  # the env's own traceback, where it arose
    (run_dir,) = (tmp_path / "runs").iterdir()
    model = run_dir / f"{script}.cleanrl_model"
    assert f"model saved to runs/{run_dir.name}/{script}.cleanrl_model" in out.stdout and "eval:" not in out.stdout
    assert ("cloned policy: mean return" in out.stdout) == script.endswith("_il")  # the evaluation before the server went
    assert np.isfinite(load_script(script).evaluate(str(model), "Pendulum-v1", 1, 0)[0])
    logged = scalars(run_dir)  # the training's logs, written out although the run ended on an error
    assert logged["charts/episodic_length"] == [200, 200] and len(logged["charts/baseline_regret"]) == 2
    assert "eval/episodic_return" not in logged


# every make_env: each script's with envs/ and with its own gym.make (fallback, as when copied alone), and envs'
EVERY_MAKE_ENV = [*((script, fallback) for script in SCRIPTS for fallback in (False, True)), ("envs", False)]


def make_env_of(script: str, fallback: bool, monkeypatch):
    if script == "envs":
        from envs import make_env

        return make_env
    module = load_script(script)
    if fallback:
        monkeypatch.setattr(module, "project_make_env", None)
    return module.make_env


@pytest.mark.parametrize("script, fallback", EVERY_MAKE_ENV)
def test_make_env_seeds_the_action_space_as_cleanrl_does(script, fallback, monkeypatch):
    """The scripts draw their own random actions, but an env or wrapper that samples its action space
    (a random disturbance) repeats with the run's seed, also in a script copied alone."""
    make_env = make_env_of(script, fallback, monkeypatch)
    draws = []
    for seed in (5, 5, 6):
        env = make_env("Pendulum-v1", seed)
        draws.append(env.action_space.sample())
        env.close()
    assert draws[0] == draws[1] != draws[2]


@pytest.mark.parametrize("script, fallback", EVERY_MAKE_ENV)
def test_an_env_id_whose_module_does_not_import_is_a_one_line_error(script, fallback, monkeypatch):
    make_env = make_env_of(script, fallback, monkeypatch)
    with pytest.raises(ValueError, match=r"^env id 'no_such_module:Env-v0' needs a module that does not import: No module named 'no_such_module'"):
        make_env("no_such_module:Env-v0", 0)


@pytest.mark.parametrize("script, fallback", EVERY_MAKE_ENV)
def test_an_env_that_refuses_its_settings_is_named(script, fallback, tmp_path, monkeypatch):
    (tmp_path / "refusing_env.py").write_text(
        "import gymnasium as gym\n\nclass Refusing(gym.Env):\n    def __init__(self, **kwargs):\n"
        "        raise ValueError('track file missing')\n\ngym.register('Refusing-v0', entry_point='refusing_env:Refusing')\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    make_env = make_env_of(script, fallback, monkeypatch)
    with pytest.raises(ValueError) as raised:  # before, the bare "track file missing": which part of the run said it?
        make_env("refusing_env:Refusing-v0", 0)
    assert str(raised.value) == "cannot make env 'refusing_env:Refusing-v0': track file missing"


# gym.make and importlib fail on these with "Empty module name", "too many values to unpack" or a TypeError traceback
MALFORMED = [":Env-v0", ".relative:Env-v0", "..x:Env-v0", "a:b:c", "x:"]


@pytest.mark.parametrize("script, fallback", EVERY_MAKE_ENV)
@pytest.mark.parametrize("env_id", MALFORMED)
def test_a_malformed_module_env_id_is_a_one_line_error_naming_the_form(script, fallback, env_id, monkeypatch):
    make_env = make_env_of(script, fallback, monkeypatch)
    expected = f"env id {env_id!r} must be a registered id or look like 'module:Env-v0' (an absolute module name, one colon)"
    with pytest.raises(ValueError) as raised:
        make_env(env_id, 0)
    assert str(raised.value) == expected


@pytest.mark.parametrize("script", [*SCRIPTS, "envs"])
@pytest.mark.parametrize("spec", [":f", "math:", ".relative:f", "..x:f", "math:pi:e", "math"])
def test_a_malformed_baseline_spec_is_a_one_line_error_naming_the_form(script, spec):
    from envs import load_baseline

    with pytest.raises(ValueError) as raised:
        load_baseline(spec) if script == "envs" else load_script(script).load_baseline(spec, "Pendulum-v1")
    assert str(raised.value) == f"baseline {spec!r} must look like 'module:function' (an absolute module name, one colon)"


# Pendulum never terminates. Its episodes here end at this many steps, far beyond the limit a test sets, which must
# stop them first: a script without its guard then fails the test instead of hanging it.
BACKSTOP = 10_000


def long_pendulum() -> gym.Env:
    return gym.wrappers.TimeLimit(PendulumEnv(), BACKSTOP)


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_baseline_episode_that_never_ends_is_an_error_not_a_hang(script, monkeypatch):
    from envs.pendulum import pendulum_swing_up

    module = load_script(script)
    monkeypatch.setattr(module, "EPISODE_LIMIT", 50)
    _, rewards = module.baseline_rollout(gym.wrappers.TimeLimit(PendulumEnv(), 50), pendulum_swing_up, 0)
    assert len(rewards) == 50  # an episode as long as the limit is fine
    with pytest.raises(ValueError, match=r"^the baseline's episode from reset seed 3 did not end within 50 steps; give the env a time limit"):
        module.baseline_rollout(long_pendulum(), pendulum_swing_up, 3)
    if script in ("ppo_il", "trpo_il"):  # the imitation phase's rollouts
        with pytest.raises(ValueError, match="did not end within 50 steps; imitation needs whole episodes"):
            module.collect_baseline_data(long_pendulum(), pendulum_swing_up, 100, 0, 0.99)


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_baseline_that_only_intervenes_cannot_be_measured_or_imitated_and_says_so(script):
    """None (no intervention) has no action to apply: the measurement names it, with the flag that
    skips it, instead of reporting None as a malformed action; so does the imitation phase."""
    module, calls = load_script(script), []

    def after_three_steps(obs):
        calls.append(obs)
        return None if len(calls) > 3 else np.zeros(1)

    with pytest.raises(ValueError, match=r"^the baseline returned None \(it only intervenes\), so it cannot be measured; use --regret-estimator off$"):
        module.baseline_rollout(gym.wrappers.TimeLimit(PendulumEnv(), 200), after_three_steps, 0)
    assert len(calls) == 4, "three steps applied, the fourth call's None named"
    if script in ("ppo_il", "trpo_il"):
        with pytest.raises(ValueError, match=r"^the baseline returned None \(it only intervenes\); imitation needs its actions everywhere$"):
            module.collect_baseline_data(gym.wrappers.TimeLimit(PendulumEnv(), 200), lambda obs: None, 100, 0, 0.99)


def test_jirl_names_every_flag_an_endless_baseline_episode_needs(tmp_path):
    (tmp_path / "endless.py").write_text(
        "import gymnasium as gym\n"
        "gym.register('EndlessPendulum-v0', entry_point='gymnasium.envs.classic_control.pendulum:PendulumEnv')  # no time limit\n"
    )  # fmt: skip
    args = ["--env-id", "endless:EndlessPendulum-v0", "--baseline", "envs.pendulum:pendulum_swing_up", "--baseline-eval-episodes", "1"]
    out = warm_python.run([str(ROOT / "jirl_sac_continuous.py"), *args], cwd=tmp_path,
                          timeout=120)  # a hang, as before the limit, fails here  # fmt: skip
    assert out.returncode != 0 and len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert out.stderr.strip().endswith("did not end within 100,000 steps; give the env a time limit (max_episode_steps)"
                                       " or use --regret-estimator off and --guidance-schedule geometric"), out.stderr


@pytest.mark.parametrize("script", SCRIPTS)
def test_an_evaluation_episode_that_never_ends_is_an_error_not_a_hang(script, tmp_path, monkeypatch):
    if "LongPendulum-v0" not in gym.registry:
        gym.register("LongPendulum-v0", entry_point="gymnasium.envs.classic_control.pendulum:PendulumEnv", max_episode_steps=BACKSTOP)
    module = load_script(script)
    monkeypatch.setattr(module, "EPISODE_LIMIT", 200)  # Pendulum-v1's own time limit
    env, path = module.make_env("LongPendulum-v0", 0), str(tmp_path / "policy.cleanrl_model")
    if script in ("ppo_il", "trpo_il"):
        module.save_checkpoint(path, "LongPendulum-v0", env, module.Agent(3, 1, 16), None, module.Args(hidden_size=16))
    else:
        module.save_checkpoint(path, "LongPendulum-v0", env, module.Actor(3, 1, 16), module.SoftQNetwork(3, 1, 16), module.Args(hidden_size=16))
    with pytest.raises(ValueError, match=r"^evaluation episode 0 did not end within 200 steps; give the env a time limit \(max_episode_steps\)$"):
        module.evaluate(path, "LongPendulum-v0", 2, 1)
    assert module.evaluate(path, "Pendulum-v1", 1, 1)[0] < 0  # an episode as long as the limit is fine


def test_envs_baselines_measures_a_baseline_as_the_scripts_apply_it(tmp_path, monkeypatch):
    from envs import rollout

    (tmp_path / "unclipped_env.py").write_text(UNCLIPPED_ENV)
    monkeypatch.syspath_prepend(str(tmp_path))
    import unclipped_env

    assert rollout(gym.make("unclipped_env:Unclipped-v0"), unclipped_env.saturating, seed=0).tolist() == [-1.0] * 20
    assert rollout(gym.make("CartPole-v1"), lambda obs: 1, seed=0).sum() > 0  # a Discrete space takes the action as given


DRIFT_ENV = """
import gymnasium as gym
import numpy as np


class Drift(gym.Env):
    '''The state is the sum of the actions applied so far, unclipped by the env; reward -|state|, 10 steps.'''

    def __init__(self):
        self.observation_space = gym.spaces.Box(-100.0, 100.0, (1,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x = 0.0
        return np.array([self.x], np.float32), {}

    def step(self, action):
        self.x += float(action[0])
        return np.array([self.x], np.float32), -abs(self.x), False, False, {}


gym.register("Drift-v0", entry_point=Drift, max_episode_steps=10)


def saturating(obs):  # asks for 3 a step: the clipped baseline drifts by 1
    return np.array([3.0])
"""


@pytest.mark.parametrize("script", ["ppo_il", "trpo_il"])
def test_imitation_visits_the_states_of_the_clipped_baseline_it_is_labelled_with(script, tmp_path, monkeypatch):
    (tmp_path / "drift_env.py").write_text(DRIFT_ENV)
    monkeypatch.syspath_prepend(str(tmp_path))
    import drift_env

    data = load_script(script).collect_baseline_data(gym.make("drift_env:Drift-v0"), drift_env.saturating, steps=10, seed=0, gamma=0.99)
    assert data["obs"][:, 0].tolist() == list(range(10))  # 0, 1, 2, ...: not 0, 3, 6, ... of the action as asked
    assert data["actions"][:, 0].tolist() == [1.0] * 10 and data["episode_returns"] == [-55.0]
