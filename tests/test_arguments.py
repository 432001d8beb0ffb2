"""Out-of-range arguments end the parse with a message naming the flag, before anything runs or is written."""

import ast
import dataclasses
import inspect
import math
import os
import re
import textwrap
import typing

import pytest

import warm_python
from conftest import ROOT, load_script

SCRIPTS = ["sac_continuous", "jirl_sac_continuous", "ppo_il", "trpo_il"]
jetracer = pytest.importorskip("deploy.jetracer")


def numeric_fields(cls) -> list[tuple[str, type]]:
    """(name, int or float) of every int or float field, Optional ones included; bools are not numbers here."""
    hints = typing.get_type_hints(cls)
    fields = []
    for f in dataclasses.fields(cls):
        kinds = [t for t in typing.get_args(hints[f.name]) or (hints[f.name],) if t is not type(None)]
        if kinds in ([int], [float]):
            fields.append((f.name, kinds[0]))
    return fields


ARG_CLASSES = {name: load_script(name).Args for name in SCRIPTS} | {f"deploy {c}": getattr(jetracer, c) for c in ("Run", "Baseline", "Train")}


@pytest.mark.parametrize("label", list(ARG_CLASSES))
def test_every_option_has_the_docstring_its_help_shows(label):
    """CleanRL's shape: each Args field is followed by its docstring, which tyro prints as the option's
    help; a field without one shows only its default in `--help`. Inherited fields (the car's common
    options) are read in the class that declares them."""
    documented = set()
    for cls in reversed([c for c in ARG_CLASSES[label].__mro__ if dataclasses.is_dataclass(c)]):
        body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0].body
        for field, after in zip(body, [*body[1:], None]):
            if isinstance(field, ast.AnnAssign):
                docstring = after.value.value if isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant) else None
                assert isinstance(docstring, str) and docstring.strip(), f"{cls.__name__}.{field.target.id} has no docstring"
                documented.add(field.target.id)
    assert documented == {f.name for f in dataclasses.fields(ARG_CLASSES[label])}


@pytest.mark.parametrize("label", list(ARG_CLASSES))
def test_every_number_has_a_range(label):
    """-1 for every int field and NaN for every float field is refused, each by its own flag; defaults pass."""
    cls = ARG_CLASSES[label]
    cls()  # the defaults are valid
    fields = numeric_fields(cls)
    assert len(fields) >= 8, fields
    for name, kind in fields:
        bad = -1 if kind is int else math.nan
        with pytest.raises(ValueError, match=f"--{name.replace('_', '-')} must be"):
            cls(**{name: bad})


def the_rule(cls, name: str, kind: type) -> str:
    """The rule an out-of-range value is told it breaks: the range as users read it."""
    flag = name.replace("_", "-")
    with pytest.raises(ValueError) as err:
        cls(**{name: -1 if kind is int else math.nan})
    return re.search(f"--{flag} must be (.*?), got ", str(err.value)).group(1)


def refused(cls, name: str, value) -> bool:
    """Whether the value alone breaks the field's own rule (another field's rule may depend on it)."""
    try:
        cls(**{name: value})
    except ValueError as err:
        return f"--{name.replace('_', '-')} must be" in str(err)
    return False


def number(text: str, kind: type):
    """'0', '1', 'inf', '2**32' as a value of the field's type."""
    if "**" in text:
        base, power = text.split("**")
        return kind(int(base) ** int(power))
    return math.inf if text == "inf" else kind(text)


# Rules that are not a bound or an interval, each checked at its edges by a test of its own below.
RULES_OF_THEIR_OWN = {("trpo_il", "num_steps"), *((f"deploy {mode}", name) for mode in ("Run", "Baseline", "Train") for name in ("watchdog_ms", "min_throttle"))}


@pytest.mark.parametrize("label", list(ARG_CLASSES))
def test_every_range_holds_exactly_at_the_edges_its_message_states(label):
    """Each bound the message states ('>= 1', '> 0', 'in (0, 1]', 'finite') is where the check turns:
    an edge it includes passes and the next value beyond it is refused, and an edge it excludes the
    other way round; infinity passes only where the range includes it ('in (0, inf]'), not for '> 0'.
    Some ranges were found by a crash: --buffer-size 0 (an IndexError at the first buffer write),
    --rl-control-window 0 (a ZeroDivisionError at the first log), --il-value-epochs 0 (a NameError
    after imitation); on the car a --control-hz of inf (a period of 0: no rate limit on the steering)
    and a negative --max-steering-rate, which steered by itself."""
    cls = ARG_CLASSES[label]
    checked = set()
    for name, kind in numeric_fields(cls):
        rule = the_rule(cls, name, kind)
        if (label, name) in RULES_OF_THEIR_OWN:
            continue
        down = (lambda x: x - 1) if kind is int else (lambda x: math.nextafter(x, -math.inf))
        up = (lambda x: x + 1) if kind is int else (lambda x: math.nextafter(x, math.inf))
        if rule == "finite":
            assert refused(cls, name, math.inf) and refused(cls, name, -math.inf), name
            assert not refused(cls, name, -1e300) and not refused(cls, name, 1e300), name
            checked.add(name)
            continue
        bound = re.fullmatch(r"(>=|>) (\S+)", rule)
        interval = re.fullmatch(r"in ([\[(])(\S+), (\S+)([\])])", rule)
        assert bound or interval, f"{label} --{name}: a rule this test cannot read: {rule!r}"
        if bound:
            low_closed, low, high_closed, high = bound.group(1) == ">=", number(bound.group(2), kind), False, math.inf
        else:
            low_closed, low = interval.group(1) == "[", number(interval.group(2), kind)
            high_closed, high = interval.group(4) == "]", number(interval.group(3), kind)
        inside_low, outside_low = (low, down(low)) if low_closed else (up(low), low)
        assert not refused(cls, name, inside_low), f"{label} --{name} {rule}: {inside_low!r} refused"
        assert refused(cls, name, outside_low), f"{label} --{name} {rule}: {outside_low!r} passes"
        if high != math.inf:
            inside_high, outside_high = (high, up(high)) if high_closed else (down(high), high)
            assert not refused(cls, name, inside_high), f"{label} --{name} {rule}: {inside_high!r} refused"
            assert refused(cls, name, outside_high), f"{label} --{name} {rule}: {outside_high!r} passes"
        elif kind is float:
            assert refused(cls, name, math.inf) != high_closed, f"{label} --{name} {rule}: inf {'refused' if high_closed else 'passes'}"
            assert not refused(cls, name, 1e300), f"{label} --{name} {rule}: 1e300 refused"
        else:
            assert not refused(cls, name, 10**9), f"{label} --{name} {rule}: 10**9 refused"
        checked.add(name)
    assert len(checked) >= 6, checked


@pytest.mark.parametrize(
    "script, field, value",
    [
        ("sac_continuous", "exp_name", "ablations/sigma"),  # the run trained, then its model could not be saved
        ("jirl_sac_continuous", "exp_name", ""),
        ("ppo_il", "exp_name", "a/b"),
        ("trpo_il", "exp_name", "a/b"),
        ("trpo_il", "num_steps", 1),  # one step's advantage has no std: the policy never moved
    ],
)
def test_edges_of_the_ranges(script, field, value):
    with pytest.raises(ValueError, match=f"--{field.replace('_', '-')} must be"):
        load_script(script).Args(**{field: value})


def test_every_problem_is_named_at_once():
    sac = load_script("sac_continuous")
    with pytest.raises(ValueError) as err:
        sac.Args(batch_size=0, q_lr=-1.0, policy_frequency=0)
    assert str(err.value).count("must be") == 3


def test_trpo_takes_a_one_step_rollout_only_without_advantage_normalisation():
    trpo = load_script("trpo_il")
    trpo.Args(num_steps=1, norm_adv=False)
    trpo.Args(num_steps=2)


def test_deploy_checks_the_car_safety_settings():
    with pytest.raises(ValueError, match="--max-steering-rate must be > 0"):
        jetracer.Run(max_steering_rate=-1.0)  # once drove: a negative rate limit turned the wheels by itself
    with pytest.raises(ValueError, match="steering change per step must be > 0"):
        jetracer.SafetyFilter(jetracer.ActionMapping(), max_steering_rate=-1.0, period=0.05)
    with pytest.raises(ValueError, match="--min-throttle must be in"):
        jetracer.Baseline(min_throttle=0.7, max_throttle=0.6)
    with pytest.raises(ValueError, match=r"--watchdog-ms must be longer than the link's send period \(20 ms\)"):
        jetracer.Baseline(watchdog_ms=20)  # 20 Hz control, 2.5 frames per period: one frame every 20 ms
    jetracer.Baseline(watchdog_ms=21)
    with pytest.raises(ValueError, match="--watchdog-ms must be"):
        jetracer.Baseline(watchdog_ms=65536)  # the protocol's field is 16 bits
    jetracer.Baseline(watchdog_ms=65535)
    jetracer.Baseline(min_throttle=0.6, max_throttle=0.6)
    jetracer.Baseline(min_throttle=0.0)
    with pytest.raises(ValueError, match="--min-throttle must be in"):
        jetracer.Baseline(min_throttle=-1e-9)


def test_the_safety_filter_refuses_a_steering_step_of_zero_or_infinity():
    for rate, period in ((0.0, 0.05), (8.0, 0.0), (math.inf, 0.05)):
        with pytest.raises(ValueError, match="steering change per step must be > 0"):
            jetracer.SafetyFilter(jetracer.ActionMapping(), max_steering_rate=rate, period=period)


def test_deploy_train_refuses_a_checkpoint_that_is_no_file_path(tmp_path):
    for bad in ("", str(tmp_path), f"{tmp_path / 'new'}/"):  # before: "... holds an earlier training", or a failed first save
        with pytest.raises(ValueError, match=r"--checkpoint must be a file's path \(not empty, not a directory\)"):
            jetracer.Train(checkpoint=bad)
    jetracer.Train(checkpoint=str(tmp_path / "train.pt"))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "command, message",
    [
        (["sac_continuous.py", "--buffer-size", "0"], "--buffer-size must be >= 1, got 0"),
        (["jirl_sac_continuous.py", "--penalty-sigma2", "-0.1"], "--penalty-sigma2 must be > 0, got -0.1"),
        (["ppo_il.py", "--total-timesteps", "-5"], "--total-timesteps must be >= 1, got -5"),
        (["trpo_il.py", "--max-kl", "0"], "--max-kl must be > 0, got 0.0"),
        (["-m", "deploy.jetracer", "train", "--train-every", "0"], "--train-every must be >= 1, got 0"),
        (["-m", "deploy.jetracer", "train", "--jirl.tau", "nan"], "--tau must be in (0, 1], got nan"),
    ],
)
def test_the_command_line_reports_and_writes_nothing(tmp_path, command, message):
    command = [str(ROOT / command[0]), *command[1:]] if command[0].endswith(".py") else command
    env = dict(os.environ, PYTHONPATH=str(ROOT), COLUMNS="300")  # one line of tyro's box holds the message
    out = warm_python.run(command, cwd=tmp_path, timeout=60, env=env)
    assert out.returncode == 2, out.stderr
    assert message in out.stderr and "Traceback" not in out.stderr, out.stderr
    assert list(tmp_path.iterdir()) == [], "nothing is written before the arguments are checked"
    if command[:2] == ["-m", "deploy.jetracer"]:  # the help it points to is a command to run, not the module's file
        assert "see python -m deploy.jetracer --help" in out.stderr and str(ROOT) not in out.stderr, out.stderr


def test_a_controller_that_refuses_to_arm_is_a_one_line_error(tmp_path):
    """The mock controller accepts watchdog periods of 50-2000 ms; the host's own rule lets 30 through."""
    command = ["-m", "deploy.jetracer", "baseline", "--watchdog-ms", "30", "--log-dir", str(tmp_path / "runs")]
    out = warm_python.run(command, cwd=ROOT, timeout=60)
    assert out.returncode != 0
    assert "did not arm with --watchdog-ms 30; it accepts 50-2000 ms" in out.stderr and "Traceback" not in out.stderr, out.stderr
    assert not (tmp_path / "runs").exists(), "no log of a session that never armed"
