"""Baseline controllers by env id, user-supplied baselines, and a CLI that measures them.

A baseline is any callable ``baseline(obs) -> action`` in the env's action units. It may return
``None`` to mean "no intervention" (JIRL's intervention mode). If it has a ``reset()`` method, the
scripts call it at the start of every episode, so a stateful controller (a PD law with a
derivative filter, say) starts clean.

    python -m envs.baselines --env-id LunarLanderContinuous-v3 --episodes 20
"""

from __future__ import annotations

import argparse
import importlib
from typing import Callable, Optional

import gymnasium as gym
import numpy as np

from envs.lane_follower import LaneFollower
from envs.lunar_lander import lunar_lander_expert, lunar_lander_slow_descent
from envs.make import make_env
from envs.pendulum import pendulum_swing_up
from envs.walker2d import Walker2DBaseline

EPISODE_LIMIT = 100_000  # steps: an episode still running after this many is in an env without a time limit

Baseline = Callable[[np.ndarray], Optional[np.ndarray]]

# A class stands for a stateful baseline: every get_baseline() call gets a fresh instance.
BASELINES: dict[str, Baseline | type] = {
    "Pendulum-v1": pendulum_swing_up,
    "LunarLanderContinuous-v3": lunar_lander_slow_descent,
    "JetRacerTrack-v0": LaneFollower,
    "Walker2DBulletEnv-v0": Walker2DBaseline,
}
# Strong controllers, for tests and imitation checks; not baselines to beat.
EXPERTS: dict[str, Baseline] = {
    "LunarLanderContinuous-v3": lunar_lander_expert,
}


def load_baseline(spec: str) -> Baseline:
    """Import ``module:attribute``; a class is instantiated with no arguments."""
    module_name, sep, attribute = spec.partition(":")
    if not (module_name and sep and attribute) or module_name.startswith(".") or sep in attribute:
        raise ValueError(f"baseline {spec!r} must look like 'module:function' (an absolute module name, one colon)")
    try:
        module = importlib.import_module(module_name)
    except (ImportError, ValueError) as err:  # a ValueError of the module itself (a missing setting) is named too
        raise ValueError(f"cannot import baseline module {module_name!r}: {err}") from None
    try:
        baseline = getattr(module, attribute)
    except AttributeError:
        raise ValueError(f"module {module_name!r} has no attribute {attribute!r}") from None
    if isinstance(baseline, type):
        try:
            baseline = baseline()
        except ValueError as err:  # a class refusing its settings; any other error keeps its traceback
            raise ValueError(f"cannot make baseline {spec!r}: {err}") from None
    if not callable(baseline):
        raise ValueError(f"baseline {spec!r} is not callable")
    return baseline


def get_baseline(env_id: str, spec: str = "") -> Baseline:
    """The baseline named by ``spec`` ('module:function'), else the project's one for ``env_id``."""
    if spec:
        return load_baseline(spec)
    if env_id not in BASELINES:
        known = ", ".join(sorted(BASELINES))
        raise ValueError(f"no baseline for {env_id!r} (known: {known}); pass --baseline module:function")
    baseline = BASELINES[env_id]
    return baseline() if isinstance(baseline, type) else baseline


def rollout(env: gym.Env, policy: Baseline, seed: int) -> np.ndarray:
    """Run one episode from ``env.reset(seed=seed)``; return the reward of every step."""
    if env.action_space.shape is None:  # a Dict or Tuple space: no count to check the baseline's actions against
        raise ValueError(f"cannot measure a baseline on the action space {env.action_space}: it has no fixed shape")
    size = int(np.prod(env.action_space.shape))
    if hasattr(policy, "reset"):
        policy.reset()
    obs, _ = env.reset(seed=seed)
    rewards = []
    while True:
        action = policy(obs)
        if action is None:
            raise ValueError("the baseline returned None (it only intervenes), so it cannot be measured on its own")
        try:
            values = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError):  # not numbers at all: the same one-line error as a wrong count
            values = np.array([np.nan])
        if values.size != size or not np.all(np.isfinite(values)):
            raise ValueError(f"the baseline returned {action!r}; expected {size} finite number(s) in env units")
        if isinstance(env.action_space, gym.spaces.Box):  # clipped to the bounds, as the scripts apply it
            action = np.clip(np.asarray(action).reshape(env.action_space.shape), env.action_space.low, env.action_space.high)
        obs, reward, terminated, truncated, _ = env.step(action)
        rewards.append(float(reward))
        if terminated or truncated:
            return np.asarray(rewards)
        if len(rewards) == EPISODE_LIMIT:  # a policy that never fails would run for ever
            raise ValueError(f"the episode from reset seed {seed} did not end within {EPISODE_LIMIT:,} steps; give the env a time limit (max_episode_steps)")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m envs.baselines", description="Measure a baseline controller.")
    parser.add_argument("--env-id", default="Pendulum-v1", help="any env id the scripts accept (default: %(default)s)")
    parser.add_argument("--baseline", default="", help="module:function; default: the env's own")
    parser.add_argument("--episodes", type=int, default=20, help="episodes to run (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="episode i is reset with seed + i (default: %(default)s)")
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.seed < 0:
        parser.error(f"--episodes must be >= 1 and --seed >= 0, got {args.episodes} and {args.seed}")
    try:
        env = make_env(args.env_id)
        baseline = get_baseline(args.env_id, args.baseline)
        traces = [rollout(env, baseline, args.seed + i) for i in range(args.episodes)]
    except ValueError as err:
        parser.exit(2, f"{parser.prog}: error: {err}\n")  # as argparse words its own errors
    returns = np.array([t.sum() for t in traces])
    lengths = np.array([len(t) for t in traces])
    print(f"{args.env_id}, {args.episodes} episodes from seed {args.seed}")
    print(f"return          {returns.mean():.1f} ± {returns.std():.1f} (min {returns.min():.1f}, max {returns.max():.1f})")
    print(f"reward per step {returns.sum() / lengths.sum():.3f}")
    print(f"episode length  {lengths.mean():.1f}")


if __name__ == "__main__":
    main()
