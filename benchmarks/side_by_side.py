"""Helpers of the benchmarks: timing implementations side by side (rotating order, fresh processes,
ratios per repetition), an earlier revision of a script, a script loaded as a module, a saved policy,
and SIGTERM ending the process a benchmark is waiting for."""

from __future__ import annotations

import argparse
import importlib.util
import re
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Callable, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def stop_children_on_sigterm() -> None:
    """Make `kill` (SIGTERM) end the benchmark's child process too. SIGTERM reaches the benchmark
    alone, and Python's default ends it at once, leaving the training it waits for running on (for
    hours, on a core another job needs). Raised as SystemExit, it makes subprocess.run kill the
    child on its way out."""

    def terminated(signum: int, frame: object) -> None:
        raise SystemExit(f"{Path(sys.argv[0]).name}: terminated; the process it was waiting for was killed")

    signal.signal(signal.SIGTERM, terminated)


def timed(cmd: list[str], workdir: Path) -> tuple[float, float]:
    """Wall-clock seconds of one process, start to exit (imports included), and the last `SPS: x` it
    printed (its training loop's own rate, imports and setup excluded; NaN if it printed none)."""
    start = time.perf_counter()
    result = checked(subprocess.run(cmd, cwd=workdir, capture_output=True, text=True))
    seconds = time.perf_counter() - start
    printed = re.findall(r"^SPS: ([0-9.]+)$", result.stdout, flags=re.MULTILINE)
    return seconds, float(printed[-1]) if printed else float("nan")


def checked(result: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    """The finished process, or a stop that shows why it failed (the end of its stderr)."""
    if result.returncode != 0:
        tail = "\n".join(result.stderr.strip().splitlines()[-15:])
        raise SystemExit(f"{' '.join(map(str, result.args))} exited with {result.returncode}:\n{tail}")
    return result


def require(parser: argparse.ArgumentParser, *modules: str) -> None:
    """One line, before anything runs, when a library the comparison needs is not installed."""
    if missing := [module for module in modules if importlib.util.find_spec(module) is None]:
        parser.error(f"needs {', '.join(missing)}: pip install -r benchmarks/requirements.txt")


def measure(command: Callable[[str, int], list[str]], names: Sequence[str], steps: int, repeats: int, workdir: Path) -> tuple[dict[str, list[float]], dict[str, list[float]]]:
    """SPS of command(name, seed) for every name, `repeats` times: over the whole process, and as the
    process itself reported it. Repetition r runs them in an order rotated by r, so no implementation
    always goes first (or always follows the same neighbour)."""
    whole: dict[str, list[float]] = {name: [] for name in names}
    in_loop: dict[str, list[float]] = {name: [] for name in names}
    for rep in range(repeats):
        shift = rep % len(names)
        for name in list(names[shift:]) + list(names[:shift]):
            seconds, reported = timed(command(name, rep + 1), workdir)
            whole[name].append(steps / seconds)
            in_loop[name].append(reported)
    return whole, in_loop


def ratio_cell(sps: dict[str, list[float]], name: str, reference: str) -> str:
    """Median (range) over repetitions of SPS[name] / SPS[reference]."""
    ratios = [a / b for a, b in zip(sps[name], sps[reference])]
    return f"{statistics.median(ratios):.2f} (range {min(ratios):.2f}-{max(ratios):.2f})"


def compare(command: Callable[[str, int], list[str]], steps: int, repeats: int, workdir: Path, names: tuple[str, str] = ("ours", "sb3")) -> str:
    """Two implementations; a markdown row tail: median SPS of each, median (range) of the per-pair
    ratios first/second, pairs."""
    sps, _ = measure(command, names, steps, repeats, workdir)
    return (f"{statistics.median(sps[names[0]]):.1f} | {statistics.median(sps[names[1]]):.1f} "
            f"| {ratio_cell(sps, *names)} | {repeats} |")  # fmt: skip


def script_at(revision: str, dest: Path, script: str = "sac_continuous.py") -> Path:
    """Write `script` as it was at git `revision` to dest/sac_before.py (run alone, without envs/)."""
    source = subprocess.run(["git", "show", f"{revision}:{script}"], cwd=ROOT, check=True, capture_output=True, text=True).stdout
    path = dest / "sac_before.py"
    path.write_text(source)
    return path


def load_module(script: str, name: str = "sac_under_test") -> ModuleType:
    """Import the algorithm script at `script` as a module (its main block does not run)."""
    spec = importlib.util.spec_from_file_location(name, script)
    if spec is None or spec.loader is None:  # a name without .py: no loader knows it
        raise ImportError(f"cannot import {script} as a module: not a Python source file")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses with postponed annotations look their module up here
    spec.loader.exec_module(module)
    return module


def checkpoint_policy(path: Path) -> tuple[str, Callable[[np.ndarray], np.ndarray]]:
    """The env id a SAC or JIRL checkpoint was trained on, and its deterministic policy in env units;
    ValueError for a file that is not such a checkpoint."""
    import torch
    from gymnasium.spaces import Box

    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from envs import make_env

    sac = load_module(str(ROOT / "sac_continuous.py"))
    checkpoint = sac.load_checkpoint(str(path))
    env = make_env(checkpoint["env_id"])
    actor = sac.actor_from_checkpoint(checkpoint, env)
    space = env.action_space
    assert isinstance(space, Box)  # actor_from_checkpoint has compared its bounds with the checkpoint's
    low, high = space.low, space.high
    env.close()

    def policy(obs: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            _, _, action = actor.get_action(torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0))
        return sac.to_env_units(action[0].numpy(), low, high)

    return checkpoint["env_id"], policy
