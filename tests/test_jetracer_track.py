"""JetRacerTrack-v0: track geometry, laps, termination, determinism, the camera pipeline and its baseline."""

import math
import tempfile

import cv2
import numpy as np
import pytest

from envs import get_baseline, make_env
from envs.car_interface import MASK_SHAPE, OBS_SIZE, ActionMapping, action_to_commands, preprocess
from envs.jetracer_track import CarSpec, JetRacerTrackEnv
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


@pytest.mark.parametrize("clockwise", [False, True])
def test_the_drawn_lane_tape_and_floor_are_where_the_projection_puts_them(clockwise):
    track = TrackSpec(straight_length=1.5, radius=0.8, lane_width=0.4, tape_width=0.05, margin=0.6, clockwise=clockwise)
    metres = 0.01  # per pixel
    image = track.texture(metres)
    half_x, half_y = 0.75 + 0.8 + 0.2 + 0.6, 0.8 + 0.2 + 0.6  # the loop, half the lane and the margin on every side
    assert image.shape == (round(2 * half_y / metres), round(2 * half_x / metres), 3)
    rng = np.random.default_rng(1)
    seen = {"lane": 0, "tape": 0, "floor": 0}
    for row, col in zip(rng.integers(0, image.shape[0], 3000), rng.integers(0, image.shape[1], 3000)):
        x, y = (col + 0.5) * metres - half_x, half_y - (row + 0.5) * metres  # row 0 at +y
        offset = abs(track.project(x, y)[1])
        if min(abs(offset - 0.15), abs(offset - 0.2)) < 1e-6:
            continue  # exactly on an edge: either colour is right
        colour = tuple(image[row, col])
        if offset <= 0.15:
            assert colour == (38, 38, 42), (x, y, offset)
            seen["lane"] += 1
        elif offset <= 0.2:
            assert colour == (235, 235, 235), (x, y, offset)
            seen["tape"] += 1
        else:
            tile = (math.floor(x / 0.3) + math.floor(y / 0.3)) % 2  # 0.3 m squares of two greys
            if min(abs(x / 0.3 - round(x / 0.3)), abs(y / 0.3 - round(y / 0.3))) > 1e-6:
                assert colour == ((196,) * 3 if tile else (178,) * 3), (x, y)
            seen["floor"] += 1
    assert min(seen.values()) > 100, seen


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
    # from s = 0, the distance driven is the laps plus where the car is now; it never points more than 0.25 rad off the lane
    assert last["progress"] == pytest.approx(last["lap_count"] * env.track.length + last["s"])
    assert max(abs(i["heading_error"]) for i in infos) < 0.25  # measured 0.197 and 0.198, across the wrap at +-pi


def test_the_lane_follower_steers_by_pd_and_forgets_its_error_when_it_loses_the_lane():
    def lane_at(columns, fraction=1.0):
        mask = np.zeros(MASK_SHAPE, dtype=np.float32)
        mask[:, columns] = fraction
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
    follower(right)
    follower.reset()  # a new episode forgets the error just as a gap does
    assert follower(centred)[0] == pytest.approx(0.0)
    follower(right)
    # under one cell's worth of lane in the look-ahead rows (6 rows x 2 cells x 0.08 = 0.96) is no lane seen
    assert follower(lane_at([9, 10], fraction=0.08)).tolist() == [0.0, THROTTLE_ACTION]
    assert follower(lane_at([9, 10], fraction=0.09))[0] == pytest.approx(-KP * 3 / 7), "0.09 makes 1.08: seen, with no rate after the gap"


def test_backward_crossing_uncounts_a_lap_and_the_lap_it_was_timing():
    env = JetRacerTrackEnv(random_start=False)
    env.reset(seed=0)
    length = env.track.length
    env._count_laps(length - 0.05, 0.1)  # forwards over the line: lap 1, its clock starts
    env._time = 3.0
    env._count_laps(0.05, -0.1)  # back over it
    assert env._laps == 0 and env._lap_started is None
    env._time = 5.0
    env._count_laps(length - 0.05, 0.1)  # forwards again: counted, and no lap time (the clock stopped going back); it restarts
    assert env._laps == 1 and env._lap_times == [] and env._lap_started == 5.0
    env._time = 18.0
    env._count_laps(length - 0.05, 0.1)
    assert env._laps == 2 and env._lap_times == [13.0]
    env.close()


def test_drive_clamps_the_steering_and_brakes_to_rest_below_the_throttle_deadband():
    first, second = JetRacerTrackEnv(random_start=False), JetRacerTrackEnv(random_start=False)
    for env in (first, second):
        env.reset(seed=0)
    first.drive(5.0, 0.6)  # a raw command past full lock steers at full lock
    second.drive(1.0, 0.6)
    np.testing.assert_array_equal(first._state, second._state)
    second.close()
    car = first.car
    for _ in range(60):  # 3 s, ten speed lags: at the speed throttle 0.6 asks for
        first.drive(0.0, 0.6)
    assert first._state[3] == pytest.approx(car.max_speed * (0.6 - car.throttle_deadband) / (1 - car.throttle_deadband), rel=1e-3)
    speeds = []
    for throttle in [0.0] * 30 + [0.1] * 30:  # STOP's 0, then a throttle inside the deadband
        first.drive(0.0, throttle)
        speeds.append(first._state[3])
    first.close()
    assert min(speeds) >= 0.0 and speeds[-1] < 1e-4, "it brakes to rest, and never backs up"


def test_a_steady_turn_follows_the_kinematic_bicycles_circle():
    env = JetRacerTrackEnv(random_start=False)
    env.reset(seed=0)
    for _ in range(60):  # 3 s: the steering and speed lags settle
        env.drive(0.6, 0.6)
    points = []
    for _ in range(40):  # 2 s at 1.25 m/s: most of a circle
        env.drive(0.6, 0.6)
        points.append(env._state[:2].copy())
    env.close()
    x, y = np.array(points).T
    cx, cy, c = np.linalg.lstsq(np.c_[2 * x, 2 * y, np.ones_like(x)], x**2 + y**2, rcond=None)[0]  # the circle through them
    radius = math.sqrt(c + cx**2 + cy**2)
    np.testing.assert_allclose(np.hypot(x - cx, y - cy), radius, atol=1e-6)
    # wheelbase / tan(steering angle); one Euler step per control period is 3.9e-4 too wide (measured), its five substeps 1.6e-5
    assert radius == pytest.approx(env.car.wheelbase / math.tan(0.6 * env.car.max_steering_angle), rel=1e-4)


@pytest.mark.parametrize("car", [CarSpec(), CarSpec(steering_lag=0.4, speed_lag=0.05)], ids=["default", "slow-servo-quick-motor"])
def test_the_servo_and_the_drive_train_follow_first_order_lags(car):
    # with a constant target, x(t) = target + (x(0) - target) exp(-t / lag) at any time t, between steps or not
    env = JetRacerTrackEnv(car=car, random_start=False)
    env.reset(seed=0)
    angle, speed = 0.6 * car.max_steering_angle, car.max_speed * (0.6 - car.throttle_deadband) / (1 - car.throttle_deadband)
    for n in range(1, 9):  # from rest, the wheel straight
        env.drive(0.6, 0.6)
        t = n * env.dt
        assert env._state[4] == pytest.approx(angle * (1 - math.exp(-t / car.steering_lag)), rel=1e-12)
        assert env._state[3] == pytest.approx(speed * (1 - math.exp(-t / car.speed_lag)), rel=1e-12)
    angle_then, speed_then = env._state[4], env._state[3]
    for n in range(1, 9):  # the wheel swung the other way, the throttle released: the same lags, towards the new targets
        env.drive(-0.3, 0.0)
        t = n * env.dt
        assert env._state[4] == pytest.approx(-0.5 * angle + (angle_then + 0.5 * angle) * math.exp(-t / car.steering_lag), rel=1e-12)
        assert env._state[3] == pytest.approx(speed_then * math.exp(-t / car.speed_lag), rel=1e-12)
    env.close()


def test_leaving_the_lane_terminates_with_the_penalty():
    env = make_env("JetRacerTrack-v0")
    _, info = env.reset(seed=1)
    ctes = [info["cte"]]
    for _ in range(200):
        _, reward, terminated, truncated, info = env.step(np.array([1.0, 1.0]))  # full left, full throttle
        ctes.append(info["cte"])
        if terminated:
            break
    env.close()
    assert terminated and reward == -10.0 and abs(ctes[-1]) > 0.25
    assert max(abs(cte) for cte in ctes[:-1]) <= 0.25, "at the first step whose centre is past the lane's edge"


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


def test_the_simulated_camera_delivers_bgr_as_the_cars_camera_does():
    # the default floor is grey, so the lane mask alone cannot tell the channel order: light the ground orange
    env = JetRacerTrackEnv(random_start=False)
    env.reset(seed=0)
    env._client.changeVisualShape(env._ground, -1, rgbaColor=[1.0, 0.5, 0.2, 1.0])  # red, green, blue
    blue, green, red = env.camera_frame_bgr().reshape(-1, 3).mean(0)
    env.close()
    assert red - green > 10 and green - blue > 10, (blue, green, red)  # measured 108.7, 123.6, 148.9


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
    assert action_to_commands(np.array([0.5, -1.0]), ActionMapping(max_steering=0.4)) == (pytest.approx(0.2), 0.45)  # a servo limited to 40 %
    for bad in (dict(min_throttle=0.7, max_throttle=0.6), dict(min_throttle=-0.1), dict(max_throttle=1.1), dict(max_steering=0.0), dict(max_steering=1.5)):
        with pytest.raises(ValueError, match="invalid action mapping"):
            ActionMapping(**bad)


def test_the_lane_mask_is_the_share_of_dark_pixels_of_a_bgr_frame_in_each_cell_below_the_crop():
    frame = np.full((112, 112, 3), 255, dtype=np.uint8)
    frame[:32] = 0  # above the crop: however dark, it is no lane
    frame[32:, ::2] = 90  # every other column at the threshold (a lane pixel), the rest one grey level above it
    frame[32:, 1::2] = 91
    mask = preprocess(frame, np.array([3.0, -7.0]))
    np.testing.assert_allclose(mask[:-2], 0.5)  # each 8 x 8 cell half lane: the share, not one pixel's value
    assert mask[-2:].tolist() == [1.0, -1.0], "the previous action, clipped to the policy's range"
    # read as BGR: blue 200, green 50, red 100 is grey 82 (dark lane); read as RGB it would be 101
    frame[32:] = (200, 50, 100)
    np.testing.assert_array_equal(preprocess(frame, np.zeros(2))[:-2], 1.0)
    with pytest.raises(ValueError, match="uint8"):
        preprocess(frame.astype(np.float32), np.zeros(2))  # a float frame would threshold at 90 of 1.0


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
    for bad in (dict(steering_lag=0.0), dict(wheelbase=-0.2), dict(throttle_deadband=1.0), dict(max_steering_angle=math.pi / 2), dict(camera_fov=math.nan), dict(speed_lag=math.nan)):
        with pytest.raises(ValueError, match="impossible car"):
            CarSpec(**bad)
    for hz in (0.0, math.inf):  # an infinite rate is a zero time step
        with pytest.raises(ValueError, match="control_hz must be > 0"):
            make_env("JetRacerTrack-v0", 0, control_hz=hz)
    with pytest.raises(ValueError, match="render_mode must be None or 'rgb_array', got 'human'"):
        JetRacerTrackEnv(render_mode="human")
    for radius in (0.2, 0.25):  # the lane (0.5 m wide) would cross the bend's centre, or its inner edge shrink to that point
        with pytest.raises(ValueError, match="impossible track"):
            TrackSpec(radius=radius)
    with pytest.raises(ValueError, match="impossible track"):
        TrackSpec(margin=math.nan)  # not the first size: min() would have let a NaN there through
    for lane_width in (0.05, 0.06):  # the two edge tapes would overlap, or meet with no lane surface between them
        with pytest.raises(ValueError, match="impossible track"):
            TrackSpec(lane_width=lane_width, tape_width=0.03)
    for fits in (dict(radius=0.26), dict(lane_width=0.07, tape_width=0.03)):  # just inside each bound: made without an error
        TrackSpec(**fits)


def test_the_track_passes_gymnasiums_env_checker_without_a_warning():
    import warnings

    from gymnasium.utils.env_checker import check_env

    env = make_env("JetRacerTrack-v0", render_mode="rgb_array")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the checker warns about what it finds: each would fail here
        check_env(env.unwrapped)  # spaces, seeded determinism of reset and step, render
    env.close()
