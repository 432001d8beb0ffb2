"""The one mapping between a policy and a JetRacer, shared by the simulator and deploy/.

Camera side: a 112x112 BGR frame (what jetcam delivers, and what the simulator renders) becomes the
policy's observation with `preprocess`. Action side: a policy action in [-1, 1]^2 becomes the car's
commands with `action_to_commands`. Only numpy and OpenCV are needed, so this runs on the car.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FRAME_SHAPE = (112, 112, 3)  # rows, cols, BGR
CROP_TOP = 32  # rows above the road (horizon, room) cut off, as on the authors' car
MASK_SHAPE = (10, 14)  # rows, cols of the lane mask the policy sees (measured choice: BENCHMARKS.md)
LANE_MAX_BRIGHTNESS = 90  # grey level at or below which a pixel counts as the dark lane surface
OBS_SIZE = MASK_SHAPE[0] * MASK_SHAPE[1] + 2  # mask, then the previous action (steering, throttle)
START_ACTION = (0.0, -1.0)  # the previous action at an episode start, the car at rest: wheel straight, slowest throttle


@dataclass(frozen=True)
class ActionMapping:
    """Policy action [-1, 1]^2 -> commands: steering in [-max_steering, max_steering] (+ = left) and a
    forward-only throttle window [min_throttle, max_throttle] (duty cycle; the paper's car: 0.45-0.6)."""

    max_steering: float = 1.0
    min_throttle: float = 0.45
    max_throttle: float = 0.6

    def __post_init__(self) -> None:
        if not (0.0 < self.max_steering <= 1.0 and 0.0 <= self.min_throttle <= self.max_throttle <= 1.0):
            raise ValueError(f"invalid action mapping {self}")


def action_to_commands(action: np.ndarray, mapping: ActionMapping = ActionMapping()) -> tuple[float, float]:
    """(steering, throttle) commands for a policy action; ValueError for a non-finite action."""
    action = np.asarray(action, dtype=np.float64).reshape(-1)
    if action.shape != (2,) or not np.all(np.isfinite(action)):
        raise ValueError(f"expected 2 finite action values, got {action!r}")
    steering, throttle = np.clip(action, -1.0, 1.0)
    throttle_command = mapping.min_throttle + (throttle + 1.0) * 0.5 * (mapping.max_throttle - mapping.min_throttle)
    return float(steering * mapping.max_steering), float(throttle_command)


def lane_mask(frame_bgr: np.ndarray) -> np.ndarray:
    """Fraction of dark lane surface in each cell of the cropped frame, shape MASK_SHAPE, float32 in [0, 1]."""
    import cv2  # imported here: the car's Python may load OpenCV slowly, and tests of other parts need none

    frame = np.asarray(frame_bgr)
    if frame.shape != FRAME_SHAPE or frame.dtype != np.uint8:
        raise ValueError(f"expected a {FRAME_SHAPE} uint8 BGR frame, got {frame.shape} {frame.dtype}")
    grey = cv2.cvtColor(frame[CROP_TOP:], cv2.COLOR_BGR2GRAY)
    lane = (grey <= LANE_MAX_BRIGHTNESS).astype(np.float32)
    return cv2.resize(lane, (MASK_SHAPE[1], MASK_SHAPE[0]), interpolation=cv2.INTER_AREA)


def preprocess(frame_bgr: np.ndarray, previous_action: np.ndarray) -> np.ndarray:
    """The policy's observation: the lane mask, flattened, then the previous action. Shape (OBS_SIZE,)."""
    previous_action = np.clip(np.asarray(previous_action, dtype=np.float32).reshape(2), -1.0, 1.0)
    return np.concatenate([lane_mask(frame_bgr).reshape(-1), previous_action]).astype(np.float32)
