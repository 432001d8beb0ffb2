"""deploy/jetracer.py: safety, and the run, baseline and train modes headless against the simulated car."""

import copy
import dataclasses
import errno
import math
import os
import pty
import re
import select
import signal
import subprocess
import sys
import time
import types
from collections import deque
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

import warm_python
from conftest import CAR_TRAIN_FAST as FAST, ROOT, fill_the_disk_for, overflow_the_actor, overflow_the_mean, refusal
from test_stopping import LOST_HEADER, on_a_terminal

jetracer = pytest.importorskip("deploy.jetracer")
from envs.car_interface import FRAME_SHAPE, ActionMapping  # noqa: E402

# the mock controller's longest watchdog: a test that checks no watchdog need not fail where a loaded machine starves the link's
# send thread for the default 250 ms
PATIENT = ["--watchdog-ms", "2000"]


def test_safety_filter_stops_on_nan_clamps_and_rate_limits():
    safety = jetracer.SafetyFilter(ActionMapping(), max_steering_rate=4.0, period=0.05)  # 0.2 per step
    assert safety(np.array([np.nan, 0.0])) is None
    assert safety(np.array([1.0, 5.0])) == (pytest.approx(0.2), pytest.approx(0.6))
    assert safety(np.array([1.0, -5.0])) == (pytest.approx(0.4), pytest.approx(0.45))
    assert safety(np.array([-1.0, 0.0]))[0] == pytest.approx(0.2)


def test_baseline_mode_drives_the_simulated_car_through_the_protocol(tmp_path):
    rewards = jetracer.baseline(jetracer.Baseline(steps=60, log_dir=str(tmp_path)))
    assert len(rewards) == 60
    assert np.allclose(rewards, 1.075)  # 1 + 0.1 * 0.45 / 0.6: the baseline's slowest throttle, never off the lane


def record_the_track(path: Path, frames: int) -> str:
    """`frames` of the simulated track's camera, driving straight on at the slowest throttle, recorded as a
    JetRacer's camera would be (MJPG at 20 fps): a `file:` camera that shows lanes."""
    import cv2
    from envs.jetracer_track import JetRacerTrackEnv

    env = JetRacerTrackEnv()
    env.reset(seed=0)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20, (FRAME_SHAPE[1], FRAME_SHAPE[0]))
    for step in range(frames):
        writer.write(env.camera_frame_bgr())
        _, _, terminated, truncated, _ = env.step(np.array([0.0, -1.0], np.float32))
        if terminated or truncated:
            env.reset(seed=step)
    writer.release()
    env.close()
    return str(path)


def test_the_car_without_the_simulator_drives_and_trains_over_a_serial_port(tmp_path, capsys):
    """The real car's configuration: no SimWorld (the port is a serial device, not mockjetracer://), the
    controller's firmware behind a pseudo-terminal opened by pyserial, and a recorded camera. The
    baseline drives; then JIRL trains with the unpaired regret alone, as on the car: no twin to pair
    with, so no paired regret is logged or printed (a 0 there would read as none)."""
    from deploy.mock_controller import PtyController

    def controller_log(expected: list) -> list:  # the firmware's thread handles the closing ESTOP after the link has written it
        deadline = time.monotonic() + 5.0
        while [what for _, what in controller.controller.log] != expected and time.monotonic() < deadline:
            time.sleep(0.01)
        return [what for _, what in controller.controller.log]

    common = dict(camera=f"file:{record_the_track(tmp_path / 'drive.avi', 300)}", log_dir=str(tmp_path / "logs"), watchdog_ms=2000)
    controller = PtyController()
    try:
        common["port"] = controller.path
        rewards = jetracer.baseline(jetracer.Baseline(steps=60, **common))
        assert rewards == [pytest.approx(1.075)] * 60  # 1 + 0.1 * 0.45 / 0.6: the baseline's slowest throttle, no lane departure seen
        assert controller_log(["armed", "e-stop"]) == ["armed", "e-stop"]  # no NACK, no watchdog, e-stopped at the end
        hp = replace(jetracer.car_jirl_defaults(), hidden_size=16, batch_size=16, learning_starts=30, guidance_steps=27_000)  # the baseline keeps control
        state = tmp_path / "train.pt"
        counters = jetracer.train(jetracer.Train(total_steps=120, train_every=40, gradient_steps=2, checkpoint=str(state), baseline_reward_per_step=1.2,
                                                 jirl=hp, **common))  # fmt: skip
        assert controller_log(["armed", "e-stop", "armed", "e-stop"]) == ["armed", "e-stop", "armed", "e-stop"]
    finally:
        controller.close()
    assert counters["step"] == 120 and counters["fabricated_transitions"] == 119 and counters["updates"] > 0
    assert counters["baseline_regret_per_step"] == pytest.approx((1.2 - 1.075) * 119)  # sum_t max(0, b - r_t), r_t = 1.075
    out = capsys.readouterr().out
    assert "paired_regret_per_step" not in counters and "paired" not in out and "lap times" not in out
    saved = torch.load(state, weights_only=True)
    assert saved["counters"]["step"] == 120 and saved["counters"]["paired_regret_per_step"] == 0.0  # the state's one layout
    baseline_logs, train_logs = sorted((tmp_path / "logs").iterdir())
    for run_dir in (baseline_logs, train_logs):
        events = EventAccumulator(str(run_dir))
        events.Reload()
        tags = events.Tags()["scalars"]
        assert "charts/lap_time" not in tags and [e.value for e in events.Scalars("loop/frames_dropped")][-1] == 0
    assert "charts/baseline_regret_per_step" in tags and "charts/paired_regret_per_step" not in tags


def test_a_stale_camera_stops_the_car(tmp_path):
    session = jetracer.CarSession(jetracer.Baseline(log_dir=str(tmp_path)), "stale")
    try:
        session.act(np.array([0.0, 1.0]))
        controller = session.link._port.controller
        session.camera = type("Frozen", (), {"read": lambda self: (np.zeros((112, 112, 3), np.uint8), 0.0)})()
        assert session.observe() is None and session.frames_dropped == 1
        assert session.link._command is None  # the send loop now sends STOP
    finally:
        session.close()
    assert controller.throttle == 0.0 and controller.estop_latched  # close(): STOP then ESTOP


def test_after_a_lane_departure_the_car_observes_what_the_simulators_reset_gives(tmp_path):
    session = jetracer.CarSession(jetracer.Baseline(log_dir=str(tmp_path)), "depart")
    try:
        for _ in range(200):  # full left at full throttle leaves the lane at the 31st step (1.55 s)
            obs = session.observe()
            if session.world.off_track:
                break
            session.act(np.array([1.0, 1.0]))
        assert session.world.off_track and session.world.resets == 1
        expected, _ = session.world.env.reset(seed=session.world.seed + session.world.resets)  # the pose it was put back at
        np.testing.assert_array_equal(obs, expected)  # the previous action is the reset's, not the departing turn's
        assert tuple(obs[-2:]) == jetracer.START_ACTION
    finally:
        session.close()


def test_train_writes_a_checkpoint_and_resumes_from_it(tmp_path):
    state = tmp_path / "train.pt"
    common = ["--train-every", "40", "--gradient-steps", "5", "--checkpoint", str(state), "--log-dir", str(tmp_path), *FAST]
    args = ["train", "--total-steps", "100", *common]
    out = warm_python.run(["-m", "deploy.jetracer", *args], cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    assert state.exists() and (tmp_path / "train.pt.actor.cleanrl_model").exists()
    with pytest.raises(SystemExit, match=f"is a jirl-car-training-v2 file, not a jirl-sac-checkpoint-v2 checkpoint; `train` keeps the policy of this training in {state}.actor.cleanrl_model$"):
        jetracer.run(jetracer.Run(checkpoint=str(state), steps=1, log_dir=str(tmp_path)))  # the training state, not the policy
    saved = torch.load(state, weights_only=True)
    assert saved["counters"]["step"] == 100 and saved["counters"]["updates"] == 15  # pauses at 40 and 80, and after step 100
    size = len(saved["buffer"]["obs"])
    assert size == 100 - 1 + saved["counters"]["fabricated_transitions"]  # the last step's transition is not complete
    out = warm_python.run(["-m", "deploy.jetracer", "train", "--total-steps", "140", "--resume", *common],
                          cwd=ROOT, timeout=120)  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "resumed at step 100" in out.stdout
    resumed = torch.load(state, weights_only=True)
    assert resumed["counters"]["step"] == 140 and len(resumed["buffer"]["obs"]) > size
    assert resumed["counters"]["updates"] == 25  # the pause at 120 and the one after step 140; none again at 100
    written = state.read_bytes()
    out = warm_python.run(["-m", "deploy.jetracer", "train", "--total-steps", "140", "--resume", *common],
                          cwd=ROOT, timeout=120)  # fmt: skip
    assert out.returncode != 0 and out.stderr.strip().splitlines()[-1] == (
        f"train: error: {state} is at step 140, and --total-steps 140 counts from the start of the training: pass more to continue it")
    assert state.read_bytes() == written and len(list(tmp_path.glob("train__*"))) == 2  # not armed: no third session logged
    (tmp_path / "broken.pt").write_bytes(b"not a checkpoint")
    out = warm_python.run(["-m", "deploy.jetracer", "train", "--resume", "--checkpoint", str(tmp_path / "broken.pt")],
                          cwd=ROOT, timeout=60)  # fmt: skip
    assert out.returncode != 0 and "not a readable training state" in out.stderr
    assert "weights_only" not in out.stderr and "Traceback" not in out.stderr, "one line, without torch's advice to load it unsafely"


@pytest.mark.parametrize("learner", ["pause", "background"])
def test_train_learns_from_learning_starts_steps_not_from_as_many_buffer_rows(tmp_path, monkeypatch, learner):
    observed, first_update = [], []
    real_observe, real_update = jetracer.CarSession.observe, jetracer.jirl.SoftActorCritic.update
    monkeypatch.setattr(jetracer.CarSession, "observe", lambda self: observed.append(1) or real_observe(self))
    monkeypatch.setattr(jetracer.jirl.SoftActorCritic, "update", lambda self, data, n: first_update.append(len(observed)) or real_update(self, data, n))
    # the baseline keeps control, so every step also stores a fabricated transition: 30 rows by step 15
    args = ["train", "--total-steps", "60", "--train-every", "20", "--gradient-steps", "2", "--learner", learner, "--jirl.learning-starts", "30",
            "--jirl.batch-size", "16", "--jirl.hidden-size", "16", "--jirl.guidance-steps", "27000", "--checkpoint", str(tmp_path / "t.pt"),
            "--log-dir", str(tmp_path)]  # fmt: skip
    jetracer.main(args)
    assert first_update and first_update[0] >= 30  # 30 steps driven (observed) before the first update
    if learner == "pause":
        assert len(first_update) == 4  # the pauses at 40 and after 60; none at 20, when the buffer held 30 rows


def test_learning_starts_at_learning_starts_steps_once_a_batch_is_stored():
    hp = jetracer.jirl.Args(learning_starts=30, batch_size=16)

    def stored(rows: int):  # what `learning` reads of a replay buffer
        return types.SimpleNamespace(size=rows)

    assert not jetracer.learning(29, stored(100), hp) and jetracer.learning(30, stored(100), hp)
    assert not jetracer.learning(30, stored(15), hp) and jetracer.learning(30, stored(16), hp)
    # --jirl.learning-starts 0: no update before a batch is stored (sampling an empty buffer raises)
    assert not jetracer.learning(0, stored(0), replace(hp, learning_starts=0))


def record_the_worlds(monkeypatch) -> tuple:
    """From here on, every observation `preprocess` makes (at each step the car's, then the twin's) and,
    for the car's and the twin's world, (steering, throttle, off track, pose) after each tick."""
    real_tick, real_preprocess = jetracer.SimWorld.tick, jetracer.preprocess
    observations, ticks = [], {"car": [], "twin": []}

    def tick(self):
        progress = real_tick(self)
        world = "twin" if isinstance(self.controller, jetracer._NullController) else "car"
        ticks[world].append((self.controller.steering, self.controller.throttle, self.off_track, tuple(self.env._state)))
        return progress

    def preprocess(frame, previous_action):
        observations.append(real_preprocess(frame, previous_action))
        return observations[-1]

    monkeypatch.setattr(jetracer.SimWorld, "tick", tick)
    monkeypatch.setattr(jetracer, "preprocess", preprocess)
    return observations, ticks


def test_train_stores_each_step_as_the_script_does_and_counts_its_regret(tmp_path, monkeypatch):
    """The car's Alg. 1, row by row against what the car was seen to do: a real transition per step
    (reward 1 + 0.1 throttle / max throttle, -10 and terminal where the step left the lane); after a
    baseline step its fabricated transition with the penalized reward; after an agent step that the
    baseline took over from, the switch penalty. Both regret estimates are summed again here from the rows
    and from the twin car's own steps; after each lane departure the twin starts from the car's pose,
    previous action and wheel. C falls to 0 at step 60. A person takes over at step 100 and steers hard
    left at full throttle until the car leaves the lane after step 105, the wheel at full left by then:
    the agent takes control back at the next episode's start, which is no control switch. A second
    takeover, at steps 140-142, is an ordinary pair of switches."""
    steps, result = [], []
    real_observe, real_act, real_record, real_train = jetracer.CarSession.observe, jetracer.CarSession.act, jetracer.jirl.Gate.record, jetracer.train
    observations, ticks = record_the_worlds(monkeypatch)
    twin = ticks["twin"]

    def observe(self):
        obs = real_observe(self)
        steps.append({"obs": obs, "off": self.world.off_track})
        return obs

    def act(self, action):
        commands = real_act(self, action)
        steps[-1].update(action=np.array(action, np.float32), commands=commands)
        return commands

    def record(self, rl_acts):
        steps[-1]["rl"] = rl_acts
        return real_record(self, rl_acts)

    def human_action(self):  # hard left at full throttle from step 100 until the car leaves the lane after 105; again at 140-142
        t = len(steps) - 1
        if 100 <= t and not any(step["off"] for step in steps[105:]):
            return np.array([1.0, 1.0], np.float32)
        return np.array([0.0, -1.0], np.float32) if 140 <= t < 143 else None

    monkeypatch.setattr(jetracer.CarSession, "observe", observe)
    monkeypatch.setattr(jetracer.CarSession, "act", act)
    monkeypatch.setattr(jetracer.jirl.Gate, "record", record)
    monkeypatch.setattr(jetracer.CarSession, "human_action", human_action)
    monkeypatch.setattr(jetracer, "train", lambda args: result.append(real_train(args)))
    state = tmp_path / "t.pt"
    jetracer.main(["train", "--total-steps", "160", "--train-every", "40", "--gradient-steps", "2", "--jirl.guidance-steps", "60", "--jirl.rl-control-window", "100",
                   "--jirl.log-every", "30", "--checkpoint", str(state), "--log-dir", str(tmp_path), *FAST, *PATIENT])  # fmt: skip
    rows = {name: value.numpy() for name, value in torch.load(state, weights_only=True)["buffer"].items()}
    (counters,) = result
    assert len(steps) == len(twin) == 160 and all(step["commands"] is not None for step in steps)
    i, regret, paired, switches = 0, 0.0, 0.0, 0
    so_far = [(0.0, 0.0, 0)]  # so_far[t]: (regret, paired regret, switches) as step t's log sees them
    for t in range(159):  # the last step's transition is never complete
        now, after = steps[t], steps[t + 1]
        previous_action = jetracer.START_ACTION if t == 0 or now["off"] else np.clip(steps[t - 1]["action"], -1.0, 1.0)
        np.testing.assert_array_equal(now["obs"][-2:], np.float32(previous_action))  # the observation ends with the last action
        reward = -10.0 if after["off"] else 1.0 + 0.1 * now["commands"][1] / 0.6
        np.testing.assert_array_equal(rows["obs"][i], now["obs"])
        np.testing.assert_array_equal(rows["actions"][i], now["action"])
        np.testing.assert_array_equal(rows["next_obs"][i], after["obs"])
        assert rows["rewards"][i, 0] == pytest.approx(reward) and rows["terminations"][i, 0] == after["off"]
        i += 1
        if not now["rl"]:  # Alg. 1, lines 12-14: the fabricated transition (s, a^rl, r^p, s')
            rl_action = rows["actions"][i]
            assert not np.array_equal(rl_action, now["action"])
            np.testing.assert_array_equal(rows["obs"][i], now["obs"])
            np.testing.assert_array_equal(rows["next_obs"][i], after["obs"])
            distance = np.linalg.norm(now["action"].astype(np.float64) - rl_action)
            assert rows["rewards"][i, 0] == pytest.approx(reward - abs(reward) * (1 - np.exp(-distance / 0.01)), abs=1e-5)
            assert rows["terminations"][i, 0] == after["off"]
            i += 1
        elif not after["rl"] and not after["off"]:  # Sec. V.A: the agent's step that the baseline took over from
            np.testing.assert_array_equal(rows["obs"][i], now["obs"])
            np.testing.assert_array_equal(rows["actions"][i], now["action"])
            np.testing.assert_array_equal(rows["next_obs"][i], after["obs"])
            assert rows["rewards"][i, 0] == -1.0 and rows["terminations"][i, 0] == 0.0
            i += 1
        switches += now["rl"] != after["rl"] and not after["off"]  # a lane departure starts a new episode
        regret += max(0.0, 1.075 - reward)
        _, twin_throttle, twin_off, _ = twin[t]
        paired += max(0.0, (-10.0 if twin_off else 1.0 + 0.1 * twin_throttle / 0.6) - reward)
        so_far.append((regret, paired, switches))
    assert i == len(rows["obs"])
    rl = [step["rl"] for step in steps]
    departure = next(t for t in range(105, 160) if steps[t]["off"])  # under the baseline
    assert len(observations) == 320
    for t in [0] + [t for t in range(160) if steps[t]["off"]]:  # the twin starts where the car starts
        np.testing.assert_array_equal(observations[2 * t + 1], observations[2 * t], err_msg=f"step {t}")
    wheel = steps[departure - 1]["commands"][0]  # hard left: the twin's own wheel followed the lane
    assert wheel == 1.0 and abs(twin[departure][0] - wheel) <= 0.4 + 1e-3  # the safety filter's 8/s at 20 Hz, from the car's wheel
    assert not any(rl[:60]) and not any(rl[100:departure]) and rl[departure] and not any(rl[140:143]) and all(rl[143:])
    assert counters["control_switches"] == switches
    assert counters["fabricated_transitions"] == 159 - sum(rl[:159])
    assert counters["baseline_regret_per_step"] == pytest.approx(regret) and regret > 0.0
    assert counters["paired_regret_per_step"] == pytest.approx(paired)
    assert counters["rl_control_fraction"] == pytest.approx(sum(rl[-100:]) / 100)
    # what TensorBoard got every 30 steps: each figure as it stood at that step (its own step's transition is not complete yet)
    (run_dir,) = tmp_path.glob("train__*")
    events = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})
    events.Reload()
    logged = {tag: {e.step: e.value for e in events.Scalars(tag)} for tag in events.Tags()["scalars"]}
    logs = [0, 30, 60, 90, 120, 150]
    expected = {
        "charts/rl_control_fraction": [sum(rl[max(0, t - 99) : t + 1]) / min(t + 1, 100) for t in logs],
        "charts/fabricated_transitions": [t - sum(rl[:t]) for t in logs],
        "charts/baseline_regret_per_step": [so_far[t][0] for t in logs],
        "charts/paired_regret_per_step": [so_far[t][1] for t in logs],
        "charts/control_switches": [so_far[t][2] for t in logs],
    }
    for tag, values in expected.items():
        assert sorted(logged[tag]) == logs, tag
        np.testing.assert_allclose([logged[tag][t] for t in logs], values, rtol=1e-5, atol=1e-5, err_msg=tag)
    assert sorted(logged["losses/qf_loss"]) == [40, 80, 120, 160]  # each pause's last update, and the one after the loop
    assert {"loop/period_p50_ms", "loop/frames_dropped", "link/rtt_p50_ms"} <= logged.keys()


@pytest.mark.parametrize("use_penalty", [True, False])
def test_the_switch_penalty_marks_a_hand_back_within_an_episode_only_and_can_be_turned_off(tmp_path, monkeypatch, use_penalty):
    """Scripted gate: the agent drives steps 0-9 and leaves the lane, the baseline drives the next episode's
    first steps (10-19: no switch, a new episode), the agent 20-21, the baseline 22-39 (a switch at 22)."""
    script, decided, ticks = [True] * 10 + [False] * 10 + [True] * 2 + [False] * 18, [], []
    monkeypatch.setattr(jetracer.jirl.Gate, "decide", lambda self, *_: decided.append(1) or script[len(decided) - 1])
    real_tick = jetracer.SimWorld.tick

    def tick(self):  # the car's 11th tick, which step 9's commands drive, leaves the lane
        progress = real_tick(self)
        if not isinstance(self.controller, jetracer._NullController):
            ticks.append(1)
            self.off_track = self.off_track or len(ticks) == 11
        return progress

    monkeypatch.setattr(jetracer.SimWorld, "tick", tick)
    state = tmp_path / "t.pt"
    switch = ["--jirl.switch-penalty", "-3"] + ([] if use_penalty else ["--jirl.no-use-switch-penalty"])
    jetracer.main(["train", "--total-steps", "40", "--checkpoint", str(state), "--log-dir", str(tmp_path), *FAST, *PATIENT, *switch])
    rows = {name: value.numpy() for name, value in torch.load(state, weights_only=True)["buffer"].items()}
    penalized = np.flatnonzero(rows["rewards"][:, 0] == -3.0)
    # 39 real transitions (the last step's is never complete), a fabricated one for each of the 27 baseline steps among them
    assert len(rows["rewards"]) == 39 + 27 + len(penalized) and rows["terminations"][:, 0].sum() == 1
    if use_penalty:  # Sec. V.A: the agent's step 21, which the baseline took over from
        (row,) = penalized
        assert row == 10 + 2 * 10 + 2 and rows["terminations"][row, 0] == 0.0  # right after step 21's real transition
        np.testing.assert_array_equal(rows["obs"][row], rows["obs"][row - 1])  # its state and action
        np.testing.assert_array_equal(rows["actions"][row], rows["actions"][row - 1])
    else:
        assert len(penalized) == 0


def test_a_car_that_drives_as_its_baseline_twin_has_no_paired_regret(tmp_path, monkeypatch):
    """Sim-in-the-loop pairs each step with the baseline's own step from the same pose (a twin car). A car
    the baseline keeps driving (C = 1e300) is that twin, lane departures included: the same pose after
    every step, the same observation at every step, paired regret 0, while the unpaired estimate charges
    each departure. The baseline is scripted to steer left at full throttle, so that it leaves the lane
    again and again, by 0.77777: a command the protocol rounds. No pause (--train-every past the end)
    stops the car mid-run."""
    monkeypatch.setattr(jetracer.LaneFollower, "__call__", lambda self, obs: np.array([0.77777, 1.0], np.float32))
    real_observe = jetracer.CarSession.observe
    observations, ticks = record_the_worlds(monkeypatch)

    def observe(self):  # the world moves on once the last command has reached the controller, as within a period on the car
        command, controller = self.link._command, self.link._port.controller
        if command is not None:
            sent = [jetracer.p.to_thousandths(value) / 1000.0 for value in command[:2]]
            deadline = time.monotonic() + 5.0
            while [controller.steering, controller.throttle] != sent:
                assert time.monotonic() < deadline, f"the command {sent} did not reach the controller"
                time.sleep(0.001)
        return real_observe(self)

    real_link = jetracer.HostLink.__init__

    def patient_link(self, *args, **kwargs):
        # the car's link sends STOP once a command is 2 periods old; here its send thread, starved that long on a loaded
        # machine, did so and the car coasted where its twin drove (4 runs of 11, the thread's clock put 150 ms ahead)
        real_link(self, *args, **{**kwargs, "command_timeout": 30.0})

    monkeypatch.setattr(jetracer.CarSession, "observe", observe)
    monkeypatch.setattr(jetracer.HostLink, "__init__", patient_link)
    state = tmp_path / "t.pt"
    jetracer.main(["train", "--total-steps", "100", "--train-every", "1000", "--gradient-steps", "1", "--jirl.gate-c", "1e300", "--jirl.guidance-steps", "0",
                   "--checkpoint", str(state), "--log-dir", str(tmp_path), *FAST, *PATIENT])  # fmt: skip
    saved = torch.load(state, weights_only=True)
    counters, rewards = saved["counters"], saved["buffer"]["rewards"][:, 0].numpy()
    departures = int(np.sum(rewards == -10.0))
    assert departures >= 2 and counters["control_switches"] == 0
    # the car's world ticks as each step observes, so its tick t + 1 applies the command of step t; its first is at rest
    poses = {world: [pose for *_, pose in ticks[world]] for world in ticks}
    assert len(poses["car"]) == len(poses["twin"]) == 100 and poses["car"][1:] == poses["twin"][:-1]
    assert len(observations) == 200
    for t in range(100):
        np.testing.assert_array_equal(observations[2 * t + 1], observations[2 * t], err_msg=f"step {t}")
    assert counters["baseline_regret_per_step"] == pytest.approx(departures * (1.075 + 10.0))  # full throttle earns 1.1 > 1.075
    assert counters["paired_regret_per_step"] == 0.0


def test_a_twin_that_leaves_the_lane_alone_is_put_back_at_rest(tmp_path, monkeypatch):
    """The twin is put back as the car would be: after a lane departure of its own (the baseline steers
    hard left; the agent drives the car, C = 0) its next observation ends with the action at rest."""
    monkeypatch.setattr(jetracer.LaneFollower, "__call__", lambda self, obs: np.array([1.0, 1.0], np.float32))
    real_observe, car_off = jetracer.CarSession.observe, []
    observations, ticks = record_the_worlds(monkeypatch)
    monkeypatch.setattr(jetracer.CarSession, "observe", lambda self: car_off.append(self.world.off_track) or real_observe(self))
    jetracer.main(["train", "--total-steps", "60", "--train-every", "1000", "--gradient-steps", "1", "--jirl.gate-c", "0", "--jirl.guidance-steps", "0",
                   "--checkpoint", str(tmp_path / "t.pt"), "--log-dir", str(tmp_path), *FAST, *PATIENT])  # fmt: skip
    twin_off = [off for _, _, off, _ in ticks["twin"]]
    alone = [t for t in range(59) if twin_off[t] and not car_off[t + 1]]  # the car stayed in the lane
    assert alone
    for t in alone:
        np.testing.assert_array_equal(observations[2 * (t + 1) + 1][-2:], np.float32(jetracer.START_ACTION))


def test_run_drives_a_checkpoint_trained_by_the_jirl_script(tmp_path):
    out = warm_python.run(
        [str(ROOT / "jirl_sac_continuous.py"), "--env-id", "JetRacerTrack-v0", "--total-timesteps", "150",
         "--learning-starts", "100", "--hidden-size", "16", "--batch-size", "16", "--save-model", "--eval-episodes", "1",
         "--baseline-eval-episodes", "1"],
        cwd=tmp_path, timeout=300,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    (checkpoint,) = (tmp_path / "runs").glob("*/*.cleanrl_model")
    rewards = jetracer.run(jetracer.Run(checkpoint=str(checkpoint), steps=40, log_dir=str(tmp_path)))
    assert len(rewards) == 40
    broken = tmp_path / "broken.cleanrl_model"
    broken.write_bytes(b"garbage")
    with pytest.raises(SystemExit, match="not a readable checkpoint"):
        jetracer.run(jetracer.Run(checkpoint=str(broken), steps=1, log_dir=str(tmp_path)))
    with pytest.raises(SystemExit) as raised:
        jetracer.run(jetracer.Run(steps=1, log_dir=str(tmp_path)))
    assert str(raised.value) == "run: error: --checkpoint is required"


def test_the_modules_annotate_their_signatures():
    """`envs/` and `deploy/` are small typed modules: every parameter (self and cls aside) and every return
    of their functions and methods is annotated, `*args` and `**kwargs` included (`__init__` returns None).
    In `benchmarks/`, whose tools hold closures and main blocks, the public top-level functions are."""
    import ast

    unannotated = []
    for folder in ("envs", "deploy", "benchmarks"):
        for path in sorted((ROOT / folder).glob("*.py")):
            tree = ast.parse(path.read_text())
            for node in tree.body if folder == "benchmarks" else ast.walk(tree):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not (folder == "benchmarks" and node.name.startswith("_")):
                    a = node.args
                    params = [*a.posonlyargs, *a.args, *a.kwonlyargs, *filter(None, (a.vararg, a.kwarg))]
                    missing = [x.arg for x in params if x.annotation is None and x.arg not in ("self", "cls")]
                    missing += ["return"] if node.returns is None and node.name != "__init__" else []
                    unannotated += [f"{path.relative_to(ROOT)}:{node.lineno} {node.name}: {', '.join(missing)}"] if missing else []
    assert unannotated == []


def test_the_modules_type_check(tmp_path):
    """mypy finds no error in `envs/`, `deploy/` and `benchmarks/` (imported modules are read, not checked;
    libraries without types are Any). A probe file with one wrong return is checked in the same run, so
    the run can fail."""
    probe = tmp_path / "probe.py"
    probe.write_text('def f() -> int:\n    return "one"\n')
    mypy = [sys.executable, "-m", "mypy", "--ignore-missing-imports", "--follow-imports=silent", "--cache-dir", str(tmp_path / "cache")]
    out = subprocess.run([*mypy, "envs", "deploy", "benchmarks", str(probe)], cwd=ROOT, capture_output=True, text=True)
    errors = [line for line in out.stdout.splitlines() if ": error: " in line]
    assert [line.split(": error: ")[0] for line in errors] == [f"{probe}:2"], out.stdout + out.stderr
    assert out.returncode == 1


def test_deploy_and_what_it_imports_run_on_python_3_8(tmp_path):
    vermin = [str(Path(sys.executable).parent / "vermin"), "--no-tips", "--violations", "-t=3.8-"]
    files = ["deploy", "jirl_sac_continuous.py", "envs/__init__.py", "envs/make.py", "envs/baselines.py",
             "envs/car_interface.py", "envs/lane_follower.py", "envs/pendulum.py", "envs/lunar_lander.py"]  # fmt: skip
    out = subprocess.run([*vermin, *files], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr
    newer = tmp_path / "newer.py"
    newer.write_text("def f(x):\n    match x:\n        case 1:\n            return 2\n")  # match: Python 3.10
    assert subprocess.run([*vermin, str(newer)], capture_output=True).returncode != 0, "the check can fail"


def test_background_learner_keeps_the_gradient_step_ratio(tmp_path):
    out = warm_python.run(
        ["-m", "deploy.jetracer", "train", "--total-steps", "100", "--train-every", "40", "--gradient-steps", "10",
         "--learner", "background", "--checkpoint", str(tmp_path / "bg.pt"), "--log-dir", str(tmp_path), *FAST],
        cwd=ROOT, timeout=120,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert ", updates 25," in out.stdout  # 100 steps x 10 / 40, trained while driving


def test_the_background_learner_refreshes_the_actor_the_car_acts_with_at_every_pause(tmp_path, monkeypatch):
    """With --learner background the car acts with a copy of the actor, refreshed at each --train-every
    step: between two refreshes every action is the mean (C = 0 and the mean after guidance) of the actor
    that the checkpoint at the first of them saved."""
    observed, applied, saved = [], [], []
    real_observe, real_act, real_save = jetracer.CarSession.observe, jetracer.CarSession.act, jetracer.save_training_state
    monkeypatch.setattr(jetracer.CarSession, "observe", lambda self: observed.append(real_observe(self)) or observed[-1])
    monkeypatch.setattr(jetracer.CarSession, "act", lambda self, action: applied.append((observed[-1], action)) or real_act(self, action))
    monkeypatch.setattr(jetracer, "save_training_state", lambda path, sac, *rest: saved.append((len(observed), copy.deepcopy(sac.actor))) or real_save(path, sac, *rest))
    jetracer.main(["train", "--total-steps", "120", "--train-every", "40", "--gradient-steps", "10", "--learner", "background",
                   "--jirl.gate-c", "0", "--jirl.guidance-steps", "0", "--jirl.deterministic-after-guidance",
                   "--checkpoint", str(tmp_path / "t.pt"), "--log-dir", str(tmp_path), *FAST, *PATIENT])  # fmt: skip
    assert [step for step, _ in saved] == [0, 40, 80, 120]  # the first checkpoint before the car is armed, the last after the run
    for (start, actor), end in zip(saved, (40, 80, 120)):
        obs, actions = (np.stack(values) for values in zip(*applied[start:end]))
        with torch.no_grad():
            np.testing.assert_allclose(actions, torch.tanh(actor(torch.from_numpy(obs))[0]).numpy(), atol=1e-6, err_msg=f"steps {start}-{end}")
    first, last = (torch.nn.utils.parameters_to_vector(actor.parameters()) for _, actor in (saved[0], saved[2]))
    assert not torch.equal(first, last), "the learner trained while the car drove"


def fifo_gamepad(tmp_path, monkeypatch) -> str:
    """A FIFO that deploy.io takes for a joystick device: the tests write its events."""
    from deploy import io

    path = str(tmp_path / "js0")
    os.mkfifo(path)
    monkeypatch.setattr(io, "joystick_shape", lambda fd: (8, 11))  # axes, buttons
    return path


def tap(button: int = 0) -> bytes:
    """Joystick events of a tap: `button` down, and up again 30 ms later."""
    import struct

    event = struct.Struct("<IhBB")
    return event.pack(10, 1, 1, button) + event.pack(40, 0, 1, button)


def test_gamepad_events_estop_and_takeover(tmp_path, monkeypatch):
    import struct

    path = fifo_gamepad(tmp_path, monkeypatch)
    writer_fd = os.open(path, os.O_RDWR | os.O_NONBLOCK)  # keeps the FIFO open for the reader
    from deploy.io import Gamepad

    pad = Gamepad(path)
    event = struct.Struct("<IhBB")
    os.write(writer_fd, event.pack(0, 32767, 2, 4) + event.pack(0, -16384, 2, 0) + event.pack(0, -32768, 2, 1) + event.pack(0, 0, 0x81, 0))
    pad.poll()
    assert pad.axes[4] == pytest.approx(1.0) and pad.axes[0] == pytest.approx(-0.5, abs=1e-4) and pad.buttons[0] is False
    assert pad.axes[1] == -1.0  # the one value past -1 the kernel reports, -32768, is -1 too
    press = event.pack(5, 1, 1, 0)
    os.write(writer_fd, press[:5])  # a read that splits an event: nothing yet, and nothing lost
    pad.poll()
    assert pad.buttons[0] is False
    os.write(writer_fd, press[5:] + event.pack(6, -32767, 2, 4)[:3])
    pad.poll()
    assert pad.buttons[0] is True and pad.axes[4] == pytest.approx(1.0)
    os.write(writer_fd, event.pack(6, -32767, 2, 4)[3:])
    pad.poll()
    assert pad.axes[4] == pytest.approx(-1.0)
    assert pad.was_pressed(0) and pad.was_pressed(0), "a button held down stays pressed"
    pad.close()
    os.close(writer_fd)


def test_a_device_that_is_no_joystick_is_refused_and_closed(tmp_path):
    from deploy import io

    fifo = str(tmp_path / "fifo")
    os.mkfifo(fifo)
    open_fds = len(os.listdir("/proc/self/fd"))
    for path in ("/dev/null", fifo, str(tmp_path)):  # a device, a FIFO, a directory: none answers the joystick API
        with pytest.raises(ValueError, match="is not a joystick device"):
            io.Gamepad(path)
    assert len(os.listdir("/proc/self/fd")) == open_fds  # each refused descriptor was closed


def test_a_gamepad_the_user_may_not_read_says_what_gives_access(monkeypatch):
    """A joystick device the user may not read (EACCES) is named with the remedy, the input group; a missing one is not."""
    from deploy import io

    real_open = os.open

    def refused(path, flags, *args):
        if path == "/dev/input/js0":
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), path)
        return real_open(path, flags, *args)

    monkeypatch.setattr(io.os, "open", refused)
    assert refusal(io.Gamepad, "/dev/input/js0") == ("cannot open gamepad '/dev/input/js0': Permission denied (on Linux: sudo usermod -aG input $USER,"
                                                     " then log in again)")
    assert refusal(io.Gamepad, "/dev/input/no_such_js") == "cannot open gamepad '/dev/input/no_such_js': No such file or directory"


@pytest.mark.parametrize(
    "option, missing",
    [(["--estop-button", "11"], "no --estop-button 11"), (["--takeover-axis", "8", "--steering-axis", "9"], "no --takeover-axis 8, --steering-axis 9")],
)
def test_a_gamepad_without_the_chosen_button_or_axis_is_refused_before_the_car_is_armed(tmp_path, monkeypatch, option, missing):
    path = fifo_gamepad(tmp_path, monkeypatch)  # 8 axes, 11 buttons
    armed, real_arm = [], jetracer.HostLink.arm
    monkeypatch.setattr(jetracer.HostLink, "arm", lambda self: armed.append(1) or real_arm(self))
    with pytest.raises(SystemExit, match=f"baseline: error: gamepad '{path}' has buttons 0-10 and axes 0-7: {missing}$"):
        jetracer.main(["baseline", "--steps", "5", "--gamepad", path, "--log-dir", str(tmp_path / "runs"), *option])
    assert not armed and not (tmp_path / "runs").exists()
    # the last button and axis exist
    jetracer.main(["baseline", "--steps", "5", "--gamepad", path, "--log-dir", str(tmp_path / "runs"), "--estop-button", "10",
                   "--takeover-axis", "7"])  # fmt: skip
    assert armed


def test_a_gamepad_refuses_a_negative_button_or_axis_too_and_closes_its_device(tmp_path, monkeypatch):
    from deploy import io

    path = fifo_gamepad(tmp_path, monkeypatch)
    open_fds = len(os.listdir("/proc/self/fd"))
    gamepad = io.Gamepad(path)  # the options refuse one; code that calls require() itself may not
    with pytest.raises(ValueError, match=r"has buttons 0-10 and axes 0-7: no button -1, axis -2$"):
        gamepad.require({"button": -1}, {"axis": -2})
    gamepad.close()
    assert len(os.listdir("/proc/self/fd")) == open_fds, "and closing it closes its device"


def test_joystick_shape_asks_the_driver_for_its_axes_and_buttons(monkeypatch):
    import fcntl

    from deploy import io

    def ior(nr: int, size: int) -> int:  # linux/ioctl.h: _IOR('j', nr, size) for the joystick API
        return (2 << 30) | (size << 16) | (ord("j") << 8) | nr

    answers = {ior(0x11, 1): 6, ior(0x12, 1): 12}  # JSIOCGAXES, JSIOCGBUTTONS

    def ioctl(fd, request, buffer):
        if request not in answers:
            raise OSError(25, "Inappropriate ioctl for device")
        buffer[0] = answers[request]

    monkeypatch.setattr(fcntl, "ioctl", ioctl)  # joystick_shape imports fcntl when called
    assert io.joystick_shape(3) == (6, 12)


def test_a_tap_of_the_e_stop_between_two_reads_still_counts(tmp_path, monkeypatch):
    from deploy.io import Gamepad

    path = fifo_gamepad(tmp_path, monkeypatch)
    writer_fd = os.open(path, os.O_RDWR | os.O_NONBLOCK)
    pad = Gamepad(path)
    os.write(writer_fd, tap(0))
    pad.poll()
    assert pad.buttons[0] is False  # the state a poll sees has it released ...
    assert pad.was_pressed(0) and not pad.was_pressed(0)  # ... the tap is kept until asked for, once
    assert not pad.was_pressed(1)
    pad.close()
    os.close(writer_fd)


def test_an_e_stop_tapped_during_a_training_pause_ends_the_run_there(tmp_path, monkeypatch):
    path = fifo_gamepad(tmp_path, monkeypatch)
    writer_fd = os.open(path, os.O_RDWR | os.O_NONBLOCK)
    real_update, estops = jetracer.jirl.SoftActorCritic.update, []
    real_estop = jetracer.HostLink.estop

    def update(self, data, step):
        if step == 0:  # the first gradient step of the first pause: a person taps the e-stop
            os.write(writer_fd, tap(0))
        return real_update(self, data, step)

    monkeypatch.setattr(jetracer.jirl.SoftActorCritic, "update", update)
    monkeypatch.setattr(jetracer.HostLink, "estop", lambda self: estops.append(1) or real_estop(self))
    state = tmp_path / "train.pt"
    jetracer.main(["train", "--total-steps", "500", "--gamepad", path, "--train-every", "40", "--gradient-steps", "20",
                   "--checkpoint", str(state), "--log-dir", str(tmp_path), *FAST])  # fmt: skip
    os.close(writer_fd)
    assert estops  # e-stopped
    saved = torch.load(state, weights_only=True)["counters"]
    assert saved["step"] == 40 and saved["updates"] == 1  # the pause ended at its next read, and the car never drove again


def test_a_lost_gamepad_raises_gamepad_lost_and_closes_quietly(tmp_path, monkeypatch):
    from deploy import io

    path = fifo_gamepad(tmp_path, monkeypatch)
    pad = io.Gamepad(path)

    def unplugged(fd, size):
        raise OSError(errno.ENODEV, os.strerror(errno.ENODEV))

    monkeypatch.setattr(io.os, "read", unplugged)
    with pytest.raises(io.GamepadLost, match=f"gamepad '{path}' lost \\(No such device\\)"):
        pad.poll()
    monkeypatch.undo()
    pad.close()
    pad.close()  # the fd is gone already: no error


def exits_with_status_1(run: Callable[[], object]) -> None:
    """`run` ends on an error, after the car stopped (and `train` saved its state): status 1, not 0."""
    with pytest.raises(SystemExit) as ended:
        run()
    assert ended.value.code == 1


def reported_steps(out: str, mode: str) -> int:
    """The steps driven, as the run's report on stdout says."""
    return int(re.search(rf"^{mode}: (\d+) steps, mean reward per step", out, re.M).group(1))


def test_training_e_stops_and_keeps_its_state_when_the_gamepad_is_lost(tmp_path, monkeypatch, capsys):
    from deploy import io

    path = fifo_gamepad(tmp_path, monkeypatch)
    polls, estops = [], []
    real_estop = jetracer.HostLink.estop

    def poll(self):
        polls.append(len(estops))
        if len(polls) > 60:  # unplugged after 60 reads: steps 0-57, and 2 in the pause at step 40 (one per gradient step)
            raise io.GamepadLost(f"gamepad {self.path!r} lost (No such device)")

    def estop(self):
        estops.append(len(polls))
        return real_estop(self)

    monkeypatch.setattr(io.Gamepad, "poll", poll)
    monkeypatch.setattr(jetracer.HostLink, "estop", estop)
    state = tmp_path / "train.pt"
    args = ["train", "--total-steps", "500", "--gamepad", path, "--train-every", "40", "--gradient-steps", "2",
            "--checkpoint", str(state), "--log-dir", str(tmp_path), *FAST]  # fmt: skip
    exits_with_status_1(lambda: jetracer.main(args))
    assert estops[0] == 61  # e-stopped on the poll that found the gamepad gone, before close()
    assert len(polls) == 61  # and no control period after it
    assert torch.load(state, weights_only=True)["counters"]["step"] == 58  # saved on the way out, nothing lost
    assert f"train: error: gamepad '{path}' lost (No such device); e-stopped" in capsys.readouterr().err


def test_a_gamepad_lost_while_the_link_is_down_does_not_claim_an_e_stop(tmp_path, monkeypatch, capsys):
    from deploy import io

    path = fifo_gamepad(tmp_path, monkeypatch)
    polls = []

    def poll(self):
        polls.append(1)
        if len(polls) > 20:
            raise io.GamepadLost(f"gamepad {self.path!r} lost (No such device)")

    def unwritable(self, *_):
        if len(polls) > 20:  # the USB hub that held both went away
            raise OSError("not connected")
        return real_send(self, *_)

    real_send = jetracer.HostLink._send
    monkeypatch.setattr(io.Gamepad, "poll", poll)
    monkeypatch.setattr(jetracer.HostLink, "_send", unwritable)
    exits_with_status_1(lambda: jetracer.baseline(jetracer.Baseline(steps=300, gamepad=path, log_dir=str(tmp_path))))
    out, err = capsys.readouterr()
    assert reported_steps(out, "baseline") == 20
    assert err.strip().splitlines() == ["baseline: the e-stop could not be sent (the link is down); the controller's watchdog stops the car",
                   f"baseline: error: gamepad '{path}' lost (No such device)"]  # fmt: skip


def at_period(monkeypatch, n: int, event: Callable) -> None:
    """Call event(session) at the end of the n-th control period (CarSession.wait, counted from 1)."""
    waits, real_wait = [], jetracer.CarSession.wait

    def wait(self):
        waits.append(1)
        if len(waits) == n:
            event(self)
        real_wait(self)

    monkeypatch.setattr(jetracer.CarSession, "wait", wait)


def test_training_ends_and_keeps_its_state_when_the_watchdog_trips(tmp_path, monkeypatch, capsys):
    # a host stall longer than the watchdog: the controller disarms itself
    at_period(monkeypatch, 50, lambda session: session.link._port.controller.poll(time.monotonic() + 10.0))
    state = tmp_path / "train.pt"
    exits_with_status_1(lambda: jetracer.main(["train", "--total-steps", "500", "--train-every", "40", "--gradient-steps", "2",
                                               "--checkpoint", str(state), "--log-dir", str(tmp_path), *FAST]))  # fmt: skip
    assert 50 <= torch.load(state, weights_only=True)["counters"]["step"] <= 52  # stopped within a period or two, saved
    err = capsys.readouterr().err
    assert "train: error: the controller is no longer armed (its watchdog tripped" in err and len(err.strip().splitlines()) == 1


def test_ctrl_c_while_the_link_is_down_ends_the_training_cleanly_and_keeps_its_state(tmp_path, monkeypatch, capsys):
    def link_down_then_ctrl_c(session):
        def unwritable(*_):
            raise OSError("not connected")

        session.link._send = unwritable  # the port is gone, not yet reopened
        capsys.readouterr()  # what the run wrote so far
        os.kill(os.getpid(), signal.SIGINT)
        assert session.stop_requested  # the handler has run
        assert capsys.readouterr().err == ""  # and wrote nothing: a print there could re-enter an interrupted write

    at_period(monkeypatch, 50, link_down_then_ctrl_c)
    state = tmp_path / "train.pt"
    jetracer.main(["train", "--total-steps", "500", "--train-every", "40", "--gradient-steps", "2",
                   "--checkpoint", str(state), "--log-dir", str(tmp_path), *FAST])  # fmt: skip
    assert torch.load(state, weights_only=True)["counters"]["step"] == 50  # saved on the way out
    assert "train: the e-stop could not be sent (the link is down); the controller's watchdog stops the car" in capsys.readouterr().err


def test_a_drive_ends_when_the_controller_restarts_unarmed(tmp_path, monkeypatch, capsys):
    # a brown-out restart: the controller comes back unarmed and says nothing
    at_period(monkeypatch, 30, lambda session: setattr(session.link._port.controller, "armed", False))
    exits_with_status_1(lambda: jetracer.baseline(jetracer.Baseline(steps=300, log_dir=str(tmp_path))))
    out, err = capsys.readouterr()
    assert 30 <= reported_steps(out, "baseline") <= 32  # no reward is counted for periods the car did not drive
    assert "baseline: error: the controller is no longer armed (it refused a command as not armed; did it restart?)" in err


def test_a_disarmed_controller_is_explained_by_the_first_cause_the_link_can_tell():
    from deploy import protocol as p
    from deploy.link import Telemetry

    def telemetry(status):
        return Telemetry(0.0, 0.0, status, 1000, 0.0)

    def refused(*reasons):  # NACKs of DRIVE commands, oldest first
        return deque(p.Message(p.NACK, seq, (seq, p.DRIVE, reason)) for seq, reason in enumerate(reasons))

    session = object.__new__(jetracer.CarSession)  # only what disarm_reason reads
    everything = telemetry(p.STATUS_WATCHDOG_TRIPPED | p.STATUS_ESTOP_LATCHED)
    cases = [  # (reconnects, telemetry, nacks) -> the reason; each case drops the cause the one before it named
        ((2, everything, refused(p.NOT_ARMED)), "the link was lost and reopened 2 time(s)"),
        ((0, everything, refused(p.NOT_ARMED)), "its watchdog tripped: no command reached it in time"),
        ((0, telemetry(p.STATUS_ESTOP_LATCHED), refused(p.NOT_ARMED)), "its e-stop is latched"),
        ((0, telemetry(p.STATUS_ARMED), refused(p.NOT_ARMED, p.ESTOP_LATCHED, p.OUT_OF_RANGE)), "it refused a command as e-stop latched; did it restart?"),
        ((0, None, refused(p.ESTOP_LATCHED, p.NOT_ARMED, p.BAD_LENGTH)), "it refused a command as not armed; did it restart?"),
        ((0, None, refused(p.OUT_OF_RANGE, p.BAD_LENGTH)), "it disarmed"),  # refusals of a bad command say nothing of arming
    ]
    for (reconnects, status, nacks), reason in cases:
        session.link = types.SimpleNamespace(reconnects=reconnects, telemetry=status, nacks=nacks)
        assert session.disarm_reason() == reason


def test_an_action_the_safety_filter_refuses_is_a_stop_and_is_not_observed_as_the_previous_action():
    # the loops refuse a non-finite action before they act; this is the session's own guard behind them
    sent = []
    session = object.__new__(jetracer.CarSession)  # only what act reads
    session.stop_requested, session.previous_action = False, np.array([0.2, -0.5], dtype=np.float32)
    session.safety = jetracer.SafetyFilter(ActionMapping(), max_steering_rate=4.0, period=0.05)
    session.link = types.SimpleNamespace(armed=True, stop=lambda: sent.append("STOP"), drive=lambda *commands: sent.append(commands))
    assert session.act(np.array([0.1, 1.0])) == (pytest.approx(0.1), pytest.approx(0.6))
    assert session.act(np.array([np.nan, 1.0])) is None
    assert sent == [(pytest.approx(0.1), pytest.approx(0.6)), "STOP"]
    np.testing.assert_array_equal(session.previous_action, np.float32([0.1, 1.0]))  # the last action the car took


def stale_camera(monkeypatch, stale: Callable[[int], bool], age: float = 1.0) -> list:
    """Make the car's simulated camera serve frames captured `age` seconds earlier on the reads (counted
    from 1) where stale(n) holds; train's shadow car, driven by the baseline, keeps fresh ones. Returns
    the list of reads."""
    from deploy import io

    reads, real_read = [], io.SimWorld.read

    def read(self):
        frame, captured = real_read(self)
        if isinstance(self.controller, jetracer._NullController):
            return frame, captured
        reads.append(1)
        return (frame, captured - age) if stale(len(reads)) else (frame, captured)

    monkeypatch.setattr(io.SimWorld, "read", read)
    return reads


@pytest.mark.parametrize("mode", ["baseline", "train"])
def test_a_camera_that_stops_delivering_ends_the_run(mode, tmp_path, monkeypatch, capsys):
    reads = stale_camera(monkeypatch, lambda n: n > 30)  # frozen after 30 periods
    state = tmp_path / "train.pt"
    if mode == "baseline":
        exits_with_status_1(lambda: jetracer.baseline(jetracer.Baseline(steps=300, log_dir=str(tmp_path))))
    else:  # before, training waited for a fresh frame for ever, the car stopped
        exits_with_status_1(lambda: jetracer.main(["train", "--total-steps", "500", "--checkpoint", str(state), "--log-dir", str(tmp_path), *FAST]))
        assert torch.load(state, weights_only=True)["counters"]["step"] == 30  # saved on the way out
    out, err = capsys.readouterr()
    assert mode == "train" or reported_steps(out, mode) == 30
    assert len(reads) == 30 + 40  # 2 s of stale frames at 20 Hz, then the run ends
    assert f"{mode}: error: no fresh camera frame for 40 periods (2 s); stopping" in err


@pytest.mark.parametrize("mode", ["baseline", "train"])
def test_a_camera_that_fails_ends_the_run_at_once_saying_why(mode, tmp_path, monkeypatch, capsys):
    from deploy import io

    reads, real_read = [], io.SimWorld.read

    def read(self):
        if isinstance(self.controller, jetracer._NullController):  # train's shadow car
            return real_read(self)
        reads.append(1)
        if len(reads) > 30:
            raise io.CameraFailed("camera 0 delivered a (480, 640) uint16 frame; expected 8-bit grey, BGR or BGRA")
        return real_read(self)

    monkeypatch.setattr(io.SimWorld, "read", read)
    stops, real_stop = [], jetracer.HostLink.stop
    monkeypatch.setattr(jetracer.HostLink, "stop", lambda self: stops.append(len(reads)) or real_stop(self))
    state = tmp_path / "train.pt"
    if mode == "baseline":
        exits_with_status_1(lambda: jetracer.baseline(jetracer.Baseline(steps=300, log_dir=str(tmp_path))))
    else:
        exits_with_status_1(lambda: jetracer.main(["train", "--total-steps", "500", "--checkpoint", str(state), "--log-dir", str(tmp_path), *FAST]))
        assert torch.load(state, weights_only=True)["counters"]["step"] == 30  # saved on the way out
    assert len(reads) == 31 and stops[0] == 31  # the car stopped at the failed read; not 2 s of stale frames
    out, err = capsys.readouterr()
    assert mode == "train" or reported_steps(out, mode) == 30
    assert f"{mode}: error: camera 0 delivered a (480, 640) uint16 frame; expected 8-bit grey, BGR or BGRA; stopping" in err
    assert "no fresh camera frame" not in err and "Traceback" not in err
    assert mode == "train" or "frames dropped 1\n" in out  # the frame that never came


def test_a_frame_is_stale_past_two_periods_and_only_2_s_of_them_in_a_row_end_a_drive(tmp_path, monkeypatch, capsys):
    def baseline_for(steps):
        rewards = jetracer.baseline(jetracer.Baseline(steps=steps, log_dir=str(tmp_path), watchdog_ms=2000))
        return len(rewards), re.search(r"frames dropped (\d+)", capsys.readouterr().out).group(1)

    stale_camera(monkeypatch, lambda n: True, age=0.06)  # 1.2 periods at 20 Hz: fresh enough to act on
    assert baseline_for(20) == (20, "0")
    monkeypatch.undo()
    stale_camera(monkeypatch, lambda n: True, age=0.15)  # 3 periods: the car waits, stopped
    assert baseline_for(20) == (0, "20")
    monkeypatch.undo()
    stale_camera(monkeypatch, lambda n: n % 31 != 0)  # 30 stale periods, one fresh frame, 30 stale, ...: never 2 s in a row
    assert baseline_for(100) == (3, "97")


def test_the_gamepad_takes_over_the_steering_while_its_trigger_is_held_past_half():
    session = object.__new__(jetracer.CarSession)  # only what human_action reads
    session.args, session.stop_requested = jetracer.Baseline(takeover_axis=4, steering_axis=0), False
    session.gamepad = types.SimpleNamespace(axes={})
    assert session.human_action() is None  # an axis not moved yet reads as released
    for trigger in (-1.0, 0.5):
        session.gamepad.axes = {4: trigger, 0: 0.3}
        assert session.human_action() is None
    session.gamepad.axes = {4: 0.51, 0: 0.3}  # the stick right of centre steers right (steering + is left), at the lowest throttle
    np.testing.assert_array_equal(session.human_action(), np.array([-0.3, -1.0], dtype=np.float32))
    session.stop_requested = True
    assert session.human_action() is None
    session.stop_requested, session.gamepad = False, None
    assert session.human_action() is None


def test_a_late_period_does_not_make_the_next_ones_short():
    """After a period that ran late (a slow read, a training pause), the loop waits a whole period again
    rather than firing a burst of periods to catch up with the schedule."""
    session = object.__new__(jetracer.CarSession)  # only what wait reads
    session.period, session.periods = 0.05, deque(maxlen=10)
    session._last_tick = time.monotonic() - 1.0
    session._next_tick = session._last_tick  # a second behind: twenty periods' worth
    session.wait()
    assert session.periods[-1] >= 1.0
    started = time.monotonic()
    session.wait()
    session.wait()
    # two whole periods from the late one's end (one of them may be shorter: the schedule makes up an overshoot)
    assert time.monotonic() - started >= 2 * 0.05 - 0.002


def test_the_loop_timing_and_each_lap_are_logged_once():
    session = object.__new__(jetracer.CarSession)  # only what timing and log read
    session.periods = deque([i / 1000 for i in range(100, 0, -1)], maxlen=2000)  # 1, 2, ..., 100 ms
    timing = session.timing()
    assert timing["period_p50_ms"] == pytest.approx(50.5) and timing["period_p99_ms"] == pytest.approx(100.0)
    assert timing["jitter_ms"] == pytest.approx(np.std(np.arange(1, 101)))
    logged = []
    session.writer = types.SimpleNamespace(add_scalar=lambda tag, value, step: logged.append((tag, value, step)))
    session.link = types.SimpleNamespace(round_trip_stats=lambda: {"p50": 0.002})
    session.world, session.laps_logged, session.frames_dropped = types.SimpleNamespace(lap_times=[12.5]), 0, 3
    session.log(100)
    session.world.lap_times.append(11.75)
    session.log(200)
    session.log(300)
    assert [entry for entry in logged if entry[0] == "charts/lap_time"] == [("charts/lap_time", 12.5, 100), ("charts/lap_time", 11.75, 200)]
    assert ("link/rtt_p50_ms", 2.0, 300) in logged and ("loop/frames_dropped", 3, 300) in logged
    assert ("loop/period_p99_ms", pytest.approx(100.0), 100) in logged


class ScriptedSession:
    """What `drive` uses of a CarSession: a human takes over at steps 2-3, and the car is e-stopped
    while it sends step 5's commands."""

    def __init__(self) -> None:
        self.stop_requested, self.world, self.mapping, self.step, self.sent = False, None, ActionMapping(), 0, []

    def observe(self):
        return np.full(3, self.step, dtype=np.float32)

    def human_action(self):
        return np.array([0.5, -1.0], dtype=np.float32) if self.step in (2, 3) else None

    def act(self, action):
        self.sent.append(np.asarray(action).tolist())
        self.stop_requested = self.step == 5
        return None if self.stop_requested else (0.0, 0.6)

    def log(self, step):
        pass

    def wait(self):
        self.step += 1


def test_drive_acts_for_the_human_while_they_hold_the_takeover_and_ends_at_an_e_stop_unrewarded():
    session, asked = ScriptedSession(), []
    rewards = jetracer.drive(session, lambda obs: asked.append(int(obs[0])) or np.array([0.1, 1.0]), steps=10)
    assert asked == [0, 1, 4, 5]  # the policy is not asked while the human drives
    assert session.sent == [[0.1, 1.0], [0.1, 1.0], [0.5, -1.0], [0.5, -1.0], [0.1, 1.0], [0.1, 1.0]]
    assert rewards == [pytest.approx(1.1)] * 5  # step 5 was never driven: no reward for it


def test_the_e_stop_is_read_while_the_frames_are_stale(tmp_path, monkeypatch, capsys):
    path = fifo_gamepad(tmp_path, monkeypatch)
    writer_fd = os.open(path, os.O_RDWR | os.O_NONBLOCK)
    reads = stale_camera(monkeypatch, lambda n: n > 30)  # frozen after 30 periods: the car waits, stopped
    at_period(monkeypatch, 35, lambda session: os.write(writer_fd, tap(0)))
    estops, real_estop = [], jetracer.HostLink.estop
    monkeypatch.setattr(jetracer.HostLink, "estop", lambda self: estops.append(len(reads)) or real_estop(self))
    rewards = jetracer.baseline(jetracer.Baseline(steps=300, gamepad=path, log_dir=str(tmp_path)))
    os.close(writer_fd)
    assert len(rewards) == 30 and estops == [35]  # e-stopped at the next read, not 2 s later as a lost camera
    assert "no fresh camera frame" not in capsys.readouterr().err


def test_a_training_pause_stops_the_car_comes_once_per_pause_step_and_restarts_the_clock(tmp_path, monkeypatch):
    """The car must not drive on blind while the agent trains; stale frames at a pause step repeat the
    step, not the pause; after a pause the next period is a whole one, not cut short to catch up."""
    events, real = [], {name: getattr(jetracer.HostLink, name) for name in ("stop", "drive")}
    monkeypatch.setattr(jetracer.HostLink, "stop", lambda self: events.append(("stop",)) or real["stop"](self))
    monkeypatch.setattr(jetracer.HostLink, "drive", lambda self, *commands: events.append(("drive",)) or real["drive"](self, *commands))
    real_update, real_save, real_observe = jetracer.jirl.SoftActorCritic.update, jetracer.save_training_state, jetracer.CarSession.observe
    monkeypatch.setattr(jetracer.jirl.SoftActorCritic, "update", lambda self, *a: events.append(("update",)) or real_update(self, *a))

    def save(path, sac, rb, counters, *rest):  # a slow disk: each save takes four periods
        events.append(("save", counters["step"]))
        time.sleep(0.2)
        return real_save(path, sac, rb, counters, *rest)

    monkeypatch.setattr(jetracer, "save_training_state", save)
    monkeypatch.setattr(jetracer.CarSession, "observe", lambda self: events.append(("observe", time.monotonic())) or real_observe(self))
    stale_camera(monkeypatch, lambda n: 41 <= n <= 43)  # the reads of step 40, right after its pause: the step is read four times
    jetracer.main(["train", "--total-steps", "60", "--train-every", "20", "--gradient-steps", "2", "--checkpoint", str(tmp_path / "t.pt"),
                   "--log-dir", str(tmp_path), *FAST, *PATIENT])  # fmt: skip
    assert [event[1] for event in events if event[0] == "save"] == [0, 20, 40, 60]
    kinds = [event[0] for event in events]
    updates = [i for i, kind in enumerate(kinds) if kind == "update"]
    assert len(updates) == 4  # learning starts at 30: two at the pause at 40, two after the last step
    for i in updates:
        last_drive = max(j for j in range(i) if kinds[j] == "drive")
        assert "stop" in kinds[last_drive:i], f"update {i} while the car drove"
    for pause in (20, 40):
        at = events.index(("save", pause))
        first, second = [event[1] for event in events[at:] if event[0] == "observe"][:2]
        assert second - first >= 0.6 * 0.05, f"the period after the pause at {pause} lasted {second - first:.3f} s"  # cut short: a step's compute


def test_a_stale_frame_ends_the_training_episode_for_the_baseline_too(tmp_path, monkeypatch):
    stale_camera(monkeypatch, lambda n: 21 <= n <= 23)  # three stale periods
    resets, new_episodes, real_new_episode = [], [], jetracer.jirl.Gate.new_episode
    monkeypatch.setattr(jetracer.LaneFollower, "reset", lambda self: resets.append(1) or setattr(self, "previous_error", None))
    monkeypatch.setattr(jetracer.jirl.Gate, "new_episode", lambda self: new_episodes.append(1) or real_new_episode(self))
    guided = ["--jirl.guidance-steps", "27000"]  # the baseline keeps control: no lane departure starts an episode
    jetracer.main(["train", "--total-steps", "60", "--checkpoint", str(tmp_path / "t.pt"), "--log-dir", str(tmp_path), *FAST, *guided])
    assert len(resets) == 3  # its steering derivative does not span the gap (the car never left the lane here)
    assert len(new_episodes) == 3  # nor does the gate's window


def test_a_failing_background_learner_stops_the_car_and_keeps_the_state(tmp_path, monkeypatch, capsys):
    updates, real_update = [], jetracer.jirl.SoftActorCritic.update

    def update(self, data, step):
        updates.append(step)
        if len(updates) > 5:
            raise RuntimeError("out of memory")
        return real_update(self, data, step)

    monkeypatch.setattr(jetracer.jirl.SoftActorCritic, "update", update)
    state = tmp_path / "train.pt"
    exits_with_status_1(lambda: jetracer.main(["train", "--total-steps", "1000", "--learner", "background", "--train-every", "10", "--gradient-steps", "5",
                                               "--checkpoint", str(state), "--log-dir", str(tmp_path), *FAST]))  # fmt: skip
    counters = torch.load(state, weights_only=True)["counters"]
    assert counters["updates"] == 5 and counters["step"] < 100  # ended soon after, not at 1000 steps without a learner
    assert "learner_error" not in counters  # a resume starts clean
    assert "train: error: the background learner failed (RuntimeError: out of memory); stopping" in capsys.readouterr().err


def test_train_checks_its_checkpoint_before_the_car_is_armed(tmp_path):
    def train(*extra):
        return warm_python.run(["-m", "deploy.jetracer", "train", "--total-steps", "50", "--log-dir", str(tmp_path / "logs"),
                               *FAST, *extra], cwd=ROOT, timeout=120)  # fmt: skip

    (tmp_path / "afile").write_text("")
    out = train("--checkpoint", str(tmp_path / "afile" / "train.pt"))  # its directory cannot be made
    assert out.returncode != 0 and "train: error: cannot write --checkpoint" in out.stderr
    assert "Traceback" not in out.stderr and not (tmp_path / "logs").exists()  # nothing driven, nothing logged
    earlier = tmp_path / "earlier.pt"
    earlier.write_bytes(b"45 minutes of training")
    out = train("--checkpoint", str(earlier))  # a fresh run would have overwritten it at its first pause
    assert out.returncode != 0 and "holds an earlier training; pass --resume to continue it" in out.stderr
    assert earlier.read_bytes() == b"45 minutes of training" and not (tmp_path / "logs").exists()


def record_closed_controllers(monkeypatch) -> list:
    """The mock controller of every session closed from now on, in order (to check it was stopped)."""
    controllers, real_close = [], jetracer.CarSession.close

    def close(self):
        controllers.append(self.link._port.controller)
        real_close(self)

    monkeypatch.setattr(jetracer.CarSession, "close", close)
    return controllers


def test_a_checkpoint_that_cannot_be_written_mid_run_stops_the_car(tmp_path, monkeypatch):
    saves, real_save = [], jetracer.save_training_state

    def save(path, sac, rb, counters, args, create=False):
        saves.append(counters["step"])
        if len(saves) == 3:  # the disk fills up as the state is written (its policy goes in another file)
            fill_the_disk_for(monkeypatch, r"t\.pt\.\d+\.tmp")
        real_save(path, sac, rb, counters, args, create)

    monkeypatch.setattr(jetracer, "save_training_state", save)
    controllers = record_closed_controllers(monkeypatch)
    state = tmp_path / "t.pt"
    with pytest.raises(SystemExit, match=r"^train: error: cannot write --checkpoint .*t\.pt: \[Errno 28\] No space left on device$"):
        jetracer.main(["train", "--total-steps", "500", "--train-every", "40", "--gradient-steps", "2",
                       "--checkpoint", str(state), "--log-dir", str(tmp_path), *FAST])  # fmt: skip
    assert saves == [0, 40, 80]  # before arming, then at every pause until the disk was full
    assert controllers[0].throttle == 0.0 and controllers[0].estop_latched  # the session was closed: STOP, ESTOP
    assert torch.load(state, weights_only=True)["counters"]["step"] == 40  # the last state that fitted, whole
    assert not list(tmp_path.glob("*.tmp"))


@pytest.mark.parametrize("learner", ["pause", "background"])
def test_a_training_that_diverges_stops_the_car_at_the_next_pause_and_keeps_its_last_sound_state(learner, tmp_path, monkeypatch):
    controllers = record_closed_controllers(monkeypatch)
    state = tmp_path / "t.pt"
    diverging = ["--jirl.q-lr", "1e6"]  # the critics' second update (one per pause from step 40) leaves them NaN
    with pytest.raises(SystemExit) as ended:
        jetracer.main(["train", "--total-steps", "2000", "--train-every", "40", "--gradient-steps", "1", "--learner", learner,
                       "--checkpoint", str(state), "--log-dir", str(tmp_path / "logs"), *FAST, *diverging])  # fmt: skip
    said = re.fullmatch(rf"train: error: the training diverged by step (\d+): NaN or infinite values in (.+); {re.escape(str(state))} keeps step (\d+)'s state", str(ended.value.code))
    assert said, ended.value.code
    diverged_by, kept = int(said[1]), int(said[3])
    if learner == "pause":  # updates at the pauses of steps 40 and 80: found at 80's, before the car acts with it
        assert (diverged_by, said[2], kept) == (80, "the critics, the target critics and the critics' optimizer", 40)
    else:  # the learner's updates run beside the car, on the rows stored by then: found at the first pause after they diverged
        assert diverged_by % 40 == 0 and kept == diverged_by - 40
    assert controllers[0].throttle == 0.0 and controllers[0].estop_latched  # the session was closed: STOP, ESTOP
    hp = replace(jetracer.car_jirl_defaults(), hidden_size=16)
    rb = jetracer.jirl.ReplayBuffer(100, jetracer.OBS_SIZE, 2, seed=0)
    counters, _ = jetracer.load_training_state(str(state), jetracer.jirl.SoftActorCritic(jetracer.OBS_SIZE, 2, hp), rb)  # a state a resume takes
    assert counters["step"] == kept
    jetracer.jirl.load_checkpoint(jetracer.policy_path(str(state)))  # and the policy beside it, for `run`


def record_the_cars_actions(monkeypatch) -> list:
    """Every action given to the car session, in order; every replay row stored is checked finite as it is added."""
    acted, real_act, real_add = [], jetracer.CarSession.act, jetracer.jirl.ReplayBuffer.add

    def add(self, obs, action, reward, next_obs, *args, **kwargs):
        assert np.isfinite(action).all() and math.isfinite(reward), "a NaN was stored"
        return real_add(self, obs, action, reward, next_obs, *args, **kwargs)

    monkeypatch.setattr(jetracer.CarSession, "act", lambda self, action: acted.append(action) or real_act(self, action))
    monkeypatch.setattr(jetracer.jirl.ReplayBuffer, "add", add)
    return acted


def make_the_actor_overflow(actor: torch.nn.Module, output: str) -> None:
    """`output` ("mean" or "log-std") of `actor` made non-finite on every input from now on, its other output
    left as it was. The mean by finite weights (`overflow_the_mean`); the log-std by replacing it with NaN:
    tanh bounds it, so finite weights make it NaN only where the CPU adds partial sums of both signs, which
    a chain of fused multiply-adds never does."""
    if output == "mean":
        overflow_the_mean(dict(actor.named_parameters()))
        return

    def forward(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std = real_forward(x)
        return mean, torch.full_like(log_std, math.nan)

    real_forward, actor.forward = actor.forward, forward  # this actor only: a copy made before keeps its own


@pytest.mark.parametrize("learner", ["pause", "background"])
@pytest.mark.parametrize("output", ["mean", "log-std"])
def test_an_update_whose_actor_overflows_is_not_saved_and_the_car_never_acts_with_it(learner, output, tmp_path, monkeypatch):
    """Finite weights pass the check of weights and moments; their output on the stored observations does not."""
    real_update, updates = jetracer.jirl.SoftActorCritic.update, []

    def update(self, batch, i):
        losses = real_update(self, batch, i)
        updates.append(i)
        if len(updates) == 4:  # the last update of the step-80 pause (two per pause from step 40): none learns from its output
            make_the_actor_overflow(self.actor, output)
        return losses

    monkeypatch.setattr(jetracer.jirl.SoftActorCritic, "update", update)
    controllers, acted = record_closed_controllers(monkeypatch), record_the_cars_actions(monkeypatch)
    state = tmp_path / "t.pt"
    with pytest.raises(SystemExit) as ended:
        jetracer.main(["train", "--total-steps", "400", "--train-every", "40", "--gradient-steps", "2", "--learner", learner,
                       "--checkpoint", str(state), "--log-dir", str(tmp_path / "logs"), *FAST])  # fmt: skip
    said = re.fullmatch(rf"train: error: the training diverged by step (\d+): the actor overflows on some of the (\d+) latest stored observations;"
                        rf" {re.escape(str(state))} keeps step (\d+)'s state", str(ended.value.code))  # fmt: skip
    assert said, ended.value.code
    diverged_by, rows, kept = int(said[1]), int(said[2]), int(said[3])
    if learner == "pause":  # found at the pause that made it, before the car acts with it
        assert (diverged_by, kept, len(acted)) == (80, 40, 80)
    else:  # the learner updates beside the car; the loop's copy of the actor takes its weights at a pause, once checked
        assert diverged_by % 40 == 0 and kept == diverged_by - 40 and len(acted) == diverged_by
    assert 0 < rows <= jetracer.OVERFLOW_ROWS
    assert controllers[0].throttle == 0.0 and controllers[0].estop_latched
    sac = jetracer.jirl.SoftActorCritic(jetracer.OBS_SIZE, 2, replace(jetracer.car_jirl_defaults(), hidden_size=16))
    rb = jetracer.jirl.ReplayBuffer(1000, jetracer.OBS_SIZE, 2, seed=0)
    assert jetracer.load_training_state(str(state), sac, rb)[0]["step"] == kept
    assert jetracer.overflow(sac.actor, rb) == ""  # the state kept is one whose actor a resume can drive with


def test_the_pauses_overflow_check_runs_the_actor_on_the_latest_stored_observations():
    rb = jetracer.jirl.ReplayBuffer(10, 1, 2, seed=0)
    for i in range(15):  # the ring has wrapped: rows 5 to 14 are stored, 14 the latest
        rb.add(np.array([i], np.float32), np.zeros(2), 0.0, np.zeros(1), False)

    def overflowing_on(n: int) -> Callable:  # an actor whose mean is infinite on observation n alone
        return lambda obs: (torch.where(obs == n, math.inf, 0.0).expand(-1, 2), torch.zeros(len(obs), 2))

    assert [jetracer.overflow(overflowing_on(n), rb, rows=3) for n in (11, 12, 14)] == ["", *["the actor overflows on some of the 3 latest stored observations"] * 2]
    assert jetracer.overflow(overflowing_on(5), rb) == "the actor overflows on some of the 10 latest stored observations"  # all there are
    assert jetracer.overflow(overflowing_on(4), rb) == ""  # overwritten
    log_std_nan = lambda obs: (torch.zeros(len(obs), 2), torch.where(obs == 14, math.nan, 0.0).expand(-1, 2))  # noqa: E731
    assert jetracer.overflow(log_std_nan, rb, rows=1) == "the actor overflows on some of the 1 latest stored observations"  # the log-std alone


@pytest.mark.parametrize("output", ["mean", "log-std"])
def test_an_actor_that_overflows_on_a_new_observation_ends_the_training_before_its_output_acts_or_is_stored(output, tmp_path, monkeypatch):
    """The pause's check sees the stored observations only; the loop checks each new one as the script does."""
    real_save = jetracer.save_training_state

    def save(path, sac, rb, counters, args, create=False):
        real_save(path, sac, rb, counters, args, create)
        if counters["step"] == 40:  # after the pause's checks and its save: as if only step 40's observation made it overflow
            make_the_actor_overflow(sac.actor, output)

    monkeypatch.setattr(jetracer, "save_training_state", save)
    controllers, acted = record_closed_controllers(monkeypatch), record_the_cars_actions(monkeypatch)
    state = tmp_path / "t.pt"
    with pytest.raises(SystemExit, match=rf"^train: error: the training diverged by step 40: the actor overflowed on this step's observation;"
                                         rf" {re.escape(str(state))} keeps step 40's state, with this actor$"):  # fmt: skip
        jetracer.main(["train", "--total-steps", "400", "--train-every", "40", "--gradient-steps", "2",
                       "--checkpoint", str(state), "--log-dir", str(tmp_path / "logs"), *FAST])  # fmt: skip
    assert len(acted) == 40  # step 40's action was neither taken nor stored
    assert controllers[0].throttle == 0.0 and controllers[0].estop_latched


def test_run_ends_on_a_policy_whose_action_is_not_finite_rather_than_stop_the_car_in_silence(tmp_path, monkeypatch, capsys):
    state = tmp_path / "t.pt"
    jetracer.main(["train", "--total-steps", "40", "--checkpoint", str(state), "--log-dir", str(tmp_path / "logs"), *FAST])
    policy = jetracer.policy_path(str(state))
    checkpoint = torch.load(policy, weights_only=True)
    overflow_the_actor(checkpoint["actor"])
    torch.save(checkpoint, policy)  # its weights are finite: it loads
    controllers, acted = record_closed_controllers(monkeypatch), record_the_cars_actions(monkeypatch)
    capsys.readouterr()
    exits_with_status_1(lambda: jetracer.run(jetracer.Run(checkpoint=policy, steps=50, log_dir=str(tmp_path))))
    out, err = capsys.readouterr()
    assert "run: error: the policy's action at step 0 is [nan, nan], not finite; stopping\n" in err
    assert reported_steps(out, "run") == 0 and acted == []
    assert controllers[0].throttle == 0.0 and controllers[0].estop_latched
    events, real_stop, real_log = [], jetracer.HostLink.stop, jetracer.CarSession.log  # a policy that fails as the car drives
    monkeypatch.setattr(jetracer.HostLink, "stop", lambda self: events.append("stop") or real_stop(self))
    monkeypatch.setattr(jetracer.CarSession, "log", lambda self, step: events.append("log") or real_log(self, step))
    driving = lambda obs: np.array([0.0, 0.0 if len(acted) < 10 else math.nan], np.float32)  # noqa: E731
    exits_with_status_1(lambda: jetracer.drive_and_report(jetracer.Run(log_dir=str(tmp_path)), "run", driving, 50))
    out, err = capsys.readouterr()
    assert "run: error: the policy's action at step 10 is [0.0, nan], not finite; stopping\n" in err
    assert reported_steps(out, "run") == 10 and len(acted) == 10
    assert events[:3] == ["log", "stop", "log"], events  # step 0's log; the car stopped at once, before the last log and the close


def test_a_resumed_training_learns_at_the_rates_it_is_given_not_at_the_saved_ones(tmp_path, capsys):
    def rates(path) -> list:  # the critics' optimizer's, then the actor's and the entropy coefficient's
        sac = torch.load(path, weights_only=True)["sac"]
        return [group["lr"] for name in ("q_optimizer", "actor_optimizer") for group in sac[name]["param_groups"]]

    state, logs = tmp_path / "t.pt", str(tmp_path / "logs")
    jetracer.main(["train", "--total-steps", "40", "--checkpoint", str(state), "--log-dir", logs, *FAST, "--jirl.q-lr", "0.01", "--jirl.policy-lr", "0.002"])
    assert rates(state) == [0.01, 0.002, 0.01]
    capsys.readouterr()
    jetracer.main(["train", "--resume", "--total-steps", "80", "--checkpoint", str(state), "--log-dir", logs, *FAST, "--jirl.q-lr", "0.0005"])
    policy_lr = jetracer.car_jirl_defaults().policy_lr  # not given: the default, as for every other setting
    assert rates(state) == [0.0005, policy_lr, 0.0005]
    out = capsys.readouterr().out
    assert "resume: --jirl.q-lr 0.0005 replaces the training's 0.01\n" in out
    assert f"resume: --jirl.policy-lr {policy_lr} replaces the training's 0.002\n" in out


@pytest.mark.parametrize("mode", ["baseline", "train"])
def test_logs_that_cannot_be_written_stop_the_car_and_training_keeps_its_state(mode, tmp_path, monkeypatch, capsys):
    from torch.utils.tensorboard import SummaryWriter

    real_add_scalar = SummaryWriter.add_scalar

    def add_scalar(self, tag, value, step=None, *args, **kwargs):  # the disk is full from the step-200 logs on
        if step >= 200:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_add_scalar(self, tag, value, step, *args, **kwargs)

    monkeypatch.setattr(SummaryWriter, "add_scalar", add_scalar)
    controllers = record_closed_controllers(monkeypatch)
    state = tmp_path / "train.pt"
    if mode == "baseline":  # the car stops at the period after the failed logs: 201 driven
        exits_with_status_1(lambda: jetracer.baseline(jetracer.Baseline(steps=1000, log_dir=str(tmp_path))))
        out, err = capsys.readouterr()
        assert reported_steps(out, mode) == 201
    else:
        exits_with_status_1(lambda: jetracer.main(["train", "--total-steps", "1000", "--checkpoint", str(state), "--log-dir", str(tmp_path), *FAST]))
        err = capsys.readouterr().err
        assert torch.load(state, weights_only=True)["counters"]["step"] == 201  # saved on the way out
    (log_dir,) = tmp_path.glob(f"{mode}__*")
    assert f"{mode}: error: cannot write the logs to {log_dir}: No space left on device; stopping" in err
    assert "Traceback" not in err and "Exception in thread" not in err, err
    assert controllers[0].throttle == 0.0 and controllers[0].estop_latched  # closed: STOP, ESTOP


def started_session(command: list, tmp_path, hangup=signal.SIG_DFL) -> subprocess.Popen:
    """`python -m deploy.jetracer COMMAND`, with SIGHUP's disposition `hangup`, once its session is up."""
    process = subprocess.Popen([sys.executable, "-m", "deploy.jetracer", *command, "--log-dir", str(tmp_path)], cwd=ROOT,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               preexec_fn=lambda: signal.signal(signal.SIGHUP, hangup))  # fmt: skip
    deadline = time.monotonic() + 60
    while not list(tmp_path.glob(f"{command[0]}__*")) and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(1.0)
    return process


def test_sigterm_stops_a_drive_cleanly(tmp_path):
    process = started_session(["baseline", "--steps", "2000"], tmp_path)
    process.send_signal(signal.SIGTERM)
    stdout, stderr = process.communicate(timeout=30)
    assert process.returncode == 0, stderr
    steps = int(stdout.split("baseline: ")[1].split(" steps")[0])
    assert 0 < steps < 2000  # stopped early, and still reported


HUNG_UP_TRAINING = ["train", "--total-steps", "3000", "--train-every", "200", "--gradient-steps", "2", *FAST]  # hung up long before its end


def test_a_hang_up_stops_training_and_saves_the_state_where_it_stopped(tmp_path):
    """A dropped ssh session sends SIGHUP: the car is e-stopped and the state saved, as on SIGTERM; it
    used to end the process at once, with the steps since the last pause lost."""
    state = tmp_path / "t.pt"
    process = started_session([*HUNG_UP_TRAINING, "--checkpoint", str(state)], tmp_path, signal.SIG_DFL)
    process.send_signal(signal.SIGHUP)
    stdout, stderr = process.communicate(timeout=60)
    assert process.returncode == 0, stderr
    steps = int(stdout.split("train: step ")[1].split(",")[0])
    assert 0 < steps < 3000
    assert torch.load(state, weights_only=True)["counters"]["step"] == steps  # saved at the stop, not at the last pause


@pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="no hang-up on Windows")
def test_a_terminal_that_hangs_up_ends_training_with_its_state_saved_and_status_0(tmp_path):
    """The same on a real terminal: its last lines ("train: step ...") find it gone (EIO) and go on in
    the session's log folder, in stdout.log. They used to raise there, after the save: exit status 1
    and a traceback nobody saw."""
    state = tmp_path / "t.pt"
    terminal, car_side = pty.openpty()
    process = subprocess.Popen([sys.executable, "-m", "deploy.jetracer", *HUNG_UP_TRAINING, "--checkpoint", str(state), "--log-dir", str(tmp_path)], cwd=ROOT,
                               stdin=car_side, stdout=car_side, stderr=car_side, start_new_session=True, preexec_fn=on_a_terminal)  # fmt: skip
    os.close(car_side)
    shown, deadline = b"", time.monotonic() + 60
    try:
        while time.monotonic() < deadline and not list(tmp_path.glob("train__*")):  # read as a terminal does, until the session is up
            if select.select([terminal], [], [], 0.1)[0]:
                shown += os.read(terminal, 4096)
        time.sleep(1.0)
    finally:
        os.close(terminal)  # the hang-up
    assert process.wait(timeout=60) == 0, shown.decode(errors="replace")
    steps = torch.load(state, weights_only=True)["counters"]["step"]
    assert 0 < steps < 3000
    (session,) = tmp_path.glob("train__*")
    kept = (session / "stdout.log").read_text()
    assert re.match(LOST_HEADER.replace("(terminal|pipe)", "terminal").replace("(stdout|stderr)", "stdout"), kept)
    assert f"\ntrain: step {steps}, " in kept


def test_a_run_started_with_nohup_drives_on_after_a_hang_up(tmp_path):
    process = started_session(["baseline", "--steps", "60"], tmp_path, signal.SIG_IGN)
    process.send_signal(signal.SIGHUP)
    stdout, stderr = process.communicate(timeout=60)
    assert process.returncode == 0, stderr
    assert "baseline: 60 steps" in stdout


def test_train_refuses_the_episode_based_schedule(tmp_path):
    assert jetracer.car_jirl_defaults().guidance_schedule == "geometric"
    args = ["train", "--total-steps", "10", "--jirl.guidance-schedule", "earned", "--checkpoint", str(tmp_path / "t.pt"), "--log-dir", str(tmp_path)]
    out = warm_python.run(["-m", "deploy.jetracer", *args], cwd=ROOT, timeout=60)
    assert out.returncode != 0 and "geometric or linear on the car" in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "t.pt").exists()


@pytest.mark.parametrize(
    "options, message",
    [
        (["--jirl.seed", "7"], "--jirl.seed (use --seed)"),
        (["--jirl.total-timesteps", "500", "--jirl.guidance-fade-steps", "100"],
         "--jirl.total-timesteps (use --total-steps); --jirl.guidance-fade-steps (the car keeps every fabricated transition)"),
        (["--jirl.intervention-mode"], "--jirl.intervention-mode (the gamepad's takeover intervenes)"),
        (["--jirl.track", "--jirl.wandb-project-name", "car"],
         "--jirl.track (the car logs to TensorBoard under --log-dir); --jirl.wandb-project-name (no --track on the car)"),
    ],
)  # fmt: skip
def test_train_refuses_jirl_options_that_the_car_does_not_use(tmp_path, options, message):
    with pytest.raises(SystemExit, match=f"^train: error: no effect on the car: {re.escape(message)}$"):
        jetracer.main(["train", "--total-steps", "10", "--checkpoint", str(tmp_path / "t.pt"), "--log-dir", str(tmp_path), *options])
    assert not list(tmp_path.iterdir())  # nothing written, the car never armed
    assert set(jetracer.CAR_IGNORES) <= set(vars(jetracer.car_jirl_defaults()))  # every name is a --jirl option


def test_trains_help_says_which_jirl_options_have_no_effect_on_the_car(capsys):
    """`train --help` lists every field of jirl.Args under --jirl., each with the script's default; those the car
    refuses (any value but the default) and the schedules it takes say so there, not only when the car refuses them."""
    import jirl_sac_continuous as jirl

    with pytest.raises(SystemExit):
        jetracer.main(["train", "--help"])
    text = " ".join(capsys.readouterr().out.replace("│", " ").split())
    for name, why in jetracer.CAR_IGNORES.items():
        assert re.search(rf"--jirl\.{name.replace('_', '-')}[ ,].{{0,60}} no effect on the car: {re.escape(why)} \(default:", text), name
    assert "geometric or linear on the car: guidance by time, as its laps are no episodes to compare (default: geometric)" in text
    assert "the gate's scaling factor C (Alg. 3)" in text, "the options the car uses keep the script's help"
    script, car = dataclasses.fields(jirl.Args), dataclasses.fields(jetracer.CarJirlArgs)
    assert [f.name for f in car] == [f.name for f in script]  # the same options, in the same order
    assert dataclasses.asdict(jetracer.CarJirlArgs()) == dataclasses.asdict(jirl.Args()), "and the same defaults"


@pytest.mark.parametrize("deterministic", [False, True])
def test_train_acts_with_the_mean_after_guidance_when_asked(tmp_path, monkeypatch, deterministic):
    observed, applied, logged = [], [], []
    real_observe, real_act, real_decide = jetracer.CarSession.observe, jetracer.CarSession.act, jetracer.jirl.Gate.decide
    monkeypatch.setattr(jetracer.CarSession, "observe", lambda self: observed.append(real_observe(self)) or observed[-1])
    # the agent also acts at steps 30-39, while C > 0: there it samples, flag or not
    monkeypatch.setattr(jetracer.jirl.Gate, "decide", lambda self, *terms: real_decide(self, *terms) or 30 <= len(observed) - 1 < 40)
    monkeypatch.setattr(jetracer.CarSession, "act", lambda self, action: applied.append((observed[-1], action)) or real_act(self, action))
    monkeypatch.setattr(jetracer.CarSession, "log", lambda self, step: logged.append(step))
    args = ["train", "--total-steps", "120", "--jirl.guidance-steps", "60", "--jirl.learning-starts", "1000", "--jirl.hidden-size", "16",
            "--jirl.log-every", "25", "--checkpoint", str(tmp_path / "t.pt"), "--log-dir", str(tmp_path)]  # fmt: skip
    jetracer.main(args + (["--jirl.deterministic-after-guidance"] if deterministic else []))
    hp = jetracer.car_jirl_defaults()
    hp.hidden_size = 16
    torch.manual_seed(0)  # train's --seed: no update ran, so the agent is the one it started with
    actor = jetracer.jirl.SoftActorCritic(jetracer.OBS_SIZE, 2, hp).actor
    for steps, mean_applied in ((slice(60, 120), deterministic), (slice(30, 40), False)):  # C = 0 from step 60: the agent acts at every step
        with torch.no_grad():
            means = torch.tanh(actor(torch.from_numpy(np.stack([obs for obs, _ in applied[steps]])))[0]).numpy()
        actions = np.stack([action for _, action in applied[steps]])
        assert np.isclose(actions, means, atol=1e-6).all(1).tolist() == [mean_applied] * len(actions)  # else sampled around the mean
    assert [step for step in logged if step < 120] == [0, 25, 50, 75, 100]  # --jirl.log-every is the car's too


def test_train_hands_over_within_its_own_total_steps_and_a_resume_keeps_that_horizon(tmp_path, monkeypatch, capsys):
    horizons = []
    real_guidance_c = jetracer.jirl.guidance_c
    monkeypatch.setattr(jetracer.jirl, "guidance_c", lambda c, step, horizon, schedule: horizons.append(horizon) or real_guidance_c(c, step, horizon, schedule))
    state = tmp_path / "t.pt"
    common = ["--checkpoint", str(state), "--log-dir", str(tmp_path), "--jirl.learning-starts", "1000", "--jirl.hidden-size", "16"]

    def train(*options: str) -> set:
        horizons.clear()
        jetracer.main(["train", *common, *options])
        assert torch.load(state, weights_only=True)["guidance_steps"] == horizons[-1], "saved with the state"
        return set(horizons)

    assert train("--total-steps", "40") == {20}  # half of this training's steps (it was 27,000 whatever the length)
    assert train("--resume", "--total-steps", "100") == {20}, "a longer resume keeps the horizon the training started with"
    assert "replaces" not in capsys.readouterr().out
    assert train("--resume", "--total-steps", "120", "--jirl.guidance-steps", "30") == {30}  # one given is used, and said
    assert "resume: --jirl.guidance-steps 30 replaces the training's 20" in capsys.readouterr().out
    saved = torch.load(state, weights_only=True)
    torch.save({key: value for key, value in saved.items() if key != "guidance_steps"}, state)  # as saved before the horizon was
    assert train("--resume", "--total-steps", "140") == {70}
    for damaged in (-5, 2.5, True):  # True is an int to Python, but no horizon
        torch.save({**saved, "guidance_steps": damaged}, state)
        with pytest.raises(SystemExit, match=f"is a damaged jirl-car-training-v2 file: its guidance_steps is {damaged}$"):
            jetracer.main(["train", *common, "--resume", "--total-steps", "160"])
        kept = torch.load(state, weights_only=True)["guidance_steps"]
        assert kept == damaged and type(kept) is type(damaged), "left as it was"


@pytest.mark.parametrize(
    "option, message",
    [
        (["--camera", "file:no_such_video.mp4"], "baseline: error: cannot open camera 'no_such_video.mp4'"),
        (["--camera", "file:{tmp}/empty.avi"], "baseline: error: camera '{tmp}/empty.avi' gave no frame: an empty video, or one in a codec this OpenCV cannot decode"),
        (["--camera", "usb:left"], "usb:N takes a device number N"),
        (["--camera", "usb:63"], "baseline: error: cannot open camera 63: there is no /dev/video63 (`ls /dev/video*` lists the cameras Linux sees)"),
        (["--camera", "webcam"], "baseline: error: unknown camera 'webcam': use csi, usb:N, file:PATH or sim"),
        (["--gamepad", "/dev/input/no_such_js"], "cannot open gamepad '/dev/input/no_such_js': No such file or directory"),
        (["--gamepad", "/dev/null"], "baseline: error: '/dev/null' is not a joystick device (/dev/input/jsN)"),
        (["--gamepad", "README.md"], "baseline: error: 'README.md' is not a joystick device (/dev/input/jsN)"),
        (["--port", "/dev/no_such_tty"], "baseline: error: cannot open the motor controller"),
    ],
)
def test_missing_hardware_is_a_one_line_error_before_the_car_is_armed(tmp_path, option, message):
    if "file:{tmp}/empty.avi" in option:  # a video that opens and has no frame
        import cv2

        cv2.VideoWriter(str(tmp_path / "empty.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 20, (FRAME_SHAPE[1], FRAME_SHAPE[0])).release()
    option, message = [part.format(tmp=tmp_path) for part in option], message.format(tmp=tmp_path)
    args = ["baseline", "--steps", "5", "--log-dir", str(tmp_path / "runs"), *option]
    out = warm_python.run(["-m", "deploy.jetracer", *args], cwd=ROOT, timeout=60)
    assert out.returncode != 0 and message in out.stderr.strip().splitlines()[-1], out.stderr  # above it, pybullet's banner
    assert "Traceback" not in out.stderr, out.stderr
    assert not (tmp_path / "runs").exists()


def test_a_serial_port_the_user_may_not_open_says_what_gives_access(tmp_path, monkeypatch):
    """On a fresh Jetson the port belongs to the dialout group, which the user is not in: pyserial's EACCES is
    named with the remedy. A port that is not there gets no such advice."""
    import serial

    def refused(url, **_):
        raise serial.SerialException(errno.EACCES, f"could not open port {url}: [Errno 13] Permission denied: '{url}'")

    monkeypatch.setattr(serial, "serial_for_url", refused)
    with pytest.raises(SystemExit) as exit_info:
        jetracer.baseline(jetracer.Baseline(steps=5, port="/dev/ttyACM0", log_dir=str(tmp_path)))
    assert str(exit_info.value) == ("baseline: error: cannot open the motor controller: [Errno 13] could not open port /dev/ttyACM0: [Errno 13]"
                                    " Permission denied: '/dev/ttyACM0'; the user needs read-write access to it (on Linux: sudo usermod -aG dialout $USER,"
                                    " then log in again)")
    monkeypatch.undo()
    with pytest.raises(SystemExit) as exit_info:
        jetracer.baseline(jetracer.Baseline(steps=5, port="/dev/no_such_tty", log_dir=str(tmp_path)))
    assert "No such file or directory" in str(exit_info.value) and "dialout" not in str(exit_info.value)
    assert not list(tmp_path.iterdir()), "no session folder for a car that never armed"


def test_a_session_puts_the_signal_handlers_back_when_it_closes(tmp_path):
    def mine(*_):
        pass

    previous = {sig: signal.signal(sig, mine) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        jetracer.baseline(jetracer.Baseline(steps=5, log_dir=str(tmp_path)))
        with pytest.raises(SystemExit, match="cannot open the motor controller"):
            jetracer.baseline(jetracer.Baseline(steps=5, port="/dev/no_such_tty", log_dir=str(tmp_path)))
        assert all(signal.getsignal(sig) is mine for sig in previous)  # not a closed session's e-stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def test_resuming_into_another_buffer_size_keeps_the_newest_transitions_in_order(tmp_path, capsys):
    hp = jetracer.car_jirl_defaults()
    hp.hidden_size = 8
    args = jetracer.Train(jirl=hp)
    sac = jetracer.jirl.SoftActorCritic(jetracer.OBS_SIZE, 2, hp)
    rb = jetracer.jirl.ReplayBuffer(5, jetracer.OBS_SIZE, 2, seed=0)
    obs = lambda i: np.full(jetracer.OBS_SIZE, float(i), dtype=np.float32)  # noqa: E731 (row i is marked by i)
    for i in range(7):  # wraps: rows 5 and 6 overwrite 0 and 1, the next write goes to row 2
        rb.add(obs(i), np.zeros(2), float(i), obs(i + 1), False)
    path = str(tmp_path / "state.pt")
    jetracer.save_training_state(path, sac, rb, dict(jetracer.TRAIN_COUNTERS, step=7), args)
    for capacity, newest in ((10, [2, 3, 4, 5, 6]), (5, [2, 3, 4, 5, 6]), (3, [4, 5, 6])):
        loaded = jetracer.jirl.ReplayBuffer(capacity, jetracer.OBS_SIZE, 2, seed=0)
        jetracer.load_training_state(path, jetracer.jirl.SoftActorCritic(jetracer.OBS_SIZE, 2, hp), loaded)
        assert loaded.size == len(newest) and loaded.pos == len(newest) % capacity
        assert loaded.rewards[: loaded.size, 0].tolist() == newest  # oldest first
        loaded.add(obs(7), np.zeros(2), 7.0, obs(8), False)  # the next write replaces the oldest once full
        expected = newest + [7] if len(newest) < capacity else newest[1:] + [7]
        assert sorted(loaded.rewards[: loaded.size, 0].tolist()) == expected
        dropped = capacity < 5  # said: a smaller buffer forgets the oldest transitions
        assert capsys.readouterr().out == (f"resume: --jirl.buffer-size {capacity} keeps the newest 3 of the 5 saved transitions\n" if dropped else "")
    hp.hidden_size = 16
    with pytest.raises(ValueError, match="holds an agent of 8 units, not --jirl.hidden-size 16"):
        jetracer.load_training_state(path, jetracer.jirl.SoftActorCritic(jetracer.OBS_SIZE, 2, hp), loaded)


COUNTER_DAMAGE = {"a count as text": ("step", "5"), "a count as a bool": ("fabricated_transitions", True), "a count as a float": ("updates", 3.0),
                  "a negative count": ("control_switches", -1), "a NaN regret sum": ("baseline_regret_per_step", float("nan")),
                  "an infinite regret sum": ("paired_regret_per_step", float("inf")), "a negative regret sum": ("baseline_regret_per_step", -0.5)}  # fmt: skip


def damage(state: dict, part: str) -> dict:
    """A copy of a training state with one part removed, made the wrong shape, or given a value no training writes."""
    state = {**state, "sac": dict(state["sac"]), "buffer": dict(state["buffer"]), "counters": dict(state["counters"])}
    if part == "counter":
        del state["counters"]["updates"]
    elif part == "buffer":
        del state["buffer"]["rewards"]
    elif part == "entropy":
        del state["sac"]["log_alpha"]
    elif part == "actions":
        state["buffer"]["actions"] = torch.zeros(len(state["buffer"]["obs"]), 3)
    elif part == "buffer table":  # a tensor where the columns' table belongs
        state["buffer"] = torch.zeros(3)
    elif part == "critic":
        state["sac"]["qf"] = {k: v[..., :-1] for k, v in state["sac"]["qf"].items()}
    elif part == "NaN weight":
        state["sac"]["actor"] = {k: v * float("nan") if k.endswith(".bias") else v for k, v in state["sac"]["actor"].items()}
    elif part == "infinite moment":  # deep in the critics' optimizer state, where a resumed Adam would spread it
        optimizer = state["sac"]["q_optimizer"]
        state["sac"]["q_optimizer"] = {**optimizer, "state": {i: {k: v * float("inf") if k == "exp_avg" else v for k, v in moments.items()} for i, moments in optimizer["state"].items()}}
    elif part in COUNTER_DAMAGE:
        key, value = COUNTER_DAMAGE[part]
        state["counters"][key] = value
    elif part.startswith("buffer_pos "):
        state["buffer_pos"] = {"5": 5, "-1": -1, "True": True}[part.split()[1]]  # True would roll by -1 as an int
    elif part == "NaN reward":
        state["buffer"]["rewards"] = state["buffer"]["rewards"].clone()
        state["buffer"]["rewards"][-1] = float("nan")
    return state


@pytest.mark.parametrize("part, message", [
    ("counter", "it has no counter updates$"), ("buffer", "it has no buffer rewards$"),
    ("buffer table", "it has no buffer obs, buffer next_obs, buffer actions, buffer rewards, buffer terminations$"), ("entropy", r"\(KeyError: 'log_alpha'\)"),
    ("actions", r"\(ValueError: could not broadcast"), ("critic", r"\(RuntimeError: Error\(s\) in loading state_dict"),
    ("NaN weight", ": its agent holds a NaN or infinite value$"), ("infinite moment", ": its agent holds a NaN or infinite value$"),
    ("NaN reward", ": its replay buffer holds a NaN or infinite value$"),
    ("buffer_pos 5", r"\(ValueError: its buffer_pos 5 is not a row of its 4 or the next\)$"),
    ("buffer_pos -1", r"\(ValueError: its buffer_pos -1 is not a row of its 4 or the next\)$"),
    ("buffer_pos True", r"\(ValueError: its buffer_pos True is not a row of its 4 or the next\)$"),
    *[(part, f": its counter {key} is {value!r}$") for part, (key, value) in COUNTER_DAMAGE.items()],
])  # fmt: skip
def test_a_damaged_training_state_is_named_and_kept(tmp_path, part, message):
    hp = jetracer.car_jirl_defaults()
    hp.hidden_size = 8
    path = tmp_path / "state.pt"
    rb = jetracer.jirl.ReplayBuffer(10, jetracer.OBS_SIZE, 2, seed=0)
    for i in range(4):
        rb.add(np.zeros(jetracer.OBS_SIZE), np.zeros(2), float(i), np.zeros(jetracer.OBS_SIZE), False)
    args = jetracer.Train(jirl=hp, checkpoint=str(path), resume=True, log_dir=str(tmp_path))
    sac = jetracer.jirl.SoftActorCritic(jetracer.OBS_SIZE, 2, hp)
    sac.update(rb.sample(4), 1)  # the optimizers hold moments to damage
    jetracer.save_training_state(str(path), sac, rb, dict(jetracer.TRAIN_COUNTERS), args)
    torch.save(damage(torch.load(path, weights_only=True), part), path)
    written = path.read_bytes()
    with pytest.raises(ValueError, match="state.pt is a damaged jirl-car-training-v2 file.*" + message) as raised:
        jetracer.load_training_state(str(path), jetracer.jirl.SoftActorCritic(jetracer.OBS_SIZE, 2, hp), rb)
    assert "\n" not in str(raised.value), "one line: torch's message for the critic runs over several"
    with pytest.raises(SystemExit, match="^train: error: .*damaged"):  # before the car is armed or anything is written
        jetracer.train(args)
    assert path.read_bytes() == written


def test_sessions_started_in_the_same_second_log_to_directories_of_their_own(tmp_path, monkeypatch):
    monkeypatch.setattr(jetracer.time, "time", lambda: 1_800_000_000.0)  # every session starts in this second
    log_dirs = []
    for _ in range(3):
        session = jetracer.CarSession(jetracer.Baseline(log_dir=str(tmp_path / "logs")), "train")
        log_dirs.append(session.writer.log_dir)
        session.close()
    assert [Path(d).name for d in log_dirs] == ["train__1800000000", "train__1800000000_2", "train__1800000000_3"]
    assert sorted(p.name for p in (tmp_path / "logs").iterdir()) == sorted(Path(d).name for d in log_dirs)
    monkeypatch.chdir(tmp_path)
    assert jetracer.claim_log_dir("", "train__1") == "train__1" and (tmp_path / "train__1").is_dir()  # "": the current directory


def test_a_fresh_run_never_overwrites_the_checkpoint_another_run_created_as_it_started(tmp_path, monkeypatch):
    path = tmp_path / "train.pt"
    path.write_bytes(b"the other run's first save")
    real_exists = jetracer.os.path.exists
    # the other run saves between this run's check and its first save: the check sees nothing
    monkeypatch.setattr(jetracer.os.path, "exists", lambda p: False if str(p) == str(path) else real_exists(p))
    hp = jetracer.car_jirl_defaults()
    hp.hidden_size = 8
    with pytest.raises(SystemExit, match=f"^train: error: another run created {re.escape(str(path))} as this one started; pass another --checkpoint$"):
        jetracer.train(jetracer.Train(jirl=hp, checkpoint=str(path), total_steps=50, log_dir=str(tmp_path / "logs")))
    assert path.read_bytes() == b"the other run's first save"
    # no temporary file left, the car never armed: no logs (the lock file goes with the state this test hides)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["train.pt"]


def test_a_training_in_progress_holds_its_checkpoint_against_a_second_one(tmp_path):
    state = tmp_path / "train.pt"

    def train(*extra, steps):
        return warm_python.run(["-m", "deploy.jetracer", "train", "--total-steps", str(steps), "--checkpoint", str(state),
                               "--log-dir", str(tmp_path / "logs"), *FAST, *extra], cwd=ROOT, timeout=120)  # fmt: skip

    assert train(steps=20).returncode == 0
    saved = state.read_bytes()
    with jetracer.holding(str(state)):  # as a training resumed from it on another car holds it
        for extra in (["--resume"], []):
            out = train(*extra, steps=40)
            assert out.returncode != 0 and "Traceback" not in out.stderr, out.stderr
            assert out.stderr.strip().splitlines()[-1] == (f"train: error: another training is using --checkpoint {state} (it holds {state}.lock);"
                                                           " wait for it to end, or pass another --checkpoint")  # fmt: skip
        with pytest.raises(SystemExit, match="another training is using"):  # a second holder in this process too
            with jetracer.holding(str(state)):
                pass
    assert state.read_bytes() == saved and len(list((tmp_path / "logs").iterdir())) == 1  # the car never armed for the refused ones
    fresh = tmp_path / "fresh.pt"  # no state yet: three fresh trainings started together on one checkpoint
    with jetracer.holding(str(fresh)):
        out = warm_python.run(["-m", "deploy.jetracer", "train", "--checkpoint", str(fresh), "--log-dir", str(tmp_path / "logs")],
                              cwd=ROOT, timeout=120)  # fmt: skip
        assert "another training is using" in out.stderr, out.stderr
        # the refused run leaves the holder's lock file: removed, the third would lock a new file beside it and run too
        with pytest.raises(SystemExit, match="another training is using"):
            with jetracer.holding(str(fresh)):
                pass
    assert not Path(f"{fresh}.lock").exists()  # the holder, with no state, leaves no lock file
    out = train("--resume", steps=40)  # released: the training goes on
    assert out.returncode == 0, out.stderr
    assert torch.load(state, weights_only=True)["counters"]["step"] == 40


def test_a_checkpoint_on_a_file_system_without_locks_still_trains_with_a_warning(tmp_path, monkeypatch, capsys):
    import errno
    import fcntl

    def no_locks(fd, operation):  # some network and FUSE file systems: not "another training holds it"
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_locks)
    with jetracer.holding(str(tmp_path / "train.pt")):
        assert (tmp_path / "train.pt.lock").exists()
    assert "train: warning: cannot lock" in capsys.readouterr().err and not (tmp_path / "train.pt.lock").exists()  # no state: no lock file


def test_resuming_from_the_policy_names_the_training_state_beside_it(tmp_path):
    hp = jetracer.car_jirl_defaults()
    hp.hidden_size = 8
    state = tmp_path / "train.pt"
    sac, rb = jetracer.jirl.SoftActorCritic(jetracer.OBS_SIZE, 2, hp), jetracer.jirl.ReplayBuffer(10, jetracer.OBS_SIZE, 2, seed=0)
    jetracer.save_training_state(str(state), sac, rb, dict(jetracer.TRAIN_COUNTERS, step=3), jetracer.Train(jirl=hp, checkpoint=str(state)))
    policy = jetracer.policy_path(str(state))
    with pytest.raises(SystemExit) as raised:  # before: "... is not a jirl-car-training-v2 file"
        jetracer.train(jetracer.Train(jirl=hp, checkpoint=policy, resume=True, total_steps=50, log_dir=str(tmp_path / "logs")))
    assert str(raised.value) == (f"train: error: {policy} is a policy (jirl-sac-checkpoint-v2), not a jirl-car-training-v2 training state;"
                                 f" resume from the training state {state}")  # fmt: skip
    assert torch.load(state, weights_only=True)["counters"]["step"] == 3 and not (tmp_path / "logs").exists()
    assert not Path(jetracer.lock_path(policy)).exists()  # no training state there: no lock file left beside the policy


def test_a_resume_that_finds_no_training_state_leaves_no_lock_file_and_a_state_keeps_its_own(tmp_path):
    hp = jetracer.car_jirl_defaults()
    hp.hidden_size = 8
    notes = tmp_path / "notes.txt"
    notes.write_text("not a training state")
    state = tmp_path / "train.pt"
    sac, rb = jetracer.jirl.SoftActorCritic(jetracer.OBS_SIZE, 2, hp), jetracer.jirl.ReplayBuffer(10, jetracer.OBS_SIZE, 2, seed=0)
    jetracer.save_training_state(str(state), sac, rb, dict(jetracer.TRAIN_COUNTERS, step=3), jetracer.Train(jirl=hp, checkpoint=str(state)))
    wider = jetracer.car_jirl_defaults()
    wider.hidden_size = 16  # a real state, read by a run with other settings
    other = tmp_path / "other.pt"
    torch.save({"format": "jirl-gaussian-checkpoint-v1"}, other)  # a readable file of another kind: PPO+IL's policy
    for path, settings, message in ((notes, hp, "is not a readable training state"), (state, wider, "holds an agent of 8 units"),
                                    (other, hp, f"^train: error: {re.escape(str(other))} is not a jirl-car-training-v2 file$")):  # fmt: skip
        with pytest.raises(SystemExit, match=message):
            jetracer.train(jetracer.Train(jirl=settings, checkpoint=str(path), resume=True, total_steps=50, log_dir=str(tmp_path / "logs")))
    assert notes.read_text() == "not a training state" and not Path(jetracer.lock_path(str(notes))).exists()  # before: notes.txt.lock stayed
    assert torch.load(other, weights_only=True) == {"format": "jirl-gaussian-checkpoint-v1"} and not Path(jetracer.lock_path(str(other))).exists()
    assert Path(jetracer.lock_path(str(state))).exists()  # beside a state the lock file stays, as after any run on it
    assert torch.load(state, weights_only=True)["counters"]["step"] == 3 and not (tmp_path / "logs").exists()


def test_a_replay_buffer_too_large_for_memory_ends_training_in_one_line_and_leaves_nothing(tmp_path):
    hp = jetracer.car_jirl_defaults()
    hp.buffer_size = 10**13  # a zero or six too many: beyond any address space
    with pytest.raises(SystemExit) as raised:  # before: numpy's MemoryError traceback
        jetracer.train(jetracer.Train(jirl=hp, checkpoint=str(tmp_path / "train.pt"), log_dir=str(tmp_path / "logs")))
    assert str(raised.value).startswith("train: error: --jirl.buffer-size 10000000000000: a replay buffer of 10,000,000,000,000 transitions (")
    assert str(raised.value).endswith(" GiB) does not fit in memory") and list(tmp_path.iterdir()) == []


def test_a_save_writes_through_a_temporary_file_of_its_own(tmp_path):
    hp = jetracer.car_jirl_defaults()
    hp.hidden_size = 8
    path = tmp_path / "train.pt"
    for other in (f"{path}.tmp", f"{path}.actor.cleanrl_model.tmp"):  # what another process could be writing
        Path(other).write_bytes(b"another process's half-written file")
    sac, rb = jetracer.jirl.SoftActorCritic(jetracer.OBS_SIZE, 2, hp), jetracer.jirl.ReplayBuffer(10, jetracer.OBS_SIZE, 2, seed=0)
    args = jetracer.Train(jirl=hp, checkpoint=str(path))
    jetracer.save_training_state(str(path), sac, rb, dict(jetracer.TRAIN_COUNTERS, step=3), args, create=True)
    assert torch.load(path, weights_only=True)["counters"]["step"] == 3
    assert jetracer.jirl.load_checkpoint(jetracer.policy_path(str(path)))["hidden_size"] == 8
    for other in (f"{path}.tmp", f"{path}.actor.cleanrl_model.tmp"):
        assert Path(other).read_bytes() == b"another process's half-written file"
    assert len(list(tmp_path.iterdir())) == 4  # the two files above, the state and its policy: nothing else left
    with pytest.raises(jetracer.CheckpointTaken):  # a fresh run's first save never replaces a file
        jetracer.save_training_state(str(path), sac, rb, dict(jetracer.TRAIN_COUNTERS, step=5), args, create=True)
    assert torch.load(path, weights_only=True)["counters"]["step"] == 3 and len(list(tmp_path.iterdir())) == 4

    def half_write(tmp):  # a disk that fills up halfway
        Path(tmp).write_bytes(b"half")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space left"):
        jetracer.write_atomically(str(path), half_write)
    assert torch.load(path, weights_only=True)["counters"]["step"] == 3 and len(list(tmp_path.iterdir())) == 4


@pytest.mark.parametrize("log_dir", ["afile", "afile/runs"])
def test_a_log_dir_that_cannot_be_made_is_a_one_line_error_before_the_car_is_armed(tmp_path, log_dir):
    (tmp_path / "afile").write_text("a user's file")
    args = ["baseline", "--steps", "5", "--log-dir", str(tmp_path / log_dir)]
    out = warm_python.run(["-m", "deploy.jetracer", *args], cwd=ROOT, timeout=60)
    assert out.returncode != 0 and "Traceback" not in out.stderr, out.stderr
    assert out.stderr.strip().splitlines()[-1] == f"baseline: error: cannot log to --log-dir {tmp_path / log_dir}: {tmp_path / 'afile'} is not a directory"
    assert (tmp_path / "afile").read_text() == "a user's file"


def test_a_log_dir_is_checked_where_it_would_be_made(tmp_path, monkeypatch):
    """The nearest part of --log-dir that exists must be a directory this process can write in and enter."""
    assert jetracer.log_dir_problem(str(tmp_path / "runs" / "car")) is None
    (tmp_path / "afile").write_text("")
    assert jetracer.log_dir_problem(str(tmp_path / "afile" / "runs")) == f"{tmp_path / 'afile'} is not a directory"
    asked = []
    for denied in (os.W_OK, os.X_OK):  # root passes both checks on any mode: ask os.access through a stand-in
        monkeypatch.setattr(jetracer.os, "access", lambda path, mode: asked.append(path) or not mode & denied)
        assert jetracer.log_dir_problem(str(tmp_path / "runs" / "car")) == f"{tmp_path} is not writable"
    assert asked == [str(tmp_path)] * 2


def test_a_log_dir_lost_as_the_car_arms_stops_the_car_with_one_line(tmp_path, monkeypatch):
    def gone(log_dir, name):
        raise PermissionError(13, "Permission denied", log_dir)

    monkeypatch.setattr(jetracer, "claim_log_dir", gone)
    controllers = record_closed_controllers(monkeypatch)
    with pytest.raises(SystemExit, match=r"^baseline: error: cannot log to --log-dir .*Permission denied"):
        jetracer.CarSession(jetracer.Baseline(log_dir=str(tmp_path / "runs")), "baseline")
    assert controllers[0].throttle == 0.0 and controllers[0].estop_latched  # closed: STOP, ESTOP


def test_a_training_whose_car_never_armed_leaves_no_state_that_blocks_the_rerun(tmp_path):
    def train(*extra, steps=20):
        return warm_python.run(["-m", "deploy.jetracer", "train", "--total-steps", str(steps), "--checkpoint", str(state),
                               "--log-dir", str(tmp_path / "logs"), *FAST, *extra], cwd=ROOT, timeout=120)  # fmt: skip

    state = tmp_path / "train.pt"
    out = train("--resume")  # nothing to resume yet
    assert out.returncode != 0 and "No such file or directory" in out.stderr and list(tmp_path.iterdir()) == []  # not even a lock file
    assert "not a readable training state" not in out.stderr  # a missing file is not a damaged one
    out = train("--camera", "webcam")  # a typo: the car never arms
    assert out.returncode != 0 and out.stderr.strip().splitlines()[-1] == "train: error: unknown camera 'webcam': use csi, usb:N, file:PATH or sim"
    assert list(tmp_path.iterdir()) == []  # not the step-0 state a rerun would refuse as "an earlier training"
    out = train()  # the corrected command
    assert out.returncode == 0, out.stderr
    assert torch.load(state, weights_only=True)["counters"]["step"] == 20
    out = train("--resume", "--camera", "webcam", steps=40)  # a resumed training keeps its state
    assert out.returncode != 0 and "unknown camera 'webcam'" in out.stderr
    assert torch.load(state, weights_only=True)["counters"]["step"] == 20 and Path(jetracer.policy_path(str(state))).exists()
