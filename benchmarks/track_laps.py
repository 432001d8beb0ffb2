"""Lap times on JetRacerTrack-v0 of saved policies (deterministic) and of the lane-follower baseline.

Drives each checkpoint written by sac_continuous.py or jirl_sac_continuous.py (--save-model) for
`--episodes` full episodes from reset seeds EVAL_SEED_OFFSET + i and reads `info["lap_times"]`
(simulated seconds, start line to start line). Prints a markdown row per policy: laps, median lap
time, how many episodes left the lane, and the median's gain over the baseline's.

    python benchmarks/track_laps.py benchmarks/results/reproduce/JetRacerTrack-v0/*/seed*/runs/*/*.cleanrl_model
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path
from typing import Callable

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from envs import get_baseline, make_env  # noqa: E402

from side_by_side import checkpoint_policy  # noqa: E402


def drive(policy: Callable[[np.ndarray], np.ndarray], episodes: int, seed_offset: int) -> tuple[list[float], int]:
    """Lap times over `episodes` episodes and how many of them ended off the lane."""
    env = make_env("JetRacerTrack-v0")
    laps, off_lane = [], 0
    for i in range(episodes):
        if hasattr(policy, "reset"):
            policy.reset()
        obs, _ = env.reset(seed=seed_offset + i)
        done = False
        while not done:
            obs, _, terminated, truncated, info = env.step(policy(obs))
            done = terminated or truncated
        laps += list(info["lap_times"])
        off_lane += int(terminated)
    env.close()
    return laps, off_lane


def track_policy(path: Path) -> Callable[[np.ndarray], np.ndarray]:
    env_id, policy = checkpoint_policy(path)
    if env_id != "JetRacerTrack-v0":
        raise ValueError(f"trained on {env_id}, not JetRacerTrack-v0")
    return policy


def row(name: str, laps: list[float], off_lane: int, episodes: int, reference: float) -> str:
    median = statistics.median(laps) if laps else float("nan")
    gain = f"{100 * (1 - median / reference):.0f} %" if laps and reference else "–"
    return f"| {name} | {len(laps)} | {median:.2f} | {off_lane}/{episodes} | {gain} |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", type=Path, nargs="*")
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--seed-offset", type=int, default=1_000_000, help="episode i resets with this + i (the scripts' evaluation seeds)")
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error("--episodes must be at least 1")
    torch.set_num_threads(1)
    base_laps, base_off = drive(get_baseline("JetRacerTrack-v0"), args.episodes, args.seed_offset)
    reference = statistics.median(base_laps) if base_laps else 0.0
    print(f"JetRacerTrack-v0, {args.episodes} episodes of 2000 steps per policy, deterministic")
    print("| policy | laps | median lap s | episodes off the lane | faster than the baseline |")
    print("|---|---|---|---|---|")
    print(row("baseline (lane follower)", base_laps, base_off, args.episodes, reference), flush=True)
    for path in args.checkpoints:
        try:
            policy = track_policy(path)
        except ValueError as err:
            print(f"| {path} | unreadable: {' '.join(str(err).split())} | | | |")  # one table row
            continue
        laps, off_lane = drive(policy, args.episodes, args.seed_offset)
        print(row(str(path), laps, off_lane, args.episodes, reference), flush=True)


if __name__ == "__main__":
    main()
