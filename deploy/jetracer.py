"""Drive a JetRacer with a trained policy or with the baseline, or train a policy on the car with JIRL.

    python -m deploy.jetracer run --checkpoint runs/RUN/jirl_sac_continuous.cleanrl_model --port /dev/ttyACM0 --camera csi
    python -m deploy.jetracer baseline --steps 600                 # simulated car behind a mock controller
    python -m deploy.jetracer train --total-steps 54000 --resume   # the paper's 45 minutes at 20 Hz

The car is reached through the serial protocol of docs/serial_protocol.md (`deploy.link`); with
`--port mockjetracer:// --camera sim` (the defaults) a mock controller drives the PyBullet track car,
so every mode runs headless through the real protocol (sim-in-the-loop). Safety on the host: steering
clamped and rate-limited, throttle held in its window, a NaN action sends STOP, a frame older than
two control periods stops the car and ends the episode, e-stop on the gamepad button, on losing the
gamepad and on Ctrl-C, SIGTERM or a hang-up; the controller's own watchdog stops the car if this process dies.
The run ends (`train` saves first) after 2 s without a fresh frame, or when the controller is no
longer armed: only a person re-arms it.
Runs on the car's Python 3.8 (JetPack 5) and newer.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import errno
import math
import os
import signal
import statistics
import sys
import threading
import time
import typing
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Dict, Iterator, List, Literal, Optional, Tuple, Union

import gymnasium as gym
import numpy as np
import tyro
from typing_extensions import Annotated  # typing's has it from Python 3.9; the car runs 3.8

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the JIRL script and envs/

import jirl_sac_continuous as jirl  # noqa: E402
from deploy import protocol as p  # noqa: E402
from deploy.io import CameraFailed, Gamepad, GamepadLost, OpenCVCamera, SimWorld, open_camera  # noqa: E402
from deploy.link import HostLink  # noqa: E402
from envs.car_interface import OBS_SIZE, START_ACTION, ActionMapping, action_to_commands, preprocess  # noqa: E402
from envs.lane_follower import LaneFollower  # noqa: E402

TRAIN_STATE_FORMAT = "jirl-car-training-v2"  # v2: the agent's twin critics as one ensemble
BUFFER_FIELDS = ("obs", "next_obs", "actions", "rewards", "terminations")  # the replay rows a training state keeps
TRAIN_COUNTERS: Dict[str, Any] = {"step": 0, "fabricated_transitions": 0, "control_switches": 0, "baseline_regret_per_step": 0.0,
                                  "paired_regret_per_step": 0.0, "updates": 0}  # fmt: skip
SENDS_PER_PERIOD = 2.5  # the link sends this many frames per control period (DRIVE or STOP, feeding the watchdog)
CAMERA_LOST_S = 2.0  # stale frames for this long end the run: the camera is gone (or a recorded video ended)
OVERFLOW_ROWS = 256  # the latest stored observations a pause runs the actor on before saving (0.2 ms at 64 units: BENCHMARKS)


@dataclass
class Common:
    """The options of every mode: the controller, the camera, the control rate and safety limits, the gamepad, the logs,
    and the simulated car's seed."""

    port: str = "mockjetracer://"
    """motor controller: a serial device (/dev/ttyACM0), mockjetracer:// (simulated car), or spy://DEVICE?file=LOG"""
    camera: str = "sim"
    """csi (Jetson CSI via GStreamer), usb:N, file:PATH (recorded video), or sim"""
    control_hz: float = 20.0
    """control rate"""
    min_throttle: float = 0.45
    """throttle command at policy throttle -1 (forward only)"""
    max_throttle: float = 0.6
    """throttle command at policy throttle +1; also the controller's throttle cap"""
    max_steering_rate: float = 8.0
    """largest steering command change per second"""
    watchdog_ms: int = 250
    """the controller stops the car if no command arrives for this long"""
    gamepad: str = ""
    """Linux joystick device (e.g. /dev/input/js0): a button e-stops, a held trigger takes over steering"""
    estop_button: int = 0
    """gamepad button that e-stops"""
    takeover_axis: int = 4
    """gamepad axis that, above 0.5, gives a human the steering (the baseline's turn in training)"""
    steering_axis: int = 0
    """gamepad axis the human steers with"""
    log_dir: str = "runs"
    """TensorBoard logs go to log_dir/{mode}__{time} (_2, _3, ... if a session started in the same second took it); so do stdout.log and stderr.log after a hang-up"""
    seed: int = 0
    """seed of the simulated car's start poses"""

    def __post_init__(self) -> None:
        """Out-of-range values end the parse with a message naming each flag (tyro prints it)."""
        problems = [f"--{name.replace('_', '-')} must be {rule}, got {getattr(self, name)}" for name, ok, rule in self.rules() if not ok]
        if problems:
            raise ValueError("; ".join(problems))

    def rules(self) -> List[Tuple[str, bool, str]]:
        """(field, whether its value is valid, the rule); NaN fails every comparison."""
        send_period_ms = 1000.0 / (SENDS_PER_PERIOD * self.control_hz) if self.control_hz > 0 else 0.0
        return [
            ("control_hz", 0.0 < self.control_hz < math.inf, "> 0"),
            ("max_throttle", 0.0 <= self.max_throttle <= 1.0, "in [0, 1]"),
            ("min_throttle", 0.0 <= self.min_throttle <= self.max_throttle, "in [0, --max-throttle]"),
            ("max_steering_rate", 0.0 < self.max_steering_rate < math.inf, "> 0"),  # a negative rate would steer by itself
            ("watchdog_ms", send_period_ms < self.watchdog_ms <= 65535, f"longer than the link's send period ({send_period_ms:.0f} ms) and <= 65535"),
            ("estop_button", self.estop_button >= 0, ">= 0"),  # a negative index would never e-stop
            ("takeover_axis", self.takeover_axis >= 0, ">= 0"),
            ("steering_axis", self.steering_axis >= 0, ">= 0"),
            ("seed", 0 <= self.seed < 2**32, "in [0, 2**32)"),
        ]


@dataclass
class Run(Common):
    """Drive the car with a trained policy (its deterministic action) and report its reward per step."""

    checkpoint: str = ""
    """a checkpoint of jirl_sac_continuous.py or sac_continuous.py trained on JetRacerTrack-v0 or by `train`"""
    steps: int = 1200
    """control steps to drive (1200 = 1 minute at 20 Hz)"""

    def rules(self) -> List[Tuple[str, bool, str]]:
        return [*super().rules(), ("steps", self.steps >= 1, ">= 1")]


@dataclass
class Baseline(Common):
    """Drive the car with the baseline lane follower and measure its reward per step."""

    steps: int = 1200
    """control steps to drive; the mean reward per step printed at the end is train's --baseline-reward-per-step"""

    def rules(self) -> List[Tuple[str, bool, str]]:
        return [*super().rules(), ("steps", self.steps >= 1, ">= 1")]


# --jirl options the car's loop does not use: a value other than the car's default is refused, with the way to get it
CAR_IGNORES = {
    "seed": "use --seed", "total_timesteps": "use --total-steps", "exp_name": "the run is named under --log-dir",
    "env_id": "the car is the env", "baseline": "the car's baseline is the lane follower, or a human on the gamepad",
    "regret_estimator": "the car's regret uses --baseline-reward-per-step", "baseline_eval_episodes": "measure it with `baseline`",
    "save_model": "the state is saved to --checkpoint", "eval_episodes": "drive the agent with `run`",
    "capture_video": "the car records no video", "guidance_fade_steps": "the car keeps every fabricated transition",
    "intervention_mode": "the gamepad's takeover intervenes",
    "track": "the car logs to TensorBoard under --log-dir", "wandb_project_name": "no --track on the car", "wandb_entity": "no --track on the car",
}  # fmt: skip


def car_jirl_args() -> type:
    """jirl.Args as `train` reads it under --jirl.: the same fields, but --help says which have no effect on the car, and why."""
    hints = typing.get_type_hints(jirl.Args)  # the script's annotations are strings (its `from __future__ import annotations`)
    car_help = {name: f"no effect on the car: {why}" for name, why in CAR_IGNORES.items()}
    car_help["guidance_schedule"] = "geometric or linear on the car: guidance by time, as its laps are no episodes to compare"
    fields = []
    for option in dataclasses.fields(jirl.Args):
        if option.name in car_help:
            default = field(default=option.default) if option.default is not dataclasses.MISSING else field(default_factory=option.default_factory)
            fields.append((option.name, Annotated[hints[option.name], tyro.conf.arg(help=car_help[option.name])], default))
    return dataclasses.make_dataclass("CarJirlArgs", fields, bases=(jirl.Args,))


if typing.TYPE_CHECKING:  # to a type checker the car's options are the script's: a class made at run time is none it can read
    CarJirlArgs = jirl.Args
else:
    CarJirlArgs = car_jirl_args()


def car_jirl_defaults() -> jirl.Args:
    """The paper's car settings (report Tables I-III): 64 units, batch 64, buffer 10k, K = 10, sigma^2 = 0.01.

    The entropy coefficient stays tuned from the script's 0.2 (the report and the authors' code disagree: README);
    guidance by time (the car's laps are no episodes to compare with the baseline's), over half of --total-steps.
    """
    return CarJirlArgs(env_id="JetRacer", hidden_size=64, batch_size=64, buffer_size=10_000, learning_starts=300,
                       gate_k=10, penalty_sigma2=0.01, guidance_schedule="geometric")  # fmt: skip


@dataclass
class Train(Common):
    """Train a policy on the car with JIRL: the gate hands control between the baseline and the agent."""

    total_steps: int = 54_000
    """control steps of training, counted from its start when resumed (54k = 45 minutes at 20 Hz, the paper's budget)"""
    train_every: int = 400
    """pause every this many steps: STOP, train, checkpoint, resume (the paper: 400)"""
    gradient_steps: int = 200
    """gradient steps per pause (the paper: 200)"""
    learner: Literal["pause", "background"] = "pause"
    """pause: stop the car to train (the paper); background: a thread trains while the car drives, at the
    same gradient steps per env step, and the car acts with a copy of the actor refreshed every --train-every steps"""
    checkpoint: str = "runs/jetracer_train.pt"
    """training state (agent, replay buffer, counters), written atomically at every pause"""
    resume: bool = False
    """continue from --checkpoint"""
    baseline_reward_per_step: float = 1.075
    """the baseline's measured reward per step (from `baseline`), for the unpaired regret estimate"""
    jirl: CarJirlArgs = field(default_factory=car_jirl_defaults)
    """JIRL and SAC hyperparameters (see jirl_sac_continuous.py --help); on the car --jirl.guidance-steps
    defaults to half of --total-steps, not of --jirl.total-timesteps, and a --resume keeps the training's"""

    def rules(self) -> List[Tuple[str, bool, str]]:
        return [
            *super().rules(),
            ("total_steps", self.total_steps >= 1, ">= 1"),
            ("train_every", self.train_every >= 1, ">= 1"),
            ("gradient_steps", self.gradient_steps >= 1, ">= 1"),
            ("baseline_reward_per_step", math.isfinite(self.baseline_reward_per_step), "finite"),
            # a directory "exists": it was refused as "an earlier training", and "" failed only as it was written
            ("checkpoint", bool(self.checkpoint) and not self.checkpoint.endswith(("/", os.sep)) and not os.path.isdir(self.checkpoint),
             "a file's path (not empty, not a directory)"),
        ]


def car_reward(throttle_command: float, off_track: bool, mapping: ActionMapping) -> float:
    """The paper's car reward: a living reward plus a bonus for speed; -10 for leaving the lane (sim only)."""
    return -10.0 if off_track else 1.0 + 0.1 * throttle_command / mapping.max_throttle


class SafetyFilter:
    """Policy action -> commands the car may receive: NaN means STOP (None); steering clamped and rate-limited."""

    def __init__(self, mapping: ActionMapping, max_steering_rate: float, period: float) -> None:
        if not 0.0 < max_steering_rate * period < math.inf:  # np.clip with bounds the wrong way round steers by itself
            raise ValueError(f"the steering change per step must be > 0, got {max_steering_rate} * {period}")
        self.mapping, self.max_step = mapping, max_steering_rate * period
        self.steering = 0.0

    def __call__(self, action: np.ndarray) -> Optional[Tuple[float, float]]:
        try:
            steering, throttle = action_to_commands(action, self.mapping)
        except ValueError:
            return None
        self.steering += float(np.clip(steering - self.steering, -self.max_step, self.max_step))
        return self.steering, throttle


def log_dir_problem(log_dir: str) -> Optional[str]:
    """Why a session's logs could not be made under log_dir, or None; checked before the car is armed,
    making nothing (a session that never armed leaves no log)."""
    path = os.path.abspath(log_dir)
    while not os.path.exists(path):  # the nearest part that exists: makedirs creates the rest in it
        path = os.path.dirname(path)
    if not os.path.isdir(path):
        return f"{path} is not a directory"
    if not os.access(path, os.W_OK | os.X_OK):
        return f"{path} is not writable"
    return None


def claim_log_dir(log_dir: str, name: str) -> str:
    """Create log_dir/name, or name_2, _3, ... if a session started in the same second took it (simulated
    cars trained side by side): two sessions never share a directory, where TensorBoard would merge their curves."""
    os.makedirs(log_dir or os.curdir, exist_ok=True)  # "" is the current directory, as in os.path.join
    path, n = os.path.join(log_dir, name), 1
    while True:
        try:
            os.mkdir(path)  # atomic: of two sessions making it at once, exactly one succeeds
            return path
        except FileExistsError:
            n += 1
            path = os.path.join(log_dir, f"{name}_{n}")


def stop_signals() -> List[signal.Signals]:
    """The signals that stop the car: Ctrl-C, SIGTERM, and SIGHUP (the ssh session to the car dropped, or
    its terminal closed), unless the run ignores it (started with nohup: it goes on after a hang-up)."""
    hangup: Optional[signal.Signals] = getattr(signal, "SIGHUP", None)  # none on Windows
    if hangup is None or signal.getsignal(hangup) is signal.SIG_IGN:
        return [signal.SIGINT, signal.SIGTERM]
    return [signal.SIGINT, signal.SIGTERM, hangup]


class CarSession:
    """The link, the camera (and the simulator behind both in sim-in-the-loop), safety, timing and logs."""

    camera: Union[OpenCVCamera, SimWorld]  # these two are set once the session is open; close() also
    writer: jirl.CheckedWriter  # closes a session whose opening failed before them

    def __init__(self, args: Common, mode: str) -> None:
        self.args, self.mode, self.period = args, mode, 1.0 / args.control_hz
        self.stop_requested = False
        self.failed = False  # the run ended on an error (end_on_error): the process exits with status 1
        self.estop_unsent = False  # set by the signal handler when the link is down; close() says it
        # Ctrl-C, SIGTERM and SIGHUP e-stop the car while the session is open; close() puts the previous handlers back
        self._previous_handlers = {sig: signal.signal(sig, self._on_signal) for sig in stop_signals()}
        self.mapping = ActionMapping(min_throttle=args.min_throttle, max_throttle=args.max_throttle)
        self.safety = SafetyFilter(self.mapping, args.max_steering_rate, self.period)
        self.world: Optional[SimWorld] = None
        self.gamepad: Optional[Gamepad] = None
        try:
            self.link = HostLink(args.port, send_hz=SENDS_PER_PERIOD * args.control_hz, command_timeout=2.0 * self.period,
                                 watchdog_ms=args.watchdog_ms, throttle_cap=args.max_throttle).start()  # fmt: skip
        except OSError as err:  # serial.SerialException is one
            self._restore_signals()
            # the first thing a new car's user meets: serial devices belong to the dialout group
            access = "; the user needs read-write access to it (on Linux: sudo usermod -aG dialout $USER, then log in again)"
            raise SystemExit(f"{mode}: error: cannot open the motor controller: {err}" + (access if err.errno == errno.EACCES else "")) from None
        try:  # a missing camera or gamepad ends the run before the car is armed, with the port closed
            self.world = SimWorld(self.link._port.controller, seed=args.seed) if args.port.startswith("mockjetracer") else None
            self.camera = open_camera(args.camera, self.world)
            self.gamepad = Gamepad(args.gamepad) if args.gamepad else None
            if self.gamepad is not None:
                self.gamepad.require({"--estop-button": args.estop_button},
                                     {"--takeover-axis": args.takeover_axis, "--steering-axis": args.steering_axis})  # fmt: skip
            problem = log_dir_problem(args.log_dir)
            if problem:
                raise ValueError(f"cannot log to --log-dir {args.log_dir}: {problem}")
        except (ValueError, OSError) as err:
            self.close()
            raise SystemExit(f"{mode}: error: {err}") from None
        self.previous_action = np.array(START_ACTION, dtype=np.float32)
        self.frames_dropped = 0
        self.stale_periods = 0  # control periods in a row without a fresh frame (periods, not time: a training pause is not a gap)
        self.laps_logged = 0
        self.periods: deque = deque(maxlen=2000)
        self._last_tick = time.monotonic()
        self._next_tick = self._last_tick
        if not self.link.arm():
            info = self.link.hello()  # the controller's INFO names the watchdog periods it accepts
            self.close()
            accepts = f"; it accepts {info.fields[3]}-{info.fields[4]} ms" if info is not None else "; it did not answer HELLO either"
            raise SystemExit(f"{mode}: error: the controller on {args.port} did not arm with --watchdog-ms {args.watchdog_ms}{accepts}")
        try:  # no log of a session that never armed
            self.writer = jirl.CheckedWriter(claim_log_dir(args.log_dir, f"{mode}__{int(time.time())}"))
        except OSError as err:  # made unwritable since it was checked
            self.close()
            raise SystemExit(f"{mode}: error: cannot log to --log-dir {args.log_dir}: {err}") from None
        if self.writer.failure:  # a full disk
            self.close()
            raise SystemExit(f"{mode}: error: {self.writer.failure}")
        jirl.OutputGuard.install(self.writer.get_logdir())  # what an ssh session that drops no longer shows is kept beside the logs

    def _on_signal(self, *_: object) -> None:
        self.stop_requested = True
        if getattr(self, "link", None) is not None and not self.link.estop():  # at once, not at the next tick
            self.estop_unsent = True  # not printed here: that could re-enter a stderr write the signal interrupted

    def end_on_error(self, message: str) -> None:
        """End the run at this period for `message`, said on stderr; the car is stopped by the caller."""
        self.stop_requested = True
        self.failed = True
        print(f"{self.mode}: error: {message}", file=sys.stderr)

    def estop(self) -> bool:
        """E-stop the car; False, said on stderr, if the link is down and only the watchdog can stop it."""
        if self.link.estop():
            return True
        self._say_estop_unsent()
        return False

    def _say_estop_unsent(self) -> None:
        print(f"{self.mode}: the e-stop could not be sent (the link is down); the controller's watchdog stops the car", file=sys.stderr)

    def observe(self) -> Optional[np.ndarray]:
        """Read the gamepad, advance the simulator (if any) one period and read the camera; None if the
        frame is stale or the run is ending."""
        self.check_gamepad()  # every period, fresh frame or not
        if self.writer.failure and not self.stop_requested:  # a full disk: stop as for a dead camera (train saves its state)
            self.link.stop()
            self.end_on_error(f"{self.writer.failure}; stopping")
        if self.stop_requested:
            return None
        if self.world is not None:
            self.world.tick()
            if self.world.off_track:  # put back at rest: observed as JetRacerTrack-v0's reset observes it
                self.previous_action = np.array(START_ACTION, dtype=np.float32)
        try:
            frame, captured = self.camera.read()
        except CameraFailed as err:  # no frame will come: stop now rather than after CAMERA_LOST_S of stale ones
            self.frames_dropped += 1
            self.link.stop()
            self.end_on_error(f"{err}; stopping")
            return None
        if frame is None or time.monotonic() - captured > 2.0 * self.period:
            self.frames_dropped += 1
            self.stale_periods += 1
            self.link.stop()
            if self.stale_periods * self.period >= CAMERA_LOST_S and not self.stop_requested:  # a dead camera, or a video's end
                self.end_on_error(f"no fresh camera frame for {self.stale_periods} periods ({CAMERA_LOST_S:.0f} s); stopping")
            return None
        self.stale_periods = 0
        return preprocess(frame, self.previous_action)

    def check_gamepad(self) -> None:
        """Read the gamepad: its e-stop button (held, or tapped since the last read) or its loss e-stops the
        car and ends the run."""
        if self.gamepad is None or self.stop_requested:
            return
        try:
            self.gamepad.poll()
        except GamepadLost as err:  # without its e-stop the car must not drive: stop it and end the run
            sent = self.estop()
            self.end_on_error(f"{err}{'; e-stopped' if sent else ''}")
            return
        if self.gamepad.was_pressed(self.args.estop_button):
            self.estop()
            self.stop_requested = True

    def human_action(self) -> Optional[np.ndarray]:
        """A human's action while the takeover axis is held (the gamepad as `observe` last read it), else None."""
        if self.gamepad is None or self.stop_requested:
            return None
        if self.gamepad.axes.get(self.args.takeover_axis, -1.0) > 0.5:
            return np.array([-self.gamepad.axes.get(self.args.steering_axis, 0.0), -1.0], dtype=np.float32)
        return None

    def act(self, action: np.ndarray) -> Optional[Tuple[float, float]]:
        """Send `action` through the safety filter; the commands sent, or None (STOP, or the run is over)."""
        if not self.link.armed:  # the car no longer drives, and only a person re-arms it: end the run here
            if not self.stop_requested:
                self.end_on_error(f"the controller is no longer armed ({self.disarm_reason()}); stopping")
            return None
        commands = self.safety(action)
        if commands is None:
            self.link.stop()
        else:
            self.link.drive(*commands)
            self.previous_action = np.clip(np.asarray(action, dtype=np.float32), -1.0, 1.0)
        return commands

    def disarm_reason(self) -> str:
        """Why the controller is no longer armed, as far as the link can tell."""
        telemetry = self.link.telemetry
        if self.link.reconnects:
            return f"the link was lost and reopened {self.link.reconnects} time(s)"
        if telemetry is not None and telemetry.watchdog_tripped:
            return "its watchdog tripped: no command reached it in time"
        if telemetry is not None and telemetry.estop_latched:
            return "its e-stop is latched"
        refused = [m for m in self.link.nacks if m.fields[2] in (p.NOT_ARMED, p.ESTOP_LATCHED)]
        if refused:
            return f"it refused a command as {p.REASONS[refused[-1].fields[2]]}; did it restart?"
        return "it disarmed"

    def wait(self) -> None:
        """Hold the control rate; record the achieved period."""
        self._next_tick += self.period
        delay = self._next_tick - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            self._next_tick = time.monotonic()  # late: do not try to catch up with a burst
        now = time.monotonic()
        self.periods.append(now - self._last_tick)
        self._last_tick = now

    def timing(self) -> dict:
        """The control loop's period over the last 2000 periods: median, 99th percentile and jitter, in ms."""
        periods = sorted(self.periods)
        if not periods:
            return {}
        p50, p99 = statistics.median(periods), periods[min(len(periods) - 1, int(0.99 * len(periods)))]
        return {"period_p50_ms": 1000 * p50, "period_p99_ms": 1000 * p99, "jitter_ms": 1000 * statistics.pstdev(periods)}

    def log(self, step: int) -> None:
        """Log the loop's timing, the link's round trips, dropped frames and new lap times at this step."""
        for key, value in self.timing().items():
            self.writer.add_scalar(f"loop/{key}", value, step)
        for key, value in self.link.round_trip_stats().items():
            self.writer.add_scalar(f"link/rtt_{key}_ms", 1000 * value, step)
        self.writer.add_scalar("loop/frames_dropped", self.frames_dropped, step)
        if self.world is not None:
            laps = self.world.lap_times
            for lap_time in laps[self.laps_logged :]:
                self.writer.add_scalar("charts/lap_time", lap_time, step)
            self.laps_logged = len(laps)

    def close(self) -> None:
        self.link.close()  # STOP, then ESTOP
        camera = getattr(self, "camera", None)
        if camera is not None and camera is not self.world and hasattr(camera, "close"):  # the tests' stand-ins may have none
            camera.close()
        if self.world is not None:
            self.world.close()
        if self.gamepad is not None:
            self.gamepad.close()
        writer = getattr(self, "writer", None)
        if writer is not None:
            writer.close()
        self._restore_signals()
        if self.estop_unsent:
            self._say_estop_unsent()

    def _restore_signals(self) -> None:
        for sig, handler in self._previous_handlers.items():
            signal.signal(sig, handler)


class CarSpaces(gym.Env):
    """The car's observation and action spaces, for checking a checkpoint against them; it has no step()."""

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Box(-1.0, 1.0, shape=(OBS_SIZE,), dtype=np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)


def drive(session: CarSession, policy: Callable[[np.ndarray], np.ndarray], steps: int) -> List[float]:
    """Drive with `policy` for `steps` control periods; the per-step car rewards."""
    rewards: List[float] = []
    for step in range(steps):
        if session.stop_requested:
            break
        obs = session.observe()
        if obs is not None:
            action = session.human_action()
            if action is None:
                action = policy(obs)
                if not np.isfinite(action).all():  # the safety filter would STOP on it, step after step, in silence
                    session.link.stop()
                    session.end_on_error(f"the policy's action at step {step} is {action.tolist()}, not finite; stopping")
                    break
            commands = session.act(action)
            if session.stop_requested:  # e-stopped or disarmed in this period: the car did not take the action
                break
            off_track = session.world is not None and session.world.off_track
            rewards.append(car_reward(commands[1] if commands else 0.0, off_track, session.mapping))
        if step % 100 == 0:
            session.log(step)
        session.wait()
    session.log(steps)
    return rewards


def run(args: Run) -> List[float]:
    """Drive `--steps` periods with the checkpoint's deterministic (mean) action; the reward of each step."""
    import torch

    if not args.checkpoint:
        raise SystemExit("run: error: --checkpoint is required")
    try:
        actor = jirl.actor_from_checkpoint(jirl.load_checkpoint(args.checkpoint), CarSpaces())
    except (ValueError, FileNotFoundError) as err:
        beside = policy_path(args.checkpoint)  # given a training state, name the policy train wrote beside it
        hint = f"; `train` keeps the policy of this training in {beside}" if os.path.exists(beside) else ""
        raise SystemExit(f"run: error: {err}{hint}")

    def policy(obs: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            _, _, action = actor.get_action(torch.from_numpy(obs).unsqueeze(0))
        return action[0].numpy()

    return drive_and_report(args, "run", policy, args.steps)


def baseline(args: Baseline) -> List[float]:
    """Drive `--steps` periods with the lane follower; the reward of each step."""
    return drive_and_report(args, "baseline", LaneFollower(), args.steps)


def drive_and_report(args: Common, mode: str, policy: Callable[[np.ndarray], np.ndarray], steps: int) -> List[float]:
    """Drive `steps` periods with `policy` in a session of its own, print the report, return the rewards;
    SystemExit(1) after the report if the drive ended on an error."""
    session = CarSession(args, mode)
    try:
        rewards = drive(session, policy, steps)
    finally:
        session.close()
    report(session, rewards, mode)
    if session.failed:  # reported all the same; the status says the drive did not end as asked
        raise SystemExit(1)
    return rewards


def report(session: CarSession, rewards: List[float], mode: str) -> None:
    """Print the drive's steps and mean reward per step, its lap times, and the loop's and the link's timing."""
    laps = session.world.lap_times if session.world is not None else []
    print(f"{mode}: {len(rewards)} steps, mean reward per step {np.mean(rewards) if rewards else float('nan'):.4f}")
    if laps:
        print(f"{mode}: lap times {', '.join(f'{t:.2f}' for t in laps)} s")
    timing, rtt = session.timing(), session.link.round_trip_stats()
    parts = [f"frames dropped {session.frames_dropped}"]
    if rtt:
        parts.insert(0, f"link round trip p50 {1000 * rtt['p50']:.2f} ms, p99 {1000 * rtt['p99']:.2f} ms")
    if timing:
        parts.insert(0, f"control period p50 {timing['period_p50_ms']:.1f} ms, p99 {timing['period_p99_ms']:.1f} ms, jitter {timing['jitter_ms']:.2f} ms")
    print(f"{mode}: {'; '.join(parts)}")


class NotATrainingState(ValueError):
    """The file given to `train --resume` is no training state at all (unreadable, or another kind of file)."""


class CheckpointTaken(Exception):
    """A fresh run's first save found its path taken (by another run started on the same --checkpoint)."""


def save_training_state(path: str, sac: jirl.SoftActorCritic, rb: jirl.ReplayBuffer, counters: dict, args: Train, create: bool = False) -> None:
    """Agent, replay buffer and counters, and beside them the policy for `run`, each written atomically.
    create: path must not exist yet (a fresh run's first save); CheckpointTaken if it does."""
    import torch

    n = rb.size
    state = {
        "format": TRAIN_STATE_FORMAT,
        "sac": sac.state_dict(),
        "buffer": {name: torch.from_numpy(getattr(rb, name)[:n].copy()) for name in BUFFER_FIELDS},
        "buffer_pos": rb.pos,
        "counters": counters,
        "hidden_size": args.jirl.hidden_size,
        "guidance_steps": args.jirl.guidance_steps,  # a resume keeps the hand-over's horizon
    }
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    write_atomically(path, lambda tmp: jirl.write_checkpoint(tmp, state), create)
    write_atomically(policy_path(path), lambda tmp: jirl.save_checkpoint(tmp, "JetRacer", CarSpaces(), sac.actor, sac.qf, args.jirl))


def write_atomically(path: str, write: Callable[[str], None], create: bool = False) -> None:
    """write(tmp) to a temporary file of this process, then rename it to path: never half-written, and
    nothing left behind on failure. create: path must not exist yet; CheckpointTaken if it does."""
    tmp = f"{path}.{os.getpid()}.tmp"  # its own: two runs given one --checkpoint must not rename each other's
    try:
        write(tmp)
        if create:  # atomic: of two fresh runs started together on one --checkpoint, exactly one gets it
            try:
                os.close(os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
            except FileExistsError:
                raise CheckpointTaken(path) from None
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def policy_path(state_path: str) -> str:
    """Where `train` writes the policy of the training state at state_path, for `run --checkpoint`."""
    return f"{state_path}.actor.cleanrl_model"


def lock_path(state_path: str) -> str:
    """The file a training holds locked while it uses the training state at state_path."""
    return f"{state_path}.lock"


def load_training_state(path: str, sac: jirl.SoftActorCritic, rb: jirl.ReplayBuffer) -> Tuple[dict, Optional[int]]:
    """Load the agent and replay buffer saved at path into sac and rb; return the counters and the
    guidance horizon the training ran with (None in a state saved before the horizon was)."""
    import torch

    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as err:  # torch raises many types for a damaged file; keep the first sentence (the rest advises weights_only=False)
        cause = (str(err).strip().splitlines() or ["the file ends early"])[0].split(". ")[0]
        raise NotATrainingState(f"{path} is not a readable training state ({type(err).__name__}: {cause})") from None
    if not isinstance(state, dict) or state.get("format") != TRAIN_STATE_FORMAT:
        found = state.get("format") if isinstance(state, dict) else None
        if found == jirl.CHECKPOINT_FORMAT:  # the policy `train` writes beside a state (or a simulated run's): say where the state is
            suffix = policy_path("")  # what policy_path appends to a state's path
            beside = path[: -len(suffix)] if path.endswith(suffix) else ""
            hint = f"; resume from the training state {beside}" if beside and os.path.exists(beside) else ""
            raise NotATrainingState(f"{path} is a policy ({found}), not a {TRAIN_STATE_FORMAT} training state{hint}")
        raise NotATrainingState(f"{path} is not a {TRAIN_STATE_FORMAT} file")

    def table(key: str) -> dict:  # a part that must be a dict, {} where it is missing or is not one
        return state[key] if isinstance(state.get(key), dict) else {}

    missing = [key for key in ("sac", "buffer", "buffer_pos", "counters", "hidden_size") if key not in state]
    missing += [f"buffer {key}" for key in BUFFER_FIELDS if key not in table("buffer")]
    missing += [f"counter {key}" for key in TRAIN_COUNTERS if key not in table("counters")]
    if missing:
        raise ValueError(f"{path} is a damaged {TRAIN_STATE_FORMAT} file: it has no {', '.join(missing)}")
    if state["hidden_size"] != sac.args.hidden_size:  # checked before anything is loaded into the agent
        raise ValueError(f"{path} holds an agent of {state['hidden_size']} units, not --jirl.hidden-size {sac.args.hidden_size}")
    guidance = state.get("guidance_steps")
    if guidance is not None and not (type(guidance) is int and guidance >= 0):
        raise ValueError(f"{path} is a damaged {TRAIN_STATE_FORMAT} file: its guidance_steps is {guidance!r}")
    for key, start in TRAIN_COUNTERS.items():  # counts are ints and regret sums floats, none below its start
        value = state["counters"][key]
        if type(value) is not type(start) or not start <= value < math.inf:
            raise ValueError(f"{path} is a damaged {TRAIN_STATE_FORMAT} file: its counter {key} is {value!r}")
    for part, what in (("sac", "agent"), ("buffer", "replay buffer")):  # no training stores one: it would turn every weight to NaN
        if not jirl.all_finite(state[part]):
            raise ValueError(f"{path} is a damaged {TRAIN_STATE_FORMAT} file: its {what} holds a NaN or infinite value")
    # The rows are saved in ring order with the next write position; rolled, they run oldest to newest,
    # so a buffer of another capacity takes the newest rows and goes on writing after them.
    try:  # a failure here leaves a half-loaded agent, which the caller discards: the run ends
        n, pos = len(state["buffer"]["obs"]), state["buffer_pos"]
        if not (type(pos) is int and 0 <= pos <= n):  # np.roll would take any int, and put the rows out of order
            raise ValueError(f"its buffer_pos {pos!r} is not a row of its {n} or the next")
        kept = min(n, rb.capacity)
        rates = {"--jirl.q-lr": (state["sac"]["q_optimizer"]["param_groups"][0]["lr"], sac.args.q_lr),
                 "--jirl.policy-lr": (state["sac"]["actor_optimizer"]["param_groups"][0]["lr"], sac.args.policy_lr)}  # fmt: skip
        sac.load_state_dict(state["sac"])
        for name in BUFFER_FIELDS:
            getattr(rb, name)[:kept] = np.roll(state["buffer"][name].numpy(), -pos, axis=0)[n - kept :]
    except (KeyError, RuntimeError, ValueError, TypeError, AttributeError) as err:
        cause = " ".join(str(err).split())  # torch's message runs over several lines: keep it on one
        raise ValueError(f"{path} is a damaged {TRAIN_STATE_FORMAT} file ({type(err).__name__}: {cause})") from None
    for flag, (saved, given) in rates.items():  # said, as for the guidance horizon: a resume is how a training that diverged is given smaller ones
        if saved != given:
            print(f"resume: {flag} {given} replaces the training's {saved}")
    rb.size, rb.pos = kept, kept % rb.capacity
    if kept < n:
        print(f"resume: --jirl.buffer-size {rb.capacity} keeps the newest {kept} of the {n} saved transitions")
    return state["counters"], guidance


@contextlib.contextmanager
def holding(checkpoint: str) -> Iterator[None]:
    """Hold {checkpoint}.lock while a training runs: two trainings resumed from one --checkpoint (two cars,
    or simulated ones) would each save over the other's steps. The lock goes with the process."""
    lock = lock_path(checkpoint)
    try:
        os.makedirs(os.path.dirname(os.path.abspath(checkpoint)), exist_ok=True)
        fd = os.open(lock, os.O_CREAT | os.O_RDWR)
    except OSError as err:
        raise SystemExit(f"train: error: cannot write --checkpoint {checkpoint}: {err}") from None
    held = False  # only the holder may remove the file: a refused run removing it let the next run lock a new one beside the holder's
    no_state = False  # whether --resume found no training state in the file
    try:
        try:
            if sys.platform == "win32":
                import msvcrt

                msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
            else:
                import fcntl

                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            if sys.platform == "win32" or isinstance(err, BlockingIOError):  # held by another process
                raise SystemExit(f"train: error: another training is using --checkpoint {checkpoint} (it holds {lock});"
                                 " wait for it to end, or pass another --checkpoint") from None
            # a file system without locks (some network and FUSE ones): train, saying what is not guarded
            print(f"train: warning: cannot lock {lock} ({err}); nothing keeps a second training off this checkpoint", file=sys.stderr)
        held = True  # this run's: locked, or on a file system without locks
        yield
    except SystemExit as end:
        no_state = isinstance(end.__cause__, NotATrainingState)
        raise
    finally:
        # no state came of it (a typo, a car that never armed, a policy given to --resume): leave no lock file either
        if held and (no_state or not os.path.exists(checkpoint)):
            with contextlib.suppress(OSError):  # Windows keeps an open file
                os.remove(lock)
        os.close(fd)  # releases the lock; beside a state the empty file stays (removed, two later runs could each lock a file of their own)


def train(args: Train) -> dict:
    """The on-car JIRL loop (Alg. 1-3), pause-and-train or with a background learner; returns the final counters."""
    hp = args.jirl
    if hp.guidance_schedule not in ("geometric", "linear"):
        raise SystemExit("train: error: --jirl.guidance-schedule must be geometric or linear on the car (guidance by time)")
    defaults = car_jirl_defaults()
    unused = [f"--jirl.{name.replace('_', '-')} ({hint})" for name, hint in CAR_IGNORES.items() if getattr(hp, name) != getattr(defaults, name)]
    if unused:
        raise SystemExit(f"train: error: no effect on the car: {'; '.join(unused)}")
    with holding(args.checkpoint):
        return train_holding(args)


def train_holding(args: Train) -> dict:
    """train(), its options checked and --checkpoint held by this process."""
    import torch

    hp = args.jirl
    torch.manual_seed(args.seed)
    torch.set_num_threads(hp.torch_threads)
    sac = jirl.SoftActorCritic(OBS_SIZE, 2, hp)
    try:
        rb = jirl.ReplayBuffer(hp.buffer_size, OBS_SIZE, 2, args.seed)
    except ValueError as err:  # more than memory holds
        raise SystemExit(f"train: error: --jirl.buffer-size {hp.buffer_size}: {err}") from None
    counters, saved_guidance = dict(TRAIN_COUNTERS), None
    if args.resume:
        try:
            counters, saved_guidance = load_training_state(args.checkpoint, sac, rb)
        except (ValueError, FileNotFoundError) as err:
            raise SystemExit(f"train: error: {err}") from err  # the cause tells holding() whether the file is a state
        if counters["step"] >= args.total_steps:  # the car would be armed to drive no step
            raise SystemExit(f"train: error: {args.checkpoint} is at step {counters['step']}, and --total-steps {args.total_steps}"
                             " counts from the start of the training: pass more to continue it")
        print(f"resumed at step {counters['step']} with {rb.size} transitions")
    elif os.path.exists(args.checkpoint):  # a fresh run would overwrite it at its first pause
        raise SystemExit(f"train: error: {args.checkpoint} holds an earlier training; pass --resume to continue it, or another --checkpoint")
    # The hand-over's horizon: as given, else the one the training started with, else half of --total-steps
    guidance = hp.guidance_steps if hp.guidance_steps is not None else saved_guidance
    if guidance is None:
        guidance = args.total_steps // 2
    if saved_guidance is not None and guidance != saved_guidance:
        print(f"resume: --jirl.guidance-steps {guidance} replaces the training's {saved_guidance}")
    args = replace(args, jirl=replace(hp, guidance_steps=guidance))  # saved with the state
    hp = args.jirl

    saved_step = counters["step"]

    def checkpoint(create: bool = False) -> None:
        nonlocal saved_step
        diverged = sac.divergence() or overflow(sac.actor, rb)
        if diverged:  # checked at each pause, before the car acts with the new weights; the last sound state is kept
            raise SystemExit(f"train: error: the training diverged by step {counters['step']}: {diverged}; {args.checkpoint} keeps step {saved_step}'s state")
        try:
            save_training_state(args.checkpoint, sac, rb, counters, args, create)
        except CheckpointTaken:  # made by another run after the exists() check in train_holding
            raise SystemExit(f"train: error: another run created {args.checkpoint} as this one started; pass another --checkpoint") from None
        except OSError as err:  # disk full, no permission: the run ends (the car stops in `finally`), saying why
            raise SystemExit(f"train: error: cannot write --checkpoint {args.checkpoint}: {err}") from None
        saved_step = counters["step"]

    checkpoint(create=not args.resume)  # before the car is armed: a checkpoint that cannot be written fails now, not at the first pause
    try:
        session = CarSession(args, "train")
    except SystemExit:  # the car never armed (a camera, gamepad, controller or --log-dir problem)
        if not args.resume:  # a rerun must not take this untrained state for an earlier training
            for path in (args.checkpoint, policy_path(args.checkpoint)):
                os.remove(path)
        raise
    follower = LaneFollower()
    gate = jirl.Gate(hp.gate_k)
    rl_control: deque = deque(maxlen=hp.rl_control_window)
    shadow = None  # sim-in-the-loop: the baseline drives a twin car from the same poses, for the paired regret
    if session.world is not None:
        car_world, shadow_controller = session.world, _NullController()
        shadow = SimWorld(shadow_controller, seed=args.seed)
        shadow_follower, shadow_previous = LaneFollower(), np.array(START_ACTION, dtype=np.float32)
        shadow_safety = SafetyFilter(session.mapping, args.max_steering_rate, session.period)  # the car's filter acts on the baseline too
    # a real car has no twin to pair with: it logs no paired regret rather than a paired regret of 0
    logged = ("fabricated_transitions", "control_switches", "baseline_regret_per_step", *(("paired_regret_per_step",) if shadow is not None else ()))
    previous: Optional[tuple] = None  # (obs, stored action, rl_action, rl_acted, throttle, baseline action, twin's reward)
    obs = None
    lock = threading.Lock()  # the background learner's updates against the loop's buffer writes
    acting = copy.deepcopy(sac.actor) if args.learner == "background" else sac.actor
    finished = threading.Event()
    learner = None
    if args.learner == "background":
        learner = threading.Thread(target=background_learner, args=(sac, rb, counters, args, lock, finished), daemon=True)
        learner.start()

    def optimise(step: int) -> None:
        """Pause-and-train: the car waits, stopped, for --gradient-steps updates."""
        session.link.stop()
        if learning(step, rb, hp):
            losses = None
            for _ in range(args.gradient_steps):
                session.check_gamepad()  # an e-stop tapped during the pause still ends the run
                if session.stop_requested:
                    break
                losses = sac.update(rb.sample(hp.batch_size), counters["updates"])
                counters["updates"] += 1
            for name, value in (losses or {}).items():
                session.writer.add_scalar(f"losses/{name}", value.item(), step)

    last_pause = counters["step"]
    try:
        while counters["step"] < args.total_steps and not session.stop_requested:
            if "learner_error" in counters:  # the background learner failed: stop the car and end the run
                session.link.stop()
                session.end_on_error(f"the background learner failed ({counters.pop('learner_error')}); stopping")
                break
            step = counters["step"]
            if step % args.train_every == 0 and step != last_pause:
                last_pause = step
                with lock:
                    if args.learner == "pause":
                        optimise(step)
                    else:
                        acting.load_state_dict(sac.actor.state_dict())
                    checkpoint()
                session._next_tick = time.monotonic()
                if session.stop_requested:  # e-stopped or signalled during the pause
                    break

            next_obs = session.observe()
            if next_obs is None:  # stale frame: the car is stopped; the episode ends here
                previous, obs = None, None
                follower.reset()
                gate.new_episode()
                session.wait()
                continue
            off_track = session.world is not None and session.world.off_track
            if previous is not None:  # the transition of the previous step is complete now
                p_obs, p_action, p_rl_action, p_rl_acted, p_throttle, p_baseline, p_twin_reward = previous
                reward = car_reward(p_throttle, off_track, session.mapping)
                counters["baseline_regret_per_step"] += max(0.0, args.baseline_reward_per_step - reward)
                if p_twin_reward is not None:  # paired: the twin's reward for this same step, so that a departure meets a departure
                    counters["paired_regret_per_step"] += max(0.0, p_twin_reward - reward)
                with lock:
                    rb.add(p_obs, p_action, reward, next_obs, off_track)  # Alg. 1, line 9: the real transition
                    if not p_rl_acted and p_baseline is not None:  # Alg. 1, lines 12-14: the fabricated transition
                        rb.add(p_obs, p_rl_action, jirl.penalized_reward(reward, p_baseline, p_rl_action, hp.penalty_sigma2), next_obs, off_track)
                        counters["fabricated_transitions"] += 1
            if off_track:
                follower.reset()
                gate.new_episode()
                previous = None
            obs = next_obs

            # Alg. 1, line 3: the baseline's action (a human takeover is the baseline, intervening)
            human = session.human_action()
            baseline_action = human if human is not None else follower(obs)
            with torch.inference_mode():
                mean, log_std = acting(torch.from_numpy(obs).unsqueeze(0))
                if not math.isfinite(sum(mean[0].tolist() + log_std[0].tolist())):  # as the script: end before the NaN is sampled, gated or stored
                    raise SystemExit(f"train: error: the training diverged by step {step}: the actor overflowed on this step's observation;"
                                     f" {args.checkpoint} keeps step {saved_step}'s state, with this actor")
                rl_action = torch.tanh(torch.normal(mean, log_std.exp()))[0].numpy()
            mean, log_std = mean[0].numpy().astype(np.float64), log_std[0].numpy().astype(np.float64)
            if human is not None:
                rl_acts = False
            else:  # Alg. 1, line 4: the gate (Alg. 3)
                c = jirl.guidance_c(hp.gate_c, step, guidance, hp.guidance_schedule)
                rl_acts = gate.decide(jirl.squashed_log_prob(mean, log_std, baseline_action), jirl.divergence(mean, log_std, baseline_action), c)
                if rl_acts and c == 0.0 and hp.deterministic_after_guidance:  # as the authors' car code did
                    rl_action = np.tanh(mean).astype(np.float32)
            if previous is not None and previous[3] and not rl_acts and hp.use_switch_penalty:
                with lock:
                    rb.add(previous[0], previous[2], hp.switch_penalty, obs, False)  # Sec. V.A
            counters["control_switches"] += gate.record(rl_acts)
            rl_control.append(rl_acts)
            action = rl_action if rl_acts else np.asarray(baseline_action, dtype=np.float32)
            car_steering = session.safety.steering  # the wheel as this step found it
            commands = session.act(action)
            if session.stop_requested:  # e-stopped or disarmed in this period: the car did not take the action
                break

            twin_reward = None
            if shadow is not None:  # the baseline's own step from the same start, paired by index
                if off_track:  # the car was put back: the twin starts from its pose, wheel and previous action
                    shadow.env.reset(seed=car_world.seed + car_world.resets)
                    shadow_follower.reset()
                    shadow_previous, shadow_safety.steering = np.array(START_ACTION, dtype=np.float32), car_steering
                shadow_action = shadow_follower(preprocess(shadow.read()[0], shadow_previous))
                shadow_commands = shadow_safety(shadow_action)
                assert shadow_commands is not None  # None is for a NaN action; the lane follower's are finite
                shadow_controller.set(*shadow_commands)
                shadow.tick()
                twin_reward = car_reward(shadow_commands[1], shadow.off_track, session.mapping)
                shadow_previous = np.clip(shadow_action, -1.0, 1.0)
                if shadow.off_track:  # the twin left the lane on its own and was put back, as the car would be
                    shadow_follower.reset()
                    shadow_previous = np.array(START_ACTION, dtype=np.float32)
            previous = (obs, action, rl_action, rl_acts, commands[1] if commands else 0.0, None if rl_acts else baseline_action, twin_reward)
            counters["step"] += 1
            if step % hp.log_every == 0:
                session.log(step)
                session.writer.add_scalar("charts/rl_control_fraction", sum(rl_control) / len(rl_control), step)
                for key in logged:
                    session.writer.add_scalar(f"charts/{key}", counters[key], step)
            session.wait()
        finished.set()
        if learner is not None:
            learner.join()
        elif counters["step"] >= args.total_steps and not session.stop_requested:
            optimise(counters["step"])  # the last steps are learnt from too: the authors' code optimised once more after its loop
        checkpoint()
    finally:
        finished.set()
        session.close()
        if shadow is not None:
            shadow.close()
    if shadow is None:  # nor prints or returns one; the training state keeps it at 0, so that states have one layout
        del counters["paired_regret_per_step"]
    counters["rl_control_fraction"] = sum(rl_control) / len(rl_control) if rl_control else 0.0
    print("train: " + ", ".join(f"{key} {value:.4g}" if isinstance(value, float) else f"{key} {value}" for key, value in counters.items()))
    if session.failed:  # the state is saved; the status says the training did not end as asked
        raise SystemExit(1)
    return counters


def overflow(actor: jirl.Actor, rb: jirl.ReplayBuffer, rows: int = OVERFLOW_ROWS) -> str:
    """'' unless the actor's mean or log-std overflows on the latest `rows` stored observations: finite
    weights large enough overflow float32, which the weights' own check cannot see."""
    import torch

    latest = (rb.pos - 1 - np.arange(min(rows, rb.size))) % rb.capacity
    with torch.inference_mode():
        mean, log_std = actor(torch.from_numpy(rb.obs[latest]))
    if bool(torch.isfinite(mean).all() and torch.isfinite(log_std).all()):
        return ""
    return f"the actor overflows on some of the {len(latest)} latest stored observations"


def learning(step: int, rb: jirl.ReplayBuffer, hp: jirl.Args) -> bool:
    """Whether the agent learns at this step: from --jirl.learning-starts steps on, as in the script and the
    authors' car code (not buffer rows, which fabricated transitions double), once a batch is stored."""
    return step >= hp.learning_starts and rb.size >= hp.batch_size


def background_learner(sac: jirl.SoftActorCritic, rb: jirl.ReplayBuffer, counters: dict, args: Train, lock: threading.Lock, finished: threading.Event) -> None:
    """Gradient steps while the car drives, keeping gradient_steps / train_every of them per env step.
    An update that raises ends the learner with the error in counters["learner_error"]; the loop then stops."""
    hp = args.jirl
    while not finished.is_set():
        with lock:
            step = counters["step"]
            ready = learning(step, rb, hp) and counters["updates"] < step * args.gradient_steps / args.train_every
            if ready:
                try:
                    sac.update(rb.sample(hp.batch_size), counters["updates"])
                except Exception as err:  # noqa: BLE001 -- any failure: the car must not drive on without its learner
                    counters["learner_error"] = f"{type(err).__name__}: {err}"
                    return
                counters["updates"] += 1
        if not ready:
            time.sleep(0.002)


class _NullController:
    """Stands in for a motor controller in the shadow simulator: it applies what it is told, in the
    protocol's thousandths, as the car's controller receives it."""

    steering = 0.0
    throttle = 0.0

    def set(self, steering: float, throttle: float) -> None:
        self.steering, self.throttle = p.to_thousandths(steering) / 1000.0, p.to_thousandths(throttle) / 1000.0


def main(argv: Optional[List[str]] = None) -> None:
    args = tyro.extras.subcommand_cli_from_dict({"run": Run, "baseline": Baseline, "train": Train}, prog="python -m deploy.jetracer", args=argv)
    jirl.OutputGuard.install()  # an ssh session that drops leaves the car's lines nowhere to go: not up as EIO (the session names its folder for them)
    modes: Dict[type, Callable[[Any], object]] = {Run: run, Baseline: baseline, Train: train}
    modes[type(args)](args)


if __name__ == "__main__":
    main()
