"""warm_python.run against a fresh interpreter: the same output, exit status and traceback for each way a run can end."""

import subprocess
import sys
import time

import pytest

import warm_python
from conftest import ROOT

PROBE = """
import atexit, os, sys, threading, time
print("argv", sys.argv[1:], "cwd", os.getcwd(), "PROBE", os.environ.get("PROBE"), "path", sys.path[0], sys.path[1] if len(sys.path) > 1 else "")
print("envs", "importable" if __import__("importlib.util").util.find_spec("envs") else "not importable")
atexit.register(lambda: print("atexit, after the worker:", done))
done = []
threading.Thread(target=lambda: (time.sleep(0.2), done.append(1))).start()  # not a daemon: joined before atexit
print("to stderr", file=sys.stderr)
ending = sys.argv[1]
if ending == "raises":
    {}["missing"]
if ending == "message":
    raise SystemExit("probe: error: a one-line message")
if ending == "status":
    sys.exit(3)
if ending == "sleeps":
    time.sleep(30)
"""


@pytest.mark.parametrize("ending", ["returns", "raises", "message", "status"])
@pytest.mark.parametrize("form", ["file", "-m", "-c"])
def test_a_run_ends_as_in_a_fresh_interpreter(ending, form, tmp_path):
    (tmp_path / "probe.py").write_text(PROBE)
    argv = {"file": [str(tmp_path / "probe.py")], "-m": ["-m", "probe"], "-c": ["-c", PROBE]}[form] + [ending]
    env = {"PROBE": "set", "PYTHONPATH": str(tmp_path / "elsewhere")}
    fresh = subprocess.run([sys.executable, *argv], cwd=tmp_path, env=env, capture_output=True, text=True)
    warm = warm_python.run(argv, cwd=tmp_path, env=env)
    runpy_frames = "".join(line + "\n" for line in fresh.stderr.splitlines() if line.startswith('  File "<frozen runpy>"'))
    assert (warm.returncode, warm.stdout, warm.stderr) == (fresh.returncode, fresh.stdout, fresh.stderr.replace(runpy_frames, ""))
    assert bool(runpy_frames) == (form == "-m" and ending == "raises")
    assert fresh.returncode == {"returns": 0, "raises": 1, "message": 1, "status": 3}[ending]
    assert "envs not importable" in warm.stdout and "atexit, after the worker: [1]" in warm.stdout  # this repository is not on its path
    if warm.returncode:
        with pytest.raises(subprocess.CalledProcessError):
            warm_python.run(argv, cwd=tmp_path, env=env, check=True)
    if ending == "raises":
        assert warm.stderr.startswith("to stderr\nTraceback (most recent call last):\n") and "KeyError: 'missing'" in warm.stderr


def test_a_run_past_its_timeout_is_killed_and_raises_as_subprocess_run_does(tmp_path):
    (tmp_path / "probe.py").write_text(PROBE)
    started = time.monotonic()
    with pytest.raises(subprocess.TimeoutExpired) as raised:
        warm_python.run([str(tmp_path / "probe.py"), "sleeps"], cwd=tmp_path, timeout=1)
    assert time.monotonic() - started < 10 and "to stderr" in raised.value.stderr


def test_a_script_of_this_repository_runs_as_in_a_fresh_interpreter(tmp_path):
    argv = [str(ROOT / "sac_continuous.py"), "--env-id", "NoSuchEnv-v0"]
    fresh = subprocess.run([sys.executable, *argv], cwd=tmp_path, capture_output=True, text=True)
    warm = warm_python.run(argv, cwd=tmp_path)
    assert (warm.returncode, warm.stdout, warm.stderr) == (fresh.returncode, fresh.stdout, fresh.stderr) and warm.returncode == 1


def test_only_files_modules_and_code_are_run():
    for argv in ([], ["-m"], ["-c"]):
        with pytest.raises(ValueError, match="warm_python runs FILE, -m MODULE or -c CODE"):
            warm_python.run(argv, cwd=ROOT)
