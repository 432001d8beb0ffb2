"""JetRacerTrack-v0: track geometry, laps, termination, determinism, the camera pipeline and its baseline."""

import math
import tempfile

import cv2
import numpy as np
import pytest

from envs import get_baseline, make_env
from envs.car_interface import MASK_SHAPE, OBS_SIZE, ActionMapping, action_to_commands, preprocess
from envs.jetracer_track import JetRacerTrackEnv
from envs.lane_follower import KD, KP, THROTTLE_ACTION, LaneFollower
from envs.track import TrackSpec


def centre_line_points(track: TrackSpec, step: float = 0.001) -> np.ndarray:
    """(x, y, s) along the counter-clockwise centre line, built from its four pieces independently of TrackSpec."""
    half, r = track.straight_length / 2, track.radius
    pieces, s0 = [], 0.0
    for x0, x1, y in ((0.0, half, -r),):
        xs = np.arange(x0, x1, step)
        pieces.append(np.stack([xs, np.full_like(xs, y), s0 + xs - x0], 1))
    s0 += half
    phis = np.arange(-math.pi / 2, math.pi / 2, step / r)
    pieces.append(np.stack([half + r * np.cos(phis), r * np.sin(phis), s0 + r * (phis + math.pi / 2)], 1))
    s0 += math.pi * r
    xs = np.arange(half, -half, -step)
    pieces.append(np.stack([xs, np.full_like(xs, r), s0 + half - xs], 1))
    s0 += 2 * half
    phis = np.arange(math.pi / 2, 3 * math.pi / 2, step / r)
    pieces.append(np.stack([-half + r * np.cos(phis), r * np.sin(phis), s0 + r * (phis - math.pi / 2)], 1))
    s0 += math.pi * r
    xs = np.arange(-half, 0.0, step)
    pieces.append(np.stack([xs, np.full_like(xs, -r), s0 + xs + half], 1))
    return np.concatenate(pieces)


@pytest.mark.parametrize("clockwise", [False, True])
def test_projection_matches_a_brute_force_nearest_point(clockwise):
    track = TrackSpec(straight_length=1.5, radius=0.8, clockwise=clockwise)
    points = centre_line_points(track)
    if clockwise:  # the mirror image in y, travelled the other way round
        points = points * [1, -1, 1]
    rng = np.random.default_rng(0)
    for _ in range(300):
        x, y, _ = points[rng.integers(len(points))]
        x, y = x + rng.uniform(-0.3, 0.3), y + rng.uniform(-0.3, 0.3)
        d = np.hypot(points[:, 0] - x, points[:, 1] - y)
        i = int(np.argmin(d))
        s, cte, _ = track.project(x, y)
        assert abs(cte) == pytest.approx(d[i], abs=2e-3)
        assert abs(track.progress(points[i, 2], s)) < 5e-3


@pytest.mark.parametrize("clockwise", [False, True])
def test_pose_and_projection_are_inverse_and_the_left_is_positive(clockwise):
    track = TrackSpec(clockwise=clockwise)
    for s in np.linspace(0, track.length, 97, endpoint=False):
        x, y, heading = track.pose_at(s)
        s2, cte, heading2 = track.project(x, y)
        assert track.progress(s, s2) == pytest.approx(0.0, abs=1e-9) and cte == pytest.approx(0.0, abs=1e-9)
        assert math.cos(heading - heading2) == pytest.approx(1.0)
        left = (x - 0.1 * math.sin(heading), y + 0.1 * math.cos(heading))
        assert track.project(*left)[1] == pytest.approx(0.1, abs=1e-9)
    assert track.pose_at(0.0)[:2] == pytest.approx((0.0, 1.0 if clockwise else -1.0))


def test_progress_wraps_across_the_start_line():
    track = TrackSpec()
    assert track.progress(track.length - 0.1, 0.1) == pytest.approx(0.2)
    assert track.progress(0.1, track.length - 0.1) == pytest.approx(-0.2)
    with pytest.raises(ValueError, match="impossible track"):
        TrackSpec(radius=0.2, lane_width=0.5)


def drive_baseline(env, steps, seed=0):
    baseline = get_baseline("JetRacerTrack-v0")
    obs, info = env.reset(seed=seed)
    infos = [info]
    for _ in range(steps):
        obs, reward, terminated, truncated, info = env.step(baseline(obs))
        infos.append(info)
        if terminated:
            break
    return infos, terminated


@pytest.mark.parametrize("clockwise", [False, True])
def test_baseline_laps_without_leaving_the_lane_and_laps_are_counted(clockwise):
    env = JetRacerTrackEnv(track=TrackSpec(clockwise=clockwise), random_start=False)  # start on the line
    infos, terminated = drive_baseline(env, 640)
    env.close()
    assert not terminated
    assert max(abs(i["cte"]) for i in infos) < 0.15  # of 0.25 allowed
    last = infos[-1]
    # the first crossing starts the clock, the second gives one lap time
    assert last["lap_count"] == 2 and len(last["lap_times"]) == 1
    lap_time = last["lap_times"][0]
    mean_speed = np.mean([i["speed"] for i in infos[len(infos) // 3 :]])
    assert lap_time == pytest.approx(env.track.length / mean_speed, rel=0.05)
    assert 12.0 < lap_time < 15.5  # measured 13.75 s; the paper's car: 13.5 s


def test_the_lane_follower_steers_by_pd_and_forgets_its_error_when_it_loses_the_lane():
    def lane_at(columns):
        mask = np.zeros(MASK_SHAPE, dtype=np.float32)
        mask[:, columns] = 1.0
        return np.concatenate([mask.ravel(), [0.0, 0.0]]).astype(np.float32)

    follower = LaneFollower()
    right = lane_at([9, 10])  # centroid at column 10 of 14: error (10 - 7) / 7
    assert follower(right)[0] == pytest.approx(-KP * 3 / 7)  # first frame: no rate of change yet
    centred = lane_at([6, 7])  # centroid at 7: error 0, a change of -3/7
    assert follower(centred)[0] == pytest.approx(KD * 3 / 7)
    follower(right)
    lost = follower(lane_at([]))
    assert lost.tolist() == [0.0, THROTTLE_ACTION]  # straight and slow
    # after the gap, proportional only: the error from before it would have kicked the wheel by KD * 3/7
    assert follower(centred)[0] == pytest.approx(0.0)


def test_backward_crossing_uncounts_a_lap():
    env = JetRacerTrackEnv(random_start=False)
    env.reset(seed=0)
    env._count_laps(0.05, -0.1)
    assert env._laps == -1 and env._lap_started is None
    env._count_laps(env.track.length - 0.05, 0.1)
    assert env._laps == 0
    env.close()


def test_leaving_the_lane_terminates_with_the_penalty():
    env = make_env("JetRacerTrack-v0")
    env.reset(seed=1)
    for _ in range(200):
        _, reward, terminated, truncated, info = env.step(np.array([1.0, 1.0]))  # full left, full throttle
        if terminated:
            break
    env.close()
    assert terminated and reward == -10.0 and abs(info["cte"]) > 0.25


def test_same_seed_same_episode():
    runs = []
    for _ in range(2):
        env = make_env("JetRacerTrack-v0")
        obs, _ = env.reset(seed=7)
        trace = [obs]
        for t in range(30):
            obs, reward, *_ = env.step(np.array([math.sin(t / 5), 0.3]))
            trace.append(obs)
        runs.append(np.array(trace))
        env.close()
    np.testing.assert_array_equal(runs[0], runs[1])


def test_frames_observations_and_rendering_have_the_promised_shapes():
    env = make_env("JetRacerTrack-v0", render_mode="rgb_array")
    obs, _ = env.reset(seed=0)
    assert obs.shape == (OBS_SIZE,) and obs.dtype == np.float32 and env.observation_space.contains(obs)
    frame = env.unwrapped.camera_frame_bgr()
    assert frame.shape == (112, 112, 3) and frame.dtype == np.uint8
    assert env.render().shape == (256, 256, 3)
    assert 0.2 < obs[:-2].mean() < 0.9, "the lane fills part of the view"
    env.close()


def test_the_track_leaves_no_files_behind_while_open_or_when_it_fails_to_build(tmp_path, monkeypatch):
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    env = JetRacerTrackEnv()
    obs, _ = env.reset(seed=0)
    assert list(scratch.iterdir()) == [], "the texture and the mesh are loaded, their files gone"
    assert 0.2 < obs[:-2].mean() < 0.9, "and the lane is still drawn"
    env.close()

    def fail(self, metres_per_pixel=0.004):
        raise MemoryError("no room for the texture")

    monkeypatch.setattr(TrackSpec, "texture", fail)
    with pytest.raises(MemoryError):
        JetRacerTrackEnv()
    assert list(scratch.iterdir()) == []


def test_preprocessing_is_the_same_for_a_sim_frame_and_the_same_frame_from_a_camera_file(tmp_path):
    env = make_env("JetRacerTrack-v0", randomize_lighting=True)
    obs, _ = env.reset(seed=3)
    frame = env.unwrapped.camera_frame_bgr()
    path = str(tmp_path / "camera.png")
    assert cv2.imwrite(path, frame)
    loaded = cv2.imread(path)  # what deploy/ reads from a recorded or live camera: BGR uint8
    np.testing.assert_array_equal(preprocess(loaded, np.array([0.0, -1.0])), obs)
    with pytest.raises(ValueError, match="112, 112, 3"):
        preprocess(loaded[:100], np.zeros(2))
    env.close()


def test_lighting_randomisation_changes_frames_but_not_what_the_baseline_sees():
    env = make_env("JetRacerTrack-v0", randomize_lighting=True)
    frames, masks = [], []
    env.unwrapped.random_start = False  # the same pose every time: only the lighting differs
    for seed in range(5):
        obs, _ = env.reset(seed=seed)
        frames.append(env.unwrapped.camera_frame_bgr().astype(int))
        masks.append(obs)
    assert max(np.abs(f - frames[0]).max() for f in frames) > 20  # the floor tiles change tint
    for mask in masks:
        np.testing.assert_allclose(mask, masks[0], atol=0.05)
    env.unwrapped.random_start = True
    infos, terminated = drive_baseline(env, 300, seed=4)
    assert not terminated
    env.close()


def test_action_mapping():
    mapping = ActionMapping()
    assert action_to_commands(np.array([0.0, -1.0]), mapping) == (0.0, 0.45)
    assert action_to_commands(np.array([1.0, 1.0]), mapping) == (1.0, pytest.approx(0.6))
    assert action_to_commands(np.array([-3.0, 0.0]), mapping) == (-1.0, pytest.approx(0.525))
    with pytest.raises(ValueError, match="finite"):
        action_to_commands(np.array([np.nan, 0.0]))
    with pytest.raises(ValueError, match="invalid action mapping"):
        ActionMapping(min_throttle=0.7, max_throttle=0.6)


def test_a_non_finite_action_or_command_is_refused_and_changes_nothing():
    env = JetRacerTrackEnv(random_start=False)
    env.reset(seed=0)
    env.step(np.array([0.2, 0.5]))
    before = (env._state.copy(), env._previous_action.copy(), env._s, env._progress, env._time)
    for bad in ([np.nan, 0.0], [0.0, np.inf]):
        with pytest.raises(ValueError, match="finite"):
            env.step(np.array(bad))
    for steering, throttle in ((math.nan, 0.5), (0.0, -math.inf)):
        with pytest.raises(ValueError, match="commands must be finite"):
            env.drive(steering, throttle)
    after = (env._state, env._previous_action, env._s, env._progress, env._time)
    for was, now in zip(before, after):
        np.testing.assert_array_equal(was, now)
    obs, *_ = env.step(np.array([0.2, 0.5]))  # the env goes on as if the bad calls never came
    assert np.all(np.isfinite(obs)) and np.all(np.isfinite(env._state))
    env.close()


def test_impossible_tracks_cars_and_rates_are_refused():
    from envs.jetracer_track import CarSpec

    for bad in (dict(steering_lag=0.0), dict(wheelbase=-0.2), dict(throttle_deadband=1.0), dict(max_steering_angle=math.pi / 2), dict(camera_fov=math.nan), dict(speed_lag=math.nan)):
        with pytest.raises(ValueError, match="impossible car"):
            CarSpec(**bad)
    with pytest.raises(ValueError, match="control_hz must be > 0"):
        make_env("JetRacerTrack-v0", 0, control_hz=0.0)
    with pytest.raises(ValueError, match="impossible track"):
        TrackSpec(radius=0.2)  # the lane (0.5 m wide) would cross the bend's centre
    with pytest.raises(ValueError, match="impossible track"):
        TrackSpec(margin=math.nan)  # not the first size: min() would have let a NaN there through


def test_the_track_passes_gymnasiums_env_checker_without_a_warning():
    import warnings

    from gymnasium.utils.env_checker import check_env

    env = make_env("JetRacerTrack-v0", render_mode="rgb_array")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the checker warns about what it finds: each would fail here
        check_env(env.unwrapped)  # spaces, seeded determinism of reset and step, render
    env.close()
