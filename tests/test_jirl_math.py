"""JIRL's gate (Alg. 3) and penalized reward (Alg. 2) against independent computations."""

import decimal
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate, stats

from conftest import ROOT, figures_stated, load_script

jirl = load_script("jirl_sac_continuous")
sac = load_script("sac_continuous")
others = [load_script("ppo_il"), load_script("trpo_il")]

floats = st.floats(-3.0, 3.0, allow_nan=False)
log_stds = st.floats(-4.0, 1.5, allow_nan=False)
actions = st.floats(-0.995, 0.995, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(floats, log_stds, actions), min_size=1, max_size=4))
def test_squashed_log_prob_matches_scipy(dims):
    mean, log_std, action = (np.array(v) for v in zip(*dims))
    # density of y = tanh(x), x ~ N(mean, std): p(atanh y) / (1 - y^2)
    expected = np.sum(stats.norm.logpdf(np.arctanh(action), mean, np.exp(log_std)) - np.log(1 - action**2))
    assert jirl.squashed_log_prob(mean, log_std, action) == pytest.approx(expected, rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("mean, log_std", [(0.0, 0.0), (1.2, -1.0), (-0.5, -2.5)])
def test_squashed_density_integrates_to_one(mean, log_std):
    def density(y):
        return math.exp(jirl.squashed_log_prob(np.array([mean]), np.array([log_std]), np.array([y])))

    edge = 1 - jirl.BASELINE_ACTION_EPS
    mass, _ = integrate.quad(density, -edge, edge, limit=200, points=[math.tanh(mean)])
    assert mass == pytest.approx(1.0, abs=2e-3)


def test_gate_density_agrees_with_the_actor_log_prob():
    torch.manual_seed(0)
    actor = jirl.Actor(3, 2, 16)
    obs = torch.randn(64, 3)
    with torch.no_grad():
        action, log_prob, _ = actor.get_action(obs)
        mean, log_std = actor(obs)
    for i in range(64):
        if np.all(np.abs(action[i].numpy()) < 1 - jirl.BASELINE_ACTION_EPS):
            got = jirl.squashed_log_prob(mean[i].double().numpy(), log_std[i].double().numpy(), action[i].double().numpy())
            assert got == pytest.approx(log_prob[i, 0].item(), abs=2e-3)


def test_baseline_action_at_the_bound_is_clipped_to_a_finite_density():
    value = jirl.squashed_log_prob(np.array([0.0]), np.array([-1.0]), np.array([1.0]))
    edge = 1 - jirl.BASELINE_ACTION_EPS
    assert math.isfinite(value)
    assert value == pytest.approx(jirl.squashed_log_prob(np.array([0.0]), np.array([-1.0]), np.array([edge])))


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(floats, log_stds, actions), min_size=1, max_size=4))
def test_divergence_is_linearised_entropy_plus_distance(dims):
    mean, log_std, baseline = (np.array(v) for v in zip(*dims))
    entropy = sum(stats.norm(m, math.exp(s)).entropy() + math.log(1 - math.tanh(m) ** 2) for m, s in zip(mean, log_std))
    distance = math.sqrt(sum((b - math.tanh(m)) ** 2 for b, m in zip(baseline, mean)))
    assert jirl.divergence(mean, log_std, baseline) == pytest.approx(entropy + distance, rel=1e-9, abs=1e-9)


def test_linearised_entropy_is_close_to_the_true_squashed_entropy_for_a_confident_policy():
    rng = np.random.default_rng(0)
    mean, log_std = np.array([0.7]), np.array([-3.0])
    x = rng.normal(mean[0], math.exp(log_std[0]), 200_000)
    y = np.tanh(x)
    monte_carlo = -np.mean(stats.norm.logpdf(x, mean[0], math.exp(log_std[0])) - np.log(1 - y**2))
    linearised = jirl.divergence(mean, log_std, np.tanh(mean))  # zero distance: rho is the entropy
    assert linearised == pytest.approx(monte_carlo, abs=0.01)


def reference_decisions(log_probs, rhos, cs, k_max):
    """Alg. 3 written out in linear space with explicit indices, for moderate numbers."""
    decisions, switch_at = [], 0
    for t in range(len(log_probs)):
        k = min(k_max, t - switch_at)
        window = range(t - k, t + 1)
        product_pi = np.prod([math.exp(log_probs[i]) for i in window])
        product_rho = np.prod([math.log1p(math.exp(rhos[i])) for i in window])  # softplus: rho may be <= 0
        decisions.append(bool(product_pi > cs[t] * product_rho))
        if t > 0 and decisions[t] != decisions[t - 1]:
            switch_at = t
    return decisions


@settings(max_examples=200, deadline=None)
@given(
    st.integers(0, 6),
    st.lists(st.tuples(st.floats(-3, 3), st.floats(-1, 4), st.floats(0.1, 3)), min_size=1, max_size=40),
)
def test_gate_decisions_match_the_written_out_rule(k_max, steps):
    log_probs, rhos, cs = (list(v) for v in zip(*steps))
    gate = jirl.Gate(k_max)
    got = []
    for lp, rho, c in zip(log_probs, rhos, cs):
        decision = gate.decide(lp, rho, c)
        gate.record(decision)
        got.append(decision)
    expected = reference_decisions(log_probs, rhos, cs, k_max)
    assert got == expected


def test_gate_window_restarts_at_a_switch_and_at_an_episode_start():
    gate = jirl.Gate(k_max=3)
    assert gate.decide(-1.0, 1.0, 1.0) is False  # log pi < log C + log rho
    gate.record(False)
    assert gate.decide(5.0, 1.0, 1.0) is True  # window: -1 + 5 > 0
    assert gate.record(True) is True  # switch: the window keeps this step only
    assert list(gate.log_probs) == [5.0]
    assert gate.decide(-4.0, 1.0, 1.0) is True  # 5 - 4 > 0: the step before the switch no longer counts
    gate.record(True)
    gate.new_episode()
    assert gate.decide(-4.0, 1.0, 1.0) is False and len(gate.log_probs) == len(gate.log_rhos) == 1
    assert gate.record(False) is False  # the agent acted last in the episode before: no switch here


def test_a_step_without_a_baseline_action_empties_both_sides_of_the_window():
    # intervention mode: a step with no a^b has no pi(a^b|s), so the products start again at the next step that has one
    gate = jirl.Gate(k_max=3)
    assert gate.decide(3.0, 50.0, 1.0) is False  # 3 < log softplus(50) = 3.91
    gate.record(False)
    gate.skip()
    gate.record(True)  # the agent acted, ungated
    assert gate.decide(0.5, 1.0, 1.0) is True  # 0.5 > log softplus(1) = 0.27: the earlier step counts on neither side
    assert list(gate.log_probs) == [0.5] and list(gate.log_rhos) == [pytest.approx(math.log(math.log1p(math.e)))]


def test_gate_never_acts_on_nan_and_handles_extremes():
    gate = jirl.Gate(2)
    assert gate.decide(float("nan"), 1.0, 1.0) is False
    gate = jirl.Gate(2)
    assert gate.decide(0.0, float("nan"), 1.0) is False
    gate = jirl.Gate(2)
    assert gate.decide(-math.inf, 1.0, 0.0) is False  # a vanished density never acts, even with C = 0
    gate = jirl.Gate(2)
    assert gate.decide(-50.0, 1.0, 0.0) is True  # C annealed to 0: any finite density acts
    gate = jirl.Gate(2)
    assert gate.decide(-2.0, -3.0, 1.0) is True  # rho = -3 counts as softplus(-3) = 0.0486: -2 > -3.02
    assert gate.log_rhos[-1] == pytest.approx(math.log(math.log1p(math.exp(-3.0))))
    assert jirl.log_positive_rho(-800.0) == pytest.approx(-800.0)  # no underflow to -inf
    assert jirl.log_positive_rho(1e6) == pytest.approx(math.log(1e6))


def test_the_readmes_single_step_thresholds_of_c():
    """The README says for which C one step passes the gate with the agent's mean on a^b = tanh(0.3), at
    the initial std and at a confident one: C up to pi(a^b|s) / softplus(rho), written out here."""
    pattern = r"a single step passes the gate for C up to ([\d.]*\d) at the initial std ([\d.]*\d), and for C up to (\d+) at std ([\d.]*\d)"
    ((c_initial, initial_std, c_confident, confident_std),) = figures_stated((ROOT / "README.md").read_text(), pattern)
    # the initial std: an untrained log-std layer outputs about 0, the middle of [LOG_STD_MIN, LOG_STD_MAX]
    assert round(math.exp((jirl.LOG_STD_MIN + jirl.LOG_STD_MAX) / 2), 2) == initial_std
    for stated_c, std in ((c_initial, initial_std), (c_confident, confident_std)):
        mean, a_b = 0.3, math.tanh(0.3)
        density = stats.norm.pdf(mean, mean, std) / (1.0 - a_b**2)  # change of variables through tanh, at the mean
        rho = 0.5 * math.log(2.0 * math.pi * math.e * std**2) + math.log(1.0 - a_b**2)  # linearised entropy; distance 0
        c_max = density / math.log1p(math.exp(rho))
        assert round(c_max, 1 if stated_c < 10 else 0) == stated_c, (std, c_max)
        log_prob = jirl.squashed_log_prob(np.array([mean]), np.array([math.log(std)]), np.array([a_b]))
        rho_script = jirl.divergence(np.array([mean]), np.array([math.log(std)]), np.array([a_b]))
        assert jirl.Gate(5).decide(log_prob, rho_script, c_max * (1 - 1e-9)) and not jirl.Gate(5).decide(log_prob, rho_script, c_max * (1 + 1e-9))


def test_log_positive_rho_is_log_softplus_to_double_precision_over_its_whole_range():
    """Against log(log(1 + e^rho)) in 200-digit decimals, through the change to rho itself below -30."""
    for rho in [*np.linspace(-60.0, 60.0, 481), -300.0, -100.0, -30.5, -29.5, 100.0, 300.0]:
        with decimal.localcontext(prec=200):
            exact = float((1 + decimal.Decimal(float(rho)).exp()).ln().ln())
        assert jirl.log_positive_rho(float(rho)) == pytest.approx(exact, rel=1e-12, abs=1e-12), rho


rewards = st.floats(-100, 100, allow_nan=False)
vectors = st.lists(st.floats(-1, 1), min_size=2, max_size=2).map(np.array)


@settings(max_examples=300, deadline=None)
@given(rewards, vectors, vectors, st.floats(1e-3, 1.0))
def test_penalized_reward_properties(r, a_b, a_rl, sigma2):
    r_p = jirl.penalized_reward(r, a_b, a_rl, sigma2)
    distance = float(np.sqrt(np.sum((a_b - a_rl) ** 2)))
    assert r_p == pytest.approx(r - abs(r) * (1 - math.exp(-distance / sigma2)), abs=1e-9)
    assert r_p <= r + 1e-12  # a penalty for either sign of r
    assert r_p >= r - abs(r) - 1e-12
    assert jirl.penalized_reward(r, a_b, a_b, sigma2) == r
    further = jirl.penalized_reward(r, a_b, a_b + 2.0 * (a_rl - a_b), sigma2)
    assert further <= r_p + 1e-12  # monotone in the distance


def test_penalized_reward_for_negative_reward_falls_towards_twice_the_reward():
    # The authors' multiplicative form r * exp(-d / sigma^2) would give -0.0 here: a bonus for deviating.
    assert jirl.penalized_reward(-5.0, np.zeros(1), np.ones(1), 0.01) == pytest.approx(-10.0)
    assert jirl.penalized_reward(-5.0, np.zeros(1), np.full(1, 0.01), 0.01) == pytest.approx(-5.0 - 5.0 * (1 - math.exp(-1)))


def test_unit_conversions_are_inverse():
    low, high = np.array([-2.0, 0.0]), np.array([2.0, 10.0])
    a = np.array([0.25, -0.5])
    np.testing.assert_allclose(jirl.to_policy_units(jirl.to_env_units(a, low, high), low, high), a)
    np.testing.assert_array_equal(jirl.to_policy_units(np.array([5.0, -1.0]), low, high), [1.0, -1.0])


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-20, 20), min_size=0, max_size=30), st.lists(st.floats(-20, 20), min_size=0, max_size=30))
def test_scripts_compute_the_same_regret(rewards, baseline_rewards):
    rewards, baseline_rewards = np.array(rewards), np.array(baseline_rewards)
    assert jirl.paired_regret(rewards, baseline_rewards) == sac.paired_regret(rewards, baseline_rewards)
    assert jirl.unpaired_regret(rewards, 0.3) == sac.unpaired_regret(rewards, 0.3)
    for script in others:
        assert script.paired_regret(rewards, baseline_rewards) == sac.paired_regret(rewards, baseline_rewards)
        assert script.unpaired_regret(rewards, 0.3) == sac.unpaired_regret(rewards, 0.3)


def test_guidance_schedules_hand_control_over_by_the_end():
    assert jirl.guidance_c(10.0, 5_000, 0, "geometric") == 10.0  # no guidance: the paper's constant C
    assert jirl.guidance_c(10.0, 0, 1000, "linear") == 10.0
    assert jirl.guidance_c(10.0, 500, 1000, "linear") == pytest.approx(5.0)
    halfway = jirl.guidance_c(10.0, 500, 1000, "geometric")
    assert math.log(halfway) == pytest.approx(0.5 * (math.log(10.0) + math.log(jirl.GUIDANCE_C_END)))
    for schedule in ("linear", "geometric"):
        values = [jirl.guidance_c(10.0, t, 1000, schedule) for t in range(0, 1200, 50)]
        assert values[0] == 10.0 and values[-1] == 0.0 and jirl.guidance_c(10.0, 1000, 1000, schedule) == 0.0
        assert all(a > b for a, b in zip(values, values[1:]) if a > 0)


def test_earned_guidance_advances_only_while_the_agent_keeps_up():
    earned = jirl.EarnedGuidance(10.0, 1000, window=2, tolerance=0.1)
    assert earned.c() == 10.0
    # (return, baseline's return, length) -> expected progress, computed by hand
    episodes = [
        (-100.0, -100.0, 200, 0.2),  # level with the baseline: forward
        (-105.0, -100.0, 200, 0.4),  # mean shortfall 2.5 <= 0.1 * 100: forward
        (-150.0, -100.0, 200, 0.2),  # window (-105, -150) vs (-100, -100): 27.5 short, back
        (-300.0, -100.0, 200, 0.0),  # back, and never below 0
        (-50.0, -100.0, 200, 0.0),  # window (-300, -50): 75 short, still back
        (-50.0, -100.0, 200, 0.2),  # the good episodes fill the window: forward again
    ]
    for episode_return, reference, length, progress in episodes:
        earned.end_episode(episode_return, reference, length)
        assert earned.progress == pytest.approx(progress)
    # C follows the geometric schedule at the earned progress, and is 0 once all is earned
    assert earned.c() == pytest.approx(jirl.guidance_c(10.0, 200, 1000, "geometric"))
    for _ in range(4):
        earned.end_episode(0.0, -100.0, 200)
    assert earned.progress == 1.0 and earned.c() == 0.0
    earned.end_episode(-1000.0, -100.0, 200)  # the agent falls behind: the baseline may take control again
    assert earned.progress == pytest.approx(0.8) and earned.c() > 0
    assert jirl.EarnedGuidance(10.0, 0, 5, 0.1).c() == 10.0  # no guidance: the paper's constant C


def test_guidance_fade_follows_c_forward_and_back():
    fade = jirl.GuidanceFade(4)
    cs = [1.0, 0.0, 0.0, 0.0, 1e-9, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 3.0, 3.0]
    # weight = 1 - n / 4, n counting up (to 4 at most) on each earlier step with C = 0 and down on one with C > 0
    expected = [1.0, 1.0, 0.75, 0.5, 0.25, 0.5, 0.25, 0.0, 0.0, 0.0, 0.0, 0.0, 0.25]
    assert [fade.weight(c) for c in cs] == pytest.approx(expected)
    # the count stops at the fade's end, so the way back starts with the first step with C > 0
    assert fade.faded == 4 - 2
    assert [fade.weight(3.0) for _ in range(3)] == pytest.approx([0.5, 0.75, 1.0])
    assert fade.faded == 0
    off = jirl.GuidanceFade(0)  # no fade: the paper
    assert [off.weight(c) for c in (0.0, 0.0, 5.0)] == [1.0, 1.0, 1.0]
