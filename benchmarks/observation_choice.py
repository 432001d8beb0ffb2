"""Which camera observation should the MLP policies of the SAC scripts see on JetRacerTrack-v0?

Renders frames from random poses on the track (position along the lane, cross-track error, heading
error all random), reduces each to a candidate observation, and measures how much of the two
quantities a lane follower needs, cross-track error and heading error, a ridge regression can read
from it (R^2 on held-out frames), against the observation's size (the first layer of every network
grows with it). Prints a markdown table.

    python benchmarks/observation_choice.py --frames 3000
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from envs.car_interface import CROP_TOP, LANE_MAX_BRIGHTNESS  # noqa: E402
from envs.jetracer_track import JetRacerTrackEnv  # noqa: E402


def candidates(frame_bgr: np.ndarray) -> dict[str, np.ndarray]:
    cropped = frame_bgr[CROP_TOP:]
    grey = cv2.cvtColor(cropped, cv2.COLOR_BGR2GRAY)
    lane = (grey <= LANE_MAX_BRIGHTNESS).astype(np.float32)
    out: dict[str, np.ndarray] = {}
    for rows, cols in [(5, 7), (10, 14), (20, 28), (40, 56)]:
        out[f"lane mask {rows}x{cols}"] = cv2.resize(lane, (cols, rows), interpolation=cv2.INTER_AREA).reshape(-1)
    out["grey 10x14"] = cv2.resize(grey, (14, 10), interpolation=cv2.INTER_AREA).reshape(-1) / 255.0
    out["grey 20x28"] = cv2.resize(grey, (28, 20), interpolation=cv2.INTER_AREA).reshape(-1) / 255.0
    return out


def ridge_r2(x: np.ndarray, y: np.ndarray, train: np.ndarray, test: np.ndarray, alpha: float = 1e-2) -> np.ndarray:
    """Held-out R^2 of a ridge regression with a quadratic feature expansion of the top principal components,
    each scaled to unit variance on the training rows, so that `alpha` is small beside every feature."""
    mean = x[train].mean(0)
    u, s, vt = np.linalg.svd(x[train] - mean, full_matrices=False)
    k = min(40, vt.shape[0])
    z = (x - mean) @ vt[:k].T / (s[:k] / np.sqrt(len(train)) + 1e-8)  # a singular value is sqrt(rows) times the component's std
    iu = np.triu_indices(k)
    features = np.hstack([np.ones((len(z), 1)), z, (z[:, :, None] * z[:, None, :])[:, iu[0], iu[1]]])
    a = features[train]
    w = np.linalg.solve(a.T @ a + alpha * np.eye(a.shape[1]), a.T @ y[train])
    residual = y[test] - features[test] @ w
    return 1.0 - residual.var(0) / y[test].var(0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=3000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    minimums = {"--frames": (args.frames, 1), "--seed": (args.seed, 0)}
    if too_small := [f"{flag} must be at least {low}" for flag, (value, low) in minimums.items() if not value >= low]:
        parser.error("; ".join(too_small))
    rng = np.random.default_rng(args.seed)
    env = JetRacerTrackEnv(random_start=False, randomize_lighting=True)
    env.reset(seed=args.seed)
    rows: dict[str, list[np.ndarray]] = {}
    targets = []
    start = time.perf_counter()
    for i in range(args.frames):
        s = rng.uniform(0, env.track.length)
        x, y, heading = env.track.pose_at(s)
        cte, heading_error = rng.uniform(-0.2, 0.2), rng.uniform(-0.5, 0.5)
        env._state[:3] = [x - math.sin(heading) * cte, y + math.cos(heading) * cte, heading + heading_error]
        if i % 50 == 0:
            env.reset(seed=args.seed + i)  # new lighting
            env._state[:3] = [x - math.sin(heading) * cte, y + math.cos(heading) * cte, heading + heading_error]
        for name, value in candidates(env.camera_frame_bgr()).items():
            rows.setdefault(name, []).append(value)
        targets.append([cte, heading_error])
    elapsed = time.perf_counter() - start
    env.close()
    truth = np.array(targets)
    order = rng.permutation(len(truth))
    train, test = order[: int(0.8 * len(truth))], order[int(0.8 * len(truth)) :]
    print(f"{args.frames} frames from random poses (|cte| <= 0.2 m, |heading error| <= 0.5 rad), lighting randomised; "
          f"{args.frames / elapsed:.0f} frames/s rendered and reduced")  # fmt: skip
    print("| observation | size | held-out R^2, cross-track error | held-out R^2, heading error |")
    print("|---|---|---|---|")
    for name, values in rows.items():
        features = np.array(values, dtype=np.float64)
        r2 = ridge_r2(features, truth, train, test)
        print(f"| {name} | {features.shape[1]} | {r2[0]:.3f} | {r2[1]:.3f} |")


if __name__ == "__main__":
    main()
