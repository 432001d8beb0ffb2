"""benchmarks/episode_start.py: each way of driving a checkpoint, against episodes run here by hand;
its refusals of bad options and of a file that is not a checkpoint."""

import sys

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.envs.classic_control.pendulum import PendulumEnv

from conftest import ROOT, load_script, overflow_the_actor, small_checkpoint, table_cells

sys.path.insert(0, str(ROOT / "benchmarks"))
import episode_start  # noqa: E402

from envs import get_baseline, rollout  # noqa: E402

SEED, LENGTH = 4, 200  # the checkpoint's run seed; Pendulum's time limit


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """A SAC checkpoint (it has no gate_k) whose actor is not the baseline, and the actor."""
    path = tmp_path_factory.mktemp("episode_start") / "pendulum.cleanrl_model"
    torch.manual_seed(3)
    actor = small_checkpoint(load_script("sac_continuous"), path, seed=SEED)
    return path, actor


def by_hand(actor, episode: int, handoff: int) -> float:
    """The return of the baseline acting for `handoff` steps, then the actor's mean action, from the
    evaluation's reset seed of `episode`."""
    sac = load_script("sac_continuous")
    env, baseline = gym.make("Pendulum-v1"), get_baseline("Pendulum-v1")
    obs, _ = env.reset(seed=SEED + sac.EVAL_SEED_OFFSET + episode)
    total = 0.0
    for step in range(LENGTH):
        if step < handoff:
            action = baseline(obs)
        else:
            with torch.inference_mode():
                mean, _ = actor(torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0))
            action = 2.0 * np.tanh(mean[0].numpy())  # Pendulum's torque bounds are -2 and 2
        obs, reward, _, _, _ = env.step(action)
        total += float(reward)
    return total


def by_hand_gate(actor, episodes: int, c: float, sample_seed: int, k: int = 5) -> list[tuple[float, int]]:
    """The return and the agent's steps of each episode under Alg. 3's gate, written out here: the window
    holds the last k + 1 terms and restarts at each switch of control; the agent acts with a^rl ~ pi,
    drawn from one generator over all the episodes. The terms and the unit conversions are the
    script's, tested on their own elsewhere."""
    sac, jirl = load_script("sac_continuous"), load_script("jirl_sac_continuous")
    env, baseline = gym.make("Pendulum-v1"), get_baseline("Pendulum-v1")
    low, high = env.action_space.low, env.action_space.high
    generator = torch.Generator().manual_seed(sample_seed)
    found = []
    for episode in range(episodes):
        obs, _ = env.reset(seed=SEED + sac.EVAL_SEED_OFFSET + episode)
        window: list[tuple[float, float]] = []
        total, rl_steps, previous = 0.0, 0, None
        for _ in range(LENGTH):
            baseline_action = jirl.to_policy_units(jirl.check_baseline_action(baseline(obs), env.action_space), low, high)
            with torch.inference_mode():
                mean, log_std = actor(torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0))
                sampled = torch.tanh(torch.normal(mean, log_std.exp(), generator=generator))[0].numpy()
            m, s = mean[0].numpy().astype(np.float64), log_std[0].numpy().astype(np.float64)
            rho = jirl.divergence(m, s, baseline_action)
            window = (window + [(jirl.squashed_log_prob(m, s, baseline_action), float(np.log(np.logaddexp(0.0, rho))))])[-(k + 1) :]
            rl_acts = sum(w[0] for w in window) > np.log(c) + sum(w[1] for w in window)
            if previous is not None and rl_acts != previous:
                window = window[-1:]
            previous = rl_acts
            rl_steps += rl_acts
            obs, reward, _, _, _ = env.step(jirl.to_env_units(sampled if rl_acts else baseline_action.astype(np.float32), low, high))
            total += float(reward)
        found.append((total, rl_steps))
    return found


def one_ulp_apart() -> float:
    """A float32 mean whose tanh, taken in float64 and rounded, is one ulp from torch's float32 tanh on this
    CPU, as the evaluation takes it (on a (1, 1) tensor). Which means differ depends on the CPU's kernels;
    on the AMD EPYC machines about 1 in 2,000."""
    grid = np.linspace(-3.0, 3.0, 20_001, dtype=np.float32)
    rounded = np.tanh(grid.astype(np.float64)).astype(np.float32)
    for mean in grid[rounded != torch.tanh(torch.from_numpy(grid)).numpy()]:
        if np.tanh(np.float64(mean)).astype(np.float32) != torch.tanh(torch.tensor([[mean]])).item():
            return float(mean)
    pytest.skip("torch's float32 tanh rounds as float64's on every mean of the grid here: no mean tells the two apart")


@pytest.mark.parametrize("constant", [False, True], ids=["trained-like", "one-ulp-apart"])
def test_alone_is_the_final_evaluation(checkpoint, tmp_path, monkeypatch, constant):
    """The evaluation's actions to the last bit: on Walker2D an action one float32 ulp away (a tanh taken
    in float64) sends an episode elsewhere. Pendulum's returns would hide it, so the actions are compared."""
    path = checkpoint[0]
    if constant:  # the fixture's checkpoint, its actor's mean made that mean in every state
        saved = torch.load(path, weights_only=False)
        saved["actor"]["fc_mean.weight"].zero_()
        saved["actor"]["fc_mean.bias"].fill_(one_ulp_apart())
        path = tmp_path / "constant.cleanrl_model"
        torch.save(saved, path)
    applied: list[bytes] = []
    step = PendulumEnv.step
    monkeypatch.setattr(PendulumEnv, "step", lambda env, u: (applied.append(np.asarray(u).tobytes()), step(env, u))[1])
    found = episode_start.drive(episode_start.load(str(path)), 2)
    by_tool, applied[:] = applied[:], []
    evaluated = load_script("sac_continuous").evaluate(str(path), "Pendulum-v1", 2, SEED)
    assert len(by_tool) == 2 * LENGTH and by_tool == applied
    assert [e.episode_return for e in found] == evaluated
    assert [(e.length, e.terminated, e.rl_steps, e.baseline_at_start, e.baseline_after) for e in found] == [(LENGTH, False, LENGTH, 0, 0)] * 2


def test_the_baseline_holds_the_first_n_steps_then_the_policy_acts(checkpoint):
    path, actor = checkpoint
    found = episode_start.drive(episode_start.load(str(path)), 2, handoff=7)
    assert [e.episode_return for e in found] == pytest.approx([by_hand(actor, i, 7) for i in range(2)], rel=1e-5)
    assert [e.rl_steps for e in found] == [LENGTH - 7] * 2
    assert abs(found[0].episode_return - by_hand(actor, 0, 0)) > 0.1  # the hand-off changed the episode, by more than the match's tolerance


def test_a_handoff_past_the_episode_is_the_baseline_alone(checkpoint):
    path, _ = checkpoint
    found = episode_start.drive(episode_start.load(str(path)), 2, handoff=LENGTH)
    env, baseline = gym.make("Pendulum-v1"), get_baseline("Pendulum-v1")
    offset = load_script("sac_continuous").EVAL_SEED_OFFSET
    assert [e.episode_return for e in found] == pytest.approx([rollout(env, baseline, SEED + offset + i).sum() for i in range(2)], rel=1e-6)
    assert [e.rl_steps for e in found] == [0, 0]


def test_the_gate_at_c_0_gives_the_agent_every_step(checkpoint):
    path, _ = checkpoint
    found = episode_start.drive(episode_start.load(str(path)), 2, gate_c=0.0)
    assert [(e.rl_steps, e.baseline_at_start, e.baseline_after) for e in found] == [(LENGTH, 0, 0)] * 2


def test_the_gate_at_a_huge_c_gives_the_baseline_every_step_and_counts_where(checkpoint):
    path, _ = checkpoint
    found = episode_start.drive(episode_start.load(str(path)), 2, gate_c=1e300, start_steps=15)
    assert [(e.rl_steps, e.baseline_at_start, e.baseline_after) for e in found] == [(0, 15, LENGTH - 15)] * 2
    alone = episode_start.drive(episode_start.load(str(path)), 2, handoff=LENGTH)
    assert [e.episode_return for e in found] == pytest.approx([e.episode_return for e in alone], rel=1e-9)


def test_the_gate_between_the_two_is_alg_3_with_the_policys_draws(checkpoint):
    path, actor = checkpoint
    found = episode_start.drive(episode_start.load(str(path)), 2, gate_c=1e3, sample_seed=2)
    by_hand = by_hand_gate(actor, 2, 1e3, 2)
    assert [e.rl_steps for e in found] == [n for _, n in by_hand] and 0 < found[0].rl_steps < LENGTH
    assert [e.episode_return for e in found] == pytest.approx([r for r, _ in by_hand], rel=1e-9)


def test_a_baseline_with_a_memory_is_reset_at_each_episode(checkpoint, monkeypatch):
    path, _ = checkpoint

    class Remembering:
        resets = 0

        def reset(self) -> None:
            self.resets += 1

        def __call__(self, obs: np.ndarray) -> np.ndarray:
            return np.zeros(1, dtype=np.float32)

    remembering = Remembering()
    monkeypatch.setattr(episode_start, "get_baseline", lambda env_id: remembering)
    episode_start.drive(episode_start.load(str(path)), 3, handoff=5)
    assert remembering.resets == 3


def test_the_gate_between_the_two_shares_the_steps_and_repeats_with_its_seed(checkpoint):
    path, _ = checkpoint
    shares = {}
    for c in (1e-3, 1.0, 1e3):
        found = episode_start.drive(episode_start.load(str(path)), 2, gate_c=c, sample_seed=1)
        assert all(e.rl_steps + e.baseline_at_start + e.baseline_after == e.length for e in found)
        assert found == episode_start.drive(episode_start.load(str(path)), 2, gate_c=c, sample_seed=1)
        shares[c] = sum(e.rl_steps for e in found)
    assert 0 < shares[1e3] < 2 * LENGTH and shares[1e-3] > shares[1e3]  # a larger C hands the baseline more steps


def test_the_gate_reports_the_log_density_it_weighs_at_the_start(checkpoint):
    path, actor = checkpoint
    sac = load_script("sac_continuous")
    env = gym.make("Pendulum-v1")
    obs, _ = env.reset(seed=SEED + sac.EVAL_SEED_OFFSET)
    with torch.inference_mode():
        mean, log_std = actor(torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0))
    baseline_action = np.asarray(get_baseline("Pendulum-v1")(obs), dtype=np.float64) / 2.0  # in [-1, 1]
    x = np.arctanh(np.clip(baseline_action, -1 + 1e-3, 1 - 1e-3))
    std = np.exp(log_std[0].numpy().astype(np.float64))
    by_hand = float(np.sum(-0.5 * ((x - mean[0].numpy()) / std) ** 2 - np.log(std * np.sqrt(2 * np.pi)) - np.log1p(-np.tanh(x) ** 2)))
    found = episode_start.drive(episode_start.load(str(path)), 1, gate_c=1e300, start_steps=1)  # the baseline acts: the episode is its own
    assert found[0].log_prob_at_start == pytest.approx(by_hand, rel=1e-4)
    assert np.isfinite(found[0].log_prob_after) and np.isnan(episode_start.drive(episode_start.load(str(path)), 1)[0].log_prob_at_start)


def test_the_table_has_a_row_per_way_and_the_evaluations_median(checkpoint, monkeypatch, capsys):
    path, _ = checkpoint
    monkeypatch.setattr(sys, "argv", ["episode_start.py", "--episodes", "3", "--handoffs", "5,9", "--gate-c", "1", str(path)])
    episode_start.main()
    rows = [table_cells(line) for line in capsys.readouterr().out.splitlines() if line.startswith(f"| {path}")]
    assert [r[1] for r in rows] == ["alone", "the baseline's first 5 steps, then the policy", "the baseline's first 9 steps, then the policy", "gate, C = 1"]
    evaluated = load_script("sac_continuous").evaluate(str(path), "Pendulum-v1", 3, SEED)
    assert rows[0][2].startswith(f"{np.median(evaluated):.1f} ({min(evaluated):.1f} to {max(evaluated):.1f})")
    assert rows[0][3] == f"{LENGTH} ({LENGTH} to {LENGTH})" and rows[0][4] == "0 of 3" and rows[3][5].endswith("%")


def test_no_handoffs_leave_the_policy_alone_and_the_gate(checkpoint, monkeypatch, capsys):
    path, _ = checkpoint
    monkeypatch.setattr(sys, "argv", ["episode_start.py", "--episodes", "1", "--handoffs", "", "--gate-c", "0", str(path)])
    episode_start.main()
    assert [table_cells(line)[1] for line in capsys.readouterr().out.splitlines() if line.startswith(f"| {path}")] == ["alone", "gate, C = 0"]


@pytest.mark.parametrize(
    "options, message",
    [
        (["--episodes", "0"], "--episodes must be at least 1"),
        (["--handoffs", "5,0"], "--handoffs must be at least 1 each"),
        (["--gate-c", "-1"], "--gate-c must be a finite number at least 0, not -1.0"),
        (["--gate-c", "nan"], "--gate-c must be a finite number at least 0, not nan"),
        (["--start-steps", "0"], "--start-steps must be at least 1"),
    ],
)
def test_bad_options_are_refused_by_name(options, message, monkeypatch, capsys, tmp_path):
    monkeypatch.setattr(sys, "argv", ["episode_start.py", *options, str(tmp_path / "x.cleanrl_model")])
    with pytest.raises(SystemExit) as stopped:
        episode_start.main()
    assert stopped.value.code == 2 and message in capsys.readouterr().err


def test_a_policy_that_overflows_is_named_in_its_rows_and_the_next_file_is_measured(checkpoint, monkeypatch, capsys, tmp_path):
    path, _ = checkpoint
    overflowing = tmp_path / "overflowing.cleanrl_model"
    saved = torch.load(path, weights_only=False)
    overflow_the_actor(saved["actor"])
    torch.save(saved, overflowing)
    with pytest.raises(ValueError, match="output at step 0 of episode 0 is not finite"):
        episode_start.drive(episode_start.load(str(overflowing)), 1)
    monkeypatch.setattr(sys, "argv", ["episode_start.py", "--episodes", "1", "--handoffs", "5", "--gate-c", "1", str(overflowing), str(path)])
    episode_start.main()
    rows = [table_cells(line) for line in capsys.readouterr().out.splitlines() if line.startswith("| ")][1:]  # below the header
    overflow = "is not finite: its network overflows float32 there"
    assert [r[1] for r in rows[:3]] == [
        f"alone: failed: the policy's output at step 0 of episode 0 {overflow}",
        f"the baseline's first 5 steps, then the policy: failed: the policy's output at step 5 of episode 0 {overflow}",  # where it first acts
        f"gate, C = 1: failed: the policy's output at step 0 of episode 0 {overflow}",  # where the gate first weighs it
    ]
    assert [r[0] for r in rows[3:]] == [str(path)] * 3


def test_a_file_that_is_no_checkpoint_is_one_row_that_says_so(checkpoint, monkeypatch, capsys, tmp_path):
    garbled = tmp_path / "garbled.cleanrl_model"
    garbled.write_bytes(b"not a checkpoint")
    path, _ = checkpoint
    monkeypatch.setattr(sys, "argv", ["episode_start.py", "--episodes", "1", "--handoffs", "5", str(garbled), str(path)])
    episode_start.main()
    out = capsys.readouterr().out.splitlines()
    rows = [table_cells(line) for line in out if line.startswith(f"| {garbled}")]
    assert len(rows) == 1 and rows[0][1].startswith("unreadable: ") and "checkpoint" in rows[0][1] and rows[0][2:] == [""] * 8
    assert len([line for line in out if line.startswith(f"| {path}")]) == 2  # the next file is still measured
