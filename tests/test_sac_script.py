"""sac_continuous.py end to end: truncation handling, logging, checkpoints, errors, copyability."""

import errno
import os
import re
import runpy
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.envs.classic_control.pendulum import PendulumEnv
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

import warm_python
from conftest import OTHER_PENDULUM_SPACES, ROOT, fill_the_disk_for, load_script, overflow_the_actor, overflow_the_policy_mean, printed_regret, readme_section, small_checkpoint

TINY = ["--hidden-size", "32", "--batch-size", "32", "--log-every", "50"]


def run_script(script: Path, args: list[str], cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    return warm_python.run([str(script), *args], cwd=cwd, env=env)


def readme_keys() -> set[str]:
    """Every TensorBoard key the README names (`group/name`, with `{a,b}` spelled out)."""
    keys = set()
    for key in re.findall(r"`((?:charts|losses|eval|gate|phases|il)/[\w{},]+)`", (ROOT / "README.md").read_text()):
        head, _, rest = key.partition("{")
        keys |= {head + choice + rest.partition("}")[2] for choice in rest.partition("}")[0].split(",")} if rest else {key}
    return keys


def scalars(run_dir: Path) -> dict[str, list[float]]:
    events = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})
    events.Reload()
    return {tag: [e.value for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def pendulum_step(obs: np.ndarray, torque: float) -> np.ndarray:
    """Pendulum-v1's dynamics, written out independently of gymnasium."""
    theta, w = np.arctan2(obs[1], obs[0]), obs[2]
    u = np.clip(torque, -2.0, 2.0)
    w = np.clip(w + (3 * 10.0 / 2 * np.sin(theta) + 3.0 * u) * 0.05, -8.0, 8.0)
    theta = theta + w * 0.05
    return np.array([np.cos(theta), np.sin(theta), w])


def test_truncated_transition_keeps_its_true_next_observation(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["sac_continuous.py", "--total-timesteps", "250", "--learning-starts", "100", *TINY])
    g = runpy.run_path(str(ROOT / "sac_continuous.py"), run_name="__main__")
    rb, seed = g["rb"], g["args"].seed
    assert rb.size == 250
    last = 199  # Pendulum-v1 truncates after 200 steps and never terminates
    assert rb.terminations[: rb.size].sum() == 0
    torque = 2.0 * rb.actions[last, 0]  # policy units [-1, 1] -> [-2, 2] N m
    np.testing.assert_allclose(rb.next_obs[last], pendulum_step(rb.obs[last], torque), atol=1e-5)
    # inside an episode, next_obs is the following obs; across the boundary it is not
    np.testing.assert_array_equal(rb.next_obs[:last], rb.obs[1 : last + 1])
    reset_obs, _ = g["make_env"]("Pendulum-v1", seed).reset(seed=seed + 1)
    np.testing.assert_array_equal(rb.obs[last + 1], reset_obs)
    assert not np.allclose(rb.next_obs[last], rb.obs[last + 1])


class EndingEpisodes(gym.Env):
    """obs = (t, the reset seed mod 3). Under a time limit of 4 steps, the episodes from a seed of 0 mod 3
    terminate at their 3rd step, those of 1 mod 3 at their 4th, where the limit also cuts them, and those
    of 2 mod 3 are cut by the limit alone."""

    observation_space = gym.spaces.Box(0.0, 4.0, (2,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t, self.kind = 0, seed % 3
        return np.array([self.t, self.kind], np.float32), {}

    def step(self, action):
        self.t += 1
        terminated = self.t == {0: 3, 1: 4}.get(self.kind)
        return np.array([self.t, self.kind], np.float32), -abs(float(action[0])), terminated, False, {}


gym.register("EndingEpisodes-v0", entry_point=EndingEpisodes, max_episode_steps=4)


def test_a_transition_is_terminal_where_its_episode_terminated_not_where_the_time_limit_cut_it(tmp_path, monkeypatch):
    """A terminal row's target has no future value; a row the time limit cut keeps it, so it is stored as
    not terminal. Where both end the episode at once, it terminated (Gymnasium's meaning of the flags)."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["sac_continuous.py", "--env-id", "EndingEpisodes-v0", "--total-timesteps", "40", "--learning-starts", "20", *TINY])
    g = runpy.run_path(str(ROOT / "sac_continuous.py"), run_name="__main__")
    rb = g["rb"]
    assert rb.size == 40
    next_t, kind = rb.next_obs[: rb.size, 0], rb.obs[: rb.size, 1]
    terminated, both, cut = (kind == 0) & (next_t == 3), (kind == 1) & (next_t == 4), (kind == 2) & (next_t == 4)
    assert (terminated.sum(), both.sum(), cut.sum()) == (3, 4, 3)  # seeds 1, 2, 3, ...: 11 steps a cycle of the three
    np.testing.assert_array_equal(rb.terminations[: rb.size, 0], terminated | both)


def test_actions_before_learning_starts_are_uniform_draws_of_the_seeded_generator(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["sac_continuous.py", "--total-timesteps", "120", "--learning-starts", "100", "--seed", "7", *TINY])
    g = runpy.run_path(str(ROOT / "sac_continuous.py"), run_name="__main__")
    rng = np.random.default_rng(7)
    expected = np.stack([rng.uniform(-1.0, 1.0, size=1).astype(np.float32) for _ in range(100)])
    np.testing.assert_array_equal(g["rb"].actions[:100], expected)
    assert not np.array_equal(g["rb"].actions[100:120], np.stack([rng.uniform(-1.0, 1.0, size=1).astype(np.float32) for _ in range(20)]))


def test_end_to_end_logs_saves_and_evaluates(tmp_path, sac):
    out = run_script(
        ROOT / "sac_continuous.py",
        ["--total-timesteps", "450", "--learning-starts", "150", "--save-model", "--eval-episodes", "2", *TINY],
        tmp_path,
    )
    assert out.returncode == 0, out.stderr
    (run_dir,) = (tmp_path / "runs").iterdir()
    assert run_dir.name.startswith("Pendulum-v1__sac_continuous__1__")
    logged = scalars(run_dir)
    for key in [
        "charts/episodic_return", "charts/episodic_length", "charts/SPS", "losses/qf_loss", "losses/actor_loss",
        "losses/alpha", "charts/baseline_regret", "charts/baseline_regret_per_step", "charts/baseline_return",
        "eval/episodic_return",
    ]:  # fmt: skip
        assert key in logged, key
        assert np.all(np.isfinite(logged[key])), key
    assert set(logged) - readme_keys() == set(), "keys the README does not name"
    assert len(logged["charts/episodic_return"]) == 2 and len(logged["eval/episodic_return"]) == 2
    # regret is cumulative and the untrained agent is worse than the swing-up baseline
    assert logged["charts/baseline_regret"][1] >= logged["charts/baseline_regret"][0] > 0
    assert logged["losses/alpha"][-1] != 0.2, "the entropy coefficient was tuned"
    # the run ends by printing the regret it logged at its last episode end (450 steps: 2 episodes of 200)
    assert "baseline regret (paired): " in out.stdout
    assert printed_regret(out.stdout) == pytest.approx((logged["charts/baseline_regret"][-1], logged["charts/baseline_regret_per_step"][-1]), abs=0.05)
    assert "RL control" not in out.stdout

    (checkpoint,) = run_dir.glob("*.cleanrl_model")
    returns = sac.evaluate(str(checkpoint), "Pendulum-v1", episodes=2, seed=1)
    np.testing.assert_allclose(returns, logged["eval/episodic_return"], rtol=1e-5)  # deterministic policy
    # the same evaluation written out: the saved weights' 2 tanh(mean) N m on gymnasium's own env, evaluation seeds
    w = torch.load(checkpoint, weights_only=True)["actor"]
    env, expected = gym.make("Pendulum-v1"), []
    for i in range(2):
        obs, _ = env.reset(seed=1 + 1_000_000 + i)
        total, done = 0.0, False
        while not done:
            x = torch.as_tensor(obs, dtype=torch.float32)
            for layer in ("fc1", "fc2"):
                x = torch.relu(w[f"{layer}.weight"] @ x + w[f"{layer}.bias"])
            torque = 2.0 * torch.tanh(w["fc_mean.weight"] @ x + w["fc_mean.bias"]).numpy()
            obs, reward, terminated, truncated, _ = env.step(torque)
            total, done = total + float(reward), terminated or truncated
        expected.append(total)
    env.close()
    np.testing.assert_allclose(returns, expected, rtol=1e-4)


def test_checkpoint_round_trip_and_errors(tmp_path, sac):
    env = sac.make_env("Pendulum-v1", 0)
    actor, qf = sac.Actor(3, 1, 16), sac.SoftQNetwork(3, 1, 16)
    args = sac.Args(hidden_size=16)
    path = tmp_path / "model.cleanrl_model"
    sac.save_checkpoint(str(path), "Pendulum-v1", env, actor, qf, args)
    restored = sac.actor_from_checkpoint(sac.load_checkpoint(str(path)), env)
    x = torch.randn(5, 3)
    torch.testing.assert_close(restored(x), actor(x))

    corrupt = tmp_path / "corrupt.cleanrl_model"
    corrupt.write_bytes(path.read_bytes()[:200])
    with pytest.raises(ValueError, match="not a readable checkpoint"):
        sac.load_checkpoint(str(corrupt))
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(2)}, other)
    with pytest.raises(ValueError, match="not a jirl-sac-checkpoint-v2 checkpoint"):
        sac.load_checkpoint(str(other))
    lander = sac.make_env("LunarLanderContinuous-v3", 0)
    with pytest.raises(ValueError, match="checkpoint expects 3 observations and 1 actions"):
        sac.actor_from_checkpoint(sac.load_checkpoint(str(path)), lander)
    saved = torch.load(path, weights_only=True)
    for key in ("actor", "hidden_size"):  # the right format tag, a part missing: named, not a KeyError later
        damaged = tmp_path / f"no_{key}.cleanrl_model"
        torch.save({k: v for k, v in saved.items() if k != key}, damaged)
        with pytest.raises(ValueError, match=f"damaged jirl-sac-checkpoint-v2 checkpoint: it has no {key}$"):
            sac.load_checkpoint(str(damaged))
        assert damaged.exists()
    assert path.exists() and corrupt.exists(), "a failed load deletes nothing"


@pytest.mark.parametrize("loader", ["sac_continuous", "jirl_sac_continuous", "ppo_il", "trpo_il"])
def test_another_scripts_checkpoint_is_named_with_its_format_and_run(tmp_path, loader):
    script = load_script(loader)
    others = {"jirl-sac-checkpoint-v2": "jirl_sac_continuous", "jirl-gaussian-checkpoint-v1": "trpo_il", "jirl-car-training-v2": None}
    for found, run in others.items():
        if found == script.CHECKPOINT_FORMAT:
            continue
        path = tmp_path / f"{found}.pt"
        torch.save({"format": found, **({"args": {"exp_name": run}} if run else {})}, path)
        origin = f" (from a {run} run)" if run else ""
        with pytest.raises(ValueError) as raised:
            script.load_checkpoint(str(path))
        assert str(raised.value) == f"{path} is a {found} file{origin}, not a {script.CHECKPOINT_FORMAT} checkpoint"
    path = tmp_path / "odd_run.pt"  # a run name that is no name is left out, not printed
    other = next(found for found in others if found != script.CHECKPOINT_FORMAT)
    torch.save({"format": other, "args": {"exp_name": 7}}, path)
    with pytest.raises(ValueError, match=f"^{path} is a {other} file, not a {script.CHECKPOINT_FORMAT} checkpoint$"):
        script.load_checkpoint(str(path))
    foreign = tmp_path / "foreign.pt"  # a format of no script here keeps the plain message
    torch.save({"format": "sb3-policy"}, foreign)
    with pytest.raises(ValueError, match=f"^{foreign} is not a {script.CHECKPOINT_FORMAT} checkpoint$"):
        script.load_checkpoint(str(foreign))


@pytest.mark.parametrize("loader", ["sac_continuous", "jirl_sac_continuous", "ppo_il", "trpo_il"])
def test_a_checkpoint_holding_a_value_no_sound_checkpoint_holds_is_damaged_in_one_line(tmp_path, loader):
    script = load_script(loader)
    env, path = script.make_env("Pendulum-v1", 0), tmp_path / "model.cleanrl_model"
    if loader.endswith("sac_continuous"):
        weights = "actor"
        script.save_checkpoint(str(path), "Pendulum-v1", env, script.Actor(3, 1, 8), script.SoftQNetwork(3, 1, 8), script.Args(hidden_size=8))
    else:
        weights = "agent"
        script.save_checkpoint(str(path), "Pendulum-v1", env, script.Agent(3, 1, 8), script.RunningMeanStd((3,)), script.Args(hidden_size=8))
    saved = torch.load(path, weights_only=True)
    last = list(saved[weights])[-1]  # a flaw in the last tensor: every one is checked, not the first alone
    matrix = max(saved[weights], key=lambda name: saved[weights][name].numel())  # one NaN among finite weights is a flaw too
    one_nan = saved[weights][matrix].clone()
    one_nan.view(-1)[-1] = float("nan")
    nan, unnamed = f"its {weights} holds a NaN or infinite weight", f"its {weights} holds an entry that is not a named tensor"
    cases = [("hidden_size", "8", "its hidden_size is '8'"), ("hidden_size", 0, "its hidden_size is 0"),
             ("obs_dim", 3.0, "its obs_dim is 3.0"), ("obs_dim", True, "its obs_dim is True"),
             ("action_low", "ab", "its action_low is 'ab'"), ("action_low", [], "its action_low is []"),
             ("obs_dim", 0, "its obs_dim is 0"), ("action_low", 5, "its action_low is 5"), ("action_low", [True], "its action_low is [True]"),
             ("action_high", [2.0, 2.0], "its action_high is [2.0, 2.0]"), ("action_high", ["2"], "its action_high is ['2']"),
             (weights, [1, 2], f"its {weights} is [1, 2]"), (weights, {**saved[weights], last: [0.0]}, unnamed),
             (weights, {**saved[weights], last: torch.full_like(saved[weights][last], float("nan"))}, nan),
             (weights, {**saved[weights], last: saved[weights][last] * float("inf")}, nan), (weights, {**saved[weights], 7: torch.zeros(1)}, unnamed),
             (weights, {**saved[weights], matrix: one_nan}, nan)]  # fmt: skip
    if weights == "agent":  # the observation statistics: both or neither, one per observation, finite, a variance >= 0
        cases += [("obs_var", -torch.ones(3), "its obs_var is tensor([-1., -1., -1.])"),
                  ("obs_mean", torch.zeros(5), "its obs_mean is tensor([0., 0., 0., 0., 0.])"), ("obs_mean", None, "its obs_mean is None"),
                  ("obs_var", None, "its obs_var is None"), ("obs_mean", torch.tensor([0.0, float("nan"), 0.0]), "its obs_mean is tensor([0., nan, 0.])"),
                  ("obs_var", torch.ones(3, dtype=torch.int64), "its obs_var is tensor([1, 1, 1])")]  # fmt: skip
    for key, value, damage in cases:
        damaged = tmp_path / "damaged.cleanrl_model"
        torch.save({**saved, key: value}, damaged)
        with pytest.raises(ValueError) as raised:  # without the check: a TypeError, a numpy error, or NaN blamed on the env
            script.evaluate(str(damaged), "Pendulum-v1", 1, 0)
        assert str(raised.value) == f"{damaged} is a damaged {script.CHECKPOINT_FORMAT} checkpoint: {damage}", (key, value)
    torch.save({k: v for k, v in saved.items() if k not in ("obs_dim", "args")}, damaged)  # every part missing is named
    with pytest.raises(ValueError) as raised:
        script.evaluate(str(damaged), "Pendulum-v1", 1, 0)
    assert str(raised.value) == f"{damaged} is a damaged {script.CHECKPOINT_FORMAT} checkpoint: it has no obs_dim, args"
    for changed, message in OTHER_PENDULUM_SPACES:  # sound, but made for other spaces than this env's
        torch.save({**saved, **changed}, tmp_path / "other_spaces.cleanrl_model")
        with pytest.raises(ValueError) as raised:
            script.evaluate(str(tmp_path / "other_spaces.cleanrl_model"), "Pendulum-v1", 1, 0)
        assert str(raised.value) == message
    assert len(script.evaluate(str(path), "Pendulum-v1", 1, 0)) == 1
    overflowing = {name: w.clone() for name, w in saved[weights].items()}  # finite weights whose action is not: sound, and refused as it acts
    if weights == "actor":
        overflow_the_actor(overflowing)
    else:
        overflow_the_policy_mean([overflowing[f"actor_mean.{layer}.{kind}"] for layer in (0, 2, 4) for kind in ("weight", "bias")])
    torch.save({**saved, weights: overflowing}, tmp_path / "overflowing.cleanrl_model")
    with pytest.raises(ValueError) as raised:  # before, the NaN reached Pendulum, and the env was blamed for it
        script.evaluate(str(tmp_path / "overflowing.cleanrl_model"), "Pendulum-v1", 1, 0)
    action = "[nan]" if weights == "actor" else "[inf]"
    assert str(raised.value) == f"the policy's action at step 0 of evaluation episode 0 is {action}, not finite: its network overflows float32 there"
    torch.save({**saved, "action_low": (-2,), "action_high": (2.0,)}, tmp_path / "tuples.cleanrl_model")  # a tuple, an int bound (an int Box's): alike
    assert script.evaluate(str(tmp_path / "tuples.cleanrl_model"), "Pendulum-v1", 1, 0) == script.evaluate(str(path), "Pendulum-v1", 1, 0)
    if weights == "agent":  # saved without observation normalization: neither statistic
        torch.save({**saved, "obs_mean": None, "obs_var": None}, tmp_path / "raw.cleanrl_model")
        assert len(script.evaluate(str(tmp_path / "raw.cleanrl_model"), "Pendulum-v1", 1, 0)) == 1
    for key, value, message in (("hidden_size", 16, "Error(s) in loading state_dict for "), (weights, {**saved[weights], "extra": torch.zeros(1)}, 'Unexpected key(s) in state_dict: "extra"')):
        torch.save({**saved, key: value}, tmp_path / "unfit.cleanrl_model")
        with pytest.raises(ValueError) as raised:  # torch's message, on one line
            script.evaluate(str(tmp_path / "unfit.cleanrl_model"), "Pendulum-v1", 1, 0)
        assert "weights do not fit: " in str(raised.value) and message in str(raised.value) and "\n" not in str(raised.value), str(raised.value)


@pytest.mark.parametrize("loader", ["sac_continuous", "jirl_sac_continuous", "ppo_il", "trpo_il", "walker2d", "deploy"])
def test_a_damaged_file_is_a_one_line_error_that_never_advises_weights_only_false(tmp_path, loader):
    if loader == "walker2d":
        from envs.walker2d import load_policy as load
    elif loader == "deploy":
        from deploy.jetracer import load_training_state

        def load(path):
            return load_training_state(path, None, None)  # fails on the file, before the agent is touched
    else:
        load = load_script(loader).load_checkpoint
    good = tmp_path / "good.pt"
    torch.save({"weights": torch.zeros(3)}, good)
    damaged = {"text": (b"garbage\n", "UnpicklingError: Weights only load failed)"), "empty": (b"", "EOFError: the file ends early)"),
               "cut": (good.read_bytes()[:100], "RuntimeError: PytorchStreamReader failed reading zip archive: failed finding central directory)")}  # fmt: skip
    for name, (data, cause) in damaged.items():
        path = tmp_path / f"{name}.pt"
        path.write_bytes(data)
        with pytest.raises(ValueError) as raised:
            load(str(path))
        message = str(raised.value)  # torch's own message runs to several lines and suggests weights_only=False
        assert message.startswith(f"{path} is not ") and message.endswith(cause), message
        assert "\n" not in message and "weights_only" not in message, message
        assert path.read_bytes() == data
    with pytest.raises(FileNotFoundError):  # no file is not a damaged one: the OS error names the path
        load(str(tmp_path / "no_such.pt"))


@pytest.mark.parametrize(
    "env_id, message",
    [("NoSuchEnv-v0", "unknown env id 'NoSuchEnv-v0'"), ("CartPole-v1", "Discrete(2) action space")],
)
def test_bad_env_id_is_a_one_line_error(tmp_path, env_id, message):
    out = run_script(ROOT / "sac_continuous.py", ["--env-id", env_id, "--total-timesteps", "10"], tmp_path)
    assert out.returncode != 0
    assert message in out.stderr
    assert "Traceback" not in out.stderr and len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert not (tmp_path / "runs").exists(), "nothing is written before the input is validated"


def test_missing_baseline_errors_only_when_regret_is_demanded(tmp_path):
    out = run_script(
        ROOT / "sac_continuous.py",
        ["--env-id", "MountainCarContinuous-v0", "--regret-estimator", "paired", "--total-timesteps", "10"],
        tmp_path,
    )
    assert out.returncode != 0 and "no baseline for MountainCarContinuous-v0" in out.stderr
    assert not (tmp_path / "runs").exists(), "the run's directory, claimed before the check, is gone"


def test_script_copied_alone_runs_with_a_user_baseline(tmp_path):
    shutil.copy(ROOT / "sac_continuous.py", tmp_path)
    (tmp_path / "my_baseline.py").write_text(
        "import numpy as np\ndef no_torque(obs):\n    return np.zeros(1, dtype=np.float32)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    args = ["--env-id", "Pendulum-v1", "--baseline", "my_baseline:no_torque", "--total-timesteps", "300",
            "--learning-starts", "100", "--baseline-eval-episodes", "1", *TINY]  # fmt: skip
    out = run_script(tmp_path / "sac_continuous.py", args, tmp_path, env)
    assert out.returncode == 0, out.stderr
    assert "baseline regret estimator: paired" in out.stdout
    (run_dir,) = (tmp_path / "runs").iterdir()
    assert "charts/baseline_regret_per_step" in scalars(run_dir)


SCRIPTS = ["sac_continuous", "jirl_sac_continuous", "ppo_il", "trpo_il"]


@pytest.mark.parametrize("script", SCRIPTS)
def test_claim_run_dir_never_gives_two_runs_one_directory(script, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    claim = load_script(script).claim_run_dir
    assert [claim("Env-v0__x__1__7") for _ in range(3)] == ["Env-v0__x__1__7", "Env-v0__x__1__7_2", "Env-v0__x__1__7_3"]
    assert claim("ns/Env-v0__x__1__7") == "ns/Env-v0__x__1__7"  # a namespaced env id ("ns/Env-v0") nests
    made = sorted(p.relative_to(tmp_path / "runs").as_posix() for p in (tmp_path / "runs").rglob("*"))
    assert made == ["Env-v0__x__1__7", "Env-v0__x__1__7_2", "Env-v0__x__1__7_3", "ns", "ns/Env-v0__x__1__7"]


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_file_named_runs_in_the_way_is_a_one_line_error(script, tmp_path):
    (tmp_path / "runs").write_text("a user's notes")
    out = run_script(ROOT / f"{script}.py", ["--env-id", "Pendulum-v1", "--total-timesteps", "10"], tmp_path)
    assert out.returncode != 0 and "Traceback" not in out.stderr, out.stderr  # before: a FileExistsError traceback
    last = out.stderr.strip().splitlines()[-1]  # then the system's words, e.g. "[Errno 17] File exists: 'runs'"
    assert last.startswith(f"{script}: error: cannot make the run's folder in runs/: ") and last.endswith("'runs'"), last
    assert (tmp_path / "runs").read_text() == "a user's notes"


@pytest.mark.parametrize("script", ["sac_continuous", "jirl_sac_continuous"])
def test_a_replay_buffer_too_large_for_memory_is_a_one_line_error_and_one_larger_than_the_run_is_cut(script, tmp_path):
    huge = str(10**13)  # 360 TB of Pendulum transitions, beyond any address space
    out = run_script(ROOT / f"{script}.py", ["--env-id", "Pendulum-v1", "--total-timesteps", huge, "--buffer-size", huge], tmp_path)
    assert out.returncode != 0 and "Traceback" not in out.stderr, out.stderr  # before: numpy's MemoryError traceback, and a run folder left
    assert out.stderr.strip().splitlines()[-1].startswith(f"{script}: error: a replay buffer of 10,000,000,000,000 transitions (335,276 GiB)")
    assert not (tmp_path / "runs").exists()
    # a buffer larger than all the run can store is allocated no larger (the ring never wraps either way)
    out = run_script(ROOT / f"{script}.py", ["--env-id", "Pendulum-v1", "--total-timesteps", "300", "--buffer-size", huge, "--learning-starts", "100",
                                             "--batch-size", "16", "--hidden-size", "8", "--baseline-eval-episodes", "1"], tmp_path)  # fmt: skip
    assert out.returncode == 0, out.stderr


@pytest.mark.parametrize("script", SCRIPTS)
def test_claim_run_dir_tries_again_when_runs_vanishes_in_between(script, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "runs").mkdir()
    real_mkdir, vanished = os.mkdir, []

    def mkdir(path, *args, **kwargs):  # runs/, empty, is removed after makedirs, as by a run that ended on bad input
        if str(path).startswith("runs/") and not vanished:
            vanished.append(path)
            (tmp_path / "runs").rmdir()
        return real_mkdir(path, *args, **kwargs)

    monkeypatch.setattr(os, "mkdir", mkdir)
    assert load_script(script).claim_run_dir("Env-v0__x__1__7") == "Env-v0__x__1__7"
    assert vanished == ["runs/Env-v0__x__1__7"] and (tmp_path / "runs" / "Env-v0__x__1__7").is_dir()


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_run_whose_name_is_taken_writes_beside_it_and_bad_input_leaves_runs_as_it_was(script, tmp_path):
    # every name the run could take in the next two minutes is taken, as by a run launched in the same second
    now = int(time.time())
    taken = {tmp_path / "runs" / f"Pendulum-v1__{script}__1__{t}" for t in range(now - 1, now + 120)}
    for earlier in taken:
        earlier.mkdir(parents=True)
        (earlier / "earlier_run").write_text("kept")
    if script in ("ppo_il", "trpo_il"):
        budget = ["--num-steps", "256", "--total-timesteps", "256", "--il-steps", "400", "--il-max-epochs", "5"]
    else:
        budget = ["--total-timesteps", "300", "--learning-starts", "100", "--batch-size", "16"]
    args = [*budget, "--hidden-size", "16", "--baseline-eval-episodes", "1", "--save-model", "--eval-episodes", "1"]
    out = run_script(ROOT / f"{script}.py", args, tmp_path)
    assert out.returncode == 0, out.stderr
    (run_dir,) = set((tmp_path / "runs").iterdir()) - taken
    assert run_dir.name.endswith("_2") and run_dir.with_name(run_dir.name[:-2]) in taken
    assert any(run_dir.glob("events.out.tfevents.*")) and any(run_dir.glob(f"{script}.cleanrl_model"))
    assert all([p.name for p in earlier.iterdir()] == ["earlier_run"] for earlier in taken), "nothing written into another run"
    out = run_script(ROOT / f"{script}.py", ["--env-id", "NoSuchEnv-v0"], tmp_path)
    assert out.returncode != 0 and "unknown env id 'NoSuchEnv-v0'" in out.stderr
    assert set((tmp_path / "runs").iterdir()) == taken | {run_dir}, "bad input removes only the directory it claimed"


@pytest.mark.parametrize("script", SCRIPTS)
def test_an_env_that_crashes_on_construction_keeps_its_traceback_and_leaves_no_run_directory(script, tmp_path):
    (tmp_path / "broken.py").write_text(
        "import gymnasium as gym\n"
        "class Broken(gym.Env):\n"
        "    def __init__(self):\n"
        "        raise RuntimeError('the simulator licence server is down')\n"
        "gym.register('Broken-v0', entry_point=Broken)\n"
    )  # fmt: skip
    out = run_script(ROOT / f"{script}.py", ["--env-id", "broken:Broken-v0"], tmp_path)
    assert out.returncode != 0 and "Traceback" in out.stderr
    assert out.stderr.strip().endswith("RuntimeError: the simulator licence server is down")
    assert not (tmp_path / "runs").exists(), "the directory claimed before make_env is gone"


def test_capture_video_records_the_training_episodes(tmp_path):
    args = ["--total-timesteps", "200", "--learning-starts", "100", "--capture-video", "--baseline-eval-episodes", "1", *TINY]
    out = run_script(ROOT / "sac_continuous.py", args, tmp_path)
    assert out.returncode == 0, out.stderr
    (video,) = (tmp_path / "videos").glob("Pendulum-v1__sac_continuous__1__*/rl-video-episode-0.mp4")
    capture, frames = cv2.VideoCapture(str(video)), []
    while (frame := capture.read()[1]) is not None:
        frames.append(frame[..., ::-1].astype(float))  # BGR -> RGB
    capture.release()
    assert len(frames) == 200 and frames[0].shape == (500, 500, 3)
    # the first frame is training episode 0's start, env.reset(seed=1), not another start
    renders = []
    for seed in (1, 2, 3, 4, 5):
        env = gym.make("Pendulum-v1", render_mode="rgb_array")
        env.reset(seed=seed)
        renders.append(env.render().astype(float))
        env.close()
    errors = [np.abs(frames[0] - render).mean() for render in renders]
    assert errors[0] < 0.5 < min(errors[1:]), errors


@pytest.mark.parametrize("script", ["sac_continuous", "jirl_sac_continuous", "ppo_il", "trpo_il"])
def test_capture_video_without_moviepy_is_a_clear_error_that_writes_nothing(tmp_path, monkeypatch, script):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setitem(sys.modules, "moviepy", None)  # `import moviepy` now raises ImportError
    with pytest.raises(ValueError, match=r"--capture-video needs moviepy \(pip install moviepy\)"):
        load_script(script).make_env("Pendulum-v1", 1, capture_video=True, run_name="run")
    assert not (tmp_path / "videos").exists()


SHORT_RUNS = {
    "sac_continuous": ["--total-timesteps", "250", "--learning-starts", "100", *TINY],
    "jirl_sac_continuous": ["--total-timesteps", "250", "--learning-starts", "100", *TINY],
    "ppo_il": ["--total-timesteps", "256", "--num-steps", "128", "--num-minibatches", "2", "--update-epochs", "1", "--il-steps", "400",
               "--il-max-epochs", "2", "--hidden-size", "16"],  # fmt: skip
    "trpo_il": ["--total-timesteps", "256", "--num-steps", "128", "--n-critic-updates", "1", "--il-steps", "400", "--il-max-epochs", "2",
                "--hidden-size", "16"],  # fmt: skip
}


@pytest.mark.parametrize("script, regret", [(script, "auto") for script in SHORT_RUNS] + [("sac_continuous", "off")])
def test_a_run_closes_every_env_it_opens(tmp_path, monkeypatch, script, regret):
    # training, shadow (the baseline's) and evaluation envs: a PyBullet env left open keeps its physics
    # server (about 29 MB for Walker2D), so in-process sweeps would leak one per run
    opened, closed = [], []
    real_init, real_close = PendulumEnv.__init__, PendulumEnv.close

    def recording_init(self, *args, **kwargs):
        opened.append(self)
        real_init(self, *args, **kwargs)

    def recording_close(self):
        closed.append(self)
        real_close(self)

    monkeypatch.setattr(PendulumEnv, "__init__", recording_init)
    monkeypatch.setattr(PendulumEnv, "close", recording_close)
    monkeypatch.chdir(tmp_path)
    args = [*SHORT_RUNS[script], "--regret-estimator", regret, "--baseline-eval-episodes", "1", "--save-model", "--eval-episodes", "1"]
    monkeypatch.setattr(sys, "argv", [f"{script}.py", *args])
    g = runpy.run_path(str(ROOT / f"{script}.py"), run_name="__main__")  # conftest checks that it gives the signal handlers back
    if regret == "off":  # SAC needs no baseline then
        assert g["shadow_env"] is None and len(opened) == 2
    else:
        assert len(opened) >= 3 and any(env is g["shadow_env"].unwrapped for env in opened)
    unclosed = [env for env in opened if not any(env is c for c in closed)]
    assert not unclosed, f"{len(unclosed)} of {len(opened)} envs left open"


def test_a_checkpoint_the_disk_cannot_hold_raises_its_os_error_and_leaves_no_file(tmp_path, monkeypatch, sac):
    path = tmp_path / "model.cleanrl_model"
    fill_the_disk_for(monkeypatch, r".*\.cleanrl_model")
    with pytest.raises(OSError) as raised:  # torch.save itself would raise RuntimeError("... unexpected pos ...")
        sac.write_checkpoint(str(path), {"weights": torch.zeros(10_000)})
    assert raised.value.errno == errno.ENOSPC
    assert not path.exists(), "half a checkpoint was left behind"
    monkeypatch.undo()
    sac.write_checkpoint(str(path), {"weights": torch.ones(3)})  # the same call where there is room
    assert torch.equal(torch.load(path, weights_only=True)["weights"], torch.ones(3))


@pytest.mark.parametrize("script, model", [*((script, ".cleanrl_model") for script in SHORT_RUNS),
                                           ("ppo_il", "_cloned.cleanrl_model"), ("trpo_il", "_cloned.cleanrl_model")])  # fmt: skip
def test_a_model_the_disk_cannot_hold_is_a_one_line_error(tmp_path, monkeypatch, script, model):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", [f"{script}.py", *SHORT_RUNS[script], "--baseline-eval-episodes", "1", "--save-model"])
    fill_the_disk_for(monkeypatch, re.escape(f"{script}{model}"))  # PPO+IL and TRPO+IL save the cloned policy first, then the trained one
    with pytest.raises(SystemExit) as raised:
        runpy.run_path(str(ROOT / f"{script}.py"), run_name="__main__")
    (run_dir,) = (tmp_path / "runs").iterdir()
    expected = f"{script}: error: cannot save the model to runs/{run_dir.name}/{script}{model}: No space left on device"
    assert str(raised.value.code) == expected
    assert not (run_dir / f"{script}{model}").exists()
    cloned_kept = script.endswith("_il") and model == ".cleanrl_model"  # saved before the disk filled
    assert [path.name for path in run_dir.glob("*.cleanrl_model")] == ([f"{script}_cloned.cleanrl_model"] if cloned_kept else [])


def test_the_readmes_saved_policy_snippet_runs(tmp_path, sac):
    section = readme_section("### Using a saved policy")
    code = section.split("```python\n", 1)[1].split("```", 1)[0]
    path = tmp_path / "model.cleanrl_model"
    small_checkpoint(sac, path)
    code = code.replace("runs/RUN_NAME/jirl_sac_continuous.cleanrl_model", str(path)).replace('render_mode="human"', "render_mode=None")
    assert str(path) in code and "render_mode=None" in code, "the snippet changed: update this test"
    out = warm_python.run(["-c", code + "print(obs.shape, float(reward))"], cwd=ROOT)
    assert out.returncode == 0, out.stderr
    shape, reward = out.stdout.rsplit(")", 1)
    assert shape == "(3," and -16.3 < float(reward) <= 0.0  # a Pendulum step's reward


@pytest.mark.parametrize("script", ["sac_continuous", "jirl_sac_continuous"])
def test_a_run_that_never_reaches_learning_starts_says_so(tmp_path, monkeypatch, capsys, script):
    """--learning-starts at or past --total-timesteps is allowed (it runs the baseline and an untrained agent),
    but a quick trial with the default 5,000 and a few thousand steps would otherwise end with no update and
    no word of it. A run that does learn says nothing."""
    monkeypatch.chdir(tmp_path)
    for learning_starts, updated in (("250", False), ("249", True)):
        monkeypatch.setattr(sys, "argv", [f"{script}.py", *SHORT_RUNS[script], "--learning-starts", learning_starts, "--baseline-eval-episodes", "1"])
        g = runpy.run_path(str(ROOT / f"{script}.py"), run_name="__main__")
        assert bool(g["sac"].q_optimizer.state) is updated  # Adam keeps state once it has taken a step
        out = capsys.readouterr().out
        note = f"note: --learning-starts {learning_starts} is not below --total-timesteps 250: the agent is never updated"
        assert (note in out.splitlines()) is not updated
        assert ("note:" in out) is not updated
