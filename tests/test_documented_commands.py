"""Every command the documentation prints is one its program accepts. A user copies them from README.md,
BENCHMARKS.md, docs/ and the benchmarks' docstrings; an option renamed or a rule tightened in code, and
not in the text, would fail there, after the setup, for the first user who tries. Each command is parsed
by its own program (tests/parse_only.py) and stops there: nothing trains. The README's tables of
defaults are checked against the scripts' Args too, and the documents' links against the files they name."""

import ast
import dataclasses
import inspect
import itertools
import json
import re
import shlex
import subprocess
import sys
from collections.abc import Sequence

from conftest import ROOT, figure_value, figures_stated, load_script, readme_section

DOCUMENTS = ["README.md", "BENCHMARKS.md", *sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "docs").rglob("*.md"))]
PROGRAMS = sorted(p.relative_to(ROOT).as_posix() for folder in (".", "benchmarks", "envs", "deploy") for p in (ROOT / folder).glob("*.py"))
NOT_OURS = {"pytest", "venv", "pip"}  # `python -m` of these is the setup's or the tests' command, run by .ci/run
PLACEHOLDERS = {"ENV": "Pendulum-v1", "N": "1000", "<checkpoint>": "CHECKPOINT"}  # words the text leaves to the reader
PYTHON = re.compile(r"(?:\.venv/bin/)?python(?:3[.\d]*)? ")


def markdown_commands(text: str) -> list[str]:
    """`python ...` lines of the shell blocks (`\\` continued, `&&` chained) and inline code spans."""
    found = []
    fenced = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)
    for language, body in fenced.findall(text):
        if language in ("", "bash", "sh", "console"):
            for line in body.replace("\\\n", " ").splitlines():
                found += [part.strip() for part in line.split("&&") if PYTHON.match(part.strip())]
    for span in re.findall(r"`([^`]+)`", fenced.sub("", text)):
        span = " ".join(span.split())  # a span may wrap across lines
        if PYTHON.match(span):
            found.append(span)
    return found


def docstring_commands(source: str) -> list[str]:
    """`python ...` lines of a module's docstring, its usage examples (`\\` continued)."""
    docstring = ast.get_docstring(ast.parse(source)) or ""
    return [line.strip() for line in docstring.replace("\\\n", " ").splitlines() if PYTHON.match(line.strip())]


def expand(word: str) -> list[str]:
    """A shell's brace expansion: `{jirl,sac}/x` is two words."""
    braces = re.search(r"\{([^{}]*,[^{}]*)\}", word)
    if braces is None:
        return [word]
    return [w for choice in braces.group(1).split(",") for w in expand(word[: braces.start()] + choice + word[braces.end() :])]


def documented() -> dict[tuple[str, ...], list[str]]:
    """Each documented command's arguments after `python`, as a shell would pass them, to where it is printed."""
    commands: dict[tuple[str, ...], list[str]] = {}
    texts = [(name, markdown_commands((ROOT / name).read_text())) for name in DOCUMENTS]
    texts += [(name, docstring_commands((ROOT / name).read_text())) for name in PROGRAMS]
    for where, lines in texts:
        for line in lines:
            words = [PLACEHOLDERS.get(w, w) for w in shlex.split(line, comments=True)[1:]]
            if words[:1] == ["-c"] or words[:1] == ["-m"] and (len(words) < 2 or words[1] in NOT_OURS):
                continue  # `python -c` code, a module named in passing
            for argv in itertools.product(*map(expand, words)):
                commands.setdefault(argv, []).append(where)
    return commands


def parse(commands: Sequence[Sequence[str]]) -> list[str | None]:
    """What each command's program said of its arguments (None: accepted), in turn."""
    lines = "".join(json.dumps(argv) + "\n" for argv in commands)
    done = subprocess.run([sys.executable, str(ROOT / "tests" / "parse_only.py")], input=lines, capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_every_documented_command_is_accepted_by_its_program():
    commands = documented()
    programs = {argv[argv[0] == "-m"] for argv in commands}
    # the extraction itself: the README's two commands' script, the car, and the benchmarks are all found
    assert {"jirl_sac_continuous.py", "sac_continuous.py", "deploy.jetracer", "envs.baselines", "benchmarks/learning.py", "benchmarks/reproduce.py"} <= programs
    assert len(commands) >= 60, sorted(commands)
    refused = {argv: said for argv, said in zip(commands, parse(list(commands))) if said is not None}
    assert refused == {}, "\n\n".join(f"python {shlex.join(argv)}\n(in {', '.join(commands[argv])}):\n{said}" for argv, said in refused.items())


def test_a_command_its_program_would_refuse_is_refused_with_its_own_words():
    """The check is no weaker than the programs: a wrong option, a value out of range, a bad value after
    learning.py's or sps_jirl_vs_sac.py's `--` (for the scripts they run), an option the latter sets
    itself, and a module that does not parse are each refused."""
    bad = [
        ["sac_continuous.py", "--no-such-option", "1"],
        ["jirl_sac_continuous.py", "--gate-c", "-1"],
        ["benchmarks/learning.py", "--script", "jirl_sac_continuous.py", "--", "--penalty-sigma2", "0"],
        ["-m", "deploy.jetracer", "train", "--total-steps", "many"],
        ["benchmarks/learning.py", "--seedz", "1"],
        ["benchmarks/sps_jirl_vs_sac.py", "--env-id", "JetRacerTrack-v0", "--", "--guidance-schedule", "sometimes"],
        ["benchmarks/sps_jirl_vs_sac.py", "--", "--seed", "2"],
        ["-m", "envs.track"],
    ]
    good = [["sac_continuous.py", "--help"], ["benchmarks/learning.py", "--script", "jirl_sac_continuous.py", "--", "--penalty-sigma2", "0.5"],
            ["benchmarks/sps_jirl_vs_sac.py", "--env-id", "JetRacerTrack-v0", "--", "--regret-estimator", "unpaired", "--guidance-fade-steps", "5000"]]  # fmt: skip
    said = parse(bad + good)
    assert all(said[: len(bad)]), said
    assert "--no-such-option" in said[0] and "--gate-c" in said[1] and "--penalty-sigma2" in said[2] and "--total-steps" in said[3]
    assert "unrecognized arguments: --seedz" in said[4]
    assert "--guidance-schedule" in said[5] and "this tool sets --env-id, --seed" in said[6]
    assert said[7] == "the program ended without parsing its arguments"
    assert said[len(bad) :] == [None, None, None]


def readme_table(section: str, header: str) -> list[list[str]]:
    """The cells of each row of the first table with this header under the README's heading `section`."""
    text = readme_section(section).split(header, 1)[1]
    rows = []
    for line in text.splitlines()[2:]:  # the header's end, then its |---| line
        if not line.startswith("|"):
            break
        rows.append([cell.strip() for cell in re.split(r"(?<!\\)\|", line)[1:-1]])  # `\|` is a pipe inside a cell
    return rows


def test_the_readmes_option_tables_give_each_scripts_defaults():
    """Each default the tables of `sac_continuous.py` and `jirl_sac_continuous.py` state is the one its
    Args holds: a number, on or off for a flag (`--x / --no-x`, or `--no-use-x` for use_x), or a
    quoted value. A default the table gives in words (the env's own baseline, half the budget) must
    be an unset one in Args: '' or None."""
    read = 0
    for section, script in (("### `sac_continuous.py` options", "sac_continuous"), ("### `jirl_sac_continuous.py`: what JIRL adds", "jirl_sac_continuous")):
        defaults = {f.name: f.default for f in dataclasses.fields(load_script(script).Args)}
        rows = readme_table(section, "| option | default | meaning |")
        assert len(rows) >= 10, rows
        for cells in rows:
            flags, stated = re.findall(r"`(--[\w-]+)", cells[0]), cells[1].split(", ")
            flags = [f for f in flags if not f.startswith("--no-") or f.startswith("--no-use-")]  # `--autotune / --no-autotune` is one
            assert len(flags) == len(stated), (flags, stated)
            for flag, text in zip(flags, stated):
                name = flag.removeprefix("--no-use-").removeprefix("--").replace("-", "_")
                name = f"use_{name}" if flag.startswith("--no-use-") else name
                value = defaults[name]
                if text in ("on", "off"):
                    assert value is (text == "on"), (flag, text, value)
                elif re.fullmatch(r"[−-]?[\d.]+(e-?\d+)?", text):
                    assert figure_value(text) == value, (flag, text, value)
                elif re.fullmatch(r"`[^`]+`", text):
                    assert text.strip("`") == value, (flag, text, value)
                else:  # in words: the env's own, your default entity, half of `--total-timesteps`
                    assert value in ("", None), (flag, text, value)
                    continue
                read += 1
    assert read >= 30, read


def test_the_readmes_hyperparameter_table_is_what_the_scripts_resolve():
    """Each row of the README's table of PPO+IL's and TRPO+IL's defaults, read back from the Args the
    script resolves for that env ('other': an env RL Zoo has no values for)."""
    ppo, trpo = load_script("ppo_il"), load_script("trpo_il")
    rows = readme_table("### `ppo_il.py` and `trpo_il.py`: trust-region methods started by imitation", "| script | env | rollout |")
    assert len(rows) == 6, rows
    for script, env_id, rollout, gamma, gae_lambda, epochs, minibatch, lr, other in rows:
        module = ppo if script == "`ppo_il.py`" else trpo
        args = module.resolve_hyperparameters(module.Args(env_id="MountainCarContinuous-v0" if env_id == "other" else env_id))
        if module is ppo:
            resolved_other = f"ent_coef {args.ent_coef}" if args.ent_coef else ""
            resolved = (args.num_steps, args.update_epochs, args.num_steps // args.num_minibatches, args.learning_rate, "")
        else:
            normalised = ", obs and reward normalisation" if args.norm_obs and args.norm_reward else ""
            resolved_other = f"max KL {args.max_kl}{normalised}"
            resolved = (args.num_steps, args.n_critic_updates, args.critic_batch_size, args.learning_rate, " (critic)")
        read = (int(rollout), int(epochs), int(minibatch), float(lr.removesuffix(" (critic)")), lr[len(lr.split()[0]):])
        assert read == resolved and (float(gamma), float(gae_lambda)) == (args.gamma, args.gae_lambda), (script, env_id)
        assert other == resolved_other, (script, env_id)


def test_the_readmes_car_sections_state_the_defaults_in_code():
    """The figures the sections on JetRacerTrack-v0 and on deploy/ give in prose are the code's defaults:
    the track, the car's dynamics and camera, the observation, the reward and time limit, the throttle
    window; the car's control rate, training pauses, JIRL settings, hand-over horizon, watchdog and
    camera timeout. No table holds them, so nothing else would notice one changed on one side only."""
    import gymnasium as gym

    from deploy import jetracer, link, mock_controller
    from envs import car_interface, jetracer_track  # importing envs registers JetRacerTrack-v0

    env_defaults = {k: p.default for k, p in inspect.signature(jetracer_track.JetRacerTrackEnv.__init__).parameters.items()}
    spec, car, mapping = env_defaults["track"], env_defaults["car"], env_defaults["mapping"]
    sim = readme_section("## JetRacerTrack-v0: the lane-following car in simulation")
    (rows, cols), crop = car_interface.MASK_SHAPE, car_interface.CROP_TOP
    claims = [
        (sim, r"two ([\d.]*\d) m straights, bends of ([\d.]*\d) m radius on the centre line, a ([\d.]*\d) m dark lane", (spec.straight_length, spec.radius, spec.lane_width)),
        (sim, r"wheelbase ([\d.]*\d) m\) with first-order lags on steering \(([\d.]*\d) s\) and speed \(([\d.]*\d) s\)", (car.wheelbase, car.steering_lag, car.speed_lag)),
        (sim, r"stepped at (\d+) Hz", (env_defaults["control_hz"],)),
        (sim, r"\((\d+)×(\d+) BGR, the top (\d+) rows cropped", (*car_interface.FRAME_SHAPE[:2], crop)),
        (sim, r"(\d+)×(\d+) mask", (rows, cols)),
        (sim, r"\((\d+) numbers;", (car_interface.OBS_SIZE,)),
        (sim, r"in the paper's ([\d.]*\d)–([\d.]*\d) window", (mapping.min_throttle, mapping.max_throttle)),
        (sim, r"progress \(m\) × (\d+) per step; (−\d+) and termination", (env_defaults["progress_reward"], env_defaults["off_track_reward"])),
        (sim, r"truncation after (\d+) steps \((\d+) s\)", (gym.spec("JetRacerTrack-v0").max_episode_steps, gym.spec("JetRacerTrack-v0").max_episode_steps / env_defaults["control_hz"])),
    ]
    common, train, hp = jetracer.Common(), jetracer.Train(), jetracer.car_jirl_defaults()
    real = readme_section("## deploy/: the real car")
    # one watchdog period by default on every side: the car's option, the host link's, the mock controller's
    assert common.watchdog_ms == inspect.signature(link.HostLink.__init__).parameters["watchdog_ms"].default == 1000 * mock_controller.MockController().watchdog_period
    claims += [
        (real, r"JIRL's gate, penalized reward and switch penalty .{0,80} at (\d+) Hz", (common.control_hz,)),
        (real, r"Every (\d+) steps the car is stopped for (\d+) gradient steps", (train.train_every, train.gradient_steps)),
        (real, r"car settings as defaults: (\d+) units, batch (\d+), buffer (\d+k), K = (\d+), σ² = ([\d.]*\d)", (hp.hidden_size, hp.batch_size, hp.buffer_size, hp.gate_k, hp.penalty_sigma2)),
        (real, r"half of `--total-steps` \(([\d,]+) of the paper's ([\d,]+)\)", (train.total_steps // 2, train.total_steps)),
        (real, r"on the (\d+) latest stored observations", (jetracer.OVERFLOW_ROWS,)),
        (real, r"no fresh camera frame has come for (\d+) s", (jetracer.CAMERA_LOST_S,)),
        (real, r"The controller's watchdog \((\d+) ms\)", (common.watchdog_ms,)),
    ]
    for text, pattern, expected in claims:
        assert all(found == expected for found in figures_stated(text, pattern)), (pattern, figures_stated(text, pattern), expected)
    # the entropy coefficient: tuned on the car, from the script's own starting value
    assert hp.autotune and figures_stated(real, r"The entropy coefficient is tuned from the script's ([\d.]*\d)") == [(hp.alpha,)] == [(load_script("jirl_sac_continuous").Args().alpha,)]


def test_every_link_between_the_documents_names_a_file_of_the_repository():
    """Relative markdown links (`[text](path)`, `![figure](path)`) of README.md, BENCHMARKS.md and docs/,
    read from the folder of the document that holds them: a file moved or renamed must take its links along."""
    links = 0
    for document in DOCUMENTS:
        for target in re.findall(r"\]\(([^)\s]+)\)", (ROOT / document).read_text()):
            if re.match(r"[a-z]+://|#|mailto:", target):
                continue
            path = (ROOT / document).parent / target.split("#", 1)[0]
            assert path.exists(), f"{document} links {target}, which is not in the repository"
            links += 1
    assert links >= 5, "the documents' links were not found: is the pattern still right?"
