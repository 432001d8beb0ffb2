"""ppo_il.py and trpo_il.py: TRPO's mathematics, the imitation phase, and short end-to-end runs."""

import os
import runpy
import shutil
import sys

import numpy as np
import pytest
import torch
from torch.func import functional_call

from conftest import ROOT, load_script
from test_sac_script import run_script, scalars

trpo = load_script("trpo_il")
ppo = load_script("ppo_il")


def test_conjugate_gradient_solves_a_positive_definite_system():
    rng = np.random.default_rng(0)
    m = rng.normal(size=(12, 12))
    a = torch.tensor(m @ m.T + 0.5 * np.eye(12))
    b = torch.tensor(rng.normal(size=12))
    x = trpo.conjugate_gradient(lambda v: a @ v, b, max_steps=40, residual_tol=1e-20)
    np.testing.assert_allclose(x.numpy(), np.linalg.solve(a.numpy(), b.numpy()), rtol=1e-8, atol=1e-8)


def test_fisher_vector_product_equals_the_explicit_fisher_matrix():
    torch.manual_seed(0)
    agent = trpo.Agent(obs_dim=2, act_dim=2, hidden_size=3).double()
    with torch.no_grad():
        agent.actor_logstd.copy_(torch.tensor([[-0.3, 0.4]]))
    obs = torch.randn(7, 2, dtype=torch.float64)
    names = ["actor_mean." + n for n, _ in agent.actor_mean.named_parameters()] + ["actor_logstd"]
    params = trpo.policy_params(agent)
    shapes = [p.shape for p in params]
    theta0 = torch.nn.utils.parameters_to_vector(params).detach()
    old_mean, old_std = agent.actor_mean(obs).detach(), agent.actor_logstd.exp().detach()

    def mean_kl(theta):  # KL(pi_old || pi_theta) for diagonal Gaussians, written out
        chunks, i = {}, 0
        for name, shape in zip(names, shapes):
            chunks[name] = theta[i : i + shape.numel()].view(shape)
            i += shape.numel()
        sub = {k.removeprefix("actor_mean."): v for k, v in chunks.items() if k.startswith("actor_mean.")}
        mean = functional_call(agent.actor_mean, sub, (obs,))
        std = chunks["actor_logstd"].exp()
        kl = torch.log(std / old_std) + (old_std**2 + (old_mean - mean) ** 2) / (2 * std**2) - 0.5
        return kl.sum(1).mean()

    fisher = torch.autograd.functional.hessian(mean_kl, theta0)
    v = torch.randn_like(theta0)
    got = trpo.fisher_vector_product(agent, obs, v, damping=0.1)
    torch.testing.assert_close(got, fisher @ v + 0.1 * v, rtol=1e-9, atol=1e-9)


def sampled_batch(seed: int, act_dim: int, hidden_size: int, n: int):
    """A fresh agent, observations, actions sampled from it, and their log-probabilities."""
    torch.manual_seed(seed)
    agent = trpo.Agent(obs_dim=3, act_dim=act_dim, hidden_size=hidden_size)
    obs = torch.randn(n, 3)
    with torch.no_grad():
        dist = trpo.policy_distribution(agent, obs)
        actions = dist.sample()
    return agent, obs, actions, dist.log_prob(actions).sum(1)


def test_trpo_step_respects_the_trust_region_and_improves_the_surrogate():
    agent, obs, actions, old_logprobs = sampled_batch(1, act_dim=2, hidden_size=16, n=512)
    with torch.no_grad():
        before = trpo.policy_distribution(agent, obs)
        before = torch.distributions.Normal(before.loc.clone(), before.scale.clone())
    advantages = (actions[:, 0] - actions[:, 1]) + 0.1 * torch.randn(512)  # learnable: prefer a0 > a1
    advantages = (advantages - advantages.mean()) / advantages.std()
    for max_kl in (0.01, 0.001):
        args = trpo.Args(max_kl=max_kl)
        result = trpo.trpo_step(agent, obs, actions, old_logprobs, advantages, args)
        assert result["accepted"]
        with torch.no_grad():
            measured = torch.distributions.kl_divergence(before, trpo.policy_distribution(agent, obs)).sum(1).mean().item()
        assert 0.0 < measured <= max_kl * (1 + 1e-6)
        assert result["objective"] > 0.0  # surrogate at the old policy is E[A] = 0
        with torch.no_grad():  # the next step starts from here
            dist = trpo.policy_distribution(agent, obs)
            old_logprobs = dist.log_prob(actions).sum(1)
            before = torch.distributions.Normal(dist.loc.clone(), dist.scale.clone())


def test_line_search_keeps_the_old_policy_when_nothing_improves():
    agent, obs, actions, old_logprobs = sampled_batch(2, act_dim=1, hidden_size=8, n=64)
    start = torch.nn.utils.parameters_to_vector(trpo.policy_params(agent)).detach().clone()
    result = trpo.trpo_step(agent, obs, actions, old_logprobs, torch.zeros(64), trpo.Args())  # zero advantages
    assert not result["accepted"]
    torch.testing.assert_close(torch.nn.utils.parameters_to_vector(trpo.policy_params(agent)), start)


@pytest.mark.parametrize("script", [ppo, trpo], ids=["ppo_il", "trpo_il"])
def test_imitation_clones_the_pendulum_baseline(script, tmp_path):
    from torch.utils.tensorboard import SummaryWriter

    from envs import BASELINES, make_env

    args = script.resolve_hyperparameters(script.Args(il_steps=6000, il_max_epochs=150, il_init_std=0.3))
    data = script.collect_baseline_data(make_env("Pendulum-v1"), BASELINES["Pendulum-v1"], 6000, 0, args.gamma)
    assert len(data["obs"]) == 6000  # 30 whole episodes of 200 steps
    rewards = data["running_returns"].reshape(30, 200).copy()  # what --norm-reward sees: G_t = gamma G_(t-1) + r_t
    rewards[:, 1:] -= args.gamma * data["running_returns"].reshape(30, 200)[:, :-1]
    for t in reversed(range(199)):  # the same rewards give the returns-to-go, summed the other way
        rewards[:, t] += args.gamma * rewards[:, t + 1]
    np.testing.assert_allclose(rewards.ravel(), data["returns"], rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(data["actions"], np.array([BASELINES["Pendulum-v1"](o) for o in data["obs"]]) / 2.0, atol=1e-6)
    torch.manual_seed(0)
    agent = script.Agent(3, 1, 64)
    x = torch.from_numpy(data["obs"])
    with torch.no_grad():
        mse_before = ((agent.actor_mean(x) - torch.from_numpy(data["actions"])) ** 2).mean().item()
        value_error_before = ((agent.critic(x)[:, 0] - torch.from_numpy(data["returns"])) ** 2).mean().item()
    writer = SummaryWriter(str(tmp_path))
    result = script.imitate(agent, data["obs"], data["actions"], data["returns"], args, writer, np.random.default_rng(0))
    writer.close()
    assert result["action_mse"] < 5e-3 < mse_before  # held-out MSE in policy units^2 (torque / 2 N m)
    assert agent.actor_logstd.exp().detach().numpy() == pytest.approx(0.3)
    with torch.no_grad():
        value_error = ((agent.critic(x)[:, 0] - torch.from_numpy(data["returns"])) ** 2).mean().item()
    assert value_error < 0.2 * value_error_before


@pytest.mark.parametrize("script", [ppo, trpo], ids=["ppo_il", "trpo_il"])
def test_imitation_that_never_fits_is_a_clear_error(script, tmp_path):
    from torch.utils.tensorboard import SummaryWriter

    obs = np.random.default_rng(0).normal(size=(200, 3)).astype(np.float32)
    obs[:, 0] = np.nan  # a broken env: every held-out error is NaN, so no fit is ever the best
    agent = script.Agent(3, 1, 16)
    writer = SummaryWriter(str(tmp_path))
    args = script.resolve_hyperparameters(script.Args(il_max_epochs=3))
    with pytest.raises(ValueError, match="no finite held-out action error"):
        script.imitate(agent, obs, np.zeros((200, 1), np.float32), np.zeros(200, np.float32), args, writer, np.random.default_rng(0))
    writer.close()


SHORT = {
    "ppo_il": ["--num-steps", "256", "--num-minibatches", "4", "--update-epochs", "2"],
    "trpo_il": ["--num-steps", "256", "--n-critic-updates", "2"],
}


@pytest.mark.parametrize("name", ["ppo_il", "trpo_il"])
def test_end_to_end_logs_saves_and_evaluates(name, tmp_path):
    args = [*SHORT[name], "--total-timesteps", "700", "--il-steps", "600", "--il-max-epochs", "20",
            "--hidden-size", "16", "--save-model", "--eval-episodes", "2", "--baseline-eval-episodes", "2"]  # fmt: skip
    out = run_script(ROOT / f"{name}.py", args, tmp_path)
    assert out.returncode == 0, out.stderr
    (run_dir,) = (tmp_path / "runs").iterdir()
    logged = scalars(run_dir)
    for key in ["charts/episodic_return", "charts/SPS", "charts/baseline_regret", "charts/baseline_regret_per_step",
                "charts/baseline_return", "losses/value_loss", "losses/explained_variance", "il/bc_loss",
                "il/action_mse", "il/env_steps", "il/eval_return", "eval/episodic_return"]:  # fmt: skip
        assert key in logged, key
        assert np.all(np.isfinite(logged[key])), key
    assert logged["il/env_steps"] == [600.0]
    assert len(logged["charts/SPS"]) == 2  # 700 steps round down to two whole rollouts of 256
    model = next(p for p in run_dir.glob("*.cleanrl_model") if not p.name.endswith("_cloned.cleanrl_model"))
    script = load_script(name)
    returns = script.evaluate(str(model), "Pendulum-v1", 2, 1)
    np.testing.assert_allclose(returns, logged["eval/episodic_return"], rtol=1e-5)
    broken = tmp_path / "broken.cleanrl_model"
    broken.write_bytes(model.read_bytes()[:100])
    with pytest.raises(ValueError, match="not a readable checkpoint"):
        script.evaluate(str(broken), "Pendulum-v1", 1, 1)
    other_bounds = torch.load(model, weights_only=True) | {"action_low": [-1.0], "action_high": [1.0]}  # same sizes, other units
    torch.save(other_bounds, tmp_path / "other_bounds.cleanrl_model")
    with pytest.raises(ValueError, match="checkpoint action bounds differ"):
        script.evaluate(str(tmp_path / "other_bounds.cleanrl_model"), "Pendulum-v1", 1, 1)
    no_statistics = {k: v for k, v in torch.load(model, weights_only=True).items() if k != "obs_var"}
    torch.save(no_statistics, tmp_path / "no_statistics.cleanrl_model")
    with pytest.raises(ValueError, match="damaged jirl-gaussian-checkpoint-v1 checkpoint: it has no obs_var$"):
        script.evaluate(str(tmp_path / "no_statistics.cleanrl_model"), "Pendulum-v1", 1, 1)


@pytest.mark.parametrize("name", ["ppo_il", "trpo_il"])
def test_norm_reward_fits_the_value_in_the_scaled_units(name, tmp_path):
    """With --norm-reward the reward scale starts from the baseline's steps, and the cloned critic
    predicts returns in those units, not in the env's (which would make RL's first advantages wrong)."""
    from envs import BASELINES, make_env

    norm_reward = ["--norm-reward"] if name == "ppo_il" else ["--norm-reward", "True"]  # trpo_il's is Optional (tuned)
    args = [*SHORT[name], *norm_reward, "--total-timesteps", "256", "--il-steps", "2000", "--il-max-epochs", "5",
            "--il-value-epochs", "100", "--save-model", "--eval-episodes", "1", "--baseline-eval-episodes", "1"]  # fmt: skip
    out = run_script(ROOT / f"{name}.py", args, tmp_path)
    assert out.returncode == 0, out.stderr
    (run_dir,) = (tmp_path / "runs").iterdir()
    env, baseline, script = make_env("Pendulum-v1"), BASELINES["Pendulum-v1"], load_script(name)
    obs_list, running, returns = [], [], []  # the imitation phase's 10 episodes, replayed here
    for episode in range(10):
        obs, _ = env.reset(seed=1 + script.IL_SEED_OFFSET + episode)
        rewards, done = [], False
        while not done:
            obs_list.append(obs)
            obs, reward, terminated, truncated, _ = env.step(baseline(obs))
            rewards.append(reward)
            running.append(0.9 * (running[-1] if len(rewards) > 1 else 0.0) + reward)  # Pendulum's gamma 0.9
            done = terminated or truncated
        returns += [sum(0.9**k * r for k, r in enumerate(rewards[t:])) for t in range(len(rewards))]
    scale = np.std(running)
    assert scalars(run_dir)["il/reward_scale"] == [pytest.approx(scale, rel=1e-3)]
    cloned = script.load_checkpoint(str(next(run_dir.glob("*_cloned.cleanrl_model"))))
    agent = script.Agent(3, 1, cloned["hidden_size"])
    agent.load_state_dict(cloned["agent"])
    with torch.no_grad():
        predicted = agent.get_value(torch.tensor(np.array(obs_list), dtype=torch.float32))[:, 0].numpy()
    target = np.array(returns) / scale
    assert abs(predicted.mean() - target.mean()) < 0.1 * abs(np.mean(returns) - target.mean())
    assert np.mean((predicted - target) ** 2) < 0.2 * np.var(target)


@pytest.mark.parametrize("name", ["ppo_il", "trpo_il"])
def test_script_copied_alone_runs_with_a_user_baseline(name, tmp_path):
    shutil.copy(ROOT / f"{name}.py", tmp_path)
    (tmp_path / "their_controller.py").write_text(
        "import numpy as np\ndef damp(obs):\n    return np.array([-1.0 * obs[2]], dtype=np.float32)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    args = [*SHORT[name], "--env-id", "Pendulum-v1", "--baseline", "their_controller:damp", "--total-timesteps", "256",
            "--il-steps", "400", "--il-max-epochs", "5", "--hidden-size", "16", "--baseline-eval-episodes", "1"]  # fmt: skip
    out = run_script(tmp_path / f"{name}.py", args, tmp_path, env)
    assert out.returncode == 0, out.stderr
    assert "baseline regret estimator: paired" in out.stdout


def test_ppo_minibatches_take_every_step_and_normalised_advantages_need_two(tmp_path):
    common = ["--total-timesteps", "257", "--il-steps", "400", "--il-max-epochs", "5", "--hidden-size", "16",
              "--update-epochs", "2", "--baseline-eval-episodes", "1"]  # fmt: skip
    # 257 steps in 4 minibatches: slicing by 64 left a minibatch of one step, whose advantage std is NaN
    out = run_script(ROOT / "ppo_il.py", [*common, "--num-steps", "257", "--num-minibatches", "4"], tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    (run_dir,) = (tmp_path / "runs").iterdir()
    logged = scalars(run_dir)
    for key in ("losses/policy_loss", "losses/value_loss", "losses/approx_kl"):
        assert len(logged[key]) == 1 and np.isfinite(logged[key][0]), key
    out = run_script(ROOT / "ppo_il.py", [*common, "--num-steps", "5", "--num-minibatches", "4"], tmp_path)
    assert out.returncode != 0 and "--num-steps 5 in --num-minibatches 4 leaves minibatches of 1 step(s); they need 2" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1
    out = run_script(ROOT / "ppo_il.py", [*common, "--num-steps", "5", "--num-minibatches", "4", "--no-norm-adv"], tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]


ONE_STEP_ENV = """
import gymnasium as gym
import numpy as np


class Bandit(gym.Env):
    \"\"\"A contextual bandit: every episode is one step, rewarded for matching the context.\"\"\"

    observation_space = gym.spaces.Box(-1.0, 1.0, (1,))
    action_space = gym.spaces.Box(-1.0, 1.0, (1,))

    def __init__(self, render_mode=None):
        self.render_mode = render_mode

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.context = self.np_random.uniform(-1.0, 1.0, (1,)).astype(np.float32)
        return self.context.copy(), {}

    def step(self, action):
        return self.context.copy(), -float(abs(action[0] - self.context[0])), True, False, {}


gym.register("Bandit-v0", entry_point=Bandit)


def match(obs):
    return obs
"""


@pytest.mark.parametrize("name", ["ppo_il", "trpo_il"])
def test_one_step_episodes_need_two_imitation_steps(name, tmp_path):
    (tmp_path / "bandit.py").write_text(ONE_STEP_ENV)
    env = os.environ | {"PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    common = [*SHORT[name], "--env-id", "bandit:Bandit-v0", "--baseline", "bandit:match", "--total-timesteps", "100",
              "--il-max-epochs", "5", "--hidden-size", "16", "--baseline-eval-episodes", "2"]  # fmt: skip
    out = run_script(ROOT / f"{name}.py", [*common, "--il-steps", "1"], tmp_path, env)
    assert out.returncode != 0 and "imitation needs at least 2 baseline steps (one is held out), got 1" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1
    out = run_script(ROOT / f"{name}.py", [*common, "--il-steps", "2"], tmp_path, env)
    assert out.returncode == 0, out.stderr
    assert "imitation: 2 baseline steps" in out.stdout and "baseline: return 0.0" in out.stdout
    assert out.stdout.count("SPS:") == 1  # 100 steps, less than a rollout, still run one whole rollout of 256


@pytest.mark.parametrize("name", ["ppo_il", "trpo_il"])
def test_unknown_env_is_a_one_line_error(name, tmp_path):
    out = run_script(ROOT / f"{name}.py", ["--env-id", "NoSuchEnv-v0"], tmp_path)
    assert out.returncode != 0 and "unknown env id 'NoSuchEnv-v0'" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "runs").exists(), "nothing is written before the input is validated"


def test_zoo_hyperparameters_fill_only_what_the_user_left_unset():
    args = ppo.resolve_hyperparameters(ppo.Args(env_id="LunarLanderContinuous-v3", gamma=0.95))
    assert (args.gamma, args.num_steps, args.gae_lambda, args.ent_coef) == (0.95, 16384, 0.98, 0.01)
    args = trpo.resolve_hyperparameters(trpo.Args(env_id="Pendulum-v1"))
    assert (args.gamma, args.n_critic_updates, args.num_steps, args.norm_obs) == (0.9, 15, 2048, False)
    args = trpo.resolve_hyperparameters(trpo.Args(env_id="MountainCarContinuous-v0"))
    assert (args.gamma, args.n_critic_updates) == (0.99, 10)


def test_unset_ppo_minibatches_hold_64_steps_of_the_rollout_the_user_set():
    # RL Zoo's 4096 / 64, 16384 / 256 and CleanRL's 2048 / 32 are all minibatches of 64 steps
    expected = {"Pendulum-v1": 64, "LunarLanderContinuous-v3": 256, "MountainCarContinuous-v0": 32}
    for env_id, minibatches in expected.items():
        assert ppo.resolve_hyperparameters(ppo.Args(env_id=env_id)).num_minibatches == minibatches
    # a shorter rollout keeps the minibatch size, not the count (64 minibatches of 4 steps before)
    assert ppo.resolve_hyperparameters(ppo.Args(num_steps=256)).num_minibatches == 4
    assert ppo.resolve_hyperparameters(ppo.Args(num_steps=100)).num_minibatches == 1
    assert ppo.resolve_hyperparameters(ppo.Args(num_steps=256, num_minibatches=8)).num_minibatches == 8


@pytest.mark.parametrize("num_steps, ends_at", [(256, [399 - 256]), (300, [399 - 300, 599 - 300])])
@pytest.mark.parametrize("name", ["ppo_il", "trpo_il"])
def test_the_last_rollouts_advantages_are_gae_summed_up_to_each_episode_end(name, num_steps, ends_at, tmp_path, monkeypatch):
    """A_t = sum_k (gamma lambda)^k delta_{t+k}, stopping at the end of s_t's episode, written as that sum
    rather than the scripts' backward recursion; the value targets are A + V. Of two rollouts, the second
    holds the end of Pendulum-v1's second episode (step 400) and ends mid-episode (256 steps, bootstrapped
    from V) or with the third episode (300 steps)."""
    monkeypatch.chdir(tmp_path)
    argv = [f"{name}.py", *SHORT[name], "--num-steps", str(num_steps), "--total-timesteps", str(2 * num_steps), "--il-steps", "200", "--il-max-epochs", "5",
            "--hidden-size", "16", "--baseline-eval-episodes", "1", "--gae-lambda", "0.9"]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    g = runpy.run_path(str(ROOT / f"{name}.py"), run_name="__main__")
    gamma, lam = g["args"].gamma, 0.9
    rewards, values, dones = (g[key].numpy().astype(np.float64) for key in ("rewards", "values", "dones"))
    next_values = np.append(values[1:], float(g["next_value"]))
    ends = np.append(dones[1:], float(g["next_done"])) == 1.0  # s_{t+1} starts a new episode: s_t's ended
    assert ends.nonzero()[0].tolist() == ends_at
    deltas = rewards + gamma * next_values * ~ends - values
    expected = np.zeros(len(rewards))
    for t in range(len(rewards)):
        for k in range(len(rewards) - t):
            expected[t] += (gamma * lam) ** k * deltas[t + k]
            if ends[t + k]:
                break
    np.testing.assert_allclose(g["advantages"].numpy(), expected, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(g["returns"].numpy(), expected + values, rtol=1e-4, atol=1e-4)
