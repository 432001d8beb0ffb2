"""benchmarks/observation_choice.py, benchmarks/track_laps.py and benchmarks/track_speed.py, whose figures
BENCHMARKS.md quotes for JetRacerTrack-v0: the observation chosen there is the one the policies see, its
R^2 is a held-out one, a lap table's medians, gains and unreadable rows are what the laps give, and the
track's speed is its steps over the time they took."""

import re
import statistics
import sys

import numpy as np
import pytest

import warm_python
from conftest import ROOT, figures_stated, small_checkpoint
from envs.car_interface import MASK_SHAPE, lane_mask
from envs.jetracer_track import JetRacerTrackEnv

sys.path.insert(0, str(ROOT / "benchmarks"))
import observation_choice  # noqa: E402
import track_laps  # noqa: E402


def test_the_chosen_candidate_is_the_mask_the_policies_see():
    """BENCHMARKS.md chose "lane mask 10x14" from this benchmark's table; that row must measure the mask
    `preprocess` gives the policies (on the track and on the car), on rendered frames and on noise."""
    env = JetRacerTrackEnv(randomize_lighting=True)
    frames = []
    for seed in range(4):
        env.reset(seed=seed)
        frames.append(env.camera_frame_bgr())
    env.close()
    frames += list(np.random.default_rng(0).integers(0, 256, size=(2, 112, 112, 3), dtype=np.uint8))
    assert MASK_SHAPE == (10, 14)
    for frame in frames:
        found = observation_choice.candidates(frame)
        np.testing.assert_array_equal(found[f"lane mask {MASK_SHAPE[0]}x{MASK_SHAPE[1]}"], lane_mask(frame).reshape(-1))
        assert {name: len(value) for name, value in found.items()} == {
            "lane mask 5x7": 35, "lane mask 10x14": 140, "lane mask 20x28": 560, "lane mask 40x56": 2240, "grey 10x14": 140, "grey 20x28": 560,
        }  # fmt: skip
    assert any(0 < m < 1 for m in lane_mask(frames[0]).reshape(-1))  # the rendered lane's edge falls inside some cells


def test_the_readme_quotes_the_chosen_rows_figures():
    """The README's account of the observation (the R^2 of the chosen mask, as good as masks 16 times
    larger, better than grey images of its size) is what BENCHMARKS.md's table of this benchmark gives."""
    benchmarks = (ROOT / "BENCHMARKS.md").read_text()
    table = benchmarks.split("Observation choice: `python benchmarks/observation_choice.py", 1)[1].split("\n\n", 2)[1]
    rows = {}
    for line in table.splitlines()[2:]:
        name, size, cross_track, heading = [cell.strip(" *") for cell in line.strip("|").split("|")]
        rows[name.replace(" (chosen)", "").replace("*", "")] = (int(size.replace(",", "")), float(cross_track.split()[0]), float(heading.split()[0]))
    chosen = [line for line in table.splitlines() if "(chosen)" in line]
    assert len(chosen) == 1 and f"lane mask {MASK_SHAPE[0]}×{MASK_SHAPE[1]}" in chosen[0]
    size, cross_track, heading = rows[f"lane mask {MASK_SHAPE[0]}×{MASK_SHAPE[1]}"]
    assert size == MASK_SHAPE[0] * MASK_SHAPE[1]
    ((stated_cross_track, stated_heading),) = figures_stated((ROOT / "README.md").read_text(), r"reads cross-track error \(R² ([\d.]+)\) and heading error \(([\d.]+)\) from the 10×14 mask")
    assert (stated_cross_track, stated_heading) == (round(cross_track, 3), round(heading, 2))
    larger = rows[f"lane mask {4 * MASK_SHAPE[0]}×{4 * MASK_SHAPE[1]}"]
    assert larger[0] == 16 * size and abs(larger[2] - heading) < 0.005 and larger[1] == cross_track  # "as well as from masks 16 times larger"
    grey = rows[f"grey {MASK_SHAPE[0]}×{MASK_SHAPE[1]}"]
    assert grey[0] == size and grey[1] < cross_track and grey[2] < heading  # "better than from grey images of the same size"


def test_ridge_r2_is_the_held_out_fit_of_a_quadratic_model():
    """On inputs of 5 dimensions, against an ordinary least-squares fit of the quadratic features of the raw
    inputs, computed here: a target quadratic in them is read whole (R^2 near 1, squares included), an
    independent one not at all (near 0, below what the training rows alone would show)."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=(500, 5))
    quadratic = 0.5 + x @ [1.0, -2.0, 0.0, 0.5, 0.0] + 0.8 * x[:, 0] ** 2 - 0.6 * x[:, 1] * x[:, 3] + 0.05 * rng.normal(size=500)
    y = np.stack([quadratic, rng.normal(size=500)], 1)
    order = rng.permutation(500)
    train, test = order[:400], order[400:]

    pairs = [(i, j) for i in range(5) for j in range(i, 5)]
    features = np.hstack([np.ones((500, 1)), x, np.stack([x[:, i] * x[:, j] for i, j in pairs], 1)])
    w, *_ = np.linalg.lstsq(features[train], y[train], rcond=None)
    residual = y[test] - features[test] @ w
    expected = 1 - ((residual - residual.mean(0)) ** 2).mean(0) / ((y[test] - y[test].mean(0)) ** 2).mean(0)

    r2 = observation_choice.ridge_r2(x, y, train, test)
    np.testing.assert_allclose(r2, expected, atol=1e-4)
    assert r2[0] > 0.99 and -0.2 < r2[1] < 0.05


def test_a_lap_row_gives_the_median_and_the_gain_over_the_baseline():
    assert track_laps.row("p", [10.0, 15.0, 11.0], 1, 2, 13.75) == "| p | 3 | 11.00 | 1/2 | 20 % |"  # the median, not the mean (12)
    assert track_laps.row("p", [10.0, 12.0, 14.0, 16.0], 0, 2, 10.0) == "| p | 4 | 13.00 | 0/2 | -30 % |"  # slower: a negative gain
    assert track_laps.row("p", [], 2, 2, 15.0) == "| p | 0 | nan | 2/2 | – |"  # no lap: no median, no gain
    assert track_laps.row("baseline", [13.0], 0, 1, 0.0) == "| baseline | 1 | 13.00 | 0/1 | – |"  # the baseline made no lap


def test_drive_counts_the_episodes_that_left_the_lane_and_resets_the_policy(monkeypatch):
    class HardLeft:
        resets = 0

        def reset(self):
            self.resets += 1

        def __call__(self, obs):
            return np.array([1.0, 1.0], np.float32)  # full left at full throttle: off the lane within seconds

    seeds = []

    def make_env(env_id):
        env = real_make_env(env_id)
        reset = env.reset
        env.reset = lambda seed=None: seeds.append(seed) or reset(seed=seed)
        return env

    real_make_env = track_laps.make_env
    monkeypatch.setattr(track_laps, "make_env", make_env)
    policy = HardLeft()
    laps, off_lane = track_laps.drive(policy, 2, 7)
    assert (laps, off_lane, policy.resets, seeds) == ([], 2, 2, [7, 8])  # episode i from seed offset + i


def test_the_lap_table_reads_each_checkpoint_and_reports_one_trained_elsewhere(tmp_path, monkeypatch, capsys, sac):
    small_checkpoint(sac, tmp_path / "pendulum.cleanrl_model")
    small_checkpoint(sac, tmp_path / "track.cleanrl_model", "JetRacerTrack-v0")
    laps = {"baseline": [13.0, 14.5, 13.5], "policy": [7.0, 7.5]}
    driven = []

    def drive(policy, episodes, seed_offset):
        driven.append((episodes, seed_offset))
        return (laps["policy"], 1) if driven[1:] else (laps["baseline"], 0)

    monkeypatch.setattr(track_laps, "drive", drive)
    monkeypatch.setattr(sys, "argv", ["track_laps.py", str(tmp_path / "pendulum.cleanrl_model"), str(tmp_path / "track.cleanrl_model"), "--episodes", "3"])
    track_laps.main()
    rows = capsys.readouterr().out.splitlines()
    gain = 100 * (1 - statistics.median(laps["policy"]) / statistics.median(laps["baseline"]))
    assert rows[3] == "| baseline (lane follower) | 3 | 13.50 | 0/3 | 0 % |"
    assert rows[4] == f"| {tmp_path / 'pendulum.cleanrl_model'} | unreadable: trained on Pendulum-v1, not JetRacerTrack-v0 | | | |"
    assert rows[5] == f"| {tmp_path / 'track.cleanrl_model'} | 2 | 7.25 | 1/3 | {gain:.0f} % |"
    assert driven == [(3, 1_000_000), (3, 1_000_000)]  # the baseline and the track's policy, on the scripts' evaluation seeds


@pytest.mark.parametrize("content", [b"", b"not a checkpoint"])
def test_a_file_that_is_no_checkpoint_is_an_unreadable_row(tmp_path, monkeypatch, capsys, content):
    (tmp_path / "bad.cleanrl_model").write_bytes(content)
    monkeypatch.setattr(track_laps, "drive", lambda policy, episodes, seed_offset: ([13.0], 0))
    monkeypatch.setattr(sys, "argv", ["track_laps.py", str(tmp_path / "bad.cleanrl_model"), "--episodes", "1"])
    track_laps.main()
    rows = capsys.readouterr().out.splitlines()
    assert len(rows) == 5 and rows[-1].startswith(f"| {tmp_path / 'bad.cleanrl_model'} | unreadable: ") and rows[-1].endswith(" | | | |")


def test_an_error_of_several_lines_stays_one_row_of_the_table(monkeypatch, capsys):
    def unreadable(path):
        raise ValueError("first line\n  second line")

    monkeypatch.setattr(track_laps, "track_policy", unreadable)
    monkeypatch.setattr(track_laps, "drive", lambda policy, episodes, seed_offset: ([13.0], 0))
    monkeypatch.setattr(sys, "argv", ["track_laps.py", "some.cleanrl_model", "--episodes", "1"])
    track_laps.main()
    assert capsys.readouterr().out.splitlines()[-1] == "| some.cleanrl_model | unreadable: first line second line | | | |"


def test_track_speed_divides_the_steps_by_each_clock_and_restarts_the_baseline_with_each_episode(monkeypatch, capsys):
    """BENCHMARKS.md's steps per second of the track: each repeat's steps over the time each clock measured
    around them, the median of the repeats; every episode, seeded or not, starts with a fresh baseline."""
    import types

    import track_speed

    class Track:
        """episodes of 5 steps, truncated and terminated in turn; each observation a new one"""

        def __init__(self):
            self.seeds, self.t, self.episode_t, self.obs = [], 0, 0, None

        def reset(self, seed=None):
            self.seeds.append(seed)
            self.episode_t, self.obs = 0, ("reset", len(self.seeds))
            return self.obs, {}

        def step(self, action):
            assert action == ("acted on", self.obs)  # the baseline's action on the latest observation
            self.t += 1
            self.episode_t += 1
            self.obs = ("step", self.t)
            end = self.episode_t == 5
            return self.obs, 0.0, end and len(self.seeds) % 2 == 0, end and len(self.seeds) % 2 == 1, {}

    class Baseline:
        resets = 0

        def reset(self):
            self.resets += 1

        def __call__(self, obs):
            return ("acted on", obs)

    track, baseline = Track(), Baseline()
    monkeypatch.setattr(track_speed, "make_env", lambda env_id: env_id == "JetRacerTrack-v0" and track)
    monkeypatch.setattr(track_speed, "get_baseline", lambda env_id: env_id == "JetRacerTrack-v0" and baseline)
    wall, cpu = [10.0, 14.0, 20.0, 21.0, 30.0, 33.0], [0.0, 1.0, 5.0, 7.0, 9.0, 9.5]  # per repeat: 4, 1, 3 s and 1, 2, 0.5 s
    monkeypatch.setattr(track_speed, "time", types.SimpleNamespace(perf_counter=iter(wall).__next__, process_time=iter(cpu).__next__))
    monkeypatch.setattr(sys, "argv", ["track_speed.py", "--steps", "12", "--repeats", "3"])
    track_speed.main()
    # per repeat, 12/4, 12/1, 12/3 = 3, 12, 4 steps per wall-clock second (median 4, mean 6.3);
    # 12/1, 12/2, 12/0.5 = 12, 6, 24 per CPU-second (median 12, mean 14)
    assert capsys.readouterr().out == (
        "JetRacerTrack-v0, lane-follower actions, 12 steps x 3 (medians): 12 steps per CPU-second, 4 steps per wall-clock second\n"
    )
    assert track.t == 36
    # each repeat starts from its seed, then 2 episodes end within its 12 steps (at 5 and 10)
    assert track.seeds == [0, None, None, 1, None, None, 2, None, None]
    assert baseline.resets == len(track.seeds)


def test_track_speed_drives_the_real_track():
    done = warm_python.run([str(ROOT / "benchmarks" / "track_speed.py"), "--steps", "30", "--repeats", "2"],
                           timeout=120)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert re.fullmatch(r"JetRacerTrack-v0, lane-follower actions, 30 steps x 2 \(medians\): [1-9]\d* steps per CPU-second, [1-9]\d* steps per wall-clock second\n", done.stdout)
