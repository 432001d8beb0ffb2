"""What JIRL's per-step work (baseline query, gate, fabricated transitions) costs: JIRL against SAC.

Both scripts train one env (Pendulum-v1 unless --env-id) with the same SAC settings, one torch thread,
alternating which runs first; SPS is env steps over the process's whole wall time. JIRL's gate, penalty
and extra transitions are all it adds (regret estimation runs in both). Options after `--` go to both
scripts, except those only JIRL has (its gate, guidance and penalty), which go to JIRL alone:

    python benchmarks/sps_jirl_vs_sac.py --widths 64 256 --repeats 3
    python benchmarks/sps_jirl_vs_sac.py --env-id JetRacerTrack-v0 --widths 64 --steps 54000 \
        --learning-starts 5000 -- --regret-estimator unpaired --guidance-schedule geometric --guidance-fade-steps 5000
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Sequence
from pathlib import Path

from side_by_side import compare, load_module, stop_children_on_sigterm

ROOT = Path(__file__).resolve().parent.parent


def flags(script: str) -> set[str]:
    """The options of a script's `Args` as tyro spells them: field x_y is --x-y, and a bool also --no-x-y."""
    module = load_module(str(ROOT / f"{script}.py"), f"{script}_options")
    is_bool = {field.name.replace("_", "-"): field.type in (bool, "bool") for field in dataclasses.fields(module.Args)}
    return {f"--{name}" for name in is_bool} | {f"--no-{name}" for name, boolean in is_bool.items() if boolean}


def split_options(extra: list[str], jirl_only: set[str]) -> tuple[list[str], list[str]]:
    """The options for both scripts, and those for JIRL alone; an option's values follow it."""
    both: list[str] = []
    jirl: list[str] = []
    target = both
    for token in extra:
        if token.startswith("--"):
            target = jirl if token.split("=", 1)[0] in jirl_only else both
        target.append(token)
    return both, jirl


def command(script: str, width: int, steps: int, learning_starts: int, seed: int, env_id: str = "Pendulum-v1", options: Sequence[str] = ()) -> list[str]:
    return [sys.executable, str(ROOT / f"{script}.py"), "--env-id", env_id, "--seed", str(seed),
            "--total-timesteps", str(steps), "--learning-starts", str(learning_starts), "--hidden-size", str(width),
            "--torch-threads", "1", *options]  # fmt: skip


SET_HERE = tuple(token for token in command("sac_continuous", 1, 1, 0, 1) if token.startswith("--"))  # refused after `--`


def main() -> None:
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    extra = argv[cut + 1 :]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog="Options after `--` go to both scripts, those only JIRL has to JIRL alone.")
    parser.add_argument("--env-id", default="Pendulum-v1")
    parser.add_argument("--widths", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--learning-starts", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workdir", type=Path, default=ROOT / "benchmarks" / "results" / "sps_jirl_vs_sac")
    if set_here := sorted({token.split("=", 1)[0] for token in extra} & set(SET_HERE)):
        parser.error(f"{', '.join(set_here)} after `--`: this tool sets {', '.join(SET_HERE)} itself (see --help)")
    args = parser.parse_args(argv[:cut])
    minimums = {"--widths": (min(args.widths), 1), "--steps": (args.steps, 1), "--repeats": (args.repeats, 1), "--learning-starts": (args.learning_starts, 0)}
    if too_small := [f"{flag} must be at least {low}" for flag, (value, low) in minimums.items() if not value >= low]:
        parser.error("; ".join(too_small))
    both, jirl = split_options(extra, flags("jirl_sac_continuous") - flags("sac_continuous"))
    options = {"jirl_sac_continuous": both + jirl, "sac_continuous": both}
    args.workdir.mkdir(parents=True, exist_ok=True)
    print(f"{args.env_id}, {args.steps} steps, learning starts {args.learning_starts}, 1 thread; "
          f"to both: {' '.join(both) or '(nothing)'}; to JIRL alone: {' '.join(jirl) or '(nothing)'}")  # fmt: skip
    print("| width | JIRL SPS (median) | SAC SPS (median) | ratio JIRL/SAC (median of pairs) | pairs |")
    print("|---|---|---|---|---|")
    for width in args.widths:
        row = compare(lambda script, seed: command(script, width, args.steps, args.learning_starts, seed, args.env_id, options[script]),
                      args.steps, args.repeats, args.workdir, names=("jirl_sac_continuous", "sac_continuous"))  # fmt: skip
        print(f"| {width} | {row}", flush=True)


if __name__ == "__main__":
    stop_children_on_sigterm()
    main()
