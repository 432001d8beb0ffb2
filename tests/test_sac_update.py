"""The optimised SAC update against a straightforward one written here.

The scripts evaluate the twin critics as one ensemble, write the Gaussian log-density out, share
one fused Adam between the actor and the entropy coefficient, and freeze the critics during the
actor loss. None of that may change the algorithm: same seed, same losses, same parameters.
"""

import io
import math

import numpy as np
import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

from conftest import load_script

OBS_DIM, ACT_DIM, WIDTH, BATCH = 3, 2, 32, 64


@pytest.fixture(params=["sac_continuous", "jirl_sac_continuous"])
def script(request):
    return load_script(request.param)


def reference_critic() -> nn.Sequential:
    return nn.Sequential(nn.Linear(OBS_DIM + ACT_DIM, WIDTH), nn.ReLU(), nn.Linear(WIDTH, WIDTH), nn.ReLU(), nn.Linear(WIDTH, 1))


def load_ensemble(ensemble: nn.Module, critics: list[nn.Sequential]) -> None:
    """Copy separate critics' layers into the ensemble (member i = critic i)."""
    with torch.no_grad():
        for name, index in (("fc1", 0), ("fc2", 2), ("fc3", 4)):
            layer = getattr(ensemble, name)
            for i, critic in enumerate(critics):
                layer.weight[i].copy_(critic[index].weight)
                layer.bias[i, 0].copy_(critic[index].bias)


def test_ensemble_equals_two_critics(script):
    torch.manual_seed(0)
    critics = [reference_critic(), reference_critic()]
    ensemble = script.SoftQNetwork(OBS_DIM, ACT_DIM, WIDTH)
    load_ensemble(ensemble, critics)
    obs = torch.randn(BATCH, OBS_DIM)
    action = torch.rand(BATCH, ACT_DIM, requires_grad=True)

    values = ensemble(obs, action)
    assert values.shape == (2, BATCH, 1)
    expected = [critic(torch.cat([obs, action], 1)) for critic in critics]
    torch.testing.assert_close(values[0], expected[0])
    torch.testing.assert_close(values[1], expected[1])

    # gradients: of every weight, and of the shared action input (summed over both critics)
    (grad_action,) = torch.autograd.grad(values.sum(), action, retain_graph=True)
    (expected_grad,) = torch.autograd.grad(expected[0].sum() + expected[1].sum(), action, retain_graph=True)
    torch.testing.assert_close(grad_action, expected_grad)
    values.square().sum().backward()
    sum(e.square().sum() for e in expected).backward()
    for i, critic in enumerate(critics):
        torch.testing.assert_close(ensemble.fc2.weight.grad[i], critic[2].weight.grad)
        torch.testing.assert_close(ensemble.fc1.bias.grad[i, 0], critic[0].bias.grad)


def test_ensemble_members_initialised_like_linear(script):
    torch.manual_seed(0)
    layer = script.EnsembleLinear(2, 400, 300)
    bound = 1.0 / math.sqrt(400)
    assert layer.weight.shape == (2, 300, 400) and layer.bias.shape == (2, 1, 300)
    for p in (layer.weight, layer.bias):
        assert p.abs().max() <= bound and p.abs().max() > 0.99 * bound
    assert not torch.equal(layer.weight[0], layer.weight[1]), "members are independent"


def reference_get_action(actor: nn.Module, obs: torch.Tensor):
    """SAC's sampling as in CleanRL, through torch.distributions."""
    mean, log_std = actor(obs)
    normal = torch.distributions.Normal(mean, log_std.exp())
    x_t = normal.rsample()
    log_prob = normal.log_prob(x_t) - 2.0 * (math.log(2.0) - x_t - F.softplus(-2.0 * x_t))
    return torch.tanh(x_t), log_prob.sum(1, keepdim=True)


class ReferenceSAC:
    """Two critics, two targets, three plain Adams, one loss and one step at a time."""

    def __init__(self, actor: nn.Module, critics: list[nn.Sequential], args):
        self.args, self.actor = args, actor
        self.critics = critics
        self.targets = [reference_critic() for _ in critics]
        for target, critic in zip(self.targets, critics):
            target.load_state_dict(critic.state_dict())
        self.q_optimizer = torch.optim.Adam([p for c in critics for p in c.parameters()], lr=args.q_lr, foreach=False)
        self.actor_optimizer = torch.optim.Adam(actor.parameters(), lr=args.policy_lr, foreach=False)
        self.log_alpha = torch.full((1,), math.log(args.alpha), requires_grad=True)
        self.a_optimizer = torch.optim.Adam([self.log_alpha], lr=args.q_lr, foreach=False)
        self.target_entropy = -float(ACT_DIM)

    def q(self, nets, obs, action):
        x = torch.cat([obs, action], 1)
        return [net(x) for net in nets]

    def update(self, data, step):
        args = self.args
        obs, actions, rewards, next_obs, terminations = data
        alpha = self.log_alpha.exp().item()
        with torch.no_grad():
            next_actions, next_log_pi = reference_get_action(self.actor, next_obs)
            q1_next, q2_next = self.q(self.targets, next_obs, next_actions)
            target = rewards + (1 - terminations) * args.gamma * (torch.min(q1_next, q2_next) - alpha * next_log_pi)
        q1, q2 = self.q(self.critics, obs, actions)
        q1_loss, q2_loss = F.mse_loss(q1, target), F.mse_loss(q2, target)
        self.q_optimizer.zero_grad()
        (q1_loss + q2_loss).backward()
        self.q_optimizer.step()
        losses = {"qf1_loss": q1_loss, "qf2_loss": q2_loss, "qf_loss": (q1_loss + q2_loss) / 2.0, "qf1_values": q1.mean(), "qf2_values": q2.mean()}
        if step % args.policy_frequency == 0:
            for _ in range(args.policy_frequency):
                pi, log_pi = reference_get_action(self.actor, obs)
                q1_pi, q2_pi = self.q(self.critics, obs, pi)
                actor_loss = (alpha * log_pi - torch.min(q1_pi, q2_pi)).mean()
                self.actor_optimizer.zero_grad()
                actor_loss.backward()
                self.actor_optimizer.step()
                losses["actor_loss"] = actor_loss
                if args.autotune:
                    alpha_loss = (-self.log_alpha.exp() * (log_pi.detach() + self.target_entropy)).mean()
                    self.a_optimizer.zero_grad()
                    alpha_loss.backward()
                    self.a_optimizer.step()
                    alpha = self.log_alpha.exp().item()
                    losses["alpha_loss"] = alpha_loss
        if step % args.target_network_frequency == 0:
            with torch.no_grad():
                for target, critic in zip(self.targets, self.critics):
                    for tp, p in zip(target.parameters(), critic.parameters()):
                        tp.mul_(1 - args.tau).add_(args.tau * p)
        return losses


@pytest.mark.parametrize("settings", [{}, {"target_network_frequency": 3}, {"autotune": False, "alpha": 0.05}], ids=["defaults", "target-every-3", "fixed-alpha"])
def test_update_matches_reference(script, settings):
    args = script.Args(hidden_size=WIDTH, batch_size=BATCH, policy_frequency=2, q_lr=1e-3, policy_lr=3e-4, **settings)
    torch.manual_seed(0)
    agent = script.SoftActorCritic(OBS_DIM, ACT_DIM, args)
    critics = [reference_critic(), reference_critic()]
    load_ensemble(agent.qf, critics)
    load_ensemble(agent.qf_target, critics)
    reference_actor = script.Actor(OBS_DIM, ACT_DIM, WIDTH)
    reference_actor.load_state_dict(agent.actor.state_dict())
    reference = ReferenceSAC(reference_actor, critics, args)

    rb = script.ReplayBuffer(1000, OBS_DIM, ACT_DIM, seed=0)
    rng = np.random.default_rng(0)
    for _ in range(500):
        rb.add(rng.normal(size=OBS_DIM), rng.uniform(-1, 1, ACT_DIM), rng.normal(), rng.normal(size=OBS_DIM), rng.random() < 0.1)

    for step in range(12):
        data = tuple(t.clone() for t in rb.sample(BATCH))
        torch.manual_seed(100 + step)  # the same noise for both
        losses = agent.update(data, step)
        torch.manual_seed(100 + step)
        expected = reference.update(data, step)
        for name, value in expected.items():
            torch.testing.assert_close(losses[name], value, rtol=1e-4, atol=1e-5, msg=f"step {step}: {name}")
        assert losses.keys() - expected.keys() == {"alpha"}, "no loss that the reference has not"

    torch.testing.assert_close(agent.log_alpha, reference.log_alpha, rtol=1e-5, atol=1e-6)
    for a, b in zip(agent.actor.parameters(), reference_actor.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    for ensemble, nets in ((agent.qf, critics), (agent.qf_target, reference.targets)):
        for name, index in (("fc1", 0), ("fc2", 2), ("fc3", 4)):
            for i, net in enumerate(nets):
                torch.testing.assert_close(getattr(ensemble, name).weight[i], net[index].weight, rtol=1e-4, atol=1e-5)
                torch.testing.assert_close(getattr(ensemble, name).bias[i, 0], net[index].bias, rtol=1e-4, atol=1e-5)
    assert not torch.equal(agent.qf.fc2.weight[0], agent.qf_target.fc2.weight[0]), "the update moved the critics"


def test_state_dict_resumes_the_same_update(script):
    """A SoftActorCritic rebuilt from a saved state_dict continues exactly like the original."""
    args = script.Args(hidden_size=WIDTH, batch_size=BATCH)
    torch.manual_seed(0)
    agent = script.SoftActorCritic(OBS_DIM, ACT_DIM, args)
    data = (torch.randn(BATCH, OBS_DIM), torch.rand(BATCH, ACT_DIM) * 2 - 1, torch.randn(BATCH, 1), torch.randn(BATCH, OBS_DIM), torch.zeros(BATCH, 1))
    for step in range(4):
        agent.update(data, step)
    copy = script.SoftActorCritic(OBS_DIM, ACT_DIM, args)
    saved = io.BytesIO()
    torch.save(agent.state_dict(), saved)  # as deploy/ saves it; the optimizers' state_dicts share tensors
    saved.seek(0)
    copy.load_state_dict(torch.load(saved, weights_only=True))
    torch.manual_seed(7)
    a = agent.update(data, 4)
    torch.manual_seed(7)
    b = copy.update(data, 4)
    for name in a:
        torch.testing.assert_close(a[name], b[name])
    torch.testing.assert_close(agent.actor.fc2.weight, copy.actor.fc2.weight)


def test_replay_buffer_sample_keeps_rows_together(script):
    rb = script.ReplayBuffer(50, OBS_DIM, ACT_DIM, seed=0)
    for i in range(30):  # every field of transition i encodes i
        rb.add(np.full(OBS_DIM, i), np.full(ACT_DIM, i / 100), float(i), np.full(OBS_DIM, i + 0.5), i % 2 == 0)
    obs, actions, rewards, next_obs, terminations = rb.sample(200)
    i = rewards[:, 0]
    assert obs.shape == (200, OBS_DIM) and actions.shape == (200, ACT_DIM) and terminations.shape == (200, 1)
    assert set(i.tolist()) <= set(range(30)) and len(set(i.tolist())) > 20
    torch.testing.assert_close(obs, i[:, None].expand(-1, OBS_DIM))
    torch.testing.assert_close(actions, (i / 100)[:, None].expand(-1, ACT_DIM))
    torch.testing.assert_close(next_obs, (i + 0.5)[:, None].expand(-1, OBS_DIM))
    torch.testing.assert_close(terminations[:, 0], (i % 2 == 0).float())


def test_replay_buffer_overwrites_its_oldest_rows_once_full(script):
    rb = script.ReplayBuffer(10, OBS_DIM, ACT_DIM, seed=0)
    for i in range(23):
        rb.add(np.full(OBS_DIM, i), np.full(ACT_DIM, i / 100), float(i), np.full(OBS_DIM, i + 0.5), False)
    assert rb.size == 10 and rb.pos == 3
    assert rb.rewards[:, 0].tolist() == [20, 21, 22, *range(13, 20)], "rows 0-12 overwritten in order, from the start"
    _, _, rewards, _, _ = rb.sample(500)
    assert set(rewards[:, 0].tolist()) == set(range(13, 23))


def test_actor_log_std_spans_exactly_minus_5_to_2(script):
    """CleanRL's bounds: tanh of the output layer mapped onto [LOG_STD_MIN, LOG_STD_MAX] = [-5, 2]."""
    actor = script.Actor(OBS_DIM, ACT_DIM, WIDTH)
    obs = torch.randn(8, OBS_DIM)
    with torch.no_grad():
        actor.fc_logstd.weight.zero_()
        for bias, expected in ((50.0, 2.0), (0.0, -1.5), (-50.0, -5.0), (math.atanh(0.5), 0.25)):
            actor.fc_logstd.bias.fill_(bias)
            _, log_std = actor(obs)
            torch.testing.assert_close(log_std, torch.full((8, ACT_DIM), expected))
