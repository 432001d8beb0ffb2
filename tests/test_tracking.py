"""--track: every script mirrors its run to Weights and Biases (offline here: WANDB_MODE=offline writes the
run to ./wandb and reaches no server). The run file is read back record by record and compared with the
TensorBoard logs it mirrors, the Args the script resolved, the script itself, and the recorded videos."""

import json
import os
import re
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from wandb.proto import wandb_internal_pb2

import warm_python
from conftest import ROOT
from test_sac_script import SHORT_RUNS

BLOCK, HEADER = 32768, 7  # the run file's log format: 32 KiB blocks of records, each after a 7-byte header
FULL, LAST = 1, 4  # a record whole in one piece, and the last piece of one split across blocks


def tracked_env(cwd: Path, **env: str) -> dict[str, str]:
    """This process's environment with no W&B setting of its own, this repository's envs/ importable, and
    a home in cwd (no login, no cache outside cwd); then `env`."""
    return {k: v for k, v in os.environ.items() if not k.startswith("WANDB_")} | {"PYTHONPATH": str(ROOT), "HOME": str(cwd)} | env


def run_copied(script: str, python_args: list[str], cwd: Path, **env: str) -> subprocess.CompletedProcess:
    """`python *python_args` in cwd and tracked_env(cwd, **env), with the script copied into cwd first
    (W&B saves the code of a program under its working directory)."""
    shutil.copy(ROOT / f"{script}.py", cwd)
    return warm_python.run(python_args, cwd=cwd, env=tracked_env(cwd, **env), timeout=300)


def run_tracked(script: str, args: list[str], cwd: Path, **env: str) -> subprocess.CompletedProcess:
    return run_copied(script, [f"{script}.py", *args], cwd, **env)


def wandb_records(path: Path) -> list:
    """The protobuf records of a W&B run file (its .wandb file), in the order they were written."""
    data = path.read_bytes()
    assert data[:7] == b":W&B" + struct.pack("<HB", 0xBEE1, 0), data[:7]  # the format's name, magic number and version 0
    records, pieces, pos = [], [], 7
    while pos + HEADER <= len(data):
        if BLOCK - pos % BLOCK < HEADER:  # a block's tail too short for a header is padding
            pos += BLOCK - pos % BLOCK
            continue
        _, length, kind = struct.unpack_from("<IHB", data, pos)  # checksum, length, piece kind
        pieces.append(data[pos + HEADER : pos + HEADER + length])
        pos += HEADER + length
        if kind in (FULL, LAST):
            record = wandb_internal_pb2.Record()
            record.ParseFromString(b"".join(pieces))
            records.append(record)
            pieces = []
    return records


def offline_run(cwd: Path) -> tuple[Path, list]:
    (run_dir,) = (cwd / "wandb").glob("offline-run-*")
    (run_file,) = run_dir.glob("run-*.wandb")
    return run_dir, wandb_records(run_file)


def history(records: list) -> dict[str, list[tuple[int, float]]]:
    """Each synced tag's (TensorBoard step, value) pairs; W&B stores the step as global_step beside them."""
    found: dict = {}
    for record in records:
        if record.WhichOneof("record_type") == "history":
            items = {item.key or "/".join(item.nested_key): json.loads(item.value_json) for item in record.history.item}
            for key, value in items.items():
                if key != "global_step" and not key.startswith("_"):
                    found.setdefault(key, []).append((items["global_step"], value))
    return found


def logged_scalars(tensorboard_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """Each TensorBoard tag's (step, value) pairs, by step."""
    events = EventAccumulator(str(tensorboard_dir), size_guidance={"scalars": 0})
    events.Reload()
    return {tag: sorted((e.step, e.value) for e in events.Scalars(tag)) for tag in events.Tags()["scalars"]}


def assert_mirrors(records: list, tensorboard_dir: Path) -> None:
    """The W&B run holds every scalar of the TensorBoard folder, each at its step, and nothing else."""
    logged = logged_scalars(tensorboard_dir)
    mirrored = {tag: sorted(pairs) for tag, pairs in history(records).items()}
    assert {"charts/episodic_return", "charts/SPS", "charts/baseline_regret"} <= set(logged)
    assert any(tag.startswith("losses/") for tag in logged)
    assert set(mirrored) == set(logged)
    for tag, pairs in logged.items():
        assert [step for step, _ in mirrored[tag]] == [step for step, _ in pairs], tag
        np.testing.assert_array_equal(np.float32([v for _, v in mirrored[tag]]), np.float32([v for _, v in pairs]), err_msg=tag)


@pytest.mark.parametrize("script", SHORT_RUNS)
def test_track_mirrors_the_tensorboard_logs_the_args_and_the_script(script, tmp_path):
    out = run_tracked(script, [*SHORT_RUNS[script], "--baseline-eval-episodes", "1", "--track"], tmp_path, WANDB_MODE="offline")
    assert out.returncode == 0, out.stderr
    (run_name,) = [p.name for p in (tmp_path / "runs").iterdir()]
    run_dir, records = offline_run(tmp_path)
    (run,) = [r.run for r in records if r.WhichOneof("record_type") == "run"]
    assert (run.display_name, run.project) == (run_name, "jirl")
    config = {item.key: json.loads(item.value_json) for item in run.config.update}
    assert config["seed"] == 1 and config["total_timesteps"] == int(SHORT_RUNS[script][1]) and config["track"] is True
    if script == "jirl_sac_continuous":
        assert config["guidance_steps"] == 125  # as the script resolved it (half the run), not the None given
    if script in ("ppo_il", "trpo_il"):
        assert config["learning_rate"] == 1e-3  # RL Zoo's for Pendulum-v1, resolved from the None given
    assert (run_dir / "files" / "code" / f"{script}.py").read_text() == (ROOT / f"{script}.py").read_text()
    (exit_record,) = [r.exit for r in records if r.WhichOneof("record_type") == "exit"]
    assert exit_record.exit_code == 0
    assert_mirrors(records, tmp_path / "runs" / run_name)


def test_runs_one_after_another_in_one_process_each_get_a_wandb_run_of_their_own(tmp_path):
    """As a notebook or a loop over seeds with runpy runs them. Each run patches TensorBoard for its own
    folder and starts a W&B run of its own (before: `Tensorboard already patched`, and outside a
    notebook wandb returns the earlier run again), whose exit code is the run's. Seed 2's env fails in
    training, which ends the run at its normal end with status 1; seed 3's baseline fails while it is
    measured, which ends the run before that, so the next run finishes its W&B run as failed."""
    (tmp_path / "failing.py").write_text(
        "import gymnasium as gym\nfrom gymnasium.envs.classic_control.pendulum import PendulumEnv\n\n"
        "class Failing(PendulumEnv):\n    def step(self, action):\n        raise ConnectionError('lost the simulator')\n\n"
        "def raising(obs):\n    raise RuntimeError('no controller')\n\n"
        "gym.register('Failing-v0', entry_point=Failing, max_episode_steps=200)\n"
    )
    args = [*SHORT_RUNS["sac_continuous"], "--baseline-eval-episodes", "1", "--track"]
    runs = [(1, []), (2, ["--env-id", "failing:Failing-v0"]), (3, ["--baseline", "failing:raising"]), (4, [])]
    loop = (
        f"import runpy, sys\nfor seed, more in {runs!r}:\n"
        f"    sys.argv = ['sac_continuous.py', *{args!r}, '--seed', str(seed), *more]\n"
        "    try:\n        runpy.run_path('sac_continuous.py', run_name='__main__')\n"
        "    except SystemExit as end:\n        print('exit', seed, end.code)\n"
    )
    out = run_copied("sac_continuous", ["-c", loop], tmp_path, PYTHONPATH=f"{tmp_path}{os.pathsep}{ROOT}", WANDB_MODE="offline")
    assert out.returncode == 0, out.stderr
    assert "exit 2 1\n" in out.stdout and "exit 3 sac_continuous: error: the baseline raised RuntimeError" in out.stdout, out.stdout
    folders = {folder.name.split("__")[2]: folder for folder in (tmp_path / "runs").iterdir()}  # by seed
    assert sorted(folders) == ["1", "2", "3", "4"]
    exit_codes, records = {}, {}
    for run_file in (tmp_path / "wandb").glob("offline-run-*/run-*.wandb"):
        run_records = wandb_records(run_file)
        (run,) = [r.run for r in run_records if r.WhichOneof("record_type") == "run"]
        (exit_record,) = [r.exit for r in run_records if r.WhichOneof("record_type") == "exit"]
        seed = run.display_name.split("__")[2]
        assert run.display_name == folders[seed].name
        exit_codes[seed], records[seed] = exit_record.exit_code, run_records
    assert exit_codes == {"1": 0, "2": 1, "3": 1, "4": 0}
    for seed in ("1", "4"):
        assert_mirrors(records[seed], folders[seed])


@pytest.mark.parametrize("script", SHORT_RUNS)
def test_a_run_whose_logs_fail_after_training_finishes_its_wandb_run_as_failed(script, tmp_path):
    """The evaluation's scalars cannot be written (a full disk): the run ends with status 1 after the
    loop, and its W&B run is finished with that status, not 0."""
    args = [*SHORT_RUNS[script], "--baseline-eval-episodes", "1", "--save-model", "--eval-episodes", "1", "--track"]
    driver = (
        "import errno, runpy, sys\nimport torch.utils.tensorboard as tensorboard\n"
        "real = tensorboard.SummaryWriter.add_scalar\n\n"
        "def add_scalar(self, tag, *args, **kwargs):\n"
        "    if tag == 'eval/episodic_return':\n        raise OSError(errno.ENOSPC, 'No space left on device')\n"
        "    return real(self, tag, *args, **kwargs)\n\n"
        f"tensorboard.SummaryWriter.add_scalar = add_scalar\nsys.argv = ['{script}.py', *{args!r}]\n"
        f"runpy.run_path('{script}.py', run_name='__main__')\n"
    )
    out = run_copied(script, ["-c", driver], tmp_path, WANDB_MODE="offline")
    (run_name,) = [p.name for p in (tmp_path / "runs").iterdir()]
    assert out.returncode == 1 and f"{script}: error: cannot write the logs to runs/{run_name}: No space left on device" in out.stderr, out.stderr
    assert "eval: mean return" in out.stdout  # the failure came after the training and the evaluation
    _, records = offline_run(tmp_path)
    (exit_record,) = [r.exit for r in records if r.WhichOneof("record_type") == "exit"]
    assert exit_record.exit_code == 1


LAST_STEP = {"sac_continuous": 249, "jirl_sac_continuous": 249, "ppo_il": 256, "trpo_il": 256}  # global_step when SHORT_RUNS' loops end


@pytest.mark.parametrize("script", SHORT_RUNS)
def test_track_sends_each_recorded_video_once_written_in_episode_order(script, tmp_path):
    out = run_tracked(script, [*SHORT_RUNS[script], "--baseline-eval-episodes", "1", "--track", "--capture-video"], tmp_path, WANDB_MODE="offline")
    assert out.returncode == 0, out.stderr
    (videos,) = (tmp_path / "videos").iterdir()
    recorded = sorted(videos.glob("*.mp4"))
    assert [p.name for p in recorded] == ["rl-video-episode-0.mp4", "rl-video-episode-1.mp4"]  # RecordVideo's cubic schedule
    run_dir, records = offline_run(tmp_path)
    rows = [{item.key or "/".join(item.nested_key): json.loads(item.value_json) for item in r.history.item} for r in records if r.WhichOneof("record_type") == "history"]
    sent = [(row["videos/path"], row["global_step"]) for row in rows if "videos/path" in row]
    assert len(sent) == 2
    # each as soon as it was written: episode 0's at the step it ended (its return's step), not at the run's end
    (episode_0_end, _), *_ = logged_scalars(tmp_path / "runs" / videos.name)["charts/episodic_return"]
    assert [step for _, step in sent] == [episode_0_end, LAST_STEP[script]]
    for (path, _), original in zip(sent, recorded):  # episode 1's, cut short by the run's end and written as the env closed, too
        assert (run_dir / "files" / path).read_bytes() == original.read_bytes()


@pytest.mark.parametrize("script", SHORT_RUNS)
def test_track_without_wandb_installed_is_a_one_line_error_that_leaves_nothing(script, tmp_path):
    hidden = tmp_path / "hidden"
    hidden.mkdir()
    (hidden / "wandb.py").write_text("raise ImportError(\"No module named 'wandb'\")\n")  # as where it is not installed
    out = run_tracked(script, [*SHORT_RUNS[script], "--track"], tmp_path, PYTHONPATH=f"{hidden}{os.pathsep}{ROOT}")
    assert out.returncode == 1 and "Traceback" not in out.stderr, out.stderr
    assert out.stderr.strip().splitlines()[-1] == f"{script}: error: --track needs Weights and Biases (pip install wandb)"
    assert not (tmp_path / "runs").exists() and not (tmp_path / "wandb").exists()


def test_track_without_a_login_is_a_one_line_error_before_anything_is_trained(tmp_path):
    out = run_tracked("jirl_sac_continuous", [*SHORT_RUNS["jirl_sac_continuous"], "--track"], tmp_path)  # online, with no API key
    assert out.returncode == 1 and "Traceback" not in out.stderr, out.stderr
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith("jirl_sac_continuous: error: --track: Weights and Biases did not start: ") and "API key" in last, last
    assert "global_step=" not in out.stdout and "baseline:" not in out.stdout
    assert not (tmp_path / "runs").exists()


def test_bad_input_with_track_starts_no_wandb_run(tmp_path):
    out = run_tracked("sac_continuous", ["--env-id", "NoSuchEnv-v0", "--track"], tmp_path, WANDB_MODE="offline")
    assert out.returncode == 1 and out.stderr.strip().splitlines()[-1].startswith("sac_continuous: error: unknown env id 'NoSuchEnv-v0'"), out.stderr
    assert not (tmp_path / "wandb").exists() and not (tmp_path / "runs").exists()


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="finds W&B's process in /proc")
def test_a_wandb_process_that_dies_during_the_run_ends_neither_the_training_nor_the_run(tmp_path):
    """W&B's own process (wandb-core, this run's child) is killed as the first video is sent, at episode
    0's end: the training goes on to its end, saves and evaluates its model, and the run exits 0. stderr
    names the video not sent and the W&B run not finished, in one line each, with no traceback (wandb's
    exit hook raised one too until torn down). A second run in the same process (a notebook's next cell)
    gets a W&B run of its own, which mirrors its folder (its start raised on the dead run until caught)."""
    args = [*SHORT_RUNS["sac_continuous"], "--baseline-eval-episodes", "1", "--save-model", "--eval-episodes", "1", "--track", "--capture-video"]
    driver = (
        "import os, runpy, signal, sys, wandb\nreal = wandb.Video.__init__\n\n"
        "def video(self, *args, **kwargs):\n"
        "    for pid in filter(str.isdigit, os.listdir('/proc')):\n"
        "        try:\n"
        "            ppid = int(open(f'/proc/{pid}/stat').read().rsplit(')', 1)[1].split()[1])\n"
        "            command = open(f'/proc/{pid}/cmdline', 'rb').read()\n"
        "        except OSError:\n            continue\n"
        "        if ppid == os.getpid() and b'wandb-core' in command:\n"
        "            os.kill(int(pid), signal.SIGKILL)\n            os.waitpid(int(pid), 0)\n            print('killed', pid, flush=True)\n"
        "    real(self, *args, **kwargs)\n\n"
        f"wandb.Video.__init__ = video\nsys.argv = ['sac_continuous.py', *{args!r}]\n"
        "runpy.run_path('sac_continuous.py', run_name='__main__')\n"
        f"sys.argv = ['sac_continuous.py', *{args[:-1]!r}, '--seed', '2']\n"  # no videos: its history is the scalars alone
        "runpy.run_path('sac_continuous.py', run_name='__main__')\n"
    )
    out = run_copied("sac_continuous", ["-c", driver], tmp_path, WANDB_MODE="offline")
    assert out.returncode == 0 and "Traceback" not in out.stderr and "Exception ignored" not in out.stderr, out.stderr
    lines = out.stdout.splitlines()
    killed = next(i for i, line in enumerate(lines) if line.startswith("killed"))
    first_end = next(i for i, line in enumerate(lines) if line.startswith("eval: mean return"))
    assert lines[killed - 1].startswith("global_step=199,") and lines[first_end - 1].startswith("model saved to") and killed < first_end
    folders = {p.name.split("__")[2]: p for p in (tmp_path / "runs").iterdir()}
    assert set(folders) == {"1", "2"} and (folders["1"] / "sac_continuous.cleanrl_model").is_file()
    second = []
    for run_file in (tmp_path / "wandb").glob("offline-run-*/run-*.wandb"):
        records = wandb_records(run_file)
        if [r.run.display_name for r in records if r.WhichOneof("record_type") == "run"] == [folders["2"].name]:
            second.append(records)
    (records,) = second
    assert [r.exit.exit_code for r in records if r.WhichOneof("record_type") == "exit"] == [0]
    assert_mirrors(records, folders["2"])
    assert re.findall(r"^--track: a video could not be sent at step (\d+) \(\w+Error: .+\); the run goes on, sending no more$", out.stderr, re.M) == ["199"], out.stderr
    assert re.search(r"^--track: Weights and Biases did not finish the run \(\w+Error: .+\); runs/ has its logs$", out.stderr, re.M), out.stderr
