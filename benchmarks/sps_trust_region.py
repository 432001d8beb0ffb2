"""Training speed of ppo_il.py and trpo_il.py against Stable-Baselines3's PPO and sb3-contrib's TRPO.

Same settings on both sides: one env, the same rollout length, epochs or critic updates, minibatch,
discount and network width (64 x 64, tanh), observation and reward normalisation where our script
normalises (TRPO on Lunar Lander), one torch thread, alternating which runs first. Our
scripts run with a minimal imitation phase (--il-steps 1000, one epoch) and regret off, so both
sides do the same RL work; SPS is env steps over the process's whole wall time (imports included,
for both). Prints a markdown table with medians and the median of per-pair ratios.

    python benchmarks/sps_trust_region.py --env-id Pendulum-v1 --steps 40960 --repeats 3
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from side_by_side import compare, require, stop_children_on_sigterm

ROOT = Path(__file__).resolve().parent.parent
# The tuned settings our scripts resolve for each env (see README), spelled for SB3 with one env.
SETTINGS = {
    ("ppo", "Pendulum-v1"): dict(n_steps=4096, batch_size=64, n_epochs=10, gamma=0.9, gae_lambda=0.95, learning_rate=1e-3),
    ("ppo", "LunarLanderContinuous-v3"): dict(n_steps=16384, batch_size=64, n_epochs=4, gamma=0.999, gae_lambda=0.98, learning_rate=3e-4, ent_coef=0.01),
    ("trpo", "Pendulum-v1"): dict(n_steps=2048, batch_size=128, n_critic_updates=15, gamma=0.9, gae_lambda=0.95, learning_rate=1e-3),
    ("trpo", "LunarLanderContinuous-v3"): dict(n_steps=2048, batch_size=128, n_critic_updates=20, gamma=0.99, gae_lambda=0.95, learning_rate=1e-3),
}
NORMALIZED = {("trpo", "LunarLanderContinuous-v3")}  # observations and rewards normalised (SB3's VecNormalize), as our script does there


def sb3_worker(algo: str, env_id: str, steps: int, seed: int) -> None:
    import torch

    torch.set_num_threads(1)
    if algo == "ppo":
        from stable_baselines3 import PPO as Algo
    else:
        from sb3_contrib import TRPO as Algo
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    settings = SETTINGS[(algo, env_id)]
    env = make_vec_env(env_id, n_envs=1, seed=seed)
    if (algo, env_id) in NORMALIZED:
        env = VecNormalize(env, norm_obs=True, norm_reward=True, gamma=settings["gamma"])
    policy_kwargs = {"net_arch": {"pi": [64, 64], "vf": [64, 64]}, "activation_fn": torch.nn.Tanh}
    model = Algo("MlpPolicy", env, seed=seed, device="cpu", policy_kwargs=policy_kwargs, **settings)
    model.learn(total_timesteps=steps)


def command(impl: str, algo: str, env_id: str, steps: int, seed: int) -> list[str]:
    if impl == "sb3":
        return [sys.executable, __file__, "--worker", algo, env_id, str(steps), str(seed)]
    return [
        sys.executable, str(ROOT / f"{algo}_il.py"), "--env-id", env_id, "--seed", str(seed), "--total-timesteps", str(steps),
        "--il-steps", "1000", "--il-max-epochs", "1", "--il-value-epochs", "1", "--regret-estimator", "off", "--torch-threads", "1",
    ]  # fmt: skip


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        sb3_worker(sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5]))
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env-id", default="Pendulum-v1", choices=sorted({env_id for _, env_id in SETTINGS}))
    parser.add_argument("--algos", nargs="+", default=["ppo", "trpo"], choices=sorted({algo for algo, _ in SETTINGS}))
    parser.add_argument("--steps", type=int, default=40960)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workdir", type=Path, default=ROOT / "benchmarks" / "results" / "sps_trust_region")
    args = parser.parse_args()
    minimums = {"--steps": (args.steps, 1), "--repeats": (args.repeats, 1)}
    if too_small := [f"{flag} must be at least {low}" for flag, (value, low) in minimums.items() if not value >= low]:
        parser.error("; ".join(too_small))
    require(parser, "stable_baselines3", *(["sb3_contrib"] if "trpo" in args.algos else []))
    args.workdir.mkdir(parents=True, exist_ok=True)
    print(f"{args.env_id}, {args.steps} steps, 1 thread")
    print("| algorithm | ours SPS (median) | SB3 SPS (median) | ratio ours/SB3 (median of pairs) | pairs |")
    print("|---|---|---|---|---|")
    for algo in args.algos:
        row = compare(lambda impl, seed: command(impl, algo, args.env_id, args.steps, seed), args.steps, args.repeats, args.workdir)
        print(f"| {algo} | {row}", flush=True)


if __name__ == "__main__":
    stop_children_on_sigterm()
    main()
