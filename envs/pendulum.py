"""A deliberately suboptimal swing-up controller for Pendulum-v1.

Pendulum-v1 integrates theta'' = 3g/(2l) sin(theta) + 3/(m l^2) u with g = 10, m = l = 1,
dt = 0.05 s and |u| <= 2 N m; theta = 0 is upright. With w = theta' the conserved energy of the
unforced pendulum is E = w^2 / 2 + 15 cos(theta), which is 15 at rest upright, and
dE/dt = 3 u w, so a torque with the sign of (E* - E) w pumps energy towards the upright.

The controller pumps with a reduced torque (so it swings up slowly, as the paper's baseline was
trained to use "lower torque values than optimal") and catches the pendulum with a PD law once
it is near the top.
"""

from __future__ import annotations

import numpy as np

TARGET_ENERGY = 15.0  # E at rest upright
PUMP_GAIN = 0.5
PUMP_TORQUE = 1.0  # N m, half the available torque: the deliberate weakness
CATCH_COS = 0.85  # switch to the PD catch within ~32 degrees of upright
KP, KD = 6.0, 1.0  # PD gains of the catch, N m per rad and per rad/s
MAX_TORQUE = 2.0


def pendulum_swing_up(obs: np.ndarray) -> np.ndarray:
    """Torque (N m, shape (1,)) for a Pendulum-v1 observation (cos theta, sin theta, theta')."""
    cos_th, sin_th, w = float(obs[0]), float(obs[1]), float(obs[2])
    theta = np.arctan2(sin_th, cos_th)
    if cos_th > CATCH_COS:
        torque = -(KP * theta + KD * w)
    else:
        energy = 0.5 * w * w + TARGET_ENERGY * cos_th
        # at rest (w = 0) sign(w) would give no torque at all: push one way to start the swing
        direction = np.sign(w) if w != 0.0 else 1.0
        torque = np.clip(PUMP_GAIN * (TARGET_ENERGY - energy) * direction, -PUMP_TORQUE, PUMP_TORQUE)
    return np.array([np.clip(torque, -MAX_TORQUE, MAX_TORQUE)], dtype=np.float32)
