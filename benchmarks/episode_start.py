"""Who holds an episode's start: a trained policy alone, after the baseline's first steps, and under the gate.

The RL-control fraction counts steps, not where they fall. Where the agent's action stays far from
the baseline's in some states, the gate keeps handing those states to the baseline, the agent never
meets their outcome of its own action (its fabricated transitions there carry the baseline's next
state), and a policy in control of 96 % of the steps may still be unable to act alone. This tool
drives each checkpoint written by sac_continuous.py or jirl_sac_continuous.py from its evaluation's
reset seeds (the run's seed + EVAL_SEED_OFFSET + i, so `alone` gives the run's final evaluation):

- alone: the deterministic policy (the mean action) from the reset, as the final evaluation runs it;
- after n: the baseline for the first n steps, then the deterministic policy, for each n of `--handoffs`;
- gate: the training's joint control (Alg. 1 and 3) with the actor frozen: at each step the gate of
  jirl_sac_continuous.py, at `--gate-c` and the run's K, applies a^rl ~ pi(.|s) or the baseline's a^b.
  It reports the share of steps the agent acted, the baseline's steps within the first
  `--start-steps` of an episode and after them, and the log-density pi(a^b|s) the gate weighs there.

    python benchmarks/episode_start.py --gate-c 2.7e-6 benchmarks/results/earned_walker200k_s5/runs/*/*.cleanrl_model
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Callable, Optional

import numpy as np
import torch
from gymnasium.spaces import Box

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from envs import get_baseline, make_env  # noqa: E402

from side_by_side import load_module  # noqa: E402


OVERFLOW = "the policy's output at step {step} of episode {episode} is not finite: its network overflows float32 there"


@dataclass(frozen=True)
class Episode:
    episode_return: float
    length: int
    terminated: bool  # ended before the time limit (Walker2D: fell)
    rl_steps: int  # steps the agent's action was applied
    baseline_at_start: int  # steps among the first `start_steps` the baseline's action was applied
    baseline_after: int  # ... and after them
    log_prob_at_start: float  # gate only: median log pi(a^b|s) over the first `start_steps` steps (else NaN)
    log_prob_after: float  # ... and after them


@dataclass(frozen=True)
class Checkpoint:
    env_id: str
    seed: int  # the run's: the final evaluation resets episode i with seed + EVAL_SEED_OFFSET + i
    gate_k: int
    actor: torch.nn.Module
    script: ModuleType  # jirl_sac_continuous.py: its gate, log-density, rho and unit conversions


def load(path: str) -> Checkpoint:
    """A SAC or JIRL checkpoint's policy and run settings; ValueError for a file that is not one."""
    script = load_module(str(ROOT / "jirl_sac_continuous.py"), "jirl_under_test")
    checkpoint = script.load_checkpoint(path)
    env = make_env(checkpoint["env_id"], 0)
    actor = script.actor_from_checkpoint(checkpoint, env)
    env.close()
    args = checkpoint["args"]  # a SAC checkpoint has no K: the JIRL default
    return Checkpoint(checkpoint["env_id"], args["seed"], args.get("gate_k", 5), actor, script)


def median_or_nan(values: list[float]) -> float:
    return float(np.median(values)) if values else math.nan


def drive(checkpoint: Checkpoint, episodes: int, handoff: int = 0, gate_c: Optional[float] = None, start_steps: int = 20, sample_seed: int = 0) -> list[Episode]:
    """Episodes of the checkpoint's policy from its evaluation's reset seeds: the baseline acts for the
    first `handoff` steps, then the deterministic policy; or, with `gate_c`, the gate decides every step
    between the baseline's action and one sampled from the policy (one torch generator, `sample_seed`,
    over all the episodes). ValueError if the policy's action is not finite where it acts."""
    jirl, actor = checkpoint.script, checkpoint.actor
    env = make_env(checkpoint.env_id, checkpoint.seed)
    baseline: Callable[[np.ndarray], np.ndarray] = get_baseline(checkpoint.env_id)
    space = env.action_space
    assert isinstance(space, Box)  # actor_from_checkpoint has compared its bounds with the checkpoint's
    low, high = space.low, space.high
    generator = torch.Generator().manual_seed(sample_seed)
    found = []
    for i in range(episodes):
        obs, _ = env.reset(seed=checkpoint.seed + jirl.EVAL_SEED_OFFSET + i)
        gate = jirl.Gate(checkpoint.gate_k)
        if hasattr(baseline, "reset"):  # a baseline with a memory (the track's lane follower) starts afresh
            baseline.reset()
        episode_return, length, rl_steps, at_start, after, done, terminated = 0.0, 0, 0, 0, 0, False, False
        log_probs: list[float] = []
        while not done:
            baseline_action = jirl.to_policy_units(jirl.check_baseline_action(baseline(obs), space), low, high)
            with torch.inference_mode():
                mean, log_std = actor(torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0))
            if gate_c is None:
                rl_acts = length >= handoff
                # the evaluation's mean action, to the last bit: on Walker2D a tanh taken in float64 moves some episodes
                action = torch.tanh(mean)[0].numpy() if rl_acts else baseline_action.astype(np.float32)
            else:  # Alg. 1, line 4: the gate (Alg. 3), as the training runs it
                mean64, log_std64 = mean[0].numpy().astype(np.float64), log_std[0].numpy().astype(np.float64)
                if not np.isfinite(mean64).all() or not np.isfinite(log_std64).all():  # the gate weighs the policy at every step
                    raise ValueError(OVERFLOW.format(step=length, episode=i))
                with torch.inference_mode():
                    sampled = torch.tanh(torch.normal(mean, log_std.exp(), generator=generator))[0].numpy()  # a^rl ~ pi(.|s)
                log_prob = jirl.squashed_log_prob(mean64, log_std64, baseline_action)
                log_probs.append(log_prob)
                rl_acts = gate.decide(log_prob, jirl.divergence(mean64, log_std64, baseline_action), gate_c)
                gate.record(rl_acts)
                action = sampled if rl_acts else baseline_action.astype(np.float32)
            if not np.isfinite(action).all():
                raise ValueError(OVERFLOW.format(step=length, episode=i))
            obs, reward, terminated, truncated, _ = env.step(jirl.to_env_units(action, low, high))
            rl_steps += rl_acts
            at_start += not rl_acts and length < start_steps
            after += not rl_acts and length >= start_steps
            episode_return, length, done = episode_return + float(reward), length + 1, terminated or truncated
        start, rest = median_or_nan(log_probs[:start_steps]), median_or_nan(log_probs[start_steps:])
        found.append(Episode(episode_return, length, bool(terminated), rl_steps, at_start, after, start, rest))
    env.close()
    return found


def row(name: str, mode: str, found: list[Episode], start_steps: int, gated: bool) -> str:
    returns = [e.episode_return for e in found]
    lengths = [e.length for e in found]
    steps = sum(lengths)
    gate = "–"
    if gated:
        gate = (
            f"{100 * sum(e.rl_steps for e in found) / steps:.1f} % | {statistics.median(e.baseline_at_start for e in found):g} of {start_steps}"
            f" | {statistics.median(e.baseline_after for e in found):g}"
            f" | {np.nanmedian([e.log_prob_at_start for e in found]):.1f} | {np.nanmedian([e.log_prob_after for e in found]):.1f}"
        )
    else:
        gate += " | – | – | – | –"
    return (
        f"| {name} | {mode} | {statistics.median(returns):.1f} ({min(returns):.1f} to {max(returns):.1f}) | {statistics.median(lengths):g} ({min(lengths)} to {max(lengths)})"
        f" | {sum(e.terminated for e in found)} of {len(found)} | {gate} |"
    )


def counts(text: str) -> list[int]:
    """`5,20,50` as [5, 20, 50]; an empty text as none."""
    return [int(word) for word in text.split(",") if word.strip()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", type=Path, nargs="+", help="files the scripts wrote with --save-model")
    parser.add_argument("--episodes", type=int, default=10, help="the final evaluation's count")
    parser.add_argument("--handoffs", type=counts, default=[5, 20, 50], help="the baseline's steps before the policy acts, comma-separated (5,20,50); none: ''")
    parser.add_argument("--gate-c", type=float, default=None, help="the gate's C, e.g. the run's last gate/c in its TensorBoard log; none: no gate rows")
    parser.add_argument("--start-steps", type=int, default=20, help="an episode's start, for the gate's count of the baseline's steps")
    parser.add_argument("--sample-seed", type=int, default=0, help="seeds the gate's draws of a^rl")
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error("--episodes must be at least 1")
    if any(n < 1 for n in args.handoffs):
        parser.error("--handoffs must be at least 1 each (the policy alone is always measured)")
    if args.gate_c is not None and not (args.gate_c >= 0.0 and math.isfinite(args.gate_c)):
        parser.error(f"--gate-c must be a finite number at least 0, not {args.gate_c}")
    if args.start_steps < 1:
        parser.error("--start-steps must be at least 1")
    torch.set_num_threads(1)
    print(
        "| checkpoint | who acts | return, median (range) | length, median (range) | terminated early | RL steps"
        " | baseline steps at the start, median | after, median | log-density of a^b at the start, median | after |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for path in args.checkpoints:
        try:
            checkpoint = load(str(path))
        except ValueError as err:
            print(f"| {path} | unreadable: {' '.join(str(err).split())} | | | | | | | | |", flush=True)  # one table row
            continue
        modes: list[tuple[str, dict]] = [("alone", {})]
        modes += [(f"the baseline's first {n} steps, then the policy", {"handoff": n}) for n in args.handoffs]
        if args.gate_c is not None:
            modes.append((f"gate, C = {args.gate_c:g}", {"gate_c": args.gate_c, "start_steps": args.start_steps, "sample_seed": args.sample_seed}))
        for mode, options in modes:
            try:
                found = drive(checkpoint, args.episodes, **options)
            except ValueError as err:  # a policy that overflows, or a failing env or baseline: say so, go on
                print(f"| {path} | {mode}: failed: {' '.join(str(err).split())} | | | | | | | | |", flush=True)
                continue
            print(row(str(path), mode, found, args.start_steps, "gate_c" in options), flush=True)

if __name__ == "__main__":
    main()
