"""`python FILE ARGS`, `python -m MODULE ARGS` and `python -c CODE ARGS` for the tests, in a process
forked off a server that has imported torch and the rest of what every script imports first.

A fresh interpreter spends about 1.5 s of CPU importing torch, and a script's first optimizer another
1.4 s importing `torch._dynamo` (torch.optim imports it then), before the script does anything of its
own, and the tests run the scripts some two hundred times. `run` gives what `subprocess.run` gives:
the run's own process, argv, working directory and environment; `sys.path` (the script's folder or
the working directory, then PYTHONPATH, then the interpreter's own: never this repository's root or
`tests/` unless PYTHONPATH names them); stdout and stderr; the exit status (a `SystemExit` message
on stderr and 1, a traceback and 1); non-daemon threads joined, then `atexit` handlers, at its end.
What differs from a fresh interpreter, so that the tests that depend on it start one:
- the modules in PRELOAD are imported already, under the environment the tests started in;
- a traceback starts at the run's own frames (a fresh `-m` run shows two of runpy's before them);
- every run has the server's hash seed, so sets iterate alike in two runs (a test comparing two runs
  for equality starts fresh interpreters, which would not);
- stdin is /dev/null, and the run is not its caller's child (signal it through its `pid`, not
  `os.waitpid`).
"""

from __future__ import annotations

import atexit
import json
import multiprocessing
import multiprocessing.forkserver
import os
import runpy
import shutil
import subprocess
import sys
import tempfile
import threading
import traceback
import types
from pathlib import Path

PRELOAD = ["numpy", "gymnasium", "torch", "torch._dynamo", "torch.optim", "torch.utils.tensorboard", "tyro", "warm_python"]
ENV_AT_START, PATH_AT_START = dict(os.environ), list(sys.path)  # what the server starts under, whatever a test has patched since
_context = None
_interpreter_path: list[str] = []


def _start() -> multiprocessing.context.BaseContext:
    """The forkserver context, its server started under the environment and sys.path the tests started with."""
    global _context
    if _context is None:
        env, path = dict(os.environ), list(sys.path)
        os.environ.clear()
        os.environ.update(ENV_AT_START)
        sys.path[:] = PATH_AT_START
        try:
            context = multiprocessing.get_context("forkserver")
            context.set_forkserver_preload(PRELOAD)
            multiprocessing.forkserver.ensure_running()
            clean = {k: v for k, v in ENV_AT_START.items() if k != "PYTHONPATH"}
            probe = "import json, sys; print(json.dumps(sys.path[1:]))"  # a fresh interpreter's own entries, after '' (or the script's folder)
            _interpreter_path[:] = json.loads(subprocess.run([sys.executable, "-c", probe], env=clean, capture_output=True, text=True, check=True).stdout)
        finally:
            os.environ.clear()
            os.environ.update(env)
            sys.path[:] = path
        _context = context
    return _context


def _own_frames(tb):
    """The traceback from the first frame that is neither this module's nor runpy's: the run's own."""
    while tb is not None and Path(tb.tb_frame.f_code.co_filename).name in ("warm_python.py", "runpy.py", "<frozen runpy>"):
        tb = tb.tb_next
    return tb


def _exit_status(code) -> int:
    """The status a fresh interpreter exits with for `SystemExit(code)`, its message written as it would."""
    if code is None:
        return 0
    if isinstance(code, int):
        return code & 0xFF
    print(code, file=sys.stderr)
    return 1


def _child(argv: list[str], cwd: str, env: dict, server_env: dict, interpreter_path: list[str], out: str, err: str) -> None:
    # the variables PRELOAD's imports set (gymnasium's PYGAME_HIDE_SUPPORT_PROMPT, torch's TORCHINDUCTOR_CACHE_DIR),
    # as they would have in this run: where its own environment does not set them
    env = {**{k: v for k, v in os.environ.items() if server_env.get(k) != v}, **env}
    for fd, name in ((1, out), (2, err)):
        opened = os.open(name, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        os.dup2(opened, fd)
        os.close(opened)
    os.chdir(cwd)
    os.environ.clear()
    os.environ.update(env)
    extra = [entry for entry in env.get("PYTHONPATH", "").split(os.pathsep) if entry]
    first = {"-m": os.getcwd(), "-c": ""}.get(argv[0], os.path.dirname(os.path.abspath(argv[0])))
    sys.path[:] = [first, *extra, *interpreter_path]
    status = 0
    try:
        if argv[0] == "-m":
            sys.argv = [argv[1], *argv[2:]]
            runpy.run_module(argv[1], run_name="__main__", alter_sys=True)
        elif argv[0] == "-c":
            sys.argv = ["-c", *argv[2:]]
            main = sys.modules["__main__"] = types.ModuleType("__main__")
            exec(compile(argv[1], "<string>", "exec"), main.__dict__)
        else:
            sys.argv = list(argv)
            runpy.run_path(argv[0], run_name="__main__")
    except SystemExit as exit:
        status = _exit_status(exit.code)
    except BaseException as error:
        traceback.print_exception(type(error), error, _own_frames(error.__traceback__))
        status = 1
    threading._shutdown()  # type: ignore[attr-defined]  # as at interpreter exit: non-daemon threads first, then atexit
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    raise SystemExit(status)


def run(argv: list[str], cwd: str | Path | None = None, env: dict | None = None, timeout: float | None = None, check: bool = False) -> subprocess.CompletedProcess:
    """What `subprocess.run([sys.executable, *argv], cwd=cwd, env=env, capture_output=True, text=True,
    timeout=timeout, check=check)` returns, for argv `[FILE, ...]`, `["-m", MODULE, ...]` or `["-c", CODE, ...]`."""
    if not argv or (argv[0] in ("-m", "-c") and len(argv) < 2):
        raise ValueError(f"warm_python runs FILE, -m MODULE or -c CODE, not {argv!r}")
    context = _start()
    folder = tempfile.mkdtemp(prefix="warm_python_")
    out, err = os.path.join(folder, "stdout"), os.path.join(folder, "stderr")
    process = context.Process(
        target=_child,
        args=(list(argv), os.getcwd() if cwd is None else str(cwd), dict(os.environ if env is None else env), ENV_AT_START, _interpreter_path, out, err),
    )
    try:
        process.start()
        process.join(timeout)
        timed_out = process.exitcode is None
        if timed_out:
            process.kill()
            process.join()

        def read(name: str) -> str:  # as strict as subprocess.run's text=True: output that is not UTF-8 fails the test
            with open(name, encoding="utf-8") as file:
                return file.read()

        stdout, stderr = read(out), read(err)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    command = [sys.executable, *argv]
    if timed_out:
        raise subprocess.TimeoutExpired(command, timeout, output=stdout, stderr=stderr)
    if check and process.exitcode:
        raise subprocess.CalledProcessError(process.exitcode, command, stdout, stderr)
    return subprocess.CompletedProcess(command, process.exitcode, stdout, stderr)
