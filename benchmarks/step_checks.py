"""What the per-step checks of a user's env and baseline cost, against the calls they wrap.

- `CheckedEnv.step` (make_env's wrapper: an env's exception, NaN or malformed return ends the run
  keeping its model) against the bare step: everything the wrapper adds, `flaw`'s checks included.
  Once on an env whose step costs next to nothing (a constant return), which isolates the wrapper's
  own cost from a simulator's noise, and once on Pendulum-v1 (as `gym.make` builds it) for scale.
- `ask_baseline` (a baseline's exception ends the run keeping its model) against the bare call.
- `CheckedWriter` (logs that cannot be written end the run keeping its model): the loop's check of it at
  every step against nothing, and its `add_scalar` against TensorBoard's own, on writers of their own
  in a temporary directory (at 1/100 of `--calls`: a scalar costs about 110 µs, and a run logs about
  one every 5 steps).
- The training loops' checks for a diverged agent, as the loops write them: SAC's of the action its
  actor returns, JIRL's of the policy's mean and log-std before it samples, each against the same query
  without it, on a 64-unit actor (at 1/20 of `--calls`: a query costs about 100 µs). And PPO+IL's and
  TRPO+IL's rollout call, whose `Normal` no longer validates its parameters (a NaN is found after the
  update instead), against the same call with torch's validation, and their check of the action it
  samples (a mean that overflows with finite weights) against the same call without it.
- The car's check at each pause of the actor's output on the 256 latest stored observations
  (`deploy.jetracer.overflow`), and, for scale, one of the pause's 200 gradient steps, each against
  nothing, at the car's defaults (64 units, a batch of 64; at 1/1000 of `--calls`), and the car's check
  at every step, JIRL's on the car's actor (142 inputs), against the same query without it.

The wrappers come from `jirl_sac_continuous.py` (the four scripts share these definitions, a test checks).
Each repeat times both sides back to back (which first alternates), the best of 3 runs of `--calls` calls each; prints the
median and range over the repeats of the time added per call.

    python benchmarks/step_checks.py --repeats 9
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import timeit
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parent.parent


def added(new: Callable[[], object], old: Callable[[], object], calls: int, repeats: int) -> tuple[float, list[float]]:
    """Seconds per call of `old`, and the seconds `new` adds per call in each repeat."""
    olds, diffs = [], []
    for i in range(repeats):
        order = (old, new) if i % 2 == 0 else (new, old)  # alternate which side runs first
        times = {f: min(timeit.repeat(f, number=calls, repeat=3)) / calls for f in order}
        t_old, t_new = times[old], times[new]
        olds.append(t_old)
        diffs.append(t_new - t_old)
    return statistics.median(olds), diffs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--calls", type=int, default=100_000)
    args = parser.parse_args()

    sys.path.insert(0, str(ROOT))
    import math

    import gymnasium as gym
    import numpy as np
    import torch
    from torch.distributions.normal import Normal

    import jirl_sac_continuous as jirl
    import ppo_il

    torch.set_num_threads(1)

    class ConstantEnv(gym.Env):
        """Pendulum's spaces, and a step that returns the same finite observation and reward."""

        observation_space = gym.spaces.Box(-8.0, 8.0, (3,), np.float32)
        action_space = gym.spaces.Box(-2.0, 2.0, (1,), np.float32)

        def __init__(self) -> None:
            self.obs = np.array([1.0, 0.0, 0.5], dtype=np.float32)

        def reset(self, *, seed=None, options=None):
            return self.obs, {}

        def step(self, action):
            return self.obs, -1.5, False, False, {}

    action = np.array([0.3], dtype=np.float32)
    sides = {}
    for name, make in (("a constant env", ConstantEnv), ("Pendulum-v1", lambda: gym.make("Pendulum-v1"))):
        bare, checked = make(), jirl.CheckedEnv(make(), name)
        bare.reset(seed=0)
        checked.reset(seed=0)  # neither ever terminates; Pendulum's time limit only flags truncation
        sides[name] = (lambda checked=checked: checked.step(action), lambda bare=bare: bare.step(action))

    def baseline(obs: np.ndarray) -> np.ndarray:
        return action

    obs = np.zeros(3, dtype=np.float32)
    logs = tempfile.TemporaryDirectory()
    checked_writer, writer = jirl.CheckedWriter(f"{logs.name}/checked"), jirl.SummaryWriter(f"{logs.name}/bare")
    stop = jirl.StopRequest()
    stop.restore()  # its state only: no signal handlers
    step = iter(range(10**9))

    actor, x = jirl.Actor(3, 1, 64), torch.from_numpy(np.array([[1.0, 0.0, 0.5]], dtype=np.float32))

    def sac_action(check: bool) -> np.ndarray:
        with torch.inference_mode():
            sampled, _, _ = actor.get_action(x)
        action = sampled[0].numpy()
        if check and not math.isfinite(sum(action.tolist())):
            raise ArithmeticError("diverged")
        return action

    def jirl_action(check: bool) -> np.ndarray:
        with torch.inference_mode():
            mean, log_std = actor(x)
            if check and not math.isfinite(sum(mean[0].tolist() + log_std[0].tolist())):
                raise ArithmeticError("diverged")
            return torch.tanh(torch.normal(mean, log_std.exp()))[0].numpy()

    agent = ppo_il.Agent(3, 1, 64)

    def validated(obs: torch.Tensor):  # Agent.get_action_and_value before: torch checks the Normal's parameters
        action_mean = agent.actor_mean(obs)
        probs = Normal(action_mean, agent.actor_logstd.expand_as(action_mean).exp())
        action = probs.sample()
        return action, probs.log_prob(action).sum(1), probs.entropy().sum(1), agent.critic(obs)

    def rollout_call(call):
        with torch.no_grad():
            return call(x)

    def ppo_action(check: bool) -> torch.Tensor:
        with torch.no_grad():
            action, _, _, _ = agent.get_action_and_value(x)
        if check and not math.isfinite(sum(action.tolist()[0])):
            raise ArithmeticError("diverged")
        return action

    from deploy import jetracer

    car_hp = jetracer.car_jirl_defaults()
    car = jirl.SoftActorCritic(jetracer.OBS_SIZE, 2, car_hp)
    car_rb = jirl.ReplayBuffer(car_hp.buffer_size, jetracer.OBS_SIZE, 2, seed=0)
    rng = np.random.default_rng(0)
    for _ in range(1_000):  # lane masks in [0, 1] and previous actions in [-1, 1], as the car stores them
        car_rb.add(rng.random(jetracer.OBS_SIZE, dtype=np.float32), rng.uniform(-1, 1, 2), 1.0, rng.random(jetracer.OBS_SIZE, dtype=np.float32), False)
    updates = iter(range(10**9))
    car_obs = torch.from_numpy(car_rb.obs[:1].copy())

    def car_action(check: bool) -> np.ndarray:  # the car loop's query of its actor, as train_holding writes it
        with torch.inference_mode():
            mean, log_std = car.actor(car_obs)
            if check and not math.isfinite(sum(mean[0].tolist() + log_std[0].tolist())):
                raise ArithmeticError("diverged")
            return torch.tanh(torch.normal(mean, log_std.exp()))[0].numpy()

    rows = [
        *[(f"CheckedEnv.step vs the bare step, {name}", new, old, args.calls) for name, (new, old) in sides.items()],
        ("ask_baseline vs the bare call", lambda: jirl.ask_baseline(baseline, obs), lambda: baseline(obs), args.calls),
        ("the loop's check of CheckedWriter vs nothing", lambda: checked_writer.failure and stop.reason is None, lambda: None, args.calls),
        ("CheckedWriter.add_scalar vs SummaryWriter's", lambda: checked_writer.add_scalar("a", 1.0, next(step)), lambda: writer.add_scalar("a", 1.0, next(step)),
         max(1, args.calls // 100)),
        ("SAC's check of its action vs none", lambda: sac_action(True), lambda: sac_action(False), max(1, args.calls // 20)),
        ("JIRL's check of its policy vs none", lambda: jirl_action(True), lambda: jirl_action(False), max(1, args.calls // 20)),
        ("PPO's rollout call, unvalidated vs validated", lambda: rollout_call(agent.get_action_and_value), lambda: rollout_call(validated), max(1, args.calls // 20)),
        ("PPO's check of its rollout action vs none", lambda: ppo_action(True), lambda: ppo_action(False), max(1, args.calls // 20)),
        ("the car's check of its policy vs none", lambda: car_action(True), lambda: car_action(False), max(1, args.calls // 20)),
        ("the car's pause check on 256 stored observations vs nothing", lambda: jetracer.overflow(car.actor, car_rb), lambda: None, max(1, args.calls // 1000)),
        ("a gradient step of the car's pause vs nothing", lambda: car.update(car_rb.sample(car_hp.batch_size), next(updates)), lambda: None, max(1, args.calls // 1000)),
    ]
    print("| check | the call it wraps | added per call: median | range |")
    print("|---|---|---|---|")
    for name, new, old, calls in rows:
        before, diffs = added(new, old, calls, args.repeats)
        print(f"| {name} | {before * 1e6:.2f} µs | {statistics.median(diffs) * 1e9:.0f} ns | {min(diffs) * 1e9:.0f} to {max(diffs) * 1e9:.0f} ns |")
    checked_writer.close()
    writer.close()
    assert not checked_writer.failure, checked_writer.failure
    logs.cleanup()


if __name__ == "__main__":
    main()
