"""Timing two implementations side by side: alternating order, fresh processes, ratios per pair."""

from __future__ import annotations

import statistics
import subprocess
import time
from pathlib import Path
from typing import Callable


def timed(cmd: list[str], workdir: Path) -> float:
    """Wall-clock seconds of one process, start to exit (imports included)."""
    start = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=workdir, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def compare(command: Callable[[str, int], list[str]], steps: int, repeats: int, workdir: Path, names: tuple[str, str] = ("ours", "sb3")) -> str:
    """Run command(names[0], seed) and command(names[1], seed) `repeats` times, alternating which goes
    first; a markdown row tail: median SPS of each, median (range) of the per-pair ratios first/second, pairs."""
    ours, theirs = [], []
    for rep in range(repeats):
        for impl in (names if rep % 2 == 0 else names[::-1]):
            sps = steps / timed(command(impl, rep + 1), workdir)
            (ours if impl == names[0] else theirs).append(sps)
    ratios = [o / t for o, t in zip(ours, theirs)]
    return (f"{statistics.median(ours):.1f} | {statistics.median(theirs):.1f} "
            f"| {statistics.median(ratios):.2f} (range {min(ratios):.2f}-{max(ratios):.2f}) | {repeats} |")  # fmt: skip
