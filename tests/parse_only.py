"""Parse command lines as their programs would, and stop there: run by test_documented_commands.py.

Reads one JSON list per line on stdin, the arguments after `python` (`["-m", "envs.baselines", ...]` or
`["benchmarks/learning.py", ...]`, paths relative to the repository), and prints a JSON list with, for
each line in turn, null when its program accepts it, or what the program said when it refused it.
Each program runs as `python` would run it, up to its argument parser's return: argparse's
`parse_args` and tyro's `cli` stop the program there, so nothing trains and nothing is written."""

import argparse
import contextlib
import io
import json
import runpy
import sys
from pathlib import Path

import tyro
import tyro.extras

ROOT = Path(__file__).resolve().parent.parent


class Parsed(Exception):
    """Raised in place of a parser's return, carrying what it returned."""


def stop_after(parse):
    def parse_and_stop(*args, **kwargs):
        raise Parsed(parse(*args, **kwargs))

    return parse_and_stop


argparse.ArgumentParser.parse_args = stop_after(argparse.ArgumentParser.parse_args)
tyro.cli = stop_after(tyro.cli)
tyro.extras.subcommand_cli_from_dict = stop_after(tyro.extras.subcommand_cli_from_dict)


# Tools whose arguments after `--` go to a script: the script's command line they start, from what they parsed
AFTER_DASHES = {
    "learning.py": lambda run_as: [run_as.script, "--env-id", run_as.env_id, "--total-timesteps", str(run_as.total_timesteps)],
    # to both scripts, JIRL's own options among them: JIRL's parser takes them all
    "sps_jirl_vs_sac.py": lambda run_as: ["jirl_sac_continuous.py", "--env-id", run_as.env_id, "--total-timesteps", str(run_as.steps),
                                          "--learning-starts", str(run_as.learning_starts)],  # fmt: skip
}


def check(argv: list[str]) -> str | None:
    """None when the program of `python *argv` accepts its arguments, else its error output."""
    if argv[0] == "-m":
        name, rest = argv[1], argv[2:]
        sys.path[0] = str(ROOT)  # as `python -m` run in the repository
        run = lambda: runpy.run_module(name, run_name="__main__", alter_sys=True)  # noqa: E731
    else:
        name, rest = argv[0], argv[1:]
        sys.path[0] = str((ROOT / name).parent)  # as `python path/script.py`: benchmarks import their neighbours
        run = lambda: runpy.run_path(str(ROOT / name), run_name="__main__")  # noqa: E731
    sys.argv = [name, *rest]
    said = io.StringIO()
    try:
        with contextlib.redirect_stderr(said), contextlib.redirect_stdout(io.StringIO()):
            run()
    except Parsed as parsed:
        if Path(name).name in AFTER_DASHES and "--" in rest:
            return check([*AFTER_DASHES[Path(name).name](parsed.args[0]), *rest[rest.index("--") + 1 :]])
        return None
    except SystemExit as end:  # --help exits 0; a refused argument 2
        return None if end.code in (0, None) else said.getvalue().strip() or f"exit status {end.code}"
    except Exception as err:  # noqa: BLE001 -- a program that fails before its parser returns is refused too
        return f"{type(err).__name__}: {err}"
    return "the program ended without parsing its arguments"


if __name__ == "__main__":
    print(json.dumps([check(json.loads(line)) for line in sys.stdin]))
