"""A training that must end early keeps what it learnt. Ctrl-C or SIGTERM ends the run at the training
loop's next turn; an env that fails (a NaN, an exception of its own) ends it before anything from it
reaches the buffer; a baseline that fails (a bad action, an exception of its own, its env failing in
its own episode) ends it with its error. The model is saved (--save-model), not evaluated, and the
process exits with the status a shell gives a signalled process, or 1. A long run stopped by hand, by
`timeout`, by a cluster's time limit, by a simulation that diverged or broke, or by a baseline that
broke keeps its model."""

import contextlib
import errno
import fcntl
import io
import os
import pty
import re
import resource
import runpy
import select
import shutil
import signal
import subprocess
import sys
import termios
import threading
import time
from pathlib import Path
from typing import Callable, Iterator

import gymnasium as gym
import numpy as np
import pytest
import torch
import torch.utils.tensorboard as tensorboard
from gymnasium.envs.classic_control.pendulum import PendulumEnv
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from conftest import ROOT, load_script
from test_sac_script import SHORT_RUNS, scalars
from test_same_seed import tensors

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
    assert (stop.reason, stop.status) == ("SIGINT received", 130)
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
    assert stop.reason is None
    stop.restore()
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN and signal.getsignal(signal.SIGINT) == handlers[signal.SIGINT]


def test_outside_the_main_thread_no_handler_is_set(sac, handlers):
    made = []
    thread = threading.Thread(target=lambda: made.append(sac.StopRequest()))  # signal.signal would raise there
    thread.start()
    thread.join()
    assert made[0].previous == {} and {sig: signal.getsignal(sig) for sig in handlers} == handlers


def test_sigterm_after_the_loop_is_gone_ends_the_process_as_by_default(tmp_path):
    """A SIGTERM that the loop that made the handler can no longer read takes the default action: the
    process ends, signalled, instead of going on as if nothing came."""
    code = (
        "import os, runpy, signal, sys, time\n"
        f"script = runpy.run_path({str(ROOT / 'sac_continuous.py')!r})\n"
        "signal.signal(signal.SIGTERM, signal.SIG_DFL)\n"
        "def loop():\n"
        "    return script['StopRequest']()  # a loop that made its request and ended without restore()\n"
        "stop = loop()\n"
        "assert signal.getsignal(signal.SIGTERM) == stop.request, 'no handler to test'\n"
        "os.kill(os.getpid(), signal.SIGTERM)\n"
        "time.sleep(5)\n"
        "print('went on after SIGTERM', stop.reason)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert done.returncode == -signal.SIGTERM, done.stdout + done.stderr
    assert "went on" not in done.stdout


# How far each run gets before it is signalled: past --learning-starts (SAC, JIRL), or two whole
# rollouts and updates (PPO+IL, TRPO+IL), so that the update code has run.
TRIGGER = {"sac_continuous": ("global_step=399,", 1), "jirl_sac_continuous": ("global_step=399,", 1), "ppo_il": ("SPS:", 2), "trpo_il": ("SPS:", 2)}
SIGNAL = {"sac_continuous": signal.SIGINT, "jirl_sac_continuous": signal.SIGTERM, "ppo_il": signal.SIGINT, "trpo_il": signal.SIGTERM}
SAVE = {"sac_continuous": True, "jirl_sac_continuous": True, "ppo_il": True, "trpo_il": False}  # one run without --save-model


@contextlib.contextmanager
def side_by_side(tmp_path: Path, start: Callable[[str, list[str], Path], subprocess.Popen], save: dict[str, bool]) -> Iterator[dict]:
    """Each script started with start(script, args, cwd) in a folder of its own, training for 10M steps (with
    --save-model where save says so), all at once: {script: (process, cwd)}. A run that hangs is killed at
    180 s, failing the test, not CI; all of them at the end, so a failed one leaves none of the others training."""
    started = {}
    for script in SCRIPTS:
        cwd = tmp_path / script
        cwd.mkdir()
        args = [*without(SHORT_RUNS[script], "--total-timesteps"), "--total-timesteps", "10000000", "--baseline-eval-episodes", "1"] + ["--save-model"] * save[script]
        started[script] = (start(script, args, cwd), cwd)
    watchdogs = [threading.Timer(180, process.kill) for process, _ in started.values()]
    for watchdog in watchdogs:
        watchdog.start()
    try:
        yield started
    finally:
        for watchdog in watchdogs:
            watchdog.cancel()
        for process, _ in started.values():
            process.kill()
            process.wait()
            if process.stdout is not None:
                process.stdout.close()


def assert_saved_not_evaluated(script: str, cwd: Path, saved: bool = True) -> Path:
    """The run in cwd logged two episodes or more and no evaluation, and saved a whole model (or none); its folder."""
    (run_dir,) = (cwd / "runs").iterdir()
    logged = scalars(run_dir)
    assert "eval/episodic_return" not in logged
    assert len(logged["charts/episodic_return"]) >= 2
    model = run_dir / f"{script}.cleanrl_model"
    if not saved:
        assert not model.exists()
    else:
        (episode_return,) = load_script(script).evaluate(str(model), "Pendulum-v1", 1, 0)
        assert np.isfinite(episode_return)
    return run_dir


def test_a_signalled_run_saves_its_model_without_evaluating_it(tmp_path):
    def start(script: str, args: list[str], cwd: Path) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, str(ROOT / f"{script}.py"), *args], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"}, preexec_fn=as_in_a_terminal)  # fmt: skip

    with side_by_side(tmp_path, start, SAVE) as started:
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
            stopped = re.search(rf"^{name} received: training stopped at step ([\d,]+) of ([\d,]+){saving}$", out, re.M)
            assert stopped, out
            step = int(stopped.group(1).replace(",", ""))
            assert step >= (400 if script.startswith(("sac", "jirl")) else 256) and step < 10_000_000
            assert "eval:" not in out and "Traceback" not in out, out
            run_dir = assert_saved_not_evaluated(script, cwd, SAVE[script])
            if SAVE[script]:
                assert f"model saved to runs/{run_dir.name}/{script}.cleanrl_model" in out


# the line OutputGuard opens a run's stdout.log or stderr.log with, once the run's terminal or pipe has gone
LOST_HEADER = r"\[\d{4}-\d\d-\d\d \d\d:\d\d:\d\d: the (terminal|pipe) of (stdout|stderr) went away \((EIO|EPIPE)\); what the run printed from then on follows\]\n"


def on_a_terminal() -> None:
    """In the child, started in a session of its own: the pty on its stdin becomes its controlling
    terminal, as an ssh session's or a terminal window's is, and SIGHUP takes its default action there."""
    fcntl.ioctl(0, termios.TIOCSCTTY, 0)
    signal.signal(signal.SIGHUP, signal.SIG_DFL)


@pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="no hang-up on Windows")
def test_a_hang_up_saves_the_model_and_keeps_the_lines_the_terminal_lost(tmp_path):
    """An ssh session that drops, or a terminal window closed: the terminal hangs up, the kernel sends
    SIGHUP to the run in it, and every write to it fails from then on (EIO). Each script ends at the
    loop's next turn, exits 129 and keeps a whole model, and its "training stopped" line in its folder's
    stderr.log; a second SIGHUP changes nothing. SIGHUP used to end the run at once, without its model;
    caught alone, the run's next line ("training stopped", on stderr) raised OSError before the save.
    With only the SIGHUP handler redirecting, a run exited 1 once in CI, most likely on an EIO that came
    before its SIGHUP; OutputGuard now takes such a write. Every terminal is read as its run writes to
    it, as an ssh server or terminal window does."""
    terminals = {}  # script: the terminal's other side, as the ssh server or terminal window holds it
    shown = dict.fromkeys(SCRIPTS, "")  # script: what its run has written there

    def start(script: str, args: list[str], cwd: Path) -> subprocess.Popen:
        terminals[script], terminal = pty.openpty()
        process = subprocess.Popen([sys.executable, str(ROOT / f"{script}.py"), *args], cwd=cwd, stdin=terminal, stdout=terminal, stderr=terminal,
                                   start_new_session=True, preexec_fn=on_a_terminal, env={**os.environ, "PYTHONUNBUFFERED": "1"})  # fmt: skip
        os.close(terminal)
        return process

    def read_the_terminals() -> None:
        ready, _, _ = select.select(list(terminals.values()), [], [], 0.05)
        for script, master in list(terminals.items()):
            if master in ready:
                try:
                    shown[script] += os.read(master, 4096).decode(errors="replace")
                except OSError:  # the run ended: nothing is left on the terminal's other side
                    os.close(terminals.pop(script))

    try:
        with side_by_side(tmp_path, start, dict.fromkeys(SCRIPTS, True)) as started:
            for script, (process, cwd) in started.items():
                trigger, times = TRIGGER[script]
                while script in terminals and shown[script].count(f"\n{trigger}") < times:
                    read_the_terminals()
                assert script in terminals, shown[script]
                os.close(terminals.pop(script))  # the hang-up
                time.sleep(0.3)
                process.send_signal(signal.SIGHUP)  # and a second one, as a shell may pass it on, while the run saves its model
                deadline = time.monotonic() + 60
                while process.poll() is None and time.monotonic() < deadline:
                    read_the_terminals()
                assert process.returncode == 128 + signal.SIGHUP, shown[script]
                kept = (assert_saved_not_evaluated(script, cwd) / "stderr.log").read_text()
                assert re.match(LOST_HEADER, kept) and "\nSIGHUP received: training stopped at step " in kept, kept
    finally:
        for master in terminals.values():
            os.close(master)


def reader_and_writer(reader: str) -> tuple[int, int]:
    """The two ends of a new terminal (its other side, as an ssh server holds it, and the run's side) or pipe."""
    return pty.openpty() if reader == "terminal" else os.pipe()


def points_at_dev_null(fd: int) -> bool:
    """Whether a file descriptor of ours is /dev/null."""
    return os.path.samestat(os.stat(fd), os.stat(os.devnull))


def points_at(link: str) -> str:
    """Where a /proc/PID/fd/N link points ("" once that process has ended)."""
    try:
        return os.readlink(link)
    except FileNotFoundError:
        return ""


def received(read_end: int, size: int) -> str:
    """What a reader gets of a run's output within 5 s, up to `size` characters (a terminal's CR LF read as LF)."""
    got = b""
    while len(got.replace(b"\r\n", b"\n")) < size and select.select([read_end], [], [], 5)[0]:
        got += os.read(read_end, 65536)
    return got.replace(b"\r\n", b"\n").decode()


def stream_on(write_end: int, buffering: str) -> io.TextIOWrapper:
    """A text stream on write_end, buffered as Python buffers stdout on a terminal ("line"), on a pipe
    ("block": 8 KB), or not at all, as under `python -u` (PYTHONUNBUFFERED): "none"."""
    if buffering == "none":
        stream = io.TextIOWrapper(io.FileIO(write_end, "w"), write_through=True)
        assert not isinstance(stream.buffer, io.BufferedIOBase)
        return stream
    return os.fdopen(write_end, "w", buffering=1 if buffering == "line" else -1)


@pytest.mark.parametrize("reader", ["terminal", "pipe"])
def test_output_guard_sends_what_has_no_reader_to_dev_null(sac, reader):
    """Without a folder. A line meets the dead reader as it is written, on a pipe too, where the guard
    buffers by line; text without a newline, at the flush."""
    read_end, write_end = reader_and_writer(reader)
    stream = stream_on(write_end, "line" if reader == "terminal" else "block")
    guard = sac.OutputGuard(stream)
    assert guard.write("read\n") == 5
    assert received(read_end, 5) == "read\n"  # with no flush
    os.close(read_end)  # the terminal hangs up, or the pipe's reader ends
    with pytest.raises(OSError) as raised:
        os.write(write_end, b"x")
    assert raised.value.errno == (errno.EIO if reader == "terminal" else errno.EPIPE)
    assert guard.write("lost") == 4
    assert not points_at_dev_null(write_end)  # still in the buffer
    guard.flush()
    assert points_at_dev_null(write_end)
    guard.write("and more\n")
    guard.flush()
    assert guard.fileno() == write_end and guard.encoding == stream.encoding  # the stream's own
    stream.close()


@pytest.mark.parametrize("reader, buffering", [("terminal", "line"), ("pipe", "block"), ("pipe", "none")])
def test_output_guard_keeps_what_its_reader_lost_in_the_runs_folder(sac, reader, buffering, tmp_path):
    """With the run's folder named, its stdout goes on in folder/stdout.log, as nohup's output goes on in
    nohup.out: a line saying when and why, then every line from the one that met the dead reader on.
    On a pipe Python passes stdout on by blocks of 8 KB, and a block that meets the dead reader is lost
    whole: the guard makes it pass each line as written (which also shows `| tee` each line as printed).
    Unbuffered, the stream drops the text of the write that failed, and the guard writes it again."""
    read_end, write_end = reader_and_writer(reader)
    stream = stream_on(write_end, buffering)
    guard = sac.OutputGuard(stream, "stdout", str(tmp_path))
    lines = [f"{i:3d} {'x' * 55}\n" for i in range(200)]  # 12 KB: more than a block
    guard.writelines(lines[:50])
    assert received(read_end, 3000) == "".join(lines[:50])  # each as written, with no flush
    os.close(read_end)
    guard.writelines(lines[50:])
    guard.flush()
    kept = (tmp_path / "stdout.log").read_text()
    header = re.match(LOST_HEADER, kept)
    assert header and header.groups() == (reader, "stdout", "EIO" if reader == "terminal" else "EPIPE")
    assert kept[header.end() :] == "".join(lines[50:])
    assert os.path.samestat(os.stat(write_end), os.stat(tmp_path / "stdout.log"))
    stream.close()


def test_output_guard_whose_folder_cannot_be_written_sends_the_output_to_dev_null(sac, tmp_path):
    read_end, write_end = os.pipe()
    os.close(read_end)
    with os.fdopen(write_end, "w") as stream:
        guard = sac.OutputGuard(stream, "stderr", str(tmp_path / "removed"))  # the run's folder deleted during the run
        guard.write("lost\n")
        guard.flush()
        assert points_at_dev_null(write_end)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("reader", ["terminal", "pipe"])
def test_output_guard_writes_lines_through_itself(sac, reader):
    read_end, write_end = reader_and_writer(reader)
    os.close(read_end)
    with os.fdopen(write_end, "w", buffering=1) as stream:
        sac.OutputGuard(stream).writelines(["lost\n", "and more\n"])
        assert points_at_dev_null(write_end)


def test_output_guard_raises_any_other_error(sac):
    class FullDisk(io.StringIO):
        def write(self, text: str) -> int:
            raise OSError(errno.ENOSPC, "No space left on device")

        def flush(self) -> None:
            raise OSError(errno.ENOSPC, "No space left on device")

    guard = sac.OutputGuard(FullDisk())
    with pytest.raises(OSError, match="No space left on device"):
        guard.write("x")
    with pytest.raises(OSError, match="No space left on device"):
        guard.flush()


def test_output_guard_wraps_each_stream_with_a_reader_once(sac, tmp_path, monkeypatch):
    """Once per process, and then keeping what it loses in the folder of the run that installed it last."""
    read_end, write_end = os.pipe()
    monkeypatch.chdir(tmp_path)
    with os.fdopen(write_end, "w") as pipe, open(tmp_path / "log", "w") as file:
        monkeypatch.setattr(sys, "stdout", pipe)
        monkeypatch.setattr(sys, "stderr", file)
        sac.OutputGuard.install("runs/first")
        assert isinstance(sys.stdout, sac.OutputGuard) and sys.stdout.stream is pipe
        assert (sys.stdout.name, sys.stdout.folder) == ("stdout", str(tmp_path / "runs" / "first"))  # not moved by a later chdir
        assert sys.stderr is file  # a file has no reader to lose
        guarded = sys.stdout
        sac.OutputGuard.install("runs/second")  # a second run in this process
        assert sys.stdout is guarded and sys.stdout.folder == str(tmp_path / "runs" / "second")
        load_script("ppo_il").OutputGuard.install("runs/third")  # or another script's: another copy of the class
        assert sys.stdout is guarded and sys.stderr is file and sys.stdout.folder == str(tmp_path / "runs" / "third")
        monkeypatch.setattr(sys, "stdout", io.StringIO())  # no file descriptor: a notebook's stream, or capsys
        sac.OutputGuard.install()
        assert isinstance(sys.stdout, io.StringIO)
    os.close(read_end)


READER = {"sac_continuous": "terminal", "jirl_sac_continuous": "pipe", "ppo_il": "pipe", "trpo_il": "terminal"}


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="reads where a run's stdout points from /proc")
def test_a_run_whose_output_lost_its_reader_trains_on(tmp_path):
    """A run under disown or setsid whose ssh session dropped gets no SIGHUP, but its terminal fails every
    write (EIO); a run piped to `tee`, whose tee ended, fails with EPIPE. Each used to end at its next print,
    with exit status 1 and no model. Now its stdout and stderr go on in its folder's stdout.log and
    stderr.log and it trains on, until SIGTERM ends it with its model and its "training stopped" line,
    on stderr, is kept there."""
    readers = {}  # script: the reader's end of its terminal or pipe

    def start(script: str, args: list[str], cwd: Path) -> subprocess.Popen:
        readers[script], output = reader_and_writer(READER[script])
        # in a session of its own without a controlling terminal: no SIGHUP reaches it
        process = subprocess.Popen([sys.executable, str(ROOT / f"{script}.py"), *args], cwd=cwd, stdin=subprocess.DEVNULL, stdout=output, stderr=output,
                                   start_new_session=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})  # fmt: skip
        os.close(output)
        return process

    try:
        with side_by_side(tmp_path, start, dict.fromkeys(SCRIPTS, True)) as started:
            for script, (process, cwd) in started.items():
                trigger, times = TRIGGER[script]
                shown = ""
                while shown.count(f"\n{trigger}") < times and process.poll() is None:
                    if select.select([readers[script]], [], [], 0.05)[0]:
                        shown += os.read(readers[script], 4096).decode(errors="replace")
                os.close(readers.pop(script))  # the terminal hangs up, or tee ends
                stdout, deadline = f"/proc/{process.pid}/fd/1", time.monotonic() + 120
                while points_at(stdout).startswith(("pipe:", "/dev/pts/")) and time.monotonic() < deadline:  # until a write meets the dead reader
                    time.sleep(0.05)
                assert process.poll() is None, f"{script} ended at its first print without a reader, status {process.returncode}: {shown}"
                (run_dir,) = (cwd / "runs").iterdir()
                assert points_at(stdout) == str(run_dir / "stdout.log"), shown
                process.send_signal(signal.SIGTERM)
                assert process.wait(timeout=60) == 128 + signal.SIGTERM
                assert_saved_not_evaluated(script, cwd)
                header = LOST_HEADER.replace("(terminal|pipe)", READER[script])
                assert re.match(header.replace("(stdout|stderr)", "stdout"), (run_dir / "stdout.log").read_text())
                kept = (run_dir / "stderr.log").read_text()
                assert re.match(header.replace("(stdout|stderr)", "stderr"), kept)
                assert re.search(r"\nSIGTERM received: training stopped at step [\d,]+ of [\d,]+; saving the model without evaluating it\n", kept), kept
    finally:
        for reader in readers.values():
            os.close(reader)


def test_flaw_names_what_makes_an_envs_return_unusable(sac):
    obs = np.array([0.5, -1.0, 3.0], dtype=np.float32)
    for reward in (-2.5, 0, True, np.float32(1.5), np.int64(-3), np.array(2.0)):  # anything float() takes as one number
        assert sac.flaw(obs, (3,), reward) == ""
    assert sac.flaw(obs, (3,)) == "" and sac.flaw(obs.astype(np.float64), (3,)) == "" and sac.flaw(np.array([1, 2, 3]), (3,)) == ""
    for bad in (np.nan, np.inf, -np.inf):
        assert sac.flaw(np.array([0.5, bad, 3.0]), (3,), bad) == "a non-finite observation"  # the observation is named first
        assert sac.flaw(obs, (3,), bad) == "a non-finite reward"
    assert sac.flaw(obs[:2], (3,)) == "an observation of shape (2,), not its space's (3,)"
    assert sac.flaw(obs.reshape(3, 1), (3,), np.nan) == "an observation of shape (3, 1), not its space's (3,)"
    assert sac.flaw(np.array([0.5, None, 3.0]), (3,)) == "an observation of dtype object, not numbers"
    assert sac.flaw(np.array(["0.5", "1", "3"]), (3,)) == "an observation of dtype <U3, not numbers"
    assert sac.flaw(obs, (3,), None) == "a reward that is not a number (None)"
    assert sac.flaw(obs, (3,), "1.0") == "a reward that is not a number ('1.0')"
    assert sac.flaw(obs, (3,), np.array([-1.25])) == "a reward that is not a number (array([-1.25]))"
    assert sac.flaw(obs, (3,), list(range(100))) == f"a reward that is not a number ({str(list(range(100)))[:60]})"  # at most 60 characters of it
    for flags in ((True, False), (np.True_, np.False_), (0, 1), (np.array([True]), False)):  # what worked before, stored as 1 and 0
        assert sac.flaw(obs, (3,), 1.0, *flags) == ""
    for flags, said in (((None, False), "None, truncated=False"), ((False, "False"), "False, truncated='False'"),
                        ((np.array([False, True]), False), "array([False,  True]), truncated=False"), ((2, False), "2, truncated=False")):  # fmt: skip
        assert sac.flaw(obs, (3,), 1.0, *flags) == f"flags terminated={said}, where each must be True or False"


class DivergingPendulum(PendulumEnv):
    """Pendulum-v1 whose episode from reset seed `failing_seed` (3: a run's third, at the default --seed
    1) fails at its 50th step, or at the reset itself, as `how` says: it diverges ("nan"), raises an error
    of its own ("raises": a simulator that lost its connection, after which it cannot close either), or
    returns an observation missing a number ("shape": a robot's bridge that dropped a sensor's field),
    or, at the step only, a termination flag of None ("flag": a field missing from the bridge's message)."""

    at_reset = False
    how = "nan"
    lost = False
    failing_seed = 3

    def fail(self, obs: np.ndarray) -> np.ndarray:
        if self.how == "raises":
            self.lost = True
            raise ConnectionError("lost the simulator")
        return obs[:2] if self.how == "shape" else obs * np.nan

    def close(self):
        super().close()
        if self.lost:
            raise ConnectionError("no simulator to close")

    def reset(self, *, seed=None, options=None):
        obs, info = super().reset(seed=seed, options=options)
        self.diverging, self.t = seed == self.failing_seed, 0
        return (self.fail(obs) if self.diverging and self.at_reset else obs), info

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        self.t += 1
        if self.diverging and self.t == 50:
            if self.how == "flag":
                return obs, reward, None, truncated, info
            return self.fail(obs), float("nan"), terminated, truncated, info
        return obs, reward, terminated, truncated, info


def line_of(code: str) -> int:
    """The number of the line of this file that holds `code`, read from the file: the line a message
    must name is found independently of the code under test."""
    with open(__file__) as file:
        (number,) = [n for n, line in enumerate(file, 1) if code in line and "line_of(" not in line]
    return number


ENV_RAISING_LINE = line_of('raise ConnectionError("lost the simulator")')


def env_failure(at_reset: bool, how: str) -> str:
    """The line DivergingPendulum's failure in the episode from reset seed 3 ends a run with."""
    where = "at reset seed 3" if at_reset else "in the episode from reset seed 3"
    if how == "raises":
        return f"DivergingPendulum-v0 raised ConnectionError (test_stopping.py, line {ENV_RAISING_LINE}) {where}: lost the simulator"
    what = {"shape": "an observation of shape (2,), not its space's (3,)", "nan": "a non-finite observation",
            "flag": "flags terminated=None, truncated=False, where each must be True or False"}[how]  # fmt: skip
    return f"DivergingPendulum-v0 returned {what} {where}"


gym.register("DivergingPendulum-v0", entry_point=DivergingPendulum, max_episode_steps=200)
FAILS_AT_RESET = ["nan", "raises", "shape"]  # DivergingPendulum's ways to fail; a reset has no flags
FAILS_AT_STEP = [*FAILS_AT_RESET, "flag"]


@pytest.mark.filterwarnings("ignore:.*(NaN value|not within the observation space).*")
@pytest.mark.parametrize("script", SCRIPTS)
def test_checked_env_passes_a_working_env_through_and_names_its_failures(script, monkeypatch, capsys):
    checked = load_script(script).CheckedEnv(gym.make("DivergingPendulum-v0"), "DivergingPendulum-v0")
    bare = gym.make("Pendulum-v1")
    for seed in (1, 3):  # what a working env returns passes unchanged (seed 3 fails only at its 50th step)
        for got, want in zip(checked.reset(seed=seed), bare.reset(seed=seed)):
            np.testing.assert_equal(got, want)
        for t in range(49):
            action = np.array([np.sin(t)], dtype=np.float32)
            for got, want in zip(checked.step(action), bare.step(action)):
                np.testing.assert_equal(got, want)
    with pytest.raises(ValueError, match=re.escape(env_failure(at_reset=False, how="nan")) + "$"):
        checked.step(np.zeros(1))
    checked.reset()  # unseeded: the message says so
    checked.unwrapped.diverging = True
    checked.unwrapped.t = 49
    with pytest.raises(ValueError, match="^DivergingPendulum-v0 returned a non-finite observation in the episode from an unseeded reset$"):
        checked.step(np.zeros(1))

    capsys.readouterr()
    for how in ("shape", "raises"):
        monkeypatch.setattr(DivergingPendulum, "how", how)
        for at_reset in (False, True):
            monkeypatch.setattr(DivergingPendulum, "at_reset", at_reset)
            with pytest.raises(ValueError) as failed:
                checked.reset(seed=3)
                for _ in range(50):
                    checked.step(np.zeros(1))
            assert str(failed.value) == env_failure(at_reset, how)
            err = capsys.readouterr().err
            if how == "raises":
                assert isinstance(failed.value.__cause__, ConnectionError)
                assert err.rstrip().endswith("ConnectionError: lost the simulator")  # its traceback, printed
            else:
                assert err == "", "a malformed return is the env's answer, not an error of its own: no traceback"
    checked.close()  # the lost simulator cannot close: one line, not a second traceback
    assert capsys.readouterr().err == "warning: DivergingPendulum-v0 failed to close: ConnectionError: no simulator to close\n"

    def interrupted(self, obs):
        raise KeyboardInterrupt  # not the env's failure: passes through as it is

    monkeypatch.setattr(DivergingPendulum, "fail", interrupted)
    with pytest.raises(KeyboardInterrupt):
        checked.reset(seed=3)


class ListPendulum(PendulumEnv):
    """Pendulum-v1 returning its observations as lists, which Gymnasium tolerates with a warning."""

    def reset(self, *, seed=None, options=None):
        obs, info = super().reset(seed=seed, options=options)
        return list(obs), info

    def step(self, action):
        obs, *rest = super().step(action)
        return (list(obs), *rest)


@pytest.mark.parametrize("script", SCRIPTS)
def test_checked_env_gives_an_observation_returned_as_a_list_as_an_array(script):
    checked, bare = load_script(script).CheckedEnv(ListPendulum(), "ListPendulum"), PendulumEnv()
    (obs, _), (want, _) = checked.reset(seed=5), bare.reset(seed=5)
    assert isinstance(obs, np.ndarray)
    np.testing.assert_array_equal(obs, want)
    for t in range(20):
        action = np.array([np.cos(t)], dtype=np.float32)
        (obs, reward, *_), (want, want_reward, *_) = checked.step(action), bare.step(action)
        assert isinstance(obs, np.ndarray) and reward == want_reward
        np.testing.assert_array_equal(obs, want)


@pytest.mark.parametrize("script", SCRIPTS)
def test_kind_names_an_exception_as_a_user_would_look_it_up(script):
    kind = load_script(script).kind
    assert kind(ZeroDivisionError("float division by zero")) == "ZeroDivisionError"
    assert kind(np.linalg.LinAlgError()) == "numpy.linalg.LinAlgError"
    assert kind(gym.error.ResetNeeded()) == "gymnasium.error.ResetNeeded"


def zero_torque(obs: np.ndarray) -> np.ndarray:
    return np.zeros(1)


@pytest.mark.filterwarnings("ignore:.*(NaN value|not within the observation space).*")  # Gymnasium's env checker says so too
@pytest.mark.parametrize("at_reset, how", [pytest.param(False, how, id=f"step-{how}") for how in FAILS_AT_STEP] + [pytest.param(True, how, id=f"reset-{how}") for how in FAILS_AT_RESET])
@pytest.mark.parametrize("script", SCRIPTS)
def test_a_failing_env_ends_the_training_with_its_model_saved_unharmed(script, at_reset, how, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(DivergingPendulum, "at_reset", at_reset)
    monkeypatch.setattr(DivergingPendulum, "how", how)
    raises = how == "raises"
    args = [*without(SHORT_RUNS[script], "--total-timesteps"), "--total-timesteps", "1000", "--env-id", "DivergingPendulum-v0",
            "--baseline", f"{__name__}:zero_torque", "--regret-estimator", "off", "--save-model"]  # fmt: skip
    monkeypatch.setattr(sys, "argv", [f"{script}.py", *args])
    with pytest.raises(SystemExit) as ended:
        runpy.run_path(str(ROOT / f"{script}.py"), run_name="__main__")
    assert ended.value.code == 1
    out, err = capsys.readouterr()
    # the reset after the second episode's last step, or the third episode's 50th step (SAC counts steps from 0, PPO from 1)
    step = (399 if at_reset else 449) + script.endswith("_il")
    total = "1,000" if script.startswith(("sac", "jirl")) else "896"  # PPO and TRPO train whole rollouts of 128
    assert f"{script}: error: {env_failure(at_reset, how)}: training stopped at step {step} of {total}; saving the model without evaluating it" in err
    assert ("ConnectionError: lost the simulator" in err) == raises, err  # the env's own error is shown where it arose
    assert ("warning: DivergingPendulum-v0 failed to close: ConnectionError: no simulator to close" in err) == raises, err
    assert "eval:" not in out
    (run_dir,) = (tmp_path / "runs").iterdir()
    checkpoint = torch.load(run_dir / f"{script}.cleanrl_model", weights_only=False)
    weights = [t for t in tensors(checkpoint).values() if t.is_floating_point()]
    assert len(weights) >= 10 and all(torch.isfinite(t).all() for t in weights), "NaN reached the networks"
    assert np.isfinite(load_script(script).evaluate(str(run_dir / f"{script}.cleanrl_model"), "Pendulum-v1", 1, 0)[0])
    if script.endswith("_il"):  # the rollout cut short is not learnt from: the last update is the third rollout's
        events = EventAccumulator(str(run_dir))
        events.Reload()
        assert events.Scalars("charts/SPS")[-1].step == 3 * 128


@pytest.mark.filterwarnings("ignore:.*(NaN value|not within the observation space).*")
@pytest.mark.parametrize("how", FAILS_AT_RESET)
@pytest.mark.parametrize("script", SCRIPTS)
def test_an_env_failing_at_the_first_reset_is_a_one_line_error(script, how, tmp_path, monkeypatch, writers_closed):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(DivergingPendulum, "at_reset", True)
    monkeypatch.setattr(DivergingPendulum, "how", how)
    args = [*SHORT_RUNS[script], "--env-id", "DivergingPendulum-v0", "--seed", "3", "--baseline", f"{__name__}:zero_torque", "--regret-estimator", "off"]
    monkeypatch.setattr(sys, "argv", [f"{script}.py", *args])
    with pytest.raises(SystemExit) as ended:
        runpy.run_path(str(ROOT / f"{script}.py"), run_name="__main__")
    assert ended.value.code == f"{script}: error: {env_failure(at_reset=True, how=how)}"


@pytest.mark.filterwarnings("ignore:.*(NaN value|not within the observation space).*")
@pytest.mark.parametrize("script", ["ppo_il", "trpo_il"])
def test_an_env_failing_in_the_cloned_policys_evaluation_is_a_one_line_error(script, tmp_path, monkeypatch, writers_closed):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(DivergingPendulum, "at_reset", True)
    monkeypatch.setattr(DivergingPendulum, "failing_seed", 1_000_001)  # the first evaluation episode's at --seed 1, measured only with regret on
    args = [*SHORT_RUNS[script], "--env-id", "DivergingPendulum-v0", "--baseline", f"{__name__}:zero_torque", "--regret-estimator", "off", "--save-model"]
    monkeypatch.setattr(sys, "argv", [f"{script}.py", *args])
    with pytest.raises(SystemExit) as ended:
        runpy.run_path(str(ROOT / f"{script}.py"), run_name="__main__")
    assert ended.value.code == f"{script}: error: DivergingPendulum-v0 returned a non-finite observation at reset seed 1000001"
    (run_dir,) = (tmp_path / "runs").iterdir()
    assert (run_dir / f"{script}_cloned.cleanrl_model").is_file()  # saved before its evaluation failed


class BaselineFailingAtCall:
    """Zero torque until its `limit`-th call, then NaN, or (`raises`) a ZeroDivisionError of its own: a
    controller that breaks at a state it was never written for."""

    limit = 1000
    raises = False

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, obs: np.ndarray) -> float:
        self.calls += 1
        if self.calls >= self.limit and self.raises:
            return 1.0 / (self.calls - self.calls)
        return float("nan") if self.calls >= self.limit else 0.0


RAISING_LINE = line_of("1.0 / (self.calls - self.calls)")
FAILURE = {False: "the baseline returned nan; expected 1 finite number(s) in env units",
           True: f"the baseline raised ZeroDivisionError (test_stopping.py, line {RAISING_LINE}): float division by zero"}  # fmt: skip


def assert_stopped_with_a_whole_model(script: str, err: str, message: str, step: int, tmp_path) -> None:
    stopped = re.search(rf"^{script}: error: {re.escape(message)}: training stopped at step {step:,} of [\d,]+; saving the model without evaluating it$", err, re.M)
    assert stopped, err
    (run_dir,) = (tmp_path / "runs").iterdir()
    model = run_dir / f"{script}.cleanrl_model"
    assert all(torch.isfinite(t).all() for t in tensors(torch.load(model, weights_only=False)).values() if t.is_floating_point())
    assert np.isfinite(load_script(script).evaluate(str(model), "Pendulum-v1", 1, 0)[0])


# The baseline's call that fails, and the training step then: 200 calls measure the baseline, 200 run the first
# paired episode, and each 200-step training episode ends with another; PPO+IL and TRPO+IL first imitate 400
# steps. JIRL also asks the baseline at every step, so its 700th call is in the paired episode after step 199
# and its 1,000th at step 399.
FAILING_CALL = {("sac_continuous", "paired"): (1000, 599), ("jirl_sac_continuous", "paired"): (700, 199),
                ("jirl_sac_continuous", "every step"): (1000, 399), ("ppo_il", "paired"): (1000, 200), ("trpo_il", "paired"): (1000, 200)}  # fmt: skip


@pytest.mark.parametrize("script, where, raises", [(*site, False) for site in FAILING_CALL] + [("sac_continuous", "paired", True), ("jirl_sac_continuous", "every step", True)])
def test_a_baseline_failing_mid_training_keeps_the_model(script, where, raises, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    call, step = FAILING_CALL[script, where]
    monkeypatch.setattr(BaselineFailingAtCall, "limit", call)
    monkeypatch.setattr(BaselineFailingAtCall, "raises", raises)
    args = [*without(SHORT_RUNS[script], "--total-timesteps"), "--total-timesteps", "1000", "--baseline", f"{__name__}:BaselineFailingAtCall",
            "--regret-estimator", "paired", "--baseline-eval-episodes", "1", "--save-model"]  # fmt: skip
    monkeypatch.setattr(sys, "argv", [f"{script}.py", *args])
    with pytest.raises(SystemExit) as ended:
        runpy.run_path(str(ROOT / f"{script}.py"), run_name="__main__")
    assert ended.value.code == 1
    err = capsys.readouterr().err
    assert_stopped_with_a_whole_model(script, err, FAILURE[raises], step, tmp_path)
    assert ("Traceback (most recent call last)" in err) == raises, err  # the user's own error is shown where it arose


@pytest.mark.parametrize("where, call", [("its measurement", 100), ("the first paired episode", 300)])  # of 200 calls each
@pytest.mark.parametrize("script", SCRIPTS)
def test_a_baseline_failing_before_training_is_a_one_line_error(script, where, call, tmp_path, monkeypatch, writers_closed):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(BaselineFailingAtCall, "limit", call + (400 if script.endswith("_il") else 0))  # after PPO+IL's and TRPO+IL's imitation data
    args = [*SHORT_RUNS[script], "--baseline", f"{__name__}:BaselineFailingAtCall", "--regret-estimator", "paired", "--baseline-eval-episodes", "1"]
    monkeypatch.setattr(sys, "argv", [f"{script}.py", *args])
    with pytest.raises(SystemExit) as ended:
        runpy.run_path(str(ROOT / f"{script}.py"), run_name="__main__")
    assert ended.value.code == f"{script}: error: {FAILURE[False]}"
    (writer,) = writers_closed
    writer.close()  # as the process's exit would
    events = EventAccumulator(writer.log_dir)
    events.Reload()
    assert ("charts/baseline_return" in events.Tags()["scalars"]) == (where == "the first paired episode")


@pytest.mark.parametrize("script", ["ppo_il", "jirl_sac_continuous"])
def test_a_baseline_raising_before_training_is_its_traceback_and_a_one_line_error(script, tmp_path, monkeypatch, capsys, writers_closed):
    # PPO+IL's 100th call falls in its imitation data, JIRL's in the baseline's measurement
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(BaselineFailingAtCall, "limit", 100)
    monkeypatch.setattr(BaselineFailingAtCall, "raises", True)
    args = [*SHORT_RUNS[script], "--baseline", f"{__name__}:BaselineFailingAtCall", "--baseline-eval-episodes", "1"]
    monkeypatch.setattr(sys, "argv", [f"{script}.py", *args])
    with pytest.raises(SystemExit) as ended:
        runpy.run_path(str(ROOT / f"{script}.py"), run_name="__main__")
    assert ended.value.code == f"{script}: error: {FAILURE[True]}"
    assert "ZeroDivisionError: float division by zero" in capsys.readouterr().err


@pytest.mark.parametrize("script", SCRIPTS)
def test_ask_baseline_names_what_a_baseline_raises_and_where(script, capsys):
    ask_baseline = load_script(script).ask_baseline
    assert ask_baseline(lambda obs: obs * 2, np.array([1.0])) == pytest.approx([2.0])
    assert ask_baseline(lambda obs: None, np.array([1.0])) is None  # an intervening baseline that does not intervene
    failing = BaselineFailingAtCall()
    failing.limit, failing.raises = 1, True
    with pytest.raises(ValueError) as raised:
        ask_baseline(failing, np.zeros(3))
    assert str(raised.value) == FAILURE[True]
    assert isinstance(raised.value.__cause__, ZeroDivisionError)
    assert capsys.readouterr().err.rstrip().endswith("ZeroDivisionError: float division by zero")

    def interrupted(obs):
        raise KeyboardInterrupt  # not the baseline's failure: passes through as it is

    with pytest.raises(KeyboardInterrupt):
        ask_baseline(interrupted, np.zeros(3))


@pytest.mark.filterwarnings("ignore:.*(NaN value|not within the observation space).*")
@pytest.mark.parametrize("how", ["nan", "raises"])
def test_an_env_failing_in_the_baselines_own_episode_keeps_the_model(how, tmp_path, monkeypatch, capsys):
    # seed 3's episode fails; with --seed 1 the paired baseline episode from reset seed 3 runs after step 399,
    # before the training episode from the same seed reaches its 50th step
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(DivergingPendulum, "how", how)
    args = [*without(SHORT_RUNS["sac_continuous"], "--total-timesteps"), "--total-timesteps", "1000", "--env-id", "DivergingPendulum-v0",
            "--baseline", f"{__name__}:zero_torque", "--regret-estimator", "paired", "--baseline-eval-episodes", "1", "--save-model"]  # fmt: skip
    monkeypatch.setattr(sys, "argv", ["sac_continuous.py", *args])
    with pytest.raises(SystemExit) as ended:
        runpy.run_path(str(ROOT / "sac_continuous.py"), run_name="__main__")
    assert ended.value.code == 1
    err = capsys.readouterr().err
    assert_stopped_with_a_whole_model("sac_continuous", err, env_failure(False, how), 399, tmp_path)
    assert ("ConnectionError: lost the simulator" in err) == (how == "raises"), err


class FullDiskWriter(tensorboard.SummaryWriter):
    """TensorBoard's writer on a disk that fills at the `at`-th write of `tag`: from then on every write
    raises ENOSPC, as the real one's do once its writing thread has failed."""

    tag, at = "charts/episodic_return", 2
    made: list = []

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.made.append(self)
        self.writes = 0

    def add_scalar(self, tag, *args, **kwargs):
        self.writes += tag == self.tag
        if self.writes >= self.at:
            raise self.error()  # not "failure": CheckedWriter, built on this class, has an attribute of that name
        super().add_scalar(tag, *args, **kwargs)

    def error(self) -> Exception:
        return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


class BuggyWriter(FullDiskWriter):
    """A writer with a bug at the first episode's return, which no check of a run catches: the loop
    crashes, as on a bug of ours or a MemoryError."""

    at = 1

    def error(self) -> Exception:
        return RuntimeError("a bug in the loop")


@pytest.mark.parametrize("script", SCRIPTS)
def test_ctrl_c_after_a_loop_crashed_in_process_interrupts_at_once(script, tmp_path, monkeypatch, handlers):
    """In a Python that goes on after the run crashed (runpy, IPython's %run), the handler the loop left
    hands the next Ctrl-C to Python's own, instead of keeping it for a loop that will never read it."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(tensorboard, "SummaryWriter", BuggyWriter)
    monkeypatch.setattr(BuggyWriter, "made", [])
    monkeypatch.setattr(sys, "argv", [f"{script}.py", *SHORT_RUNS[script]])
    with pytest.raises(RuntimeError, match="a bug in the loop"):
        runpy.run_path(str(ROOT / f"{script}.py"), run_name="__main__")
    (writer,) = BuggyWriter.made
    writer.close()  # as the script would have; puts back the thread hook it set
    left = signal.getsignal(signal.SIGINT)
    assert type(getattr(left, "__self__", None)).__name__ == "StopRequest"  # the crash skipped the loop's restore()
    with pytest.raises(KeyboardInterrupt):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(1)
    assert {sig: signal.getsignal(sig) for sig in handlers} == handlers


@pytest.fixture
def full_disk(monkeypatch):
    monkeypatch.setattr(tensorboard, "SummaryWriter", FullDiskWriter)
    monkeypatch.setattr(FullDiskWriter, "made", [])
    yield
    for writer in FullDiskWriter.made:  # the real writer under the failing one, which the run no longer closes
        tensorboard.SummaryWriter.close(writer)


# The step the training stops at when the second episode's return cannot be logged: SAC and JIRL log it at step 399
# and stop at the next; PPO+IL and TRPO+IL log it at step 400, in their fourth rollout, which they finish and learn from.
LOGS_FAIL_AT = {"sac_continuous": 400, "jirl_sac_continuous": 400, "ppo_il": 512, "trpo_il": 512}


@pytest.mark.parametrize("tag", ["charts/episodic_return", "eval/episodic_return"])
@pytest.mark.parametrize("script", SCRIPTS)
def test_logs_that_cannot_be_written_end_the_run_with_its_model_saved(script, tag, tmp_path, monkeypatch, capsys, full_disk):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(FullDiskWriter, "tag", tag)
    monkeypatch.setattr(FullDiskWriter, "at", 2 if tag.startswith("charts") else 1)
    args = [*without(SHORT_RUNS[script], "--total-timesteps"), "--total-timesteps", "1000", "--eval-episodes", "1", "--save-model"]
    monkeypatch.setattr(sys, "argv", [f"{script}.py", *args])
    with pytest.raises(SystemExit) as ended:
        runpy.run_path(str(ROOT / f"{script}.py"), run_name="__main__")
    out, err = capsys.readouterr()
    (run_dir,) = (tmp_path / "runs").iterdir()
    failure = f"cannot write the logs to runs/{run_dir.name}: No space left on device"
    if tag.startswith("charts"):  # mid-training: stopped as for a failing env
        assert ended.value.code == 1
        assert_stopped_with_a_whole_model(script, err, failure, LOGS_FAIL_AT[script], tmp_path)
        assert "eval:" not in out
    else:  # after training: the model is saved and evaluated, and the run still says its logs are short
        assert ended.value.code == f"{script}: error: {failure}"
        assert "training stopped" not in err and "eval: mean return" in out
    assert "Traceback" not in err
    assert len(FullDiskWriter.made) == 1 and FullDiskWriter.made[0].writes == FullDiskWriter.at  # nothing written after the failure


def test_checked_writer_says_a_failure_of_its_thread_once_and_drops_what_follows(sac, tmp_path, monkeypatch):
    handled = []
    monkeypatch.setattr(threading, "excepthook", handled.append)  # the hook before the writer's
    writer = sac.CheckedWriter(str(tmp_path / "logs"))
    writer.add_scalar("a", 1.0, 0)
    writer.flush()
    assert writer.failure == ""
    shutil.rmtree(tmp_path / "logs")  # the next record cannot be appended to the event file
    writer.add_scalar("a", 2.0, 1)
    deadline = time.monotonic() + 10
    while not writer.failure and time.monotonic() < deadline:  # the thread fails on its own time; the next call says so
        writer.add_text("b", "text")
        time.sleep(0.01)
    assert writer.failure == f"cannot write the logs to {tmp_path / 'logs'}: No such file or directory"
    assert handled == []  # the writing thread's OSError went to no other hook

    def other_thread(error):
        raise error

    for error in (ValueError("not the writer's"), OSError(errno.EIO, "a user's reader thread")):  # an OSError too: not TensorBoard's thread
        thread = threading.Thread(target=other_thread, args=(error,))
        thread.start()
        thread.join()
    assert [type(args.exc_value) for args in handled] == [ValueError, OSError]  # any other thread's error goes on as before
    reached = []
    monkeypatch.setattr(tensorboard.SummaryWriter, "add_scalar", lambda *args, **kwargs: reached.append(args))
    writer.add_scalar("a", 3.0, 2)
    assert reached == []  # dropped, not tried again
    writer.close()  # neither raises
    assert not (tmp_path / "logs").exists()
    assert threading.excepthook == handled.append  # the hook it found is back


FILE_SIZE_LIMIT = 8192  # bytes: more than a model of 8-unit networks (7.4 kB at most), less than a 2,048-step run's logs


def with_a_file_size_limit() -> None:
    """`ulimit -f` as a quota or a nearly full disk acts: a write past the limit fails with EFBIG
    (SIGXFSZ ignored, as it would otherwise end the process first)."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (FILE_SIZE_LIMIT, FILE_SIZE_LIMIT))


def test_logs_failing_for_real_end_each_script_in_one_line_with_its_model_saved(tmp_path):
    """TensorBoard's own writer and its writing thread, which fails first and would print a traceback."""
    started = {}
    for script in SCRIPTS:  # side by side
        cwd = tmp_path / script
        cwd.mkdir()
        args = [*without(without(SHORT_RUNS[script], "--total-timesteps"), "--hidden-size"), "--hidden-size", "8", "--total-timesteps", "2048", "--save-model"]
        started[script] = (subprocess.Popen([sys.executable, str(ROOT / f"{script}.py"), *args], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                            text=True, preexec_fn=with_a_file_size_limit), cwd)  # fmt: skip
    try:
        for script, (process, cwd) in started.items():
            out, err = process.communicate(timeout=300)
            (run_dir,) = (cwd / "runs").iterdir()
            stopped = re.search(rf"^{script}: error: cannot write the logs to runs/{run_dir.name}: File too large: training stopped at step ([\d,]+) of 2,048;"
                                " saving the model without evaluating it$", err, re.M)  # fmt: skip
            assert process.returncode == 1 and stopped, err
            assert "Traceback" not in err and "Exception in thread" not in err, err
            (events,) = run_dir.glob("events.out.tfevents.*")
            assert events.stat().st_size <= FILE_SIZE_LIMIT
            model = run_dir / f"{script}.cleanrl_model"
            assert f"model saved to runs/{run_dir.name}/{model.name}" in out
            assert np.isfinite(load_script(script).evaluate(str(model), "Pendulum-v1", 1, 0)[0])
    finally:  # a failed run leaves none of the others running
        for process, _ in started.values():
            process.kill()
            process.communicate()
