"""Controllers for LunarLanderContinuous-v3: a weak baseline and a strong expert.

Observation: x, y (pad at (0, 0)), vx, vy, angle (rad, positive = tilted left), angular
velocity, and two leg-contact flags. Action: main engine in [-1, 1] (off below 0, 50-100 %
power from 0 to 1) and lateral engines in [-1, 1] (|a| < 0.5 is off). Firing the main engine
costs 0.3 reward per frame at full power, so a slow descent is an expensive one.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from gymnasium.envs.box2d.lunar_lander import heuristic

# Slow-descent baseline: a descent-rate reference plus an attitude PD. The low reference sink rate
# keeps the main engine firing for most of the flight: the lander lands safely but burns fuel.
SINK_RATE_FLOOR = 0.04  # normalised vertical speed held just above the pad
SINK_RATE_PER_HEIGHT = 0.12  # faster sink when high
VERTICAL_GAIN = 12.0  # main-engine command per unit of sink-rate error
HOVER_BIAS = 0.25  # main-engine command that roughly cancels gravity
TILT_PER_OFFSET, TILT_PER_SPEED, MAX_TILT = 0.4, 1.2, 0.3  # lean towards the pad, rad
ATTITUDE_KP, ATTITUDE_KD = 8.0, 16.0  # lateral command per rad and per rad/s


def lunar_lander_slow_descent(obs: np.ndarray) -> np.ndarray:
    """The project's suboptimal baseline: lands reliably, slowly and wastefully. Shape (2,)."""
    x, y, vx, vy, angle, angular_velocity = (float(v) for v in obs[:6])
    legs_down = obs[6] > 0.5 or obs[7] > 0.5
    sink_reference = -(SINK_RATE_FLOOR + SINK_RATE_PER_HEIGHT * max(y, 0.0))
    main = HOVER_BIAS + VERTICAL_GAIN * (sink_reference - vy)
    tilt_target = np.clip(TILT_PER_OFFSET * x + TILT_PER_SPEED * vx, -MAX_TILT, MAX_TILT)
    lateral = ATTITUDE_KP * (angle - tilt_target) + ATTITUDE_KD * angular_velocity
    if legs_down:  # on the ground: only cushion the fall, stop steering
        main = -1.0 if vy > -0.05 else VERTICAL_GAIN * -vy
        lateral = 0.0
    return np.clip(np.array([main, lateral], dtype=np.float32), -1.0, 1.0)


def lunar_lander_expert(obs: np.ndarray) -> np.ndarray:
    """Gymnasium's own heuristic lander (about 282 per episode): a strong expert, not a baseline."""
    env = SimpleNamespace(unwrapped=SimpleNamespace(continuous=True))
    return np.asarray(heuristic(env, obs), dtype=np.float32)
