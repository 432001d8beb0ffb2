"""What a trained policy still pays in baseline regret: the floor under a regret target.

Drives each checkpoint written by sac_continuous.py or jirl_sac_continuous.py (deterministic, the
mean action) and the env's baseline from the same `--episodes` reset seeds (seed offset + i), and
scores every episode with the scripts' own paired estimator, so the numbers are those that
`charts/baseline_regret` (episode form) and `charts/baseline_regret_per_step` (the paper's
Definition 1) would add for that episode. A policy that beats the baseline on average still loses to
it from some initial states; the mean regret per episode times the episodes of a training budget is
what the policy would accumulate if it acted alone from the first step, and what any method pays,
on average, for the steps in which a policy of that quality acts alone.

    python benchmarks/regret_floor.py --budget-steps 280000 benchmarks/results/det_buf50k_280k/runs/*/*.cleanrl_model
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from envs import get_baseline, make_env, rollout  # noqa: E402

from side_by_side import checkpoint_policy, load_module  # noqa: E402

Policy = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Floor:
    policy_return: float  # mean over the episodes
    baseline_return: float
    regret_per_episode: float  # episode form: mean of max(0, R^b - R)
    regret_per_step_per_episode: float  # per-step form (Definition 1), summed over an episode, mean
    behind_share: float  # share of episodes with R < R^b
    mean_length: float  # of the policy's episodes

    def over(self, budget_steps: int) -> tuple[float, float]:
        """Both regret forms accumulated over `budget_steps` steps of episodes like these."""
        episodes = budget_steps / self.mean_length
        return episodes * self.regret_per_episode, episodes * self.regret_per_step_per_episode


def measure(env_id: str, policy: Policy, baseline: Policy, episodes: int, seed_offset: int) -> Floor:
    """The policy against the baseline, paired by reset seed, scored as the training scripts score it."""
    sac = load_module(str(ROOT / "sac_continuous.py"))
    env = make_env(env_id, seed_offset)
    forms, returns, baseline_returns, lengths = [], [], [], []
    for i in range(episodes):
        rewards = rollout(env, policy, seed_offset + i)
        baseline_rewards = rollout(env, baseline, seed_offset + i)
        forms.append(sac.paired_regret(rewards, baseline_rewards))
        returns.append(rewards.sum())
        baseline_returns.append(baseline_rewards.sum())
        lengths.append(len(rewards))
    env.close()
    forms_arr = np.asarray(forms)
    return Floor(
        policy_return=float(np.mean(returns)),
        baseline_return=float(np.mean(baseline_returns)),
        regret_per_episode=float(forms_arr[:, 0].mean()),
        regret_per_step_per_episode=float(forms_arr[:, 1].mean()),
        behind_share=float(np.mean(np.asarray(returns) < np.asarray(baseline_returns))),
        mean_length=float(np.mean(lengths)),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", type=Path, nargs="+")
    parser.add_argument("--episodes", type=int, default=300)
    parser.add_argument("--seed-offset", type=int, default=2_000_000, help="episode i resets with this + i (disjoint from training and evaluation)")
    parser.add_argument("--budget-steps", type=int, default=0, help="also print the floor over this many steps")
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error("--episodes must be at least 1")
    if args.budget_steps < 0:
        parser.error("--budget-steps must be at least 0 (0: no floor column)")
    torch.set_num_threads(1)
    print("| checkpoint | return | baseline | behind the baseline | regret per episode | per step, per episode | floor over the budget (episode / per step) |")
    print("|---|---|---|---|---|---|---|")
    for path in args.checkpoints:
        try:
            env_id, policy = checkpoint_policy(path)
        except ValueError as err:
            print(f"| {path} | unreadable: {' '.join(str(err).split())} | | | | | |", flush=True)  # one table row
            continue
        floor = measure(env_id, policy, get_baseline(env_id), args.episodes, args.seed_offset)
        budget = "–"
        if args.budget_steps:
            episode_form, per_step = floor.over(args.budget_steps)
            budget = f"{episode_form:,.0f} / {per_step:,.0f}"
        print(
            f"| {path} | {floor.policy_return:.1f} | {floor.baseline_return:.1f} | {100 * floor.behind_share:.0f} %"
            f" | {floor.regret_per_episode:.2f} | {floor.regret_per_step_per_episode:.2f} | {budget} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
