"""ppo_il.py and trpo_il.py: TRPO's mathematics, the imitation phase, and short end-to-end runs."""

import os
import runpy
import shutil
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.envs.classic_control.pendulum import PendulumEnv
from torch.func import functional_call

from conftest import ROOT, load_script, printed_regret
from test_sac_script import readme_keys, run_script, scalars

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
    theta0 = torch.nn.utils.parameters_to_vector(trpo.policy_params(agent)).detach()
    old_mean, old_std = agent.actor_mean(obs).detach(), agent.actor_logstd.exp().detach()

    def mean_kl(theta):  # KL(pi_old || pi_theta) for diagonal Gaussians, written out
        return mean_gaussian_kl(old_mean, old_std, *policy_at(agent, theta, obs))

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


def gaussian_log_density(actions, mean, std):
    """log N(actions; mean, std^2) summed over the action dimensions, for numpy arrays or torch tensors."""
    log_std = std.log() if isinstance(std, torch.Tensor) else np.log(std)
    return (-0.5 * ((actions - mean) / std) ** 2 - log_std - 0.5 * np.log(2 * np.pi)).sum(1)


def mean_gaussian_kl(old_mean, old_std, mean, std) -> torch.Tensor:
    """KL(N(old_mean, old_std^2) || N(mean, std^2)) summed over the action dimensions, averaged over the states."""
    return (torch.log(std / old_std) + (old_std**2 + (old_mean - mean) ** 2) / (2 * std**2) - 0.5).sum(1).mean()


def mean_gaussian_entropy(std: torch.Tensor) -> torch.Tensor:
    """The entropy of N(mean, std^2) summed over the action dimensions, averaged over the states."""
    return (0.5 + 0.5 * np.log(2 * np.pi) + std.log()).sum(1).mean()


def policy_at(agent, theta: torch.Tensor, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The policy's mean and std with its parameters (actor_mean's, then the log-std) set to theta."""
    chunks, i = {}, 0
    for name, p in [*agent.actor_mean.named_parameters(), ("log_std", agent.actor_logstd)]:
        chunks[name] = theta[i : i + p.numel()].view(p.shape)
        i += p.numel()
    log_std = chunks.pop("log_std")
    return functional_call(agent.actor_mean, chunks, (obs,)), log_std.exp().expand(len(obs), -1)


@pytest.mark.parametrize("max_kl, line_search_max_iter", [(1e-3, 10), (100.0, 10), (100.0, 3)])
def test_trpo_step_is_the_natural_gradient_step_shrunk_until_the_kl_fits_and_the_surrogate_improves(max_kl, line_search_max_iter):
    """The step is sqrt(2 max_kl / s^T F s) s with s = F^-1 g from the explicit (damped) Fisher matrix,
    times the first of 1, 0.8, 0.64, ... at which the mean KL is within --max-kl and the surrogate is
    above its start, both written out here; if none is, the policy is left exactly as it was. The
    advantages prefer actions near 1, so a long step overshoots: at max_kl 100 the search rejects
    fractions for their KL and one for its surrogate alone before it accepts the eighth."""
    torch.manual_seed(0)
    agent = trpo.Agent(obs_dim=3, act_dim=1, hidden_size=4).double()
    obs = torch.randn(256, 3, dtype=torch.float64)
    theta0 = torch.nn.utils.parameters_to_vector(trpo.policy_params(agent)).detach().clone()
    with torch.no_grad():
        old_mean, old_std = policy_at(agent, theta0, obs)
        actions = torch.normal(old_mean, old_std)
    old_logprobs = gaussian_log_density(actions, old_mean, old_std)
    advantages = -((actions[:, 0] - 1.0) ** 2)
    advantages = (advantages - advantages.mean()) / advantages.std()

    def mean_kl(theta):
        mean, std = policy_at(agent, theta, obs)
        return mean_gaussian_kl(old_mean, old_std, mean, std)

    def surrogate(theta):
        return (torch.exp(gaussian_log_density(actions, *policy_at(agent, theta, obs)) - old_logprobs) * advantages).mean()

    damping = 0.1
    fisher = torch.autograd.functional.hessian(mean_kl, theta0) + damping * torch.eye(len(theta0), dtype=torch.float64)
    gradient = torch.autograd.functional.jacobian(surrogate, theta0)
    direction = torch.linalg.solve(fisher, gradient)
    full_step = torch.sqrt(2 * max_kl / (direction @ fisher @ direction)) * direction
    with torch.no_grad():
        fractions = 0.8 ** np.arange(line_search_max_iter)
        kls = np.array([mean_kl(theta0 + f * full_step).item() for f in fractions])
        objectives = np.array([surrogate(theta0 + f * full_step).item() for f in fractions])
        start = surrogate(theta0).item()
    acceptable = (kls <= max_kl) & (objectives > start)

    args = trpo.Args(max_kl=max_kl, cg_damping=damping, cg_max_steps=100, line_search_max_iter=line_search_max_iter)
    result = trpo.trpo_step(agent, obs, actions, old_logprobs, advantages, args)
    theta = torch.nn.utils.parameters_to_vector(trpo.policy_params(agent)).detach()
    if line_search_max_iter == 3:  # nothing acceptable: the policy is untouched
        assert not acceptable.any() and not result["accepted"] and result["step_fraction"] == 0.0
        assert torch.equal(theta, theta0) and result["objective"] == pytest.approx(start)
        return
    first = int(np.argmax(acceptable))
    assert acceptable.any() and result["accepted"] and result["step_fraction"] == pytest.approx(fractions[first])
    assert result["kl"] == pytest.approx(kls[first], rel=1e-6) and result["objective"] == pytest.approx(objectives[first], rel=1e-6)
    torch.testing.assert_close(theta, theta0 + fractions[first] * full_step, rtol=1e-4, atol=1e-6)  # CG stops at its tolerance
    if max_kl < 1:  # a short step: the quadratic model holds, the whole step is taken and its KL is near max_kl
        assert first == 0 and 0.85 * max_kl < kls[0] <= max_kl
    else:
        rejected = slice(0, first)
        assert first == 7
        assert (kls[rejected] > max_kl).any() and ((kls[rejected] <= max_kl) & (objectives[rejected] <= start)).any()


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


class ScalarLog:
    """The writer's add_scalar, kept in memory: key -> [(step, value), ...]."""

    def __init__(self) -> None:
        self.scalars: dict = {}

    def add_scalar(self, key: str, value: float, step: int) -> None:
        self.scalars.setdefault(key, []).append((step, value))


@pytest.mark.parametrize("script", [ppo, trpo], ids=["ppo_il", "trpo_il"])
def test_cloning_trains_on_nine_tenths_stops_on_the_other_tenth_and_keeps_its_best_epoch(script):
    """Behaviour cloning never trains on its held-out tenth; each epoch takes every other step once, in a
    new order; it stops --il-patience epochs after the best held-out error (or at once below
    --il-target-mse) and keeps that best epoch's mean. The value is then fitted on every step."""
    n = 60
    data_rng = np.random.default_rng(1)
    obs = data_rng.normal(size=(n, 3)).astype(np.float32)
    obs[:, 0] = np.arange(n) / n  # names each row
    actions = np.tanh(obs @ np.array([[1.5], [-0.8], [0.6]])).astype(np.float32)
    returns = data_rng.normal(size=n).astype(np.float32)
    order = np.random.default_rng(0).permutation(n)  # the split imitate draws from the same rng
    held_out, fit = order[:6], order[6:]

    calls = []  # (network, training?, rows), at every forward pass

    def record(network):
        return lambda module, inputs, output: calls.append((network, torch.is_grad_enabled(), [int(i) for i in torch.round(inputs[0][:, 0] * n)]))

    torch.manual_seed(0)
    agent = script.Agent(3, 1, 32)
    agent.actor_mean.register_forward_hook(record("mean"))
    agent.critic.register_forward_hook(record("critic"))
    args = script.resolve_hyperparameters(script.Args(il_lr=0.03, il_batch_size=16, il_patience=3, il_target_mse=0.0,
                                                      il_max_epochs=200, il_value_epochs=5, il_init_std=0.4))  # fmt: skip
    log = ScalarLog()
    result = script.imitate(agent, obs, actions, returns, args, log, np.random.default_rng(0))

    held_out_mse = [value for _, value in log.scalars["il/action_mse"]]
    epochs = len(held_out_mse)
    assert [step for step, _ in log.scalars["il/action_mse"]] == list(range(1, epochs + 1)) and result["epochs"] == epochs
    best = int(np.argmin(held_out_mse))
    assert epochs == best + 1 + 3 < 200  # three epochs without a better held-out error end it
    trained = [rows for network, training, rows in calls if network == "mean" and training]
    checked = [rows for network, training, rows in calls if network == "mean" and not training]
    assert [len(rows) for rows in trained] == [16, 16, 16, 6] * epochs
    per_epoch = [sum(trained[4 * e : 4 * e + 4], []) for e in range(epochs)]
    assert all(sorted(rows) == sorted(fit) for rows in per_epoch)  # the held-out rows never
    assert all(a != b for a, b in zip(per_epoch, per_epoch[1:]))  # reshuffled every epoch
    assert checked == [list(held_out)] * epochs
    with torch.no_grad():
        kept = ((agent.actor_mean(torch.from_numpy(obs[held_out])) - torch.from_numpy(actions[held_out])) ** 2).mean().item()
    assert kept == pytest.approx(held_out_mse[best], rel=1e-6) == result["action_mse"]
    assert held_out_mse[best] < held_out_mse[-1]
    assert agent.actor_logstd.exp().item() == pytest.approx(0.4)
    valued = [rows for network, training, rows in calls if network == "critic" and training]
    assert [len(rows) for rows in valued] == [16, 16, 16, 12] * 5
    per_value_epoch = [sum(valued[4 * e : 4 * e + 4], []) for e in range(5)]
    assert all(sorted(rows) == list(range(n)) for rows in per_value_epoch)  # the held-out rows too
    assert all(a != b for a, b in zip(per_value_epoch, per_value_epoch[1:]))

    loose = script.resolve_hyperparameters(script.Args(il_target_mse=10.0, il_patience=3, il_value_epochs=1))
    quick = script.imitate(script.Agent(3, 1, 32), obs, actions, returns, loose, ScalarLog(), np.random.default_rng(0))
    assert quick["epochs"] == 1  # the first held-out error is already below the target


@pytest.mark.parametrize("script", [ppo, trpo], ids=["ppo_il", "trpo_il"])
def test_evaluation_replays_the_mean_action_on_the_saved_statistics_from_the_evaluation_seeds(script, tmp_path):
    torch.manual_seed(0)
    agent = script.Agent(3, 1, 16)
    with torch.no_grad():
        agent.actor_mean[4].weight.mul_(100.0)  # torques of 0.6 N m (the median), not the initial 0.01
    obs_rms = script.RunningMeanStd((3,))
    mean, var = np.array([0.5, -0.2, 1.0]), np.array([0.3, 0.6, 4.0])
    obs_rms.mean, obs_rms.var = mean.copy(), var.copy()
    path = tmp_path / "model.cleanrl_model"
    script.save_checkpoint(str(path), "Pendulum-v1", script.make_env("Pendulum-v1", 0), agent, obs_rms, script.Args(hidden_size=16))
    expected, torques = [], []
    for i in range(2):  # written out: episode i from reset seed 7 + 1,000,000 + i, the mean action, 2 N m per policy unit
        env = gym.make("Pendulum-v1")
        obs, _ = env.reset(seed=7 + 1_000_000 + i)
        episode_return, done = 0.0, False
        while not done:
            x = np.clip((obs - mean) / np.sqrt(var + 1e-8), -10.0, 10.0).astype(np.float32)
            with torch.no_grad():
                torque = 2.0 * agent.actor_mean(torch.from_numpy(x)).numpy()
            obs, reward, terminated, truncated, _ = env.step(torque)
            episode_return, done = episode_return + reward, terminated or truncated
            torques.append(abs(torque[0]))
        expected.append(episode_return)
    assert np.median(torques) > 0.3
    assert script.evaluate(str(path), "Pendulum-v1", 2, 7) == pytest.approx(expected, rel=1e-6)


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
    assert set(logged) - readme_keys() == set(), "keys the README does not name"
    assert logged["il/env_steps"] == [600.0]
    assert len(logged["charts/SPS"]) == 2  # 700 steps round down to two whole rollouts of 256
    # the run ends by printing the regret it logged at its last episode end
    assert "baseline regret (paired): " in out.stdout
    assert printed_regret(out.stdout) == pytest.approx((logged["charts/baseline_regret"][-1], logged["charts/baseline_regret_per_step"][-1]), abs=0.05)
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
def test_normalisation_starts_from_the_baseline_steps_and_the_value_is_fitted_in_the_scaled_units(name, tmp_path):
    """With --norm-obs and --norm-reward the observation statistics and the reward scale start from the
    baseline's steps, and the cloned critic predicts returns in those units, not in the env's (which
    would make RL's first advantages wrong)."""
    from envs import BASELINES, make_env

    on = [] if name == "ppo_il" else ["True"]  # trpo_il's are Optional (tuned)
    args = [*SHORT[name], "--norm-obs", *on, "--norm-reward", *on, "--total-timesteps", "256", "--il-steps", "2000", "--il-max-epochs", "5",
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
    obs_array = np.array(obs_list, dtype=np.float64)
    np.testing.assert_allclose(cloned["obs_mean"].numpy(), obs_array.mean(0), rtol=1e-6)  # the prior's count of 1e-4 is below that
    np.testing.assert_allclose(cloned["obs_var"].numpy(), obs_array.var(0), rtol=1e-6)
    agent = script.Agent(3, 1, cloned["hidden_size"])
    agent.load_state_dict(cloned["agent"])
    normalised = np.clip((obs_array - cloned["obs_mean"].numpy()) / np.sqrt(cloned["obs_var"].numpy() + 1e-8), -10.0, 10.0)
    with torch.no_grad():
        predicted = agent.get_value(torch.tensor(normalised, dtype=torch.float32))[:, 0].numpy()
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


@pytest.mark.parametrize(
    "env_id, message",
    [("NoSuchEnv-v0", "unknown env id 'NoSuchEnv-v0'"),
     ("MountainCarContinuous-v0", "{method} imitates a baseline and MountainCarContinuous-v0 has none; pass --baseline module:function")],
)  # fmt: skip
@pytest.mark.parametrize("name", ["ppo_il", "trpo_il"])
def test_an_unknown_env_or_one_without_a_baseline_is_a_one_line_error(name, env_id, message, tmp_path):
    out = run_script(ROOT / f"{name}.py", ["--env-id", env_id], tmp_path)
    assert out.returncode != 0 and message.format(method={"ppo_il": "PPO+IL", "trpo_il": "TRPO+IL"}[name]) in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1, out.stderr
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


class EndingPendulum(PendulumEnv):
    """Pendulum-v1 whose episodes end in each of the ways an episode can end, under a time limit of 50 steps:
    from reset seed 2 it terminates at its 30th step, from seed 3 at its 50th, where the time limit also
    truncates it, and from any other seed the time limit alone truncates it. Each instance, in order of
    creation, keeps the observation and reward of every step it took."""

    instances: list = []

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.steps = []
        EndingPendulum.instances.append(self)

    def reset(self, *, seed=None, options=None):
        self.end_at, self.t = {2: 30, 3: 50}.get(seed), 0
        return super().reset(seed=seed, options=options)

    def step(self, action):
        obs, reward, _, truncated, info = super().step(action)
        self.t += 1
        self.steps.append((obs.copy(), float(reward)))
        return obs, reward, self.t == self.end_at, truncated, info


gym.register("EndingPendulum-v0", entry_point=EndingPendulum, max_episode_steps=50)


@pytest.mark.parametrize("name", ["ppo_il", "trpo_il"])
def test_a_rollout_bootstraps_an_episode_cut_by_the_time_limit_and_no_other_end(name, tmp_path, monkeypatch):
    """The reward stored for an episode's last step is the env's, plus gamma V(s_T) of the observation the
    step returned when the time limit alone ended the episode: its future was cut off, not ended. An
    episode that terminated, at the time limit or before it, adds nothing. V is the critic the rollout
    acted with (the model kept before the update). One rollout of 256 steps, from --seed 1, holds
    episodes from reset seeds 1 to 6: cut at steps 50, 180 and 230, terminated at 80 and, with the limit's
    cut as well, at 130; the sixth runs on past the rollout's end, which GAE bootstraps instead."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(EndingPendulum, "instances", [])
    norm = [] if name == "ppo_il" else ["--norm-obs", "False", "--norm-reward", "False"]  # trpo_il's are Optional (tuned)
    argv = [f"{name}.py", *SHORT[name], "--env-id", "EndingPendulum-v0", "--baseline", "envs.pendulum:pendulum_swing_up", *norm,
            "--total-timesteps", "256", "--il-steps", "200", "--il-max-epochs", "2", "--hidden-size", "16", "--seed", "1",
            "--baseline-eval-episodes", "1", "--eval-episodes", "1", "--save-model"]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    g = runpy.run_path(str(ROOT / f"{name}.py"), run_name="__main__")
    training = EndingPendulum.instances[0]  # the training env is made first
    assert len(training.steps) == 256
    kept_step, weights, _ = g["sound"]
    assert kept_step == 256
    agent = load_script(name).Agent(3, 1, 16)
    agent.load_state_dict(weights)
    cut, ended = [49, 179, 229], [79, 129]
    with torch.no_grad():
        values = agent.get_value(torch.tensor(np.array([training.steps[t][0] for t in cut]))).numpy()[:, 0]
    expected = np.array([reward for _, reward in training.steps])
    expected[cut] += g["args"].gamma * values
    np.testing.assert_allclose(g["rewards"].numpy(), expected, rtol=1e-6, atol=1e-6)
    assert np.all(np.abs(g["args"].gamma * values) > 1e-3)  # the bootstrap is not too small to be seen
    ends = np.append(g["dones"].numpy()[1:], float(g["next_done"])) == 1.0
    assert ends.nonzero()[0].tolist() == sorted(cut + ended)


@pytest.mark.parametrize("script", [ppo, trpo], ids=["ppo_il", "trpo_il"])
@pytest.mark.parametrize("shape", [(3,), ()], ids=["observations", "returns"])
def test_running_statistics_are_the_moments_of_everything_fed_to_them(script, shape):
    """Chan et al.'s merge of batch moments, fed one row at a time as a rollout feeds it and in batches as
    the imitation phase does, against the moments of all the rows at once. The statistics start as a
    pseudo-row of weight c = 1e-4 with mean 0 and variance 1, so the reference holds it too:
    mean = sum(x) / (n + c), var = (c (1 + mean^2) + sum((x - mean)^2)) / (n + c)."""
    rng = np.random.default_rng(4)
    batches = [rng.normal(loc, scale, size=(n, *shape)) for loc, scale, n in ((5.0, 0.1, 1), (-2.0, 3.0, 7), (40.0, 2.0, 64), (-7.0, 0.5, 200))]
    batches += [rng.normal(3.0, 1.0, size=shape) for _ in range(50)]  # single rows, unbatched
    rms = script.RunningMeanStd(shape)
    for batch in batches:
        rms.update(batch)
    x, c = np.concatenate([np.reshape(b, (-1, *shape)) for b in batches]), 1e-4
    mean = x.sum(0) / (len(x) + c)
    var = (c * (1.0 + mean**2) + ((x - mean) ** 2).sum(0)) / (len(x) + c)
    np.testing.assert_allclose(rms.mean, mean, rtol=1e-12)
    np.testing.assert_allclose(rms.var, var, rtol=1e-10)
    assert rms.count == pytest.approx(len(x) + c, rel=1e-15)
    far = mean + 20.0 * np.sqrt(var)  # normalised, beyond the clip at 10
    np.testing.assert_allclose(rms.normalize(np.stack([x[-1], far])), [(x[-1] - mean) / np.sqrt(var + 1e-8), np.full(shape, 10.0)], rtol=1e-6)


@pytest.mark.parametrize("target_kl, clip_vloss", [(None, True), (1e-12, True), (None, False)], ids=["3-epochs", "target-kl", "no-clip-vloss"])
def test_ppo_minimises_the_clipped_surrogate_and_value_loss_it_logs(target_kl, clip_vloss, tmp_path, monkeypatch):
    """The last minibatch's losses and gradient, written out here at the weights it was taken at:
    CleanRL's clipped surrogate on advantages normalised over the minibatch, the value loss clipped
    around the rollout's values (not with --no-clip-vloss), and loss = pg - ent_coef * entropy + vf_coef * v.
    A small clip coefficient, a large learning rate, three epochs and returns of order one (--norm-reward)
    make both clips bind on both sides, on Lunar Lander's two action dimensions; --target-kl 1e-12 stops
    after the first epoch."""
    monkeypatch.chdir(tmp_path)
    clip, ent_coef, vf_coef, max_grad_norm = 0.05, 0.01, 0.7, 0.1
    argv = ["ppo_il.py", "--env-id", "LunarLanderContinuous-v3", "--num-steps", "128", "--total-timesteps", "128", "--num-minibatches", "2",
            "--update-epochs", "3", "--learning-rate", "3e-3", "--clip-coef", str(clip), "--ent-coef", str(ent_coef), "--vf-coef", str(vf_coef),
            "--max-grad-norm", str(max_grad_norm), "--norm-reward", "--il-steps", "200", "--il-max-epochs", "5", "--hidden-size", "16",
            "--baseline-eval-episodes", "1", *([] if target_kl is None else ["--target-kl", str(target_kl)]), *([] if clip_vloss else ["--no-clip-vloss"])]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    taken = []  # (gradient before clipping, after it, its norm) at every PPO minibatch
    real_clip = torch.nn.utils.clip_grad_norm_

    def recording_clip(parameters, max_norm, *a, **kw):
        parameters = list(parameters)
        before = {id(p): p.grad.detach().clone() for p in parameters}
        norm = real_clip(parameters, max_norm, *a, **kw)
        taken.append((before, {id(p): p.grad.detach().clone() for p in parameters}, float(norm)))
        return norm

    monkeypatch.setattr(torch.nn.utils, "clip_grad_norm_", recording_clip)
    real_step = torch.optim.Adam.step
    weights = []

    def recording_step(self, *a, **kw):  # the weights each PPO loss was computed at (imitation's steps too)
        weights.append({id(p): p.detach().clone() for group in self.param_groups for p in group["params"]})
        return real_step(self, *a, **kw)

    monkeypatch.setattr(torch.optim.Adam, "step", recording_step)
    g = runpy.run_path(str(ROOT / "ppo_il.py"), run_name="__main__")
    agent, mb = g["agent"], g["mb_inds"]
    epochs = 1 if target_kl is not None else 3
    assert len(taken) == 2 * epochs and len(g["clipfracs"]) == 2 * epochs and g["epoch"] == epochs - 1
    assert sorted(mb) != list(range(64, 128)) and len(set(mb)) == 64  # a shuffled half of the rollout
    names = {id(p): name for name, p in agent.named_parameters()}
    agent.double()

    def forward(weights: dict, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The policy's mean and std and the value at obs, with the agent's weights set to `weights`."""
        mean = functional_call(agent.actor_mean, {k.removeprefix("actor_mean."): v for k, v in weights.items() if k.startswith("actor_mean.")}, (obs,))
        value = functional_call(agent.critic, {k.removeprefix("critic."): v for k, v in weights.items() if k.startswith("critic.")}, (obs,))[:, 0]
        return mean, weights["actor_logstd"].exp(), value

    # the log-probabilities stored at acting are the rollout policy's: the weights before the first update
    rollout_policy = {names[i]: v.double() for i, v in weights[-len(taken)].items()}
    with torch.no_grad():
        mean, std, _ = forward(rollout_policy, g["obs_buf"].double())
        np.testing.assert_allclose(g["logprobs"].numpy(), gaussian_log_density(g["actions"].double(), mean, std).numpy(), rtol=1e-5, atol=1e-5)

    # the last minibatch's losses at the weights it was taken at (the last Adam step's)
    w = {names[i]: v.double().requires_grad_() for i, v in weights[-1].items()}
    assert set(w) == set(names.values())
    mean, std, new_value = forward(w, g["obs_buf"].double()[mb])
    log_ratio = gaussian_log_density(g["actions"].double()[mb], mean, std) - g["logprobs"].double()[mb]
    ratio = log_ratio.exp()
    adv = g["advantages"].double()[mb]
    adv = (adv - adv.mean()) / (adv.std() + 1e-8)  # over the minibatch
    returns, old_values = g["returns"].double()[mb], g["values"].double()[mb]
    unclipped = (new_value - returns) ** 2
    clipped = (old_values + (new_value - old_values).clamp(-clip, clip) - returns) ** 2
    pg_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - clip, 1 + clip)).mean()
    v_loss = 0.5 * (torch.max(unclipped, clipped) if clip_vloss else unclipped).mean()
    entropy = mean_gaussian_entropy(std)
    if target_kl is None:  # the clips bind, both ways: min, max or no clip would each give other numbers
        outside = (ratio - 1).abs() > clip
        if clip_vloss:  # without it the policy trains otherwise; the 3-epochs case shows the surrogate's clip binding
            assert (ratio > 1 + clip).any() and (ratio < 1 - clip).any() and outside[adv > 0].any() and outside[adv < 0].any()
        assert (clipped > unclipped).any() and (clipped < unclipped).any()
    np.testing.assert_allclose(g["pg_loss"].item(), pg_loss.item(), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(g["v_loss"].item(), v_loss.item(), rtol=1e-4)
    np.testing.assert_allclose(g["entropy_loss"].item(), entropy.item(), rtol=1e-5)
    np.testing.assert_allclose(g["approx_kl"].item(), ((ratio - 1) - log_ratio).mean().item(), rtol=1e-3, atol=1e-7)
    np.testing.assert_allclose(g["old_approx_kl"].item(), (-log_ratio).mean().item(), rtol=1e-3, atol=1e-7)
    assert g["clipfracs"][-1] == pytest.approx(((ratio - 1).abs() > clip).double().mean().item())
    y, y_pred = g["returns"].numpy().astype(np.float64), g["values"].numpy().astype(np.float64)
    assert g["explained_var"] == pytest.approx(1 - np.var(y - y_pred) / np.var(y), rel=1e-4)

    # the gradient the script clipped is that of pg - ent_coef * entropy + vf_coef * v, and the clip scaled it to max_grad_norm
    (pg_loss - ent_coef * entropy + vf_coef * v_loss).backward()
    before, after, norm = taken[-1]
    for i, grad in before.items():
        np.testing.assert_allclose(grad.numpy(), w[names[i]].grad.numpy(), rtol=2e-3, atol=1e-6, err_msg=names[i])
    total = np.sqrt(sum((v.grad**2).sum().item() for v in w.values()))
    assert norm == pytest.approx(total, rel=1e-3) and total > max_grad_norm
    for i, grad in after.items():
        np.testing.assert_allclose(grad.numpy(), before[i].numpy() * max_grad_norm / norm, rtol=1e-4, atol=1e-9, err_msg=names[i])


@pytest.mark.parametrize("anneal", [True, False], ids=["anneal-lr", "no-anneal-lr"])
def test_ppo_anneals_its_learning_rate_linearly_over_the_run(anneal, tmp_path, monkeypatch):
    """CleanRL's schedule: of N rollouts, the k-th (from 0) updates at lr (1 - k / N), the last at lr / N;
    --no-anneal-lr keeps lr. Three rollouts of two epochs of two minibatches: four Adam steps each."""
    monkeypatch.chdir(tmp_path)
    argv = ["ppo_il.py", "--num-steps", "128", "--total-timesteps", "384", "--num-minibatches", "2", "--update-epochs", "2", "--learning-rate", "1e-3",
            "--il-steps", "200", "--il-max-epochs", "2", "--hidden-size", "16", "--baseline-eval-episodes", "1", *([] if anneal else ["--no-anneal-lr"])]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    real_step, rates = torch.optim.Adam.step, []

    def recording_step(self, *a, **kw):
        rates.append((self, self.param_groups[0]["lr"]))
        return real_step(self, *a, **kw)

    monkeypatch.setattr(torch.optim.Adam, "step", recording_step)
    g = runpy.run_path(str(ROOT / "ppo_il.py"), run_name="__main__")
    taken = [lr for optimizer, lr in rates if optimizer is g["optimizer"]]  # not the imitation phase's
    assert taken == pytest.approx([1e-3 * (1.0 - k / 3 if anneal else 1.0) for k in range(3) for _ in range(4)], rel=1e-12)


def test_trpo_steps_from_the_rollouts_policy_on_normalised_advantages_then_fits_the_value(tmp_path, monkeypatch):
    """One Lunar Lander rollout through trpo_il.py: the stored log-probabilities are the policy's that
    the step starts from, the step sees the rollout's advantages normalised, the logged KL, objective
    and entropy are those of the policy it ends at (written out here), and the value loss is the last
    shuffled critic minibatch's, at the weights its gradient was taken at."""
    monkeypatch.chdir(tmp_path)
    argv = ["trpo_il.py", "--env-id", "LunarLanderContinuous-v3", "--num-steps", "128", "--total-timesteps", "128", "--n-critic-updates", "2",
            "--critic-batch-size", "48", "--il-steps", "200", "--il-max-epochs", "5", "--hidden-size", "16", "--baseline-eval-episodes", "1"]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    starts, real_to_vector = [], torch.nn.utils.parameters_to_vector

    def recording_to_vector(params):  # trpo_step reads the policy it starts from with it, once a step
        starts.append(real_to_vector(params).detach().clone())
        return starts[-1]

    monkeypatch.setattr(torch.nn.utils, "parameters_to_vector", recording_to_vector)
    real_step, steps = torch.optim.Adam.step, []

    def recording_step(self, *a, **kw):
        steps.append((self, {id(p): p.detach().clone() for group in self.param_groups for p in group["params"]}))
        return real_step(self, *a, **kw)

    monkeypatch.setattr(torch.optim.Adam, "step", recording_step)
    g = runpy.run_path(str(ROOT / "trpo_il.py"), run_name="__main__")
    agent, step = g["agent"], g["step"]
    obs, actions = g["obs_buf"].double(), g["actions"].double()
    agent.double()
    (start,) = starts  # one policy step
    end = torch.nn.utils.parameters_to_vector(trpo.policy_params(agent)).detach()

    def log_density(theta):
        return gaussian_log_density(actions, *policy_at(agent, theta, obs))

    with torch.no_grad():
        np.testing.assert_allclose(g["logprobs"].numpy(), log_density(start.double()).numpy(), rtol=1e-5, atol=1e-5)
        advantages = g["advantages"].double()
        normalised = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
        np.testing.assert_allclose(g["b_advantages"].numpy(), normalised.numpy(), rtol=1e-5, atol=1e-6)
        assert step["accepted"] and not torch.equal(start, end)
        old_mean, old_std = policy_at(agent, start.double(), obs)
        mean, std = policy_at(agent, end, obs)
        kl = mean_gaussian_kl(old_mean, old_std, mean, std).item()
        assert step["kl"] == pytest.approx(kl, rel=1e-4) and 0.0 < kl <= 0.01
        ratio = torch.exp(log_density(end) - log_density(start.double()))
        assert step["objective"] == pytest.approx((ratio * normalised).mean().item(), rel=1e-4) and step["objective"] > 0.0
        assert g["entropy"] == pytest.approx(mean_gaussian_entropy(std).item(), rel=1e-5)

    critic_steps = [weights for optimizer, weights in steps if optimizer is g["value_optimizer"]]
    assert len(critic_steps) == 2 * 3  # two epochs of minibatches of 48, 48 and 32 steps
    mb = g["mb_inds"]
    assert len(mb) == 32 and sorted(mb) != list(range(96, 128))  # the last of a shuffled epoch
    names = {id(p): name.removeprefix("critic.") for name, p in agent.critic.named_parameters()}
    weights = {names[i]: w.double() for i, w in critic_steps[-1].items()}
    with torch.no_grad():
        value = functional_call(agent.critic, weights, (obs[mb],))[:, 0]
        v_loss = 0.5 * ((value - g["returns"].double()[mb]) ** 2).mean().item()
    assert g["v_loss"].item() == pytest.approx(v_loss, rel=1e-4)
