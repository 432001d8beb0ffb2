"""JetRacerTrack-v0: a JetRacer-sized car following a stadium lane from its forward camera.

The car is a kinematic bicycle (steering and speed each behind a first-order lag, as a servo and an
ESC), stepped at a 20 Hz control rate; PyBullet only renders what the camera sees: one textured quad
carrying the drawn track, through the CPU TinyRenderer. The observation is `car_interface.preprocess`
of the 112x112 BGR frame, exactly what the real car computes.

Reward: centre-line progress per step (m) x `progress_reward` (faster laps earn more),
`off_track_reward` once when the car's centre leaves the lane, which terminates the episode;
truncation at the registered step limit. `info`: cross-track error (m), heading error (rad), speed
(m/s), s and progress (m), lap count, lap times (simulated s).
"""

from __future__ import annotations

import contextlib
import math
import os
import tempfile
from dataclasses import dataclass
from typing import Any, Iterator, Optional

import gymnasium as gym
import numpy as np

from envs.car_interface import FRAME_SHAPE, OBS_SIZE, START_ACTION, ActionMapping, action_to_commands, preprocess
from envs.track import TrackSpec, wrap_angle


@dataclass(frozen=True)
class CarSpec:
    """The car's geometry, dynamics and camera pose, each in the unit beside it; ValueError for an impossible car."""

    wheelbase: float = 0.2  # m
    max_steering_angle: float = 0.5  # rad at steering command 1
    max_speed: float = 2.5  # m/s at throttle 1
    throttle_deadband: float = 0.2  # throttle below which the motor does not turn the wheels
    steering_lag: float = 0.1  # s, first-order time constant of the servo
    speed_lag: float = 0.3  # s, of the drive train
    camera_height: float = 0.18  # m above the floor
    camera_forward: float = 0.08  # m ahead of the car's reference point, the rear axle
    camera_pitch: float = 0.45  # rad below the horizon
    camera_fov: float = 120.0  # degrees, vertical (the car's camera is a wide-angle one)

    def __post_init__(self) -> None:
        lengths = (self.wheelbase, self.max_speed, self.steering_lag, self.speed_lag)  # the lags divide the step
        if not (all(v > 0 for v in lengths) and 0 < self.max_steering_angle < math.pi / 2 and 0 <= self.throttle_deadband < 1 and 0 < self.camera_fov < 180):
            raise ValueError(f"impossible car: {self} (wheelbase, speed and lags > 0, steering angle in (0, pi/2), deadband in [0, 1), fov in (0, 180))")


@contextlib.contextmanager
def _quiet_stdout() -> Iterator[None]:
    """PyBullet's C code prints to file descriptor 1 on import and connect; keep the scripts' output clean."""
    import sys

    sys.stdout.flush()
    saved = os.dup(1)
    with open(os.devnull, "w") as devnull:
        os.dup2(devnull.fileno(), 1)
        try:
            yield
        finally:
            os.dup2(saved, 1)
            os.close(saved)


class JetRacerTrackEnv(gym.Env):
    """The lane-following car (module docstring). Observation: float32 (142,), the 10x14 lane mask in [0, 1]
    row by row, then the previous action in [-1, 1]. Action: float32 (2,), (steering, throttle) in [-1, 1]."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(
        self,
        track: TrackSpec = TrackSpec(),
        car: CarSpec = CarSpec(),
        mapping: ActionMapping = ActionMapping(),
        control_hz: float = 20.0,
        progress_reward: float = 10.0,
        off_track_reward: float = -10.0,
        random_start: bool = True,
        randomize_lighting: bool = False,
        render_mode: Optional[str] = None,
    ):
        with _quiet_stdout():
            import pybullet
            from pybullet_utils import bullet_client

        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if not 0 < control_hz < math.inf:
            raise ValueError(f"control_hz must be > 0, got {control_hz}")
        self.track, self.car, self.mapping = track, car, mapping
        self.dt = 1.0 / control_hz
        self.progress_reward, self.off_track_reward = progress_reward, off_track_reward
        self.random_start, self.randomize_lighting, self.render_mode = random_start, randomize_lighting, render_mode
        self.observation_space = gym.spaces.Box(0.0, 1.0, shape=(OBS_SIZE,), dtype=np.float32)
        self.observation_space.low[-2:] = -1.0
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)

        self._p = pybullet
        with _quiet_stdout():
            self._client = bullet_client.BulletClient(connection_mode=pybullet.DIRECT)
        self._ground = self._load_ground()
        marker = self._client.createVisualShape(pybullet.GEOM_BOX, halfExtents=[0.1, 0.06, 0.04], rgbaColor=[0.1, 0.6, 0.2, 1])
        self._marker = self._client.createMultiBody(baseVisualShapeIndex=marker, basePosition=[0, 0, -1])
        self._projection = self._client.computeProjectionMatrixFOV(car.camera_fov, 1.0, 0.02, 6.0)
        self._state = np.zeros(5)  # x, y, yaw, speed, steering angle

    def _load_ground(self) -> int:
        import cv2

        half_x, half_y = self.track.extent
        with tempfile.TemporaryDirectory(prefix="jetracer_track_") as assets:  # PyBullet keeps what it loads in memory
            texture_path = os.path.join(assets, "track.png")
            cv2.imwrite(texture_path, cv2.cvtColor(self.track.texture(), cv2.COLOR_RGB2BGR))
            mesh_path = os.path.join(assets, "quad.obj")
            with open(mesh_path, "w") as f:  # one quad with UVs 0..1, so the texture is not tiled
                f.write("v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvn 0 0 1\nf 1/1/1 2/2/1 3/3/1\nf 1/1/1 3/3/1 4/4/1\n")
            shape = self._client.createVisualShape(self._p.GEOM_MESH, fileName=mesh_path, meshScale=[half_x, half_y, 1])
            self._texture = self._client.loadTexture(texture_path)
        body = self._client.createMultiBody(baseVisualShapeIndex=shape)
        self._client.changeVisualShape(body, -1, textureUniqueId=self._texture)
        return body

    def _camera_frame(self, width: int = FRAME_SHAPE[1], height: int = FRAME_SHAPE[0], chase: bool = False) -> np.ndarray:
        """RGB uint8 image from the car's camera (or, for rendering, from above and behind the car)."""
        x, y, yaw = self._state[:3]
        forward = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        if chase:
            eye = np.array([x, y, 0.0]) - 0.9 * forward + [0, 0, 1.1]
            target = np.array([x, y, 0.0]) + 0.6 * forward
        else:
            eye = np.array([x, y, self.car.camera_height]) + self.car.camera_forward * forward
            pitch = self.car.camera_pitch
            target = eye + math.cos(pitch) * forward - [0, 0, math.sin(pitch)]
        view = self._client.computeViewMatrix(eye.tolist(), target.tolist(), [0, 0, 1])
        _, _, rgba, _, _ = self._client.getCameraImage(
            width, height, view, self._projection, shadow=0, renderer=self._p.ER_TINY_RENDERER, flags=self._p.ER_NO_SEGMENTATION_MASK
        )
        return np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)[..., :3]

    def camera_frame_bgr(self) -> np.ndarray:
        """The current 112x112 BGR frame, as the car's camera would deliver it."""
        return np.ascontiguousarray(self._camera_frame()[..., ::-1])

    def _observe(self) -> np.ndarray:
        return preprocess(self.camera_frame_bgr(), self._previous_action)

    def _info(self) -> dict[str, Any]:
        x, y, yaw, speed, _ = self._state
        s, cte, heading = self.track.project(x, y)
        return {
            "cte": cte,
            "heading_error": wrap_angle(yaw - heading),
            "speed": speed,
            "s": s,
            "progress": self._progress,
            "lap_count": self._laps,
            "lap_times": list(self._lap_times),
            "time": self._time,
        }

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None) -> tuple[np.ndarray, dict]:
        """With `random_start`, anywhere on the centre line, up to 5 cm beside it and 0.1 rad off its heading;
        else at the start line. With `randomize_lighting`, the floor gets a new tint."""
        super().reset(seed=seed)
        s0 = self.np_random.uniform(0.0, self.track.length) if self.random_start else 0.0
        x, y, heading = self.track.pose_at(s0)
        offset = self.np_random.uniform(-0.05, 0.05) if self.random_start else 0.0
        x, y = x - math.sin(heading) * offset, y + math.cos(heading) * offset
        yaw = heading + (self.np_random.uniform(-0.1, 0.1) if self.random_start else 0.0)
        self._state = np.array([x, y, yaw, 0.0, 0.0])
        self._s, self._progress, self._time = self.track.project(x, y)[0], 0.0, 0.0
        self._laps = 0
        self._lap_times: list[float] = []  # simulated s, each from line to line
        self._lap_started: Optional[float] = None
        self._previous_action = np.array(START_ACTION, dtype=np.float32)
        if self.randomize_lighting:
            tint = self.np_random.uniform(0.65, 1.0) * self.np_random.uniform(0.9, 1.0, size=3)
            self._client.changeVisualShape(self._ground, -1, rgbaColor=[*tint, 1.0])
        return self._observe(), self._info()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        """One control period under `action`, mapped to commands as on the car; ValueError for a non-finite one."""
        commands = action_to_commands(action, self.mapping)  # ValueError for a non-finite action, before any state changes
        self._previous_action = np.clip(np.asarray(action, dtype=np.float32), -1.0, 1.0)
        progress, terminated = self.drive(*commands)
        reward = self.off_track_reward if terminated else progress * self.progress_reward
        return self._observe(), float(reward), terminated, False, self._info()

    def drive(self, steering_command: float, throttle_command: float) -> tuple[float, bool]:
        """Advance one control period under raw commands, as a motor controller applies them (a
        throttle below the deadband, e.g. STOP's 0, brakes the car to rest). Returns (centre-line
        progress in m, whether the car has left the lane). `step` is this after the action mapping.
        ValueError for a non-finite command, which would put NaN into the car's pose."""
        if not (math.isfinite(steering_command) and math.isfinite(throttle_command)):
            raise ValueError(f"commands must be finite, got steering {steering_command} and throttle {throttle_command}")
        car = self.car
        steering_target = float(np.clip(steering_command, -1.0, 1.0)) * car.max_steering_angle
        speed_target = car.max_speed * max(0.0, throttle_command - car.throttle_deadband) / (1.0 - car.throttle_deadband)
        x, y, yaw, speed, steering = self._state
        substeps = 5
        h = self.dt / substeps
        for _ in range(substeps):
            steering += (steering_target - steering) * (1.0 - math.exp(-h / car.steering_lag))
            speed += (speed_target - speed) * (1.0 - math.exp(-h / car.speed_lag))
            x += speed * math.cos(yaw) * h
            y += speed * math.sin(yaw) * h
            yaw += speed / car.wheelbase * math.tan(steering) * h
        self._state = np.array([x, y, wrap_angle(yaw), speed, steering])
        self._time += self.dt

        s, cte, _ = self.track.project(x, y)
        progress = self.track.progress(self._s, s)
        self._count_laps(self._s, progress)
        self._s, self._progress = s, self._progress + progress
        self._marker_follows()
        return progress, abs(cte) > self.track.lane_width / 2.0

    def _count_laps(self, s_before: float, progress: float) -> None:
        """A lap is counted when the car crosses the start line (s = 0) forwards, un-counted backwards."""
        crossed_forward = progress > 0 and s_before + progress >= self.track.length
        crossed_backward = progress < 0 and s_before + progress < 0.0
        if crossed_forward:
            self._laps += 1
            if self._lap_started is not None:
                self._lap_times.append(self._time - self._lap_started)
            self._lap_started = self._time
        elif crossed_backward:
            self._laps -= 1
            self._lap_started = None  # a lap time needs a clean forward lap from line to line

    def _marker_follows(self) -> None:
        if self.render_mode is not None:
            x, y, yaw = self._state[:3]
            orientation = self._p.getQuaternionFromEuler([0, 0, yaw])
            # behind the camera, so the camera never sees it
            self._client.resetBasePositionAndOrientation(self._marker, [x - 0.1 * math.cos(yaw), y - 0.1 * math.sin(yaw), 0.04], orientation)

    def render(self) -> Optional[np.ndarray]:
        """A chase view of the car, (256, 256, 3) uint8 RGB, for videos; None unless render_mode is "rgb_array"."""
        if self.render_mode != "rgb_array":
            return None
        self._marker_follows()
        return self._camera_frame(256, 256, chase=True)

    def close(self) -> None:
        if getattr(self, "_client", None) is not None:
            self._client.disconnect()
            self._client = None
