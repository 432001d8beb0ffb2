"""benchmarks/regret_floor.py: the paired regret of a fixed policy, against numbers computed here;
benchmarks/learning.py's table from the logs; the speed comparisons comparing like with like (SB3's
settings are ours, relu_variants.py's critics compute the script's, step_checks.py's and tracking_cost.py's
copies are the scripts' code, profile_sac.py profiles the script's default update); the benchmark tools refusing counts out of range, and ending their child
process on SIGTERM."""

import dataclasses
import sys
import time

import gymnasium as gym
import numpy as np
import pytest
import torch

from conftest import ROOT, load_script, small_checkpoint

sys.path.insert(0, str(ROOT / "benchmarks"))
import regret_floor  # noqa: E402

from envs import get_baseline  # noqa: E402


def rewards_of(policy, seed):
    env = gym.make("Pendulum-v1")
    obs, _ = env.reset(seed=seed)
    rewards, done = [], False
    while not done:
        obs, reward, terminated, truncated, _ = env.step(policy(obs))
        rewards.append(reward)
        done = terminated or truncated
    return np.array(rewards)


def test_the_baseline_against_itself_pays_nothing():
    baseline = get_baseline("Pendulum-v1")
    floor = regret_floor.measure("Pendulum-v1", baseline, baseline, episodes=2, seed_offset=7)
    assert floor.regret_per_episode == 0.0 and floor.regret_per_step_per_episode == 0.0
    assert floor.behind_share == 0.0
    assert floor.policy_return == pytest.approx(floor.baseline_return)
    assert floor.mean_length == 200


def test_a_weaker_policy_against_an_independent_computation():
    baseline = get_baseline("Pendulum-v1")

    def no_torque(obs):
        return np.zeros(1, dtype=np.float32)

    floor = regret_floor.measure("Pendulum-v1", no_torque, baseline, episodes=3, seed_offset=11)
    episode_form, per_step, behind = [], [], []
    for seed in (11, 12, 13):
        r, r_b = rewards_of(no_torque, seed), rewards_of(baseline, seed)
        episode_form.append(max(0.0, r_b.sum() - r.sum()))
        per_step.append(np.clip(r_b - r, 0.0, None).sum())
        behind.append(r.sum() < r_b.sum())
    assert floor.regret_per_episode == pytest.approx(np.mean(episode_form), rel=1e-6)
    assert floor.regret_per_step_per_episode == pytest.approx(np.mean(per_step), rel=1e-6)
    assert floor.behind_share == pytest.approx(np.mean(behind))
    assert floor.regret_per_episode > 0.0


def test_the_floor_over_a_budget():
    floor = regret_floor.Floor(-150.0, -230.0, 2.0, 10.0, 0.4, 200.0)
    assert floor.over(280_000) == pytest.approx((2_800.0, 14_000.0))
    assert floor.over(300) == pytest.approx((3.0, 15.0))  # a budget of 1.5 episodes: not rounded to whole ones


def test_the_floor_of_episodes_of_unequal_lengths(monkeypatch):
    """Episodes that end early (a lander that crashes): each is paired with the baseline's from its reset
    seed, zero after the shorter one ends, and the episodes of a budget are counted by the policy's
    mean length (5 here; the median would be 3)."""

    def policy(obs):
        raise AssertionError("rollout is scripted here")

    def baseline(obs):
        raise AssertionError("rollout is scripted here")

    episodes = {policy: ([1.0, 1.0], [8.0] * 3, [0.0] * 10), baseline: ([2.0, 0.0, 3.0], [2.0] * 3, [0.5] * 10)}
    monkeypatch.setattr(regret_floor, "rollout", lambda env, actor, seed: np.array(episodes[actor][seed - 40]))
    floor = regret_floor.measure("Pendulum-v1", policy, baseline, episodes=3, seed_offset=40)
    # episode form: max(0, 5 - 2), max(0, 6 - 24), max(0, 5 - 0); per step: [1, 0, 3] summed, 0, 10 * 0.5
    assert dataclasses.astuple(floor) == pytest.approx((26 / 3, 16 / 3, 8 / 3, 9 / 3, 2 / 3, 5.0))
    assert floor.over(1_000) == pytest.approx((200 * 8 / 3, 200 * 3.0))


def test_a_checkpoint_acts_with_its_mean_action_in_env_units(tmp_path, sac):
    actor = small_checkpoint(sac, tmp_path / "model.cleanrl_model")
    env_id, policy = regret_floor.checkpoint_policy(tmp_path / "model.cleanrl_model")
    assert env_id == "Pendulum-v1"
    for obs in np.random.default_rng(0).uniform(-1, 1, size=(5, 3)).astype(np.float32):
        with torch.no_grad():
            mean, _ = actor(torch.from_numpy(obs).unsqueeze(0))
        np.testing.assert_allclose(policy(obs), 2.0 * np.tanh(mean[0].numpy()), rtol=1e-5, atol=1e-6)  # Pendulum: [-2, 2]; float32 near 0


def test_a_file_that_is_not_python_source_is_refused_as_a_script(tmp_path):
    import side_by_side

    text = tmp_path / "sac_continuous.txt"
    text.write_text("print('never run')\n")
    with pytest.raises(ImportError, match=f"cannot import {text} as a module: not a Python source file"):
        side_by_side.load_module(str(text), "not_a_script")
    assert "not_a_script" not in sys.modules


def test_a_corrupt_checkpoint_is_reported_and_the_rest_still_run(tmp_path, monkeypatch, capsys, sac):
    good = tmp_path / "good.cleanrl_model"
    small_checkpoint(sac, good)
    bad = tmp_path / "bad.cleanrl_model"
    bad.write_bytes(b"not a checkpoint")
    monkeypatch.setattr(sys, "argv", ["regret_floor.py", "--episodes", "1", "--budget-steps", "400", str(bad), str(good)])
    regret_floor.main()
    rows = capsys.readouterr().out.splitlines()
    assert str(bad) in rows[2] and "unreadable" in rows[2]
    assert str(good) in rows[3] and "unreadable" not in rows[3]
    cells = [cell.strip() for cell in rows[3].split("|")[1:-1]]
    episode_form, per_step = (float(x.replace(",", "")) for x in cells[6].split(" / "))
    # 400 steps are 2 episodes of 200; the budget cells are rounded to whole numbers
    assert per_step == pytest.approx(2 * float(cells[5]), abs=0.6)
    assert episode_form == pytest.approx(2 * float(cells[4]), abs=0.6)
    assert per_step > 0.0


@pytest.mark.parametrize("option, message", [(["--episodes", "0"], "--episodes must be at least 1"),
                                             (["--budget-steps", "-1"], "--budget-steps must be at least 0")])
def test_counts_out_of_range_are_refused(monkeypatch, capsys, option, message):
    monkeypatch.setattr(sys, "argv", ["regret_floor.py", *option, "x.cleanrl_model"])
    with pytest.raises(SystemExit):
        regret_floor.main()
    assert message in capsys.readouterr().err


def test_learning_stops_at_a_failed_seed_with_one_line(monkeypatch, tmp_path):
    import learning

    monkeypatch.setattr(sys, "argv", ["learning.py", "--seeds", "1", "--total-timesteps", "0", "--workdir", str(tmp_path)])
    with pytest.raises(SystemExit, match="learning: error: seed 1 failed"):
        learning.main()


def test_learning_tabulates_the_newest_run_of_each_seed(monkeypatch, tmp_path, capsys):
    """Each seed's row: the mean of its evaluation episodes and the last value of each chart, read from
    the run the script just wrote (an older run of the same seed is left alone); then the median and the
    mean with its confidence interval over the seeds."""
    import os
    import subprocess
    import time

    import learning
    from torch.utils.tensorboard import SummaryWriter

    commands = []

    def train(cmd, cwd, stdout):  # stands for the script: logs what a finished run logs
        commands.append(cmd)
        seed = int(cmd[cmd.index("--seed") + 1])
        for name, scale, age in ((f"Pendulum-v1__jirl_sac_continuous_bench__{seed}__5", 1.0, 0), (f"Pendulum-v1__jirl_sac_continuous_bench__{seed}__9", 7.0, 100)):
            writer = SummaryWriter(str(cwd / "runs" / name))
            for value in (-100.0 * seed, -100.0 * seed - 30.0, -100.0 * seed + 60.0):
                writer.add_scalar("eval/episodic_return", scale * value, 0)
            for step, base, regret, per_step, control, sps in ((100, -500.0, 1.0, 2.0, 0.0, 10.0), (200, -200.0, 10.0 * seed, 30.0 * seed, 0.2 * seed, 40.0 + seed)):
                for tag, value in (("baseline_return", base), ("baseline_regret", regret), ("baseline_regret_per_step", per_step), ("rl_control_fraction", control), ("SPS", sps)):
                    writer.add_scalar(f"charts/{tag}", scale * value, step)
            writer.close()
            os.utime(cwd / "runs" / name, (time.time() - age, time.time() - age))
        return subprocess.CompletedProcess(cmd, 0)

    monkeypatch.setattr(learning.subprocess, "run", train)
    arguments = ["--script", "jirl_sac_continuous.py", "--seeds", "1", "2", "--total-timesteps", "300", "--workdir", str(tmp_path)]
    monkeypatch.setattr(sys, "argv", ["learning.py", *arguments, "--", "--learning-starts", "100"])
    learning.main()
    assert [cmd[cmd.index("--seed") + 1] for cmd in commands] == ["1", "2"] and all(cmd[-2:] == ["--learning-starts", "100"] for cmd in commands)
    rows = {line.split(" | ")[0]: line.split(" | ")[1:] for line in capsys.readouterr().out.splitlines() if line.startswith("| ") and "---" not in line}
    # eval mean -100 s + 10 (its median would be -100 s); the last logs: baseline -200, regrets 10 s and 30 s, RL control 0.2 s, SPS 40 + s
    assert rows["| 1"][:6] == ["-90.0", "-200.0", "10.0", "30.0", "0.2", "41.0"]
    assert rows["| 2"][:6] == ["-190.0", "-200.0", "20.0", "60.0", "0.4", "42.0"]
    assert rows["| median"][:6] == ["-140.0", "-200.0", "15.0", "45.0", "0.3", "41.5"]
    assert rows["| mean ± 95 % CI"][0] == learning.mean_ci([-90.0, -190.0])


def test_side_by_side_rotates_the_order_and_pairs_the_ratios_by_repetition(monkeypatch):
    """The timing under every speed ratio BENCHMARKS.md quotes: repetition r runs the implementations in
    an order rotated by r, each with seed r + 1, and a ratio is the median over repetitions of the
    per-repetition ratios, not a ratio of medians."""
    import side_by_side

    seconds = {"a": [10.0, 5.0, 20 / 6], "b": [20.0, 20.0, 5.0], "c": [1.0, 1.0, 1.0]}  # 1,000 steps: a 100, 200, 300 SPS; b 50, 50, 200
    ran = []

    def timed(cmd, workdir):
        ran.append(cmd)
        name, seed = cmd
        return seconds[name][int(seed) - 1], float(seed)

    monkeypatch.setattr(side_by_side, "timed", timed)
    whole, in_loop = side_by_side.measure(lambda name, seed: [name, str(seed)], ("a", "b", "c"), steps=1_000, repeats=3, workdir=ROOT)
    assert ran == [["a", "1"], ["b", "1"], ["c", "1"], ["b", "2"], ["c", "2"], ["a", "2"], ["c", "3"], ["a", "3"], ["b", "3"]]
    assert whole["a"] == pytest.approx([100.0, 200.0, 300.0]) and whole["b"] == pytest.approx([50.0, 50.0, 200.0])
    assert in_loop == {"a": [1.0, 2.0, 3.0], "b": [1.0, 2.0, 3.0], "c": [1.0, 2.0, 3.0]}
    # a / b per repetition: 2, 4, 1.5 (the ratio of the medians would be 200 / 50 = 4)
    assert side_by_side.ratio_cell(whole, "a", "b") == "2.00 (range 1.50-4.00)"


def test_side_by_side_times_a_process_and_reads_its_last_rate(tmp_path):
    import side_by_side

    seconds, sps = side_by_side.timed([sys.executable, "-c", "print('SPS: 12.5'); print('SPS: 40.25')"], tmp_path)
    assert sps == 40.25 and 0.0 < seconds < 60.0  # the loop's last report: its rate at the end
    assert np.isnan(side_by_side.timed([sys.executable, "-c", "print('no rate')"], tmp_path)[1])
    failing = [sys.executable, "-c", "import sys; print('\\n'.join(f'line {i}' for i in range(20)), file=sys.stderr); sys.exit(3)"]
    with pytest.raises(SystemExit) as stopped:
        side_by_side.timed(failing, tmp_path)
    assert "exited with 3:\nline 5\n" in str(stopped.value) and str(stopped.value).endswith("line 19")  # the last 15 lines of its stderr


def test_track_laps_refuses_zero_episodes(monkeypatch, capsys):
    import track_laps

    monkeypatch.setattr(sys, "argv", ["track_laps.py", "--episodes", "0"])
    with pytest.raises(SystemExit):
        track_laps.main()
    assert "--episodes must be at least 1" in capsys.readouterr().err


@pytest.mark.parametrize(
    "tool, option, message",
    [
        ("sps_jirl_vs_sac", ["--learning-starts", "-1"], "--learning-starts must be at least 0"),
        ("sps_jirl_vs_sac", ["--", "--buffer-size", "100", "--seed=3"], "--seed after `--`: this tool sets --env-id, --seed"),
        ("sps_vs_sb3", ["--widths", "64", "0"], "--widths must be at least 1"),
        ("sps_trust_region", ["--steps", "0"], "--steps must be at least 1"),
        ("sps_trust_region", ["--algos", "ppo", "sac"], "argument --algos: invalid choice: 'sac'"),  # was a KeyError after the first runs
        ("sps_trust_region", ["--env-id", "Hopper-v4"], "argument --env-id: invalid choice: 'Hopper-v4'"),
        ("update_speed", ["--repeats", "0"], "--repeats must be at least 1"),  # each was a median of nothing
        ("relu_variants", ["--repeats", "0"], "--repeats must be at least 1"),
        ("track_speed", ["--repeats", "0"], "--repeats must be at least 1"),
        ("profile_sac", ["--rows", "0"], "--rows must be at least 1"),
        ("deploy_link", ["--send-hz", "nan", "--trials", "0"], "--trials must be at least 1; --send-hz must be at least 1"),
        ("observation_choice", ["--seed", "-1"], "--seed must be at least 0"),
    ],
)
def test_the_speed_and_choice_benchmarks_refuse_counts_out_of_range(tool, option, message, monkeypatch, capsys, tmp_path):
    import importlib

    monkeypatch.setattr(sys, "argv", [f"{tool}.py", *option])
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        importlib.import_module(tool).main()
    assert exit_info.value.code == 2 and message in capsys.readouterr().err


def test_relu_variants_stops_at_a_failed_measurement_showing_why(monkeypatch, tmp_path):
    import subprocess

    import relu_variants

    def failing(cmd, **kwargs):
        return subprocess.CompletedProcess(cmd, 1, stdout="", stderr="Traceback ...\nRuntimeError: the variant broke")

    monkeypatch.setattr(relu_variants.subprocess, "run", failing)
    monkeypatch.setattr(sys, "argv", ["relu_variants.py", "--widths", "8", "--repeats", "1", "--workdir", str(tmp_path)])
    with pytest.raises(SystemExit, match="exited with 1:\nTraceback ...\nRuntimeError: the variant broke"):
        relu_variants.main()
    assert (tmp_path / "sac_copy.py").exists() and (tmp_path / "sac_fused.py").exists()


def test_the_relu_variants_compute_what_the_script_computes(tmp_path):
    """relu_variants.py times two rewrites of the critics (a ReLU that copies, and each hidden layer fused
    into one autograd node with a hand-written backward). Its figures compare like with like only if
    each variant gives the script's Q-values and the script's gradients, for the weights and the inputs."""
    import relu_variants
    from side_by_side import load_module

    paths = relu_variants.write_variants(tmp_path)
    assert paths["fused"].read_text().count("EnsembleLinearReLU.apply") == 2 and "inplace=True" not in paths["copy"].read_text()
    obs, actions = torch.randn(32, 3, dtype=torch.float64), torch.rand(32, 1, dtype=torch.float64) * 2 - 1
    found = {}
    for name, path in paths.items():
        torch.manual_seed(0)
        qf = load_module(str(path), f"sac_{name}").SoftQNetwork(3, 1, 16).double()
        inputs = obs.clone().requires_grad_()
        q = qf(inputs, actions)
        (q.square().sum() + q[0].sum()).backward()  # the two critics' gradients differ
        found[name] = [q.detach(), inputs.grad, *(p.grad for p in qf.parameters())]
    for name in ("copy", "fused"):
        for mine, script in zip(found[name], found["now"]):
            torch.testing.assert_close(mine, script, rtol=1e-12, atol=1e-12)


def test_the_trust_region_speed_benchmark_gives_sb3_the_settings_our_scripts_resolve():
    """sps_trust_region.py compares SPS "at the same settings": each SB3 or sb3-contrib setting it spells out
    is the one ppo_il.py or trpo_il.py resolves for that env (rollout, minibatch, epochs or critic updates,
    discount, GAE lambda, learning rate, entropy coefficient), and SB3 normalises observations and rewards
    exactly where our script does."""
    import sps_trust_region

    for (algo, env_id), settings in sps_trust_region.SETTINGS.items():
        script = load_script(f"{algo}_il")
        args = script.resolve_hyperparameters(script.Args(env_id=env_id))
        ours = dict(n_steps=args.num_steps, gamma=args.gamma, gae_lambda=args.gae_lambda, learning_rate=args.learning_rate)
        if algo == "ppo":
            ours |= dict(batch_size=args.num_steps // args.num_minibatches, n_epochs=args.update_epochs, ent_coef=args.ent_coef)
            normalised = False  # ppo_il.py has no normalisation
        else:
            ours |= dict(batch_size=args.critic_batch_size, n_critic_updates=args.n_critic_updates)
            normalised = args.norm_obs and args.norm_reward
            assert args.norm_obs == args.norm_reward
        assert ({"ent_coef": 0.0} if algo == "ppo" else {}) | settings == ours, (algo, env_id)  # SB3's PPO defaults ent_coef to 0
        assert ((algo, env_id) in sps_trust_region.NORMALIZED) == normalised, (algo, env_id)


class FakeSAC:
    """Stable-Baselines3's SAC as the SAC speed benchmarks call it, recording what it is given."""

    made: dict = {}

    def __init__(self, policy, env, **kwargs):
        FakeSAC.made = dict(kwargs, policy=policy, env=env)
        self.start_time = 0

    def learn(self, total_timesteps):
        self.start_time = time.time_ns() - 10**9

    def predict(self, obs):
        return obs[:1], None

    def train(self, gradient_steps, batch_size):
        FakeSAC.made.setdefault("trained_with", set()).add((gradient_steps, batch_size))


@pytest.mark.parametrize("tool", ["sps_vs_sb3", "update_speed"])
def test_the_sac_speed_benchmarks_give_sb3_the_settings_ours_train_with(tool, monkeypatch, tmp_path, capsys):
    """Both compare SPS "with the same hyperparameters": SB3's learning rate, batch, replay, discount,
    Polyak coefficient, update schedule, widths and entropy tuning are those of the command or the
    `Args` they run our SAC with."""
    import importlib

    import tyro

    monkeypatch.setitem(sys.modules, "stable_baselines3", type(sys)("stable_baselines3"))
    monkeypatch.setattr(sys.modules["stable_baselines3"], "SAC", FakeSAC, raising=False)
    module = importlib.import_module(tool)
    sac = load_script("sac_continuous")
    if tool == "sps_vs_sb3":
        module.sb3_worker(64, 5000, 500, 3)
        assert capsys.readouterr().out.startswith("SPS: ")
        options = module.command("sac_continuous", 64, 5000, 500, 3, tmp_path)[2:]
        assert module.command("jirl_sac_continuous", 64, 5000, 500, 3, tmp_path)[2:] == options  # JIRL runs with SAC's options
        args = tyro.cli(sac.Args, args=options)
        made = FakeSAC.made
        assert (made.pop("learning_starts"), made.pop("seed"), made.pop("env")) == (args.learning_starts, args.seed, args.env_id)
    else:
        module.sb3_worker(64, 3)
        made = FakeSAC.made
        assert made.pop("trained_with") == {(1, 256)} and made.pop("env") == "Pendulum-v1"
        del made["learning_starts"], made["seed"]  # SB3's warm-up and seed; ours samples a filled buffer
        built = []

        def load_module(script):  # the script training_step times, its agent's Args recorded
            loaded = real_load_module(script)
            monkeypatch.setattr(loaded, "SoftActorCritic", lambda obs_dim, act_dim, args: built.append(args) or real_agent(obs_dim, act_dim, args))
            return loaded

        real_load_module, real_agent = module.load_module, sac.SoftActorCritic
        monkeypatch.setattr(module, "load_module", load_module)
        module.training_step(str(ROOT / "sac_continuous.py"), 64)
        (args,) = built
    assert args.policy_lr == args.q_lr and args.policy_frequency == args.target_network_frequency == 1 and args.autotune
    expected = dict(policy="MlpPolicy", learning_rate=args.policy_lr, batch_size=args.batch_size, train_freq=1, gradient_steps=1,
                    ent_coef=f"auto_{args.alpha}", policy_kwargs={"net_arch": [args.hidden_size] * 2}, device="cpu")  # fmt: skip
    if tool == "sps_vs_sb3":
        expected |= dict(buffer_size=int(args.buffer_size), tau=args.tau, gamma=args.gamma)
    else:  # SB3's defaults for these
        assert (args.tau, args.gamma) == (0.005, 0.99)
    assert made == expected


def test_the_jirl_speed_benchmark_gives_both_scripts_the_same_sac_options_and_jirl_alone_its_own(monkeypatch, tmp_path, capsys):
    """sps_jirl_vs_sac.py compares JIRL with SAC "at the same SAC settings" on any env: an option after
    `--` that SAC's Args has goes to both scripts, one only JIRL's has goes to JIRL alone (SAC's parser
    would refuse it), and without `--` the command is Pendulum's as before."""
    import sps_jirl_vs_sac
    import tyro

    ran = []

    def compare(command, steps, repeats, workdir, names):
        ran.extend(command(name, 7) for name in names)
        return "1.0 | 1.0 | 1.00 (range 1.00-1.00) | 1 |"

    monkeypatch.setattr(sps_jirl_vs_sac, "compare", compare)
    given = ["--regret-estimator", "unpaired", "--guidance-schedule", "geometric", "--guidance-fade-steps=5000",
             "--no-use-switch-penalty", "--switch-penalty", "-2.5", "--buffer-size", "20000"]  # fmt: skip
    monkeypatch.setattr(sys, "argv", ["sps_jirl_vs_sac.py", "--env-id", "JetRacerTrack-v0", "--widths", "32", "--steps", "600",
                                      "--learning-starts", "100", "--workdir", str(tmp_path), "--", *given])  # fmt: skip
    sps_jirl_vs_sac.main()
    assert "JetRacerTrack-v0, 600 steps" in capsys.readouterr().out
    jirl_cmd, sac_cmd = ran
    assert jirl_cmd[1].endswith("jirl_sac_continuous.py") and sac_cmd[1].endswith("sac_continuous.py")
    jirl = tyro.cli(load_script("jirl_sac_continuous").Args, args=jirl_cmd[2:])
    sac = tyro.cli(load_script("sac_continuous").Args, args=sac_cmd[2:])
    for name in ("env_id", "seed", "total_timesteps", "learning_starts", "hidden_size", "torch_threads", "regret_estimator", "buffer_size"):
        assert getattr(jirl, name) == getattr(sac, name), name
    assert (sac.env_id, sac.seed, sac.total_timesteps, sac.learning_starts, sac.hidden_size, sac.torch_threads) == ("JetRacerTrack-v0", 7, 600, 100, 32, 1)
    assert (sac.regret_estimator, sac.buffer_size) == ("unpaired", 20000)
    assert (jirl.guidance_schedule, jirl.guidance_fade_steps, jirl.use_switch_penalty, jirl.switch_penalty) == ("geometric", 5000, False, -2.5)
    for option in (["--guidance-schedule", "geometric"], ["--guidance-fade-steps=5000"], ["--no-use-switch-penalty"], ["--switch-penalty", "-2.5"]):
        with pytest.raises(SystemExit):
            tyro.cli(load_script("sac_continuous").Args, args=option)
    capsys.readouterr()
    ran.clear()
    monkeypatch.setattr(sys, "argv", ["sps_jirl_vs_sac.py", "--widths", "64", "--workdir", str(tmp_path)])
    sps_jirl_vs_sac.main()
    assert [cmd[2:] for cmd in ran] == [["--env-id", "Pendulum-v1", "--seed", "7", "--total-timesteps", "4000", "--learning-starts", "1000",
                                         "--hidden-size", "64", "--torch-threads", "1"]] * 2  # fmt: skip


def test_profile_sac_profiles_the_scripts_default_update_after_its_warm_up(monkeypatch, capsys):
    """BENCHMARKS.md's profile of one SAC step: the script's acting and update at the width asked, with
    the script's default delayed actor update, 30 steps of warm-up outside the profiler, the time per
    profiled step, and a table of the rows asked for."""
    import math
    import types

    import profile_sac

    sac = load_script("sac_continuous")
    made, stepped = [], []

    def training_step(script, width, **options):
        made.append((script, width, options))
        step = real_training_step(script, width, **options)
        return lambda i: stepped.append(i) or step(i)

    real_training_step = profile_sac.training_step
    monkeypatch.setattr(profile_sac, "training_step", training_step)
    monkeypatch.setattr(profile_sac, "time", types.SimpleNamespace(perf_counter=iter([1.0, 1.6]).__next__))
    monkeypatch.setattr(sys, "argv", ["profile_sac.py", "--width", "8", "--steps", "3", "--rows", "1000"])
    profile_sac.main()
    out = capsys.readouterr().out
    frequency = sac.Args().policy_frequency
    assert frequency > 1 and made == [(str(ROOT / "sac_continuous.py"), 8, {"policy_frequency": frequency})]
    assert stepped == [*range(30), *range(3)]
    assert out.startswith("width 8: 200.00 ms per step under the profiler\n")  # 0.6 s over 3 steps
    (adam,) = [line.split() for line in out.splitlines() if line.split()[:1] == ["Optimizer.step#Adam.step"]]
    # one critic step per update, and the actor's (alpha's with it) `frequency` times every `frequency`
    # updates: the 3 profiled steps only
    assert int(adam[-1]) == 3 + frequency * math.ceil(3 / frequency)

    monkeypatch.setattr(profile_sac, "time", types.SimpleNamespace(perf_counter=iter([1.0, 1.6]).__next__))
    monkeypatch.setattr(sys, "argv", ["profile_sac.py", "--width", "8", "--steps", "3", "--rows", "2"])
    profile_sac.main()
    rules = [i for i, line in enumerate(capsys.readouterr().out.splitlines()) if line.startswith("---")]
    assert len(rules) == 3 and rules[2] - rules[1] == 3  # two rows between the header's rule and the last


def test_step_checks_times_the_divergence_checks_the_loops_run():
    """benchmarks/step_checks.py times each training loop's check for a diverged agent "as the loops write
    them", in copies of its own: each copy's condition is, word for word, the one in its loop."""
    import re

    copies = re.findall(r"if check and (not math\.isfinite\(.+\)):\n", (ROOT / "benchmarks" / "step_checks.py").read_text())
    loops = ["sac_continuous.py", "jirl_sac_continuous.py", "ppo_il.py", "deploy/jetracer.py"]  # the order of sac_, jirl_, ppo_ and car_action
    assert len(copies) == len(loops)
    for condition, loop in zip(copies, loops):
        assert f"if {condition}:  #" in (ROOT / loop).read_text(), (condition, loop)
    assert f"if {copies[2]}:  #" in (ROOT / "trpo_il.py").read_text()  # TRPO's rollout, timed as PPO's


def test_tracking_cost_times_the_script_with_only_its_w_and_b_start_changed():
    """tracking_cost.py's third form is sac_continuous.py with CleanRL's `sync_tensorboard=True` in place of
    the named TensorBoard folder: two lines differ, and the text is still Python. A change to how the script
    starts W&B must reach the benchmark (it stops at its own check), not make it time something else."""
    import ast

    import tracking_cost

    script = (ROOT / "sac_continuous.py").read_text()
    rewritten = tracking_cost.with_sync_tensorboard(script)
    ast.parse(rewritten)
    before, after = script.splitlines(), rewritten.splitlines()
    changed = [(old.strip(), new.strip()) for old, new in zip(before, after) if old != new]
    assert len(before) == len(after) and len(changed) == 2
    assert changed[0][0].startswith('wandb.tensorboard.patch(root_logdir=f"runs/{run_name}")') and changed[0][1].startswith("pass")
    assert changed[1][1] == changed[1][0].replace("save_code=True)", "save_code=True, sync_tensorboard=True)") != changed[1][0]
    with pytest.raises(AssertionError, match="start_tracking changed"):
        tracking_cost.with_sync_tensorboard(script.replace("save_code=True)", "save_code=False)"))


def test_sigterm_ends_the_training_a_benchmark_waits_for(tmp_path):
    """`kill` reaches the benchmark alone; the training it started must not run on unseen."""
    import os
    import signal
    import subprocess
    import time

    pid_file = tmp_path / "training.pid"
    stand_in = tmp_path / "training.py"  # stands for an algorithm script: records its pid, then trains a minute
    stand_in.write_text(f"import os, time\nopen({str(pid_file)!r}, 'w').write(str(os.getpid()))\ntime.sleep(60)\n")
    err_file = tmp_path / "stderr.txt"  # a file, not a pipe: a training left running would hold a pipe open
    with err_file.open("w") as err:
        bench = subprocess.Popen(
            [sys.executable, str(ROOT / "benchmarks" / "learning.py"), "--script", str(stand_in), "--seeds", "1", "--workdir", str(tmp_path / "work")],
            stderr=err,
        )  # fmt: skip
    deadline = time.monotonic() + 30
    while not (pid_file.exists() and pid_file.read_text()) and time.monotonic() < deadline:
        time.sleep(0.1)
    training = int(pid_file.read_text())
    try:
        bench.send_signal(signal.SIGTERM)
        bench.wait(timeout=10)  # the fixed benchmark has reaped its child by now; the old one left it running
        with pytest.raises(ProcessLookupError):
            os.kill(training, 0)
        assert bench.returncode == 1 and "learning.py: terminated; the process it was waiting for was killed" in err_file.read_text()
    finally:
        try:
            os.kill(training, signal.SIGKILL)
        except ProcessLookupError:
            pass
