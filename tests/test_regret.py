"""Baseline regret (paper, Definition 1): the paired and unpaired estimators of the scripts."""

import numpy as np
import pytest

from envs import BASELINES, make_env


def run_episode(env, policy, seed):
    """The training side: reset with the episode's seed and act with `policy`."""
    obs, _ = env.reset(seed=seed)
    rewards, done = [], False
    while not done:
        obs, reward, terminated, truncated, _ = env.step(policy(obs))
        rewards.append(float(reward))
        done = terminated or truncated
    return np.array(rewards)


@pytest.mark.parametrize("env_id", ["Pendulum-v1", "LunarLanderContinuous-v3"])
def test_baseline_own_actions_give_exactly_zero_paired_regret(sac, env_id):
    train_env, shadow_env = make_env(env_id), make_env(env_id)
    baseline = BASELINES[env_id]
    total = (0.0, 0.0)
    for seed in (11, 12):
        rewards = run_episode(train_env, baseline, seed)
        _, baseline_rewards = sac.baseline_rollout(shadow_env, baseline, seed)
        np.testing.assert_array_equal(rewards, baseline_rewards)  # pairing has no noise floor
        regret = sac.paired_regret(rewards, baseline_rewards)
        total = (total[0] + regret[0], total[1] + regret[1])
    assert total == (0.0, 0.0)


def test_worse_policy_regret_matches_a_hand_computation(sac):
    env, shadow = make_env("Pendulum-v1"), make_env("Pendulum-v1")
    rewards = run_episode(env, lambda obs: np.zeros(1, dtype=np.float32), seed=5)  # never swings up
    _, baseline_rewards = sac.baseline_rollout(shadow, BASELINES["Pendulum-v1"], 5)
    per_step = 0.0
    for r, r_b in zip(rewards, baseline_rewards):
        if r_b > r:
            per_step += r_b - r
    episode = max(0.0, sum(baseline_rewards) - sum(rewards))
    got = sac.paired_regret(rewards, baseline_rewards)
    assert got[0] == pytest.approx(episode, rel=1e-12)
    assert got[1] == pytest.approx(per_step, rel=1e-12)
    assert got[1] >= got[0] > 0


def test_paired_regret_pads_the_shorter_episode_with_zero_reward(sac):
    # The agent crashes after 2 steps; the baseline keeps earning for 4.
    agent, baseline = np.array([1.0, 3.0]), np.array([2.0, 1.0, 0.5, -1.0])
    # per step: max(0, 2-1) + max(0, 1-3) + max(0, 0.5-0) + max(0, -1-0) = 1 + 0 + 0.5 + 0
    assert sac.paired_regret(agent, baseline) == (0.0, 1.5)  # episode: 2.5 - 4 < 0
    # roles swapped, the baseline stops after 2 steps: 0 + max(0, 3-1) + 0 + max(0, 0-(-1)) = 3; episode 4 - 2.5
    assert sac.paired_regret(baseline, agent) == (1.5, 3.0)


def test_unpaired_regret_uses_the_baseline_reward_per_step(sac):
    rewards = np.array([0.5, -1.0, 2.0])
    # b = 0.4: episode max(0, 1.2 - 1.5) = 0; per step 0 + 1.4 + 0
    assert sac.unpaired_regret(rewards, 0.4) == pytest.approx((0.0, 1.4))
    # b = 1.0: episode 3 - 1.5 = 1.5; per step 0.5 + 2.0 + 0
    assert sac.unpaired_regret(rewards, 1.0) == pytest.approx((1.5, 2.5))
