"""The Walker2D baseline: the shipped SAC actor, run deterministically with torch alone."""

import errno
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from envs import get_baseline, make_env, rollout
from envs.walker2d import WEIGHTS, Walker2DBaseline, export, load_policy, main

import warm_python
from conftest import ROOT, fill_the_disk_for, load_script, small_checkpoint

# BENCHMARKS.md: the shipped baseline's mean return over 10 episodes (seeds 0-9, min 1494.9, max 1566.2)
MEASURED_RETURN = 1543.3


def test_shipped_weights_say_how_they_were_made():
    _, low, high, metadata = load_policy(WEIGHTS)
    assert "sac_continuous.py" in metadata["command"] and "Walker2DBulletEnv-v0" in metadata["command"]
    assert len(metadata["commit"]) >= 7 and metadata["total_timesteps"] > 0
    np.testing.assert_array_equal(low, -np.ones(6))
    np.testing.assert_array_equal(high, np.ones(6))
    assert WEIGHTS.stat().st_size < 1_000_000, "small enough to commit"


def test_action_is_the_actor_mean_computed_independently():
    baseline = get_baseline("Walker2DBulletEnv-v0")
    assert isinstance(baseline, Walker2DBaseline)
    weights = {k: v.double().numpy() for k, v in torch.load(WEIGHTS, weights_only=True)["policy"].items()}
    rng = np.random.default_rng(0)
    for _ in range(5):
        obs = rng.normal(size=22)
        h = np.maximum(weights["fc1.weight"] @ obs + weights["fc1.bias"], 0.0)
        h = np.maximum(weights["fc2.weight"] @ h + weights["fc2.bias"], 0.0)
        expected = np.tanh(weights["fc_mean.weight"] @ h + weights["fc_mean.bias"])  # action bounds are [-1, 1]
        np.testing.assert_allclose(baseline(obs), expected, atol=1e-5)
    with pytest.raises(ValueError, match="expects 22 observations"):
        baseline(np.zeros(3))


def test_baseline_walks():
    env = make_env("Walker2DBulletEnv-v0")
    rewards = rollout(env, get_baseline("Walker2DBulletEnv-v0"), seed=0)
    env.close()
    assert len(rewards) == 1000 and rewards.sum() > 0.95 * MEASURED_RETURN, f"return {rewards.sum():.1f}, {len(rewards)} steps"


def test_every_cpu_gives_the_same_actions(tmp_path):
    """float32 products round differently with AVX-512, AVX2 and older kernels, and the walker's 1,000 steps
    grow that into another return (with MKL held to AVX2 on one CPU, a fall). The baseline runs in float64
    and rounds its action to float32, so that every CPU acts alike: here three processes leave MKL and
    oneDNN to this CPU's best kernels, hold them to AVX2 ones and to SSE4.2 ones, and their actions over
    an episode's first 300 steps agree to the bit. (Where a CPU's MKL picks the same kernels in all three,
    the test cannot tell float32 from float64.)"""
    code = (
        "import sys\n"
        "import numpy as np\n"
        "from envs import get_baseline, make_env\n"
        "env, baseline = make_env('Walker2DBulletEnv-v0'), get_baseline('Walker2DBulletEnv-v0')\n"
        "obs, _ = env.reset(seed=3)\n"
        "actions = []\n"
        "for _ in range(300):\n"
        "    actions.append(baseline(obs))\n"
        "    obs, *_ = env.step(actions[-1])\n"
        "np.save(sys.argv[1], np.array(actions))\n"
    )
    held = {
        "avx2": {"MKL_ENABLE_INSTRUCTIONS": "AVX2", "DNNL_MAX_CPU_ISA": "AVX2", "ONEDNN_MAX_CPU_ISA": "AVX2", "ATEN_CPU_CAPABILITY": "avx2"},
        "sse42": {"MKL_ENABLE_INSTRUCTIONS": "SSE4_2", "DNNL_MAX_CPU_ISA": "SSE41", "ONEDNN_MAX_CPU_ISA": "SSE41", "ATEN_CPU_CAPABILITY": "default"},
    }
    best = {k: v for k, v in os.environ.items() if not any(k in settings for settings in held.values())}
    for name, env in {"best": best, **{name: {**best, **settings} for name, settings in held.items()}}.items():
        done = subprocess.run([sys.executable, "-c", code, str(tmp_path / name)], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
    actions = np.load(tmp_path / "best.npy")
    assert actions.shape == (300, 6) and actions.dtype == np.float32
    for name in held:
        np.testing.assert_array_equal(np.load(tmp_path / f"{name}.npy"), actions, err_msg=name)


def test_bad_files_give_clear_errors_and_lose_nothing(tmp_path):
    corrupt = tmp_path / "weights.pt"
    corrupt.write_bytes(WEIGHTS.read_bytes()[:300])
    with pytest.raises(ValueError, match="not readable policy weights"):
        Walker2DBaseline(corrupt)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a torch file" * 8)
    with pytest.raises(ValueError, match="garbage.pt is not readable policy weights") as raised:
        load_policy(garbage)
    assert "\n" not in str(raised.value) and "weights_only" not in str(raised.value), "one line, without torch's advice to load it unsafely"
    other = tmp_path / "other.pt"
    torch.save({"format": "something-else"}, other)
    with pytest.raises(ValueError, match="not a jirl-policy-weights-v1 file"):
        load_policy(other)
    with pytest.raises(ValueError, match="not a sac_continuous.py checkpoint"):
        export(other, tmp_path / "out.pt")
    a_list = tmp_path / "list.pt"
    torch.save([1, 2], a_list)
    with pytest.raises(ValueError, match="is not a policy weights file"):
        load_policy(a_list)
    resized = tmp_path / "resized.pt"
    weights = torch.load(WEIGHTS, weights_only=True)
    torch.save({**weights, "hidden_size": weights["hidden_size"] // 2}, resized)
    with pytest.raises(ValueError, match="the weights do not fit the stated sizes"):
        load_policy(resized)
    with pytest.raises(FileNotFoundError):
        load_policy(tmp_path / "missing.pt")
    no_policy = tmp_path / "no_policy.pt"
    torch.save({k: v for k, v in weights.items() if k != "policy"}, no_policy)
    with pytest.raises(ValueError, match="no_policy.pt is a damaged jirl-policy-weights-v1 file: it has no policy$"):
        load_policy(no_policy)
    no_metadata = tmp_path / "no_metadata.pt"
    torch.save({k: v for k, v in weights.items() if k != "metadata"}, no_metadata)
    with pytest.raises(ValueError, match="no_metadata.pt is a damaged jirl-policy-weights-v1 file: it has no metadata$"):
        load_policy(no_metadata)
    short = tmp_path / "short.pt"  # one tensor missing: loading the rest would act with that layer's random init
    torch.save({**weights, "policy": {k: v for k, v in weights["policy"].items() if k != "fc2.bias"}}, short)
    with pytest.raises(ValueError, match="the weights do not fit the stated sizes.*fc2.bias") as raised:
        load_policy(short)
    assert "\n" not in str(raised.value), "torch's message, on one line"
    nan_bias = {**weights["policy"], "fc_mean.bias": weights["policy"]["fc_mean.bias"] * float("nan")}
    for key, value, damage in (("hidden_size", "256", "its hidden_size is '256'"), ("hidden_size", 0, "its hidden_size is 0"), ("obs_dim", 0, "its obs_dim is 0"),
                               ("action_low", 5, "its action_low is 5"), ("action_low", [], "its action_low is []"),
                               ("action_low", [None] * 6, "its action_low is [None, None, None, None, None, None]"), ("action_high", [1.0], "its action_high is [1.0]"),
                               ("action_high", [True] * 6, "its action_high is [True, True, True, True, True, True]"),
                               ("policy", {**weights["policy"], 7: torch.zeros(1)}, "its policy holds an entry that is not a named tensor"),
                               ("metadata", None, "its metadata is None"), ("policy", [], "its policy is []"),
                               ("policy", nan_bias, "its policy holds a NaN or infinite weight")):  # fmt: skip
        valued = tmp_path / "valued.pt"  # without the check: a TypeError building the policy, or a baseline acting NaN
        torch.save({**weights, key: value}, valued)
        with pytest.raises(ValueError) as raised:
            load_policy(valued)
        assert str(raised.value) == f"{valued} is a damaged jirl-policy-weights-v1 file: {damage}", key
    assert corrupt.exists() and other.exists() and resized.exists() and no_policy.exists() and not (tmp_path / "out.pt").exists()


def test_export_round_trip_from_a_sac_checkpoint(tmp_path):
    """A checkpoint written by sac_continuous.py exports to weights that act like its actor."""
    checkpoint = tmp_path / "model.cleanrl_model"
    actor = small_checkpoint(load_script("sac_continuous"), checkpoint, "Walker2DBulletEnv-v0", total_timesteps=123)
    out = tmp_path / "weights.pt"
    result = warm_python.run(["-m", "envs.walker2d", "export", str(checkpoint), "--out", str(out), "--command", "cmd", "--commit", "abc1234"],
                             cwd=ROOT)  # fmt: skip
    assert result.returncode == 0, result.stderr
    baseline = Walker2DBaseline(out)
    assert baseline.metadata == {"seed": 1, "total_timesteps": 123, "command": "cmd", "commit": "abc1234"}
    obs = np.random.default_rng(1).normal(size=22).astype(np.float32)
    with torch.no_grad():
        _, _, expected = actor.get_action(torch.from_numpy(obs).unsqueeze(0))
    np.testing.assert_allclose(baseline(obs), expected[0].numpy(), atol=1e-6)
    assert not baseline.policy.training
    # other bounds than Walker2D's [-1, 1]: tanh(mean) is mapped linearly onto [low, high]
    low, high = np.array([-2.0, -1.0, 0.0, -0.5, 1.0, -3.0]), np.array([2.0, 0.0, 4.0, 0.5, 3.0, -1.0])
    rescaled = tmp_path / "rescaled.pt"
    torch.save({**torch.load(out, weights_only=True), "action_low": low.tolist(), "action_high": high.tolist()}, rescaled)
    np.testing.assert_allclose(Walker2DBaseline(rescaled)(obs), low + (expected[0].numpy() + 1) / 2 * (high - low), atol=1e-5)
    saved = torch.load(checkpoint, weights_only=True)
    v1 = tmp_path / "v1.cleanrl_model"  # a checkpoint from before the critics' storage changed still exports
    torch.save({**saved, "format": "jirl-sac-checkpoint-v1"}, v1)
    export(v1, tmp_path / "from_v1.pt")
    np.testing.assert_allclose(Walker2DBaseline(tmp_path / "from_v1.pt")(obs), expected[0].numpy(), atol=1e-6)
    no_args, resized = tmp_path / "no_args.cleanrl_model", tmp_path / "resized.cleanrl_model"
    torch.save({k: v for k, v in saved.items() if k != "args"}, no_args)
    torch.save({**saved, "hidden_size": 8}, resized)
    valued, unfinite = tmp_path / "valued.cleanrl_model", tmp_path / "unfinite.cleanrl_model"
    torch.save({**saved, "args": ["--seed", "1"]}, valued)
    torch.save({**saved, "actor": {**saved["actor"], "fc1.weight": saved["actor"]["fc1.weight"] * float("inf")}}, unfinite)
    for path, message in ((no_args, "is a damaged sac_continuous.py checkpoint: it has no args\n"),
                          (resized, "the actor's weights do not fit the stated sizes: Error(s) in loading state_dict for MeanPolicy: size mismatch"),
                          (valued, "is a damaged sac_continuous.py checkpoint: its args is ['--seed', '1']\n"),
                          (unfinite, "is a damaged sac_continuous.py checkpoint: its actor holds a NaN or infinite weight\n")):  # fmt: skip
        result = warm_python.run(["-m", "envs.walker2d", "export", str(path), "--out", str(tmp_path / "bad.pt")],
                                 cwd=ROOT)  # fmt: skip
        assert result.returncode == 2 and message in result.stderr and "Traceback" not in result.stderr, result.stderr
        assert len(result.stderr.splitlines()) == 1, result.stderr
    assert not (tmp_path / "bad.pt").exists() and not (tmp_path / "bad.pt.tmp").exists()


def test_weights_the_disk_cannot_hold_leave_the_old_ones_and_no_half_file(tmp_path, monkeypatch, capsys):
    checkpoint, out = tmp_path / "model.cleanrl_model", tmp_path / "weights.pt"
    small_checkpoint(load_script("sac_continuous"), checkpoint, "Walker2DBulletEnv-v0")
    out.write_bytes(b"the weights exported before")
    fill_the_disk_for(monkeypatch, r"weights\.pt\.tmp")
    with pytest.raises(OSError) as raised:  # torch.save alone raises RuntimeError("... unexpected pos ...")
        export(checkpoint, out)
    assert raised.value.errno == errno.ENOSPC
    with pytest.raises(SystemExit) as ended:
        main(["export", str(checkpoint), "--out", str(out)])
    assert ended.value.code == 2
    assert capsys.readouterr().err == f"error: [Errno 28] cannot write {out}: No space left on device\n"
    assert out.read_bytes() == b"the weights exported before" and not (tmp_path / "weights.pt.tmp").exists()
    monkeypatch.undo()
    export(checkpoint, out)  # the same call where there is room
    assert Walker2DBaseline(out).metadata["seed"] == 1
