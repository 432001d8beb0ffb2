"""The JetRacer baseline: a classical lane follower, steering by a PD law at a slow constant throttle.

It reads the lane mask of `car_interface.preprocess` (the dark lane surface, found by thresholding the
camera frame with OpenCV), so the same object drives the simulator and the real car. The lateral
error is the offset of the lane's centroid from the image centre, averaged over the look-ahead rows;
on bends the far rows lead the near ones, which is what lets a PD law take the curve.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from envs.car_interface import MASK_SHAPE

LOOK_AHEAD_ROWS = slice(2, 8)  # mask rows (0 = top of the cropped frame) whose lane centroid is followed
KP, KD = 1.6, 0.6  # steering command per unit of normalised error, and per unit of its change per step
THROTTLE_ACTION = -1.0  # the slowest throttle of the window: the baseline is safe, not fast


class LaneFollower:
    """Call with an observation; returns the action (steering, throttle) in [-1, 1]. Stateful: call reset()."""

    def __init__(self) -> None:
        self.previous_error: Optional[float] = None

    def reset(self) -> None:
        self.previous_error = None

    def lateral_error(self, observation: np.ndarray) -> Optional[float]:
        """Normalised offset of the lane to the right of the image centre, in [-1, 1]; None if no lane is seen."""
        mask = np.asarray(observation[: MASK_SHAPE[0] * MASK_SHAPE[1]]).reshape(MASK_SHAPE)[LOOK_AHEAD_ROWS]
        weight = mask.sum()
        if weight < 1.0:
            return None
        columns = np.arange(MASK_SHAPE[1]) + 0.5
        centroid = float((mask * columns).sum() / weight)
        return (centroid - MASK_SHAPE[1] / 2.0) / (MASK_SHAPE[1] / 2.0)

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        error = self.lateral_error(observation)
        if error is None:  # lost the lane: hold the wheel straight and crawl
            self.previous_error = None  # an error from before the gap is no rate of change after it
            return np.array([0.0, THROTTLE_ACTION], dtype=np.float32)
        change = 0.0 if self.previous_error is None else error - self.previous_error
        self.previous_error = error
        steering = -(KP * error + KD * change)  # lane to the right -> steer right (negative)
        return np.array([np.clip(steering, -1.0, 1.0), THROTTLE_ACTION], dtype=np.float32)
