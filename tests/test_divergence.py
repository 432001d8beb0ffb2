"""A training that diverges (a learning rate or a reward far too large) ends in one line that says so and
names the parts holding a NaN or an infinity, before its NaN acts on the env, is learnt from or is
logged; the scripts save their last sound model, and the car's training keeps the last state it saved
before the divergence. Before, SAC's NaN
action reached the env, which was blamed for it (or, on envs that ignore a NaN action, the run went on
to the end), and JIRL, PPO+IL and TRPO+IL stopped with torch's traceback."""

import math
import re
import runpy
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.envs.classic_control.pendulum import PendulumEnv
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from conftest import ROOT, load_script, overflow_the_actor, overflow_the_policy_mean
from test_sac_script import SHORT_RUNS, scalars
from test_stopping import SCRIPTS, without


class RecordingPendulum(PendulumEnv):
    """Pendulum-v1 that keeps, per instance in order of creation, every action it is given. With `scale`
    set, its episode from reset seed 3 (a run's third, at --seed 1) pays `scale` times Pendulum's reward:
    with 1e37 the rewards stay finite in float32 (1.6e38 at most), so CheckedEnv passes them, but their
    returns do not, and a critic fitted to them diverges. With `wild_at` set to (a reset seed, n), the n-th
    step of that episode returns an observation of 1e4 in every component: finite, as a sensor's glitch
    may be."""

    instances: list = []
    scale = 1.0
    wild_at = None

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.actions = []
        RecordingPendulum.instances.append(self)

    def reset(self, *, seed=None, options=None):
        self.factor = self.scale if seed == 3 else 1.0
        self.wild, self.t = (self.wild_at[1] if self.wild_at and seed == self.wild_at[0] else None), 0
        return super().reset(seed=seed, options=options)

    def step(self, action):
        self.actions.append(np.array(action, dtype=np.float64))
        obs, reward, terminated, truncated, info = super().step(action)
        self.t += 1
        if self.t == self.wild:
            obs = np.full_like(obs, 1e4)
        return obs, reward * self.factor, terminated, truncated, info


gym.register("RecordingPendulum-v0", entry_point=RecordingPendulum, max_episode_steps=200)


@pytest.fixture
def recorded(monkeypatch):
    monkeypatch.setattr(RecordingPendulum, "instances", [])
    return RecordingPendulum.instances


TOO_LARGE_A_STEP = {"sac_continuous": ["--policy-lr", "1e8", "--q-lr", "1e8"], "jirl_sac_continuous": ["--policy-lr", "1e8", "--q-lr", "1e8"],
                    "ppo_il": ["--learning-rate", "1e8", "--max-grad-norm", "1e12"]}  # fmt: skip
SAC_ALL = "NaN or infinite values in the actor, the critics, the target critics, the critics' optimizer, the actor's optimizer and the entropy coefficient"
PPO_ALL = "NaN or infinite weights in the policy's mean, the policy's log-std and the critic"
# (script, cause, the reason given, the step the run stops at). A step too large: SAC and JIRL diverge some
# steps after their updates start at --learning-starts 100. A reward too large: the third episode's steps
# 401-600 (PPO and TRPO count from 1) fall in the fourth rollout of 128, whose update diverges. A NaN in
# one head of the actor alone, or its mean head's weights and bias at 3e38 (finite, but not their sum),
# put there by its second update (of step 100, the first): the other head is finite.
DIVERGING = [("sac_continuous", "step", SAC_ALL, None), ("jirl_sac_continuous", "step", SAC_ALL, None),
             *[(script, head, "NaN or infinite values in the actor", 101) for script in ("sac_continuous", "jirl_sac_continuous") for head in ("mean head", "log-std head")],
             ("jirl_sac_continuous", "overflow", "the actor overflowed", 101), ("sac_continuous", "overflow to NaN", "the actor overflowed", 101),
             ("ppo_il", "step", PPO_ALL, 128), ("ppo_il", "reward", PPO_ALL, 512), ("trpo_il", "reward", "NaN or infinite weights in the critic", 512),
             *[(script, "overflow", "the policy's mean overflowed", 129) for script in ("ppo_il", "trpo_il")]]  # fmt: skip


def poison(tensor: torch.Tensor, value: float) -> None:
    with torch.no_grad():
        tensor.view(-1)[0] = value


def poison_the_actor(monkeypatch, how: str, at_step: int = 2) -> None:
    """Right after the actor's second optimizer step (or its at_step-th), a NaN in the bias of its mean head
    ("mean head") or of its log-std head ("log-std head"), its mean head's weights and bias at 3e38
    ("overflow": an infinite mean, which SAC's tanh turns into a finite action), `overflow_the_actor`
    ("overflow to NaN": a NaN mean, and SAC's action NaN), or a NaN in the critics' first weight, the actor
    left finite until its next step ("critics"). The actor's parameters are fc1's weight and bias, fc2's,
    fc_mean's and fc_logstd's, in that order."""
    real_step, calls, critics = torch.optim.Adam.step, [], []

    def step(self, *args, **kwargs):
        loss = real_step(self, *args, **kwargs)
        if len(self.param_groups) == 1:  # the critics' optimizer
            critics.append(self)
        if len(self.param_groups) == 2:  # the actor's optimizer: its second group is the entropy coefficient
            calls.append(self)
            if len(calls) == at_step:
                params = self.param_groups[0]["params"]
                if how == "critics":
                    poison(critics[-1].param_groups[0]["params"][0], math.nan)
                elif how == "overflow":
                    with torch.no_grad():
                        params[-4].fill_(3e38)
                        params[-3].fill_(3e38)
                elif how == "overflow to NaN":
                    overflow_the_actor(dict(zip([f"{layer}.{kind}" for layer in ("fc1", "fc2", "fc_mean", "fc_logstd") for kind in ("weight", "bias")], params)))
                else:
                    poison(params[-3 if how == "mean head" else -1], math.nan)
        return loss

    monkeypatch.setattr(torch.optim.Adam, "step", step)


def overflow_on_a_wild_speed(mean: list) -> None:
    """PPO's and TRPO's `actor_mean` parameters (16 units) made finite weights whose mean is exactly 0 while
    the normalized angular speed x is below 7, and +inf above 8.9 (observations are clipped at 10): the
    first layer gives tanh(10 x - 90), exactly -1 below 7; the second the mean of those plus 1, from 0 to
    2; the last sums 16 times 3e38 tanh(that), beyond float32 once tanh(that) passes 0.071."""
    with torch.no_grad():
        mean[0].zero_()
        mean[0][:, 2] = 10.0
        mean[1].fill_(-90.0)
        mean[2].fill_(1 / 16)
        mean[3].fill_(1.0)
        mean[4].fill_(3e38)
        mean[5].zero_()


def overflow_the_policy_at_its_first_update(monkeypatch, script: str, rig=overflow_the_policy_mean) -> None:
    """PPO's or TRPO's policy left by its first update with finite weights whose mean overflows: everywhere
    (`overflow_the_policy_mean`), or as `rig` makes it. PPO: after its optimizer's second step (two
    minibatches, one epoch: the whole update). TRPO: after each parameter write of its line search, so that
    whatever it ends with, an accepted trial step or the start written back, is rigged too."""
    if script == "ppo_il":
        real_step, calls = torch.optim.Adam.step, []

        def step(self, *args, **kwargs):
            loss = real_step(self, *args, **kwargs)
            params = self.param_groups[0]["params"]
            if len(params) == 13:  # the RL phase's optimizer: the log-std (the agent's own parameter comes first), the critic's 6 tensors, the mean's 6
                calls.append(self)
                if len(calls) == 2:
                    rig(params[7:])
            return loss

        monkeypatch.setattr(torch.optim.Adam, "step", step)
    else:
        real_write = torch.nn.utils.vector_to_parameters

        def write(vector, params):  # policy_params: the mean's 6 tensors, then the log-std
            real_write(vector, params)
            rig(params[:6])

        monkeypatch.setattr(torch.nn.utils, "vector_to_parameters", write)


def run_on_recording_pendulum(script: str, total: int, cwd: Path, monkeypatch, *extra: str) -> Path:
    """A --save-model run of the script for `total` steps in cwd, with `extra` arguments; its model. Nothing
    in it depends on `total` but its length (JIRL's hand-over is given a horizon and PPO's learning rate is
    not annealed), so that runs of two lengths train alike."""
    args = [*without(SHORT_RUNS[script], "--total-timesteps"), "--total-timesteps", str(total), "--env-id", f"{__name__}:RecordingPendulum-v0",
            "--baseline", "test_stopping:zero_torque", "--regret-estimator", "off", "--save-model", "--eval-episodes", "1",
            *{"jirl_sac_continuous": ["--guidance-steps", "500"], "ppo_il": ["--no-anneal-lr"]}.get(script, []), *extra]  # fmt: skip
    cwd.mkdir(exist_ok=True)
    monkeypatch.chdir(cwd)
    monkeypatch.setattr(sys, "argv", [f"{script}.py", *args])
    runpy.run_path(str(ROOT / f"{script}.py"), run_name="__main__")
    (run_dir,) = (cwd / "runs").iterdir()
    return run_dir / f"{script}.cleanrl_model"


@pytest.mark.parametrize("script, cause, reason, step", DIVERGING)
def test_a_diverging_training_ends_naming_what_diverged_before_its_nan_acts(script, cause, reason, step, tmp_path, monkeypatch, capsys, recorded):
    if cause == "reward":
        monkeypatch.setattr(RecordingPendulum, "scale", 1e37)
    if cause == "overflow" and script.endswith("_il"):
        overflow_the_policy_at_its_first_update(monkeypatch, script)
    elif cause.endswith("head") or cause.startswith("overflow"):
        poison_the_actor(monkeypatch, cause)
    with pytest.raises(SystemExit) as ended:
        run_on_recording_pendulum(script, 1000, tmp_path, monkeypatch, *(TOO_LARGE_A_STEP[script] if cause == "step" else []))
    assert ended.value.code == 1
    out, err = capsys.readouterr()
    total = "1,000" if script.startswith(("sac", "jirl")) else "896"
    stopped = re.search(rf"^{script}: error: the training diverged: {re.escape(reason)}: training stopped at step ([\d,]+) of {total};"
                        r" saving the model(?: of step ([\d,]+), the last sound one,)? without evaluating it$", err, re.M)  # fmt: skip
    assert stopped, err
    at = int(stopped[1].replace(",", ""))
    kept = stopped[2] and int(stopped[2].replace(",", ""))
    # PPO and TRPO keep the agent of the last rollout's end, from before the update that diverged or made the
    # policy overflow; SAC and JIRL diverge here before their first episode ends, and have none to keep
    assert kept == (at // 128 * 128 if script.endswith("_il") else None)
    if step is not None:
        assert at == step
    else:  # SAC and JIRL: some steps after the updates start at --learning-starts 100
        assert 100 < at < 1000
    assert "Traceback" not in err and "returned a non-finite" not in err and "eval:" not in out
    training_env = recorded[0]  # made first; PPO's and TRPO's imitation and their cloned policy's evaluation have envs of their own
    applied = at - 1 if script.endswith("_il") and cause == "overflow" else at  # PPO and TRPO count steps from 1: step 129 is the one not taken
    assert len(training_env.actions) == applied  # no action of the step it stopped at was applied
    assert all(np.isfinite(a).all() for env in recorded for a in env.actions)  # no NaN ever reached an env
    (run_dir,) = (tmp_path / "runs").iterdir()
    logged = scalars(run_dir)
    assert all(math.isfinite(v) for tag, values in logged.items() for v in values if tag != "losses/explained_variance"), "a NaN was logged"
    if script.endswith("_il"):  # the diverged update is not logged: the last one logged is the rollout's before
        events = EventAccumulator(str(run_dir))
        events.Reload()
        logged_at = [e.step for e in events.Scalars("charts/SPS")] if "charts/SPS" in events.Tags()["scalars"] else []
        assert logged_at == list(range(128, at, 128))
    model = run_dir / f"{script}.cleanrl_model"  # SAC's and JIRL's saved as it is: refused by name when loaded, if a weight is NaN
    if script.endswith("_il") or cause == "overflow":  # the agent kept; or finite weights: it loads, and SAC's tanh(mean) saturates
        assert np.isfinite(load_script(script).evaluate(str(model), "Pendulum-v1", 1, 0)).all()
    elif cause == "overflow to NaN":  # it loads, and its evaluation refuses the action before the env is blamed for it
        with pytest.raises(ValueError, match=r"^the policy's action at step 0 of evaluation episode 0 is \[nan\], not finite: its network overflows float32 there$"):
            load_script(script).evaluate(str(model), "Pendulum-v1", 1, 0)
    else:
        with pytest.raises(ValueError, match=r"damaged .* checkpoint: its (actor|agent) holds a NaN or infinite weight$"):
            load_script(script).evaluate(str(model), "Pendulum-v1", 1, 0)


# script: (how it diverges, the step it stops at, the step of the model it keeps, the length of a run of the
# same seed that ends with that model, the parts of its checkpoint). SAC's and JIRL's episode end of step 199
# comes before that step's update, the last of a 199-step run; PPO's and TRPO's agent at the end of the rollout
# of step 512 is the one after the update of step 384, the last of a 384-step run.
LATE_DIVERGENCE = {"sac_continuous": ("actor", 299, 199, 199, ("actor", "qf")), "jirl_sac_continuous": ("actor", 299, 199, 199, ("actor", "qf")),
                   "ppo_il": ("reward", 512, 512, 384, ("agent",)), "trpo_il": ("reward", 512, 512, 384, ("agent",))}  # fmt: skip


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_training_that_diverges_saves_its_last_sound_model(script, tmp_path, monkeypatch, capsys, recorded):
    """Hours of training are not lost to a divergence. SAC and JIRL keep the model of the last episode end
    before it (step 199 here; the actor poisoned at its 200th optimizer step, step 298); PPO+IL and
    TRPO+IL the agent of the last rollout's end, from before the update that diverged (step 512, on the
    third episode's rewards). It is the same, bit for bit, as what a run of the same seed that ends there
    saves: a run of 199 steps, or of the 3 rollouts before (384 steps)."""
    how, stop, kept, reference_length, parts = LATE_DIVERGENCE[script]
    if how == "reward":
        monkeypatch.setattr(RecordingPendulum, "scale", 1e37)
    reference = run_on_recording_pendulum(script, reference_length, tmp_path / "reference", monkeypatch)
    if how == "actor":
        poison_the_actor(monkeypatch, "mean head", at_step=200)
    with pytest.raises(SystemExit) as ended:
        run_on_recording_pendulum(script, 1000, tmp_path / "diverged", monkeypatch)
    assert ended.value.code == 1
    err = capsys.readouterr().err
    stopped = re.search(rf"^{script}: error: the training diverged: .*: training stopped at step {stop} of (1,000|896);"
                        rf" saving the model of step {kept}, the last sound one, without evaluating it$", err, re.M)  # fmt: skip
    assert stopped, err
    (run_dir,) = (tmp_path / "diverged" / "runs").iterdir()
    model = run_dir / f"{script}.cleanrl_model"
    saved, expected = torch.load(model, weights_only=True), torch.load(reference, weights_only=True)
    for part in parts:
        assert saved[part].keys() == expected[part].keys()
        assert all(torch.equal(saved[part][name], expected[part][name]) for name in saved[part]), part
    assert np.isfinite(load_script(script).evaluate(str(model), "Pendulum-v1", 1, 0)).all()


NORM_OBS = {"ppo_il": ["--norm-obs"], "trpo_il": ["--norm-obs", "True"]}  # TRPO's default follows the env: on for Lunar Lander


@pytest.mark.parametrize("script", ["ppo_il", "trpo_il"])
def test_the_last_sound_agent_is_saved_with_the_observation_statistics_of_its_rollout(script, tmp_path, monkeypatch, capsys, recorded):
    """A policy that overflows mid-rollout, on an observation unlike any before (1e4 at step 250, the 50th
    of the episode from reset seed 2), is rolled back to the agent of step 128, and its observation
    statistics with it: those of a 128-step run, not ones that the rollout since, the wild observation
    among them, has moved."""
    reference = torch.load(run_on_recording_pendulum(script, 128, tmp_path / "reference", monkeypatch, *NORM_OBS[script]), weights_only=True)
    capsys.readouterr()
    monkeypatch.setattr(RecordingPendulum, "wild_at", (2, 50))
    first = len(recorded)
    overflow_the_policy_at_its_first_update(monkeypatch, script, rig=overflow_on_a_wild_speed)
    with pytest.raises(SystemExit):
        run_on_recording_pendulum(script, 1000, tmp_path / "diverged", monkeypatch, *NORM_OBS[script])
    err = capsys.readouterr().err
    assert re.search(rf"^{script}: error: the training diverged: the policy's mean overflowed: training stopped at step 251 of 896;"
                     " saving the model of step 128, the last sound one, without evaluating it$", err, re.M), err  # fmt: skip
    assert len(recorded[first].actions) == 250  # the rigged policy was finite up to the wild observation: the run's training env, made first
    (run_dir,) = (tmp_path / "diverged" / "runs").iterdir()
    model = run_dir / f"{script}.cleanrl_model"
    saved = torch.load(model, weights_only=True)
    for stat in ("obs_mean", "obs_var"):
        assert torch.equal(saved[stat], reference[stat]), stat
    assert np.isfinite(load_script(script).evaluate(str(model), "Pendulum-v1", 1, 0)).all()


@pytest.mark.parametrize("script", ["sac_continuous", "jirl_sac_continuous"])
def test_an_episode_end_whose_critics_hold_a_nan_is_not_kept(script, tmp_path, monkeypatch, capsys, recorded):
    """The critics poisoned right after the actor's 100th step (step 198): at the episode end of step 199
    the actor is finite and the critics are not, so that model is not kept; the actor diverges at its next
    update, and with no sound model before, the diverged one is saved, refused when loaded."""
    poison_the_actor(monkeypatch, "critics", at_step=100)
    with pytest.raises(SystemExit):
        run_on_recording_pendulum(script, 1000, tmp_path / "run", monkeypatch)
    err = capsys.readouterr().err
    assert re.search(rf"^{script}: error: the training diverged: NaN or infinite values in the actor, .*: training stopped at step 201 of 1,000;"
                     " saving the model without evaluating it$", err, re.M), err  # fmt: skip
    (run_dir,) = (tmp_path / "run" / "runs").iterdir()
    with pytest.raises(ValueError, match=r"its actor holds a NaN or infinite weight$"):
        load_script(script).evaluate(str(run_dir / f"{script}.cleanrl_model"), "Pendulum-v1", 1, 0)


@pytest.mark.parametrize("script", ["sac_continuous", "jirl_sac_continuous"])
def test_sac_names_each_part_whose_weights_or_moments_hold_a_nan_or_an_infinity(script):
    module = load_script(script)
    sac = module.SoftActorCritic(3, 1, module.Args(hidden_size=8, batch_size=4))
    batch = tuple(torch.zeros(4, n) for n in (3, 1, 1, 3, 1))
    sac.update(batch, 0)  # both optimizers hold moments
    assert sac.divergence() == ""
    poison(sac.actor.fc_logstd.bias, math.nan)
    assert sac.divergence() == "NaN or infinite values in the actor"
    poison(sac.q_target_params[-1], -math.inf)
    assert sac.divergence() == "NaN or infinite values in the actor and the target critics"
    poison(sac.q_optimizer.state[sac.q_params[0]]["exp_avg_sq"], math.inf)  # a squared gradient beyond float32
    assert sac.divergence() == "NaN or infinite values in the actor, the target critics and the critics' optimizer"
    poison(sac.log_alpha, math.inf)
    poison(sac.q_params[0], math.nan)
    poison(sac.actor_optimizer.state[sac.log_alpha]["exp_avg"], math.nan)
    assert sac.divergence() == SAC_ALL


@pytest.mark.parametrize("script", ["ppo_il", "trpo_il"])
def test_the_gaussian_agent_names_each_part_that_holds_a_nan_or_an_infinity_and_a_degenerate_std(script):
    module = load_script(script)
    agent = module.Agent(3, 2, 8)
    assert agent.divergence() == ""
    for log_std, std in ((-200.0, 0.0), (100.0, math.inf)):  # finite, but exp() underflows or overflows in float32
        with torch.no_grad():
            agent.actor_logstd.copy_(torch.tensor([[0.5, log_std]]))
        assert torch.exp(torch.tensor(log_std)).item() == std
        assert agent.divergence() == f"a policy standard deviation of 0 or infinity (log-std [0.5, {log_std}])"
    poison(agent.actor_logstd, math.nan)
    assert agent.divergence() == "NaN or infinite weights in the policy's log-std"
    poison(list(agent.critic.parameters())[-1], math.inf)
    assert agent.divergence() == "NaN or infinite weights in the policy's log-std and the critic"
    poison(list(agent.actor_mean.parameters())[2], -math.inf)
    assert agent.divergence() == "NaN or infinite weights in the policy's mean, the policy's log-std and the critic"


class NoLogs:
    def add_scalar(self, *args, **kwargs) -> None:
        pass


@pytest.mark.parametrize("script", ["ppo_il", "trpo_il"])
def test_imitation_that_diverges_is_an_error_naming_the_part(script):
    module = load_script(script)
    rng = np.random.default_rng(0)
    obs, actions = rng.normal(size=(40, 3)).astype(np.float32), rng.uniform(-1, 1, size=(40, 1)).astype(np.float32)
    returns = np.full(40, -np.inf, dtype=np.float32)  # what float32 made of returns beyond its range, fitted by the value function
    args = module.Args(il_max_epochs=2, il_value_epochs=1)
    with pytest.raises(ValueError, match=r"^imitation diverged: NaN or infinite weights in the critic$"):
        module.imitate(module.Agent(3, 1, 8), obs, actions, returns, args, NoLogs(), rng)
    module.imitate(module.Agent(3, 1, 8), obs, actions, np.full(40, -1e30, dtype=np.float32), args, NoLogs(), rng)  # large, finite: fitted


class ConstantRewardPendulum(PendulumEnv):
    reward = -1e37

    def step(self, action):
        obs, _, terminated, truncated, info = super().step(action)
        return obs, self.reward, terminated, truncated, info


gym.register("ConstantRewardPendulum-v0", entry_point=ConstantRewardPendulum, max_episode_steps=200)


@pytest.mark.parametrize("script", ["ppo_il", "trpo_il"])
def test_baseline_returns_beyond_float32_are_a_one_line_error_before_imitation(script, tmp_path, monkeypatch, writers_closed):
    monkeypatch.chdir(tmp_path)
    largest = 1e37 * sum(0.99**k for k in range(200))  # the first step's return-to-go in a 200-step episode of reward -1e37
    assert largest > float(np.finfo(np.float32).max)
    args = [*SHORT_RUNS[script], "--env-id", f"{__name__}:ConstantRewardPendulum-v0", "--gamma", "0.99", "--baseline", "test_stopping:zero_torque",
            "--regret-estimator", "off", "--save-model"]  # fmt: skip
    monkeypatch.setattr(sys, "argv", [f"{script}.py", *args])
    with pytest.raises(SystemExit) as ended:
        runpy.run_path(str(ROOT / f"{script}.py"), run_name="__main__")
    assert ended.value.code == f"{script}: error: the baseline's discounted returns reach {largest:.3g}, beyond float32's range; scale the env's rewards down"
    assert not list(tmp_path.glob("runs/*/*.cleanrl_model"))


def test_trpos_line_search_rejects_a_trial_step_to_a_policy_that_is_no_distribution():
    trpo = load_script("trpo_il")
    torch.manual_seed(0)
    agent = trpo.Agent(3, 1, 8)
    obs, advantages = torch.randn(64, 3), torch.randn(64)
    with torch.no_grad():
        actions, logprobs, _, _ = agent.get_action_and_value(obs)
    before = [p.clone() for p in agent.parameters()]
    args = trpo.Args(max_kl=1e30)  # a region so wide that every trial step's standard deviation is 0 or infinite in float32
    step = trpo.trpo_step(agent, obs, actions, logprobs, advantages, args)
    assert step["accepted"] is False and step["kl"] == 0.0  # each rejected (its KL is not <= max_kl), not torch's error
    assert all(torch.equal(a, b) for a, b in zip(agent.parameters(), before)) and agent.divergence() == ""
