"""jirl_sac_continuous.py end to end: buffer accounting, intervention mode, logging, copyability, errors."""

import os
import runpy
import shutil
import sys

import numpy as np
import pytest
import torch
from scipy import stats

from conftest import ROOT, load_script, printed_regret
from envs.pendulum import pendulum_swing_up
from test_sac_script import TINY, readme_keys, run_script, scalars

jirl = load_script("jirl_sac_continuous")

INTERVENER = '''
import numpy as np
from envs.pendulum import pendulum_swing_up

def when_spinning_right(obs):
    """Intervenes (returns an action) only while theta' > 0; otherwise lets the agent act."""
    return pendulum_swing_up(obs) if obs[2] > 0 else None

def never(obs):
    return None
'''


def test_buffer_holds_real_fabricated_and_switch_penalty_transitions(tmp_path, monkeypatch):
    (tmp_path / "interveners.py").write_text(INTERVENER)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    argv = ["jirl_sac_continuous.py", "--baseline", "interveners:when_spinning_right", "--intervention-mode",
            "--regret-estimator", "off", "--total-timesteps", "260", "--learning-starts", "100",
            "--penalty-sigma2", "0.05", *TINY]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    g = runpy.run_path(str(ROOT / "jirl_sac_continuous.py"), run_name="__main__")
    rb, intervene = g["rb"], g["baseline"]
    i, steps, baseline_steps, penalties, previous = 0, 0, 0, 0, None
    while i < rb.size:
        obs, action, reward, next_obs = rb.obs[i], rb.actions[i], float(rb.rewards[i, 0]), rb.next_obs[i]
        baseline_action = intervene(obs)
        i += 1
        if baseline_action is None:  # the agent acted: one transition
            previous = (obs, action, next_obs)
        else:  # the baseline acted: real, fabricated and, after an agent step, the switch penalty
            np.testing.assert_allclose(action, baseline_action / 2.0, atol=1e-6)  # stored in policy units
            fabricated_action, fabricated_reward = rb.actions[i], float(rb.rewards[i, 0])
            np.testing.assert_array_equal(rb.obs[i], obs)
            np.testing.assert_array_equal(rb.next_obs[i], next_obs)
            assert np.all(np.abs(fabricated_action) <= 1.0)
            distance = np.linalg.norm(action.astype(np.float64) - fabricated_action)
            assert fabricated_reward == pytest.approx(reward - abs(reward) * (1 - np.exp(-distance / 0.05)), rel=1e-4, abs=1e-5)
            i += 1
            baseline_steps += 1
            if previous is not None and np.array_equal(previous[2], obs):
                np.testing.assert_array_equal(rb.obs[i], previous[0])
                np.testing.assert_array_equal(rb.actions[i], previous[1])
                assert rb.rewards[i, 0] == -1.0 and rb.terminations[i, 0] == 0.0
                np.testing.assert_array_equal(rb.next_obs[i], obs)
                i += 1
                penalties += 1
            previous = None
        steps += 1
    assert steps == 260 and i == rb.size == 260 + baseline_steps + penalties
    assert g["fabricated_transitions"] == baseline_steps > 20 and penalties > 5
    assert sum(g["rl_control"]) == 260 - baseline_steps


ALTERNATING_ENV = '''
import gymnasium as gym
import numpy as np


class Alternating(gym.Env):
    """obs = (t, parity of the reset seed); every episode terminates after 5 steps."""

    observation_space = gym.spaces.Box(0.0, 5.0, (2,), np.float32)
    action_space = gym.spaces.Box(-2.0, 2.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t, self.parity = 0, seed % 2
        return np.array([self.t, self.parity], np.float32), {}

    def step(self, action):
        self.t += 1
        return np.array([self.t, self.parity], np.float32), -1.0 - abs(float(action[0])), self.t == 5, False, {}


gym.register("Alternating-v0", entry_point=Alternating)
gym.register("CutAlternating-v0", entry_point=Alternating, max_episode_steps=4)  # cut before the end at 5


def every_other_step(obs):
    """Intervenes where t + parity is odd: episodes alternate agent, baseline, ... and baseline, agent, ..."""
    return np.array([1.0], np.float32) if (int(obs[0]) + int(obs[1])) % 2 else None
'''


def run_alternating(tmp_path, monkeypatch, *args: str, env_id: str = "alternating:Alternating-v0") -> dict:
    """JIRL on the alternating env, in process. A baseline that only intervenes cannot be measured, so
    neither the regret nor the earned schedule (which compares returns with the baseline's) can run."""
    (tmp_path / "alternating.py").write_text(ALTERNATING_ENV)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    argv = ["jirl_sac_continuous.py", "--env-id", env_id, "--baseline", "alternating:every_other_step",
            "--regret-estimator", "off", "--guidance-schedule", "geometric", "--learning-starts", "20", "--batch-size", "16",
            "--hidden-size", "16", *args]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    return runpy.run_path(str(ROOT / "jirl_sac_continuous.py"), run_name="__main__")


def test_transitions_end_with_their_episode(tmp_path, monkeypatch):
    """Fabricated rows keep the real row's termination; neither a switch penalty nor a control switch
    reaches across an episode's end; only fabricated and switch-penalty rows are marked as guidance."""
    g = run_alternating(tmp_path, monkeypatch, "--intervention-mode", "--total-timesteps", "53")
    rb, i = g["rb"], 0
    steps, baseline_steps, penalties, switches, parities = 0, 0, 0, 0, set()  # parities: which patterns ran
    while i < rb.size:
        obs, next_obs, terminated = rb.obs[i], rb.next_obs[i], rb.terminations[i, 0]
        t, parity = int(obs[0]), int(obs[1])
        parities.add(parity)
        assert t == steps % 5 and terminated == (t == 4) and not rb.guidance[i]
        switches += t > 0  # the pattern alternates within an episode
        i += 1
        if (t + parity) % 2:  # the baseline acted: its fabricated transition ends where the real one does
            assert rb.guidance[i] and rb.terminations[i, 0] == terminated
            np.testing.assert_array_equal(rb.obs[i], obs)
            np.testing.assert_array_equal(rb.next_obs[i], next_obs)
            i += 1
            baseline_steps += 1
            if t > 0:  # after an agent step of the same episode: the switch penalty
                assert rb.guidance[i] and rb.rewards[i, 0] == -1.0 and rb.terminations[i, 0] == 0.0
                np.testing.assert_array_equal(rb.obs[i], [t - 1, parity])
                np.testing.assert_array_equal(rb.next_obs[i], obs)
                i += 1
                penalties += 1
        steps += 1
    assert parities == {0, 1}, "episodes of either pattern ran"
    assert steps == 53 and i == rb.size == 53 + baseline_steps + penalties
    assert g["fabricated_transitions"] == baseline_steps and g["control_switches"] == switches
    assert rb.guidance[: rb.size].sum() == baseline_steps + penalties
    assert g["args"].guidance_steps == 26, "unset: half of --total-timesteps"


def test_an_episode_cut_by_the_time_limit_ends_no_transition(tmp_path, monkeypatch):
    """A time limit's cut is not a termination: the real row of the step it cuts, and the fabricated row
    when the baseline acted there, keep termination 0 and bootstrap from their next state, as SAC's do.
    The episodes are cut after 4 steps, before the env's own end at 5: the baseline acts at the cut in
    those of even parity, the agent in those of odd parity."""
    g = run_alternating(tmp_path, monkeypatch, "--intervention-mode", "--total-timesteps", "40", env_id="alternating:CutAlternating-v0")
    rb = g["rb"]
    cut, parity, guidance = rb.next_obs[: rb.size, 0] == 4, rb.obs[: rb.size, 1], rb.guidance[: rb.size]
    assert (cut & ~guidance).sum() == 10, "each of the 10 episodes' last step, one real row"
    assert (cut & guidance).sum() == (cut & ~guidance & (parity == 0)).sum() == 5, "a fabricated row where the baseline acted"
    assert rb.terminations[: rb.size].sum() == 0


def test_a_step_without_a_baseline_action_breaks_the_gate_window(tmp_path, monkeypatch):
    """With C = 0 the agent acts at every gated step, so no switch restarts the window: only the step
    without a baseline action between two gated ones keeps the earlier one out of the product."""
    g = run_alternating(tmp_path, monkeypatch, "--gate-c", "0", "--guidance-steps", "0", "--total-timesteps", "53")
    # the last step, t = 2 of an episode with parity 1, is gated; t = 1 had no baseline action, t = 0 was gated
    np.testing.assert_array_equal(g["obs"], [3, 1])
    assert len(g["gate"].log_probs) == 1 and g["fabricated_transitions"] == 0


def test_end_to_end_logs_gate_and_regret(tmp_path):
    args = ["--total-timesteps", "420", "--learning-starts", "150", "--guidance-steps", "300", "--guidance-schedule", "geometric", "--save-model",
            "--eval-episodes", "1", "--baseline-eval-episodes", "2", *TINY]  # fmt: skip
    out = run_script(ROOT / "jirl_sac_continuous.py", args, tmp_path)
    assert out.returncode == 0, out.stderr
    (run_dir,) = (tmp_path / "runs").iterdir()
    logged = scalars(run_dir)
    keys = ["charts/episodic_return", "charts/SPS", "losses/qf_loss", "losses/actor_loss", "charts/rl_control_fraction",
            "charts/baseline_regret", "charts/baseline_regret_per_step", "charts/control_switches",
            "charts/fabricated_transitions", "gate/log_prob_baseline", "gate/log_rho", "gate/c", "charts/baseline_return",
            "phases/baseline_regret_per_step_0_50", "phases/baseline_regret_per_step_50_100",
            "phases/baseline_regret_per_step_100", "eval/episodic_return"]  # fmt: skip
    for key in keys:
        assert key in logged, key
        assert np.all(np.isfinite(logged[key])), key
    assert set(logged) - readme_keys() == set(), "keys the README does not name"
    assert logged["gate/c"][-1] == 0.0, "C annealed to 0 over --guidance-steps"
    assert logged["charts/rl_control_fraction"][-1] > logged["charts/rl_control_fraction"][0]
    phases = sum(logged[f"phases/baseline_regret_per_step_{p}"][-1] for p in ("0_50", "50_100", "100"))
    assert phases == pytest.approx(logged["charts/baseline_regret_per_step"][-1], rel=1e-5)
    (checkpoint,) = run_dir.glob("*.cleanrl_model")
    sac = load_script("sac_continuous")
    assert sac.evaluate(str(checkpoint), "Pendulum-v1", 1, 1) == pytest.approx(logged["eval/episodic_return"], rel=1e-5)
    # the run ends by printing the regret it logged at its last episode end (420 steps: 2 episodes of 200)
    assert "baseline regret (paired): " in out.stdout
    assert printed_regret(out.stdout) == pytest.approx((logged["charts/baseline_regret"][-1], logged["charts/baseline_regret_per_step"][-1]), abs=0.05)


def test_the_run_ends_by_printing_who_held_control(tmp_path, monkeypatch, capsys):
    """10 episodes of 5 steps from reset seeds 1-10, the baseline intervening where t + parity is odd: it acts
    at 3 steps of each odd-parity episode and 2 of each even one (25 of 50), control changes hands at every
    step but an episode's first (4 switches an episode), and each baseline step stores a fabricated row. No
    regret is measured, so none is printed."""
    run_alternating(tmp_path, monkeypatch, "--intervention-mode", "--total-timesteps", "50")
    out = capsys.readouterr().out.splitlines()
    assert "RL control: 50% of the last 50 steps; 40 control switches, 25 fabricated transitions" in out
    assert "baseline regret estimator: off" in out and not any(line.startswith("baseline regret (") for line in out)


def test_gate_charts_are_the_means_of_the_gates_terms_since_the_last_log(tmp_path, monkeypatch):
    """gate/log_prob_baseline and gate/log_rho: the means, over the steps since the last log, of
    log pi(a^b|s) and log softplus(rho), recomputed here with scipy from the states the buffer stored.
    The agent never updates (--learning-starts = the total), so the actor the run leaves is the one
    that was asked at every step."""
    monkeypatch.chdir(tmp_path)
    argv = ["jirl_sac_continuous.py", "--total-timesteps", "260", "--learning-starts", "260", "--regret-estimator", "off",
            "--baseline-eval-episodes", "1", *TINY]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    g = runpy.run_path(str(ROOT / "jirl_sac_continuous.py"), run_name="__main__")
    rb = g["rb"]
    states = rb.obs[: rb.size][~rb.guidance[: rb.size]]  # the real rows: one per step, in order
    assert len(states) == 260
    with torch.no_grad():
        mean, log_std = (t.double().numpy() for t in g["actor"](torch.from_numpy(states)))
    edge = 1 - jirl.BASELINE_ACTION_EPS
    log_probs, log_rhos = [], []
    for s, m, ls in zip(states, mean, log_std):
        b = pendulum_swing_up(s.astype(np.float64)) / 2.0  # policy units
        y = np.clip(b, -edge, edge)
        log_probs.append(np.sum(stats.norm.logpdf(np.arctanh(y), m, np.exp(ls)) - np.log(1 - y**2)))
        entropy = np.sum(stats.norm(m, np.exp(ls)).entropy() + np.log(1 - np.tanh(m) ** 2))
        rho = entropy + np.linalg.norm(b - np.tanh(m))
        log_rhos.append(np.log(np.log1p(np.exp(rho))))
    (run_dir,) = (tmp_path / "runs").iterdir()
    logged = scalars(run_dir)
    windows = [slice(0, 51), slice(51, 101), slice(101, 151), slice(151, 201), slice(201, 251)]  # logs at steps 50, ..., 250
    np.testing.assert_allclose(logged["gate/log_prob_baseline"], [np.mean(log_probs[w]) for w in windows], rtol=1e-5)
    np.testing.assert_allclose(logged["gate/log_rho"], [np.mean(log_rhos[w]) for w in windows], rtol=1e-5)


def test_an_episode_regret_goes_to_the_phase_of_the_rl_control_fraction_at_its_end(tmp_path):
    """Table I's phases: 0-50 %, 50-<100 %, 100 % of the last --rl-control-window steps. C falls
    linearly from an insurmountable 1e300 and reaches 0 at step 390: the baseline drives the first
    episode alone (regret 0, paired) and the second until then; at the second's end (step 399) the agent
    has acted in 10 of the last 20 steps, exactly 50 %."""
    args = ["--total-timesteps", "400", "--learning-starts", "150", "--guidance-schedule", "linear", "--gate-c", "1e300",
            "--guidance-steps", "390", "--rl-control-window", "20", "--baseline-eval-episodes", "1", *TINY]  # fmt: skip
    out = run_script(ROOT / "jirl_sac_continuous.py", args, tmp_path)
    assert out.returncode == 0, out.stderr
    (run_dir,) = (tmp_path / "runs").iterdir()
    logged = scalars(run_dir)
    first, second = logged["charts/baseline_regret"]  # cumulative, at the two episodes' ends
    assert first == pytest.approx(0.0, abs=1e-6) and abs(second - first) > 1e-3
    assert logged["phases/baseline_regret_0_50"] == [first, first]
    assert logged["phases/baseline_regret_50_100"] == [0.0, pytest.approx(second - first)]
    assert logged["phases/baseline_regret_100"] == [0.0, 0.0]


def test_a_baseline_that_never_intervenes_leaves_the_agent_in_control(tmp_path, monkeypatch):
    (tmp_path / "interveners.py").write_text(INTERVENER)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    argv = ["jirl_sac_continuous.py", "--baseline", "interveners:never", "--regret-estimator", "off", "--guidance-schedule", "geometric",
            "--total-timesteps", "120", "--learning-starts", "60", *TINY]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    g = runpy.run_path(str(ROOT / "jirl_sac_continuous.py"), run_name="__main__")
    assert g["rb"].size == 120 and g["fabricated_transitions"] == 0 and all(g["rl_control"])


def test_measuring_an_intervening_baseline_is_a_clear_error(tmp_path):
    (tmp_path / "interveners.py").write_text(INTERVENER)
    env = dict(os.environ, PYTHONPATH=f"{tmp_path}{os.pathsep}{ROOT}")
    out = run_script(ROOT / "jirl_sac_continuous.py", ["--baseline", "interveners:never", "--total-timesteps", "10"], tmp_path, env)
    assert out.returncode != 0 and "use --regret-estimator off and --guidance-schedule geometric" in out.stderr and "Traceback" not in out.stderr


@pytest.mark.parametrize(
    "args, message",
    [
        (["--env-id", "MountainCarContinuous-v0"], "JIRL needs a baseline"),
        (["--env-id", "CartPole-v1"], "Discrete(2) action space"),
    ],
)
def test_bad_input_is_a_one_line_error(tmp_path, args, message):
    out = run_script(ROOT / "jirl_sac_continuous.py", [*args, "--total-timesteps", "10"], tmp_path)
    assert out.returncode != 0 and message in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert not (tmp_path / "runs").exists()


def test_script_copied_alone_runs_with_a_user_baseline(tmp_path):
    shutil.copy(ROOT / "jirl_sac_continuous.py", tmp_path)
    (tmp_path / "their_controller.py").write_text(
        "import numpy as np\n"
        "def damp(obs):\n    return np.array([-1.0 * obs[2]], dtype=np.float32)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    args = ["--env-id", "Pendulum-v1", "--baseline", "their_controller:damp", "--total-timesteps", "300",
            "--learning-starts", "100", "--baseline-eval-episodes", "1", *TINY]  # fmt: skip
    out = run_script(tmp_path / "jirl_sac_continuous.py", args, tmp_path, env)
    assert out.returncode == 0, out.stderr
    (run_dir,) = (tmp_path / "runs").iterdir()
    logged = scalars(run_dir)
    assert "charts/rl_control_fraction" in logged and "charts/baseline_regret_per_step" in logged
    assert "gate/guidance_progress" in logged and set(logged) - readme_keys() == set(), "the earned schedule's keys, all in the README"


@pytest.mark.parametrize("estimator", ["paired", "unpaired"])
def test_earned_guidance_follows_the_episodes_against_the_baseline(tmp_path, monkeypatch, estimator):
    monkeypatch.chdir(tmp_path)
    argv = ["jirl_sac_continuous.py", "--guidance-schedule", "earned", "--guidance-steps", "400",
            "--handover-episodes", "2", "--regret-estimator", estimator, "--baseline-eval-episodes", "2",
            "--total-timesteps", "1000", "--learning-starts", "200", *TINY]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    g = runpy.run_path(str(ROOT / "jirl_sac_continuous.py"), run_name="__main__")
    (run_dir,) = (tmp_path / "runs").iterdir()
    logged = scalars(run_dir)
    returns = logged["charts/episodic_return"]
    assert len(returns) == 5 and len(logged["gate/guidance_progress"]) == 5

    # the reference, recomputed here: the baseline's episode from the same reset seed, or its mean return
    from envs import get_baseline, make_env
    from envs.baselines import rollout

    env, baseline = make_env("Pendulum-v1"), get_baseline("Pendulum-v1")
    if estimator == "paired":
        references = [rollout(env, baseline, 1 + e).sum() for e in range(5)]
    else:
        references = [np.mean([rollout(env, baseline, 1 + jirl.EVAL_SEED_OFFSET + i).sum() for i in range(2)])] * 5
    progress = 0.0
    for e in range(5):
        recent, reference = np.mean(returns[max(0, e - 1) : e + 1]), np.mean(references[max(0, e - 1) : e + 1])
        progress = min(1.0, progress + 0.5) if recent >= reference - 0.1 * abs(reference) else max(0.0, progress - 0.5)
        assert logged["gate/guidance_progress"][e] == pytest.approx(progress), e
    assert g["earned"].progress == pytest.approx(progress)
    moves = np.diff([0.0, *logged["gate/guidance_progress"]])
    assert moves.max() > 0 and moves.min() < 0, "this run exercises both directions"


def test_guidance_weight_sets_how_often_fabricated_rows_are_drawn():
    rb = jirl.ReplayBuffer(10, 1, 1, seed=0)
    kinds = [False, True, True, False, False, True, False]  # True: fabricated or switch penalty
    for i, guidance in enumerate(kinds):
        rb.add(np.array([i]), np.array([0.0]), float(i), np.array([i + 1]), False, guidance)
    np.testing.assert_array_equal(rb.guidance[:7], kinds)
    guidance_rows = {1, 2, 5}
    for weight, expected in [(1.0, 3 / 7), (0.5, 1.5 / 5.5), (0.0, 0.0)]:
        obs, _, rewards, next_obs, _ = (t.numpy()[:, 0] for t in rb.sample(40_000, weight))
        share = np.isin(obs, list(guidance_rows)).mean()
        assert share == pytest.approx(expected, abs=0.01), weight
        np.testing.assert_array_equal(rewards, obs)  # rows stay whole
        np.testing.assert_array_equal(next_obs, obs + 1)


def test_guidance_transitions_fade_after_the_hand_over(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    argv = ["jirl_sac_continuous.py", "--guidance-steps", "300", "--guidance-schedule", "geometric", "--guidance-fade-steps", "100", "--regret-estimator", "off",
            "--total-timesteps", "500", "--learning-starts", "200", *TINY]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    draws = []  # per batch sampled: the weight it was drawn with, and which of its rows are fabricated or switch-penalty rows

    def trace(frame, event, arg):  # the script defines its buffer as it runs, so its sample() is watched rather than patched
        if frame.f_code.co_name != "sample" or not frame.f_code.co_filename.endswith("jirl_sac_continuous.py"):
            return None

        def on_return(frame, event, arg):
            if event == "return":
                local = frame.f_locals
                draws.append((local["guidance_weight"], local["self"].guidance[local["idx"]].copy()))
            return on_return

        return on_return

    previous = sys.gettrace()  # a coverage run's tracer, say: put back after the run
    sys.settrace(trace)
    try:
        g = runpy.run_path(str(ROOT / "jirl_sac_continuous.py"), run_name="__main__")
    finally:
        sys.settrace(previous)
    (run_dir,) = (tmp_path / "runs").iterdir()
    weights = scalars(run_dir)["charts/guidance_weight"]  # logged at steps 50, 100, ..., 450
    np.testing.assert_allclose(weights, [1, 1, 1, 1, 1, 1, 0.5, 0, 0])  # C = 0 from step 300
    assert g["fade"].faded == 100 and g["fabricated_transitions"] > 0  # C = 0 from step 300: the fade is complete
    # the updates of steps 200-499 draw with the weight of their step: 1 until C reaches 0 at step 300, 0 from step 400
    assert [weight for weight, _ in draws] == pytest.approx([1.0] * 101 + [1 - k / 100 for k in range(1, 100)] + [0.0] * 100)
    assert sum(rows.sum() for _, rows in draws[:101]) > 500  # the baseline acted until about step 300: 1,554 of these 3,232 rows (measured)
    assert not any(rows.any() for weight, rows in draws if weight == 0.0)


@pytest.mark.parametrize("deterministic", [True, False])
def test_deterministic_after_guidance_applies_the_mean_action_once_c_is_0(tmp_path, monkeypatch, deterministic):
    monkeypatch.chdir(tmp_path)
    flag = ["--deterministic-after-guidance"] if deterministic else []
    # no updates (learning starts at the end), so the final actor is the one that acted throughout
    argv = ["jirl_sac_continuous.py", "--guidance-steps", "150", "--guidance-schedule", "geometric", "--regret-estimator", "off",
            "--total-timesteps", "250", "--learning-starts", "250", *flag, *TINY]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    g = runpy.run_path(str(ROOT / "jirl_sac_continuous.py"), run_name="__main__")
    rb = g["rb"]
    with torch.no_grad():
        mean, _ = g["actor"](torch.from_numpy(rb.obs[: rb.size]).float())
    is_mean_action = np.all(np.abs(rb.actions[: rb.size] - np.tanh(mean.numpy())) < 1e-5, axis=1)
    alone = is_mean_action[-100:]  # C = 0 from step 150: one row per step, the agent's
    assert alone.all() if deterministic else not alone.any()
    assert g["fabricated_transitions"] > 0 and not is_mean_action[:-100].any()  # samples and baseline actions before
