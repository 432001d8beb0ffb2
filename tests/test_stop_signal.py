"""Ctrl-C or SIGTERM during training ends the run at the training loop's next turn: what was learnt is
saved (--save-model), not evaluated, and the process exits with the status a shell gives a signalled
process. A long run stopped by hand, by `timeout` or by a cluster's time limit keeps its model."""

import os
import re
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from conftest import ROOT, load_script
from test_sac_script import SHORT_RUNS, scalars

SCRIPTS = list(SHORT_RUNS)


def without(args: list[str], flag: str) -> list[str]:
    i = args.index(flag)
    return args[:i] + args[i + 2 :]


def as_in_a_terminal() -> None:
    """SIGINT and SIGTERM as Python sets them up when started from a terminal. A background job of a
    non-interactive shell (CI, `nohup pytest &` in a script) starts with SIGINT ignored, and a run
    keeps an ignored signal ignored."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


@pytest.fixture
def handlers():
    """SIGINT and SIGTERM handlers as in a terminal, by signal; afterwards, those the test found."""
    found = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    as_in_a_terminal()
    yield {sig: signal.getsignal(sig) for sig in found}
    for sig, handler in found.items():
        signal.signal(sig, handler)


@pytest.mark.parametrize("script", SCRIPTS)
def test_the_first_signal_is_recorded_and_the_second_acts_as_before(script, handlers):
    stop = load_script(script).StopRequest()
    assert signal.getsignal(signal.SIGINT) == stop.request and signal.getsignal(signal.SIGTERM) == stop.request
    os.kill(os.getpid(), signal.SIGINT)
    time.sleep(0.01)  # Python runs the handler in the main thread at its next instruction
    assert stop.signum == signal.SIGINT
    assert {sig: signal.getsignal(sig) for sig in handlers} == handlers
    with pytest.raises(KeyboardInterrupt):  # the handler Python starts with
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(1)
    stop.restore()  # again, at the end of the loop: changes nothing
    assert {sig: signal.getsignal(sig) for sig in handlers} == handlers


def test_an_ignored_signal_stays_ignored(sac, handlers):
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # as nohup leaves SIGHUP, a script's background job SIGINT
    stop = sac.StopRequest()
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(0.01)
    assert stop.signum is None
    stop.restore()
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN and signal.getsignal(signal.SIGINT) == handlers[signal.SIGINT]


def test_outside_the_main_thread_no_handler_is_set(sac, handlers):
    made = []
    thread = threading.Thread(target=lambda: made.append(sac.StopRequest()))  # signal.signal would raise there
    thread.start()
    thread.join()
    assert made[0].previous == {} and {sig: signal.getsignal(sig) for sig in handlers} == handlers


# How far each run gets before it is signalled: past --learning-starts (SAC, JIRL), or two whole
# rollouts and updates (PPO+IL, TRPO+IL), so that the update code has run.
TRIGGER = {"sac_continuous": ("global_step=399,", 1), "jirl_sac_continuous": ("global_step=399,", 1), "ppo_il": ("SPS:", 2), "trpo_il": ("SPS:", 2)}
SIGNAL = {"sac_continuous": signal.SIGINT, "jirl_sac_continuous": signal.SIGTERM, "ppo_il": signal.SIGINT, "trpo_il": signal.SIGTERM}
SAVE = {"sac_continuous": True, "jirl_sac_continuous": True, "ppo_il": True, "trpo_il": False}  # one run without --save-model


def test_a_signalled_run_saves_its_model_without_evaluating_it(tmp_path):
    started = {}
    for script in SCRIPTS:  # side by side
        cwd = tmp_path / script
        cwd.mkdir()
        args = [*without(SHORT_RUNS[script], "--total-timesteps"), "--total-timesteps", "10000000", "--baseline-eval-episodes", "1"] + ["--save-model"] * SAVE[script]
        process = subprocess.Popen([sys.executable, str(ROOT / f"{script}.py"), *args], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                   text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"}, preexec_fn=as_in_a_terminal)  # fmt: skip
        started[script] = (process, cwd)
    watchdogs = [threading.Timer(180, process.kill) for process, _ in started.values()]  # a run that hangs fails the test, not CI
    for watchdog in watchdogs:
        watchdog.start()
    try:
        for script, (process, cwd) in started.items():
            (trigger, times), lines, seen = TRIGGER[script], [], 0
            for line in process.stdout:
                lines.append(line)
                seen += line.startswith(trigger)
                if seen == times:
                    break
            assert seen == times, "".join(lines)
            process.send_signal(SIGNAL[script])
            out = "".join(lines) + process.communicate(timeout=60)[0]
            name = SIGNAL[script].name
            assert process.returncode == 128 + SIGNAL[script], out
            saving = "; saving the model without evaluating it" if SAVE[script] else ""
            stopped = re.search(rf"^{name}: training stopped at step ([\d,]+) of ([\d,]+){saving}$", out, re.M)
            assert stopped, out
            step = int(stopped.group(1).replace(",", ""))
            assert step >= (400 if script.startswith(("sac", "jirl")) else 256) and step < 10_000_000
            assert "eval:" not in out and "Traceback" not in out, out
            (run_dir,) = (cwd / "runs").iterdir()
            logged = scalars(run_dir)
            assert "eval/episodic_return" not in logged
            assert len(logged["charts/episodic_return"]) >= 2
            model = run_dir / f"{script}.cleanrl_model"
            if not SAVE[script]:
                assert not model.exists()
                continue
            assert f"model saved to runs/{run_dir.name}/{model.name}" in out
            (episode_return,) = load_script(script).evaluate(str(model), "Pendulum-v1", 1, 0)  # the saved model is whole
            assert np.isfinite(episode_return)
    finally:  # a failed run leaves none of the others training on
        for watchdog in watchdogs:
            watchdog.cancel()
        for process, _ in started.values():
            process.kill()
            process.wait()
