"""Shared test helpers: load an algorithm script as a module without running its main block; a full disk;
the TensorBoard writers of a run ended in-process, closed; policies whose finite weights give a NaN or
an infinite action; checkpoint spaces unlike Pendulum's; and a check that no test leaves a signal
handler changed."""

import builtins
import errno
import importlib.util
import io
import os
import re
import signal
import sys
from pathlib import Path

import pytest
import torch
import torch.utils.tensorboard as tensorboard

ROOT = Path(__file__).resolve().parent.parent
CAR_TRAIN_FAST = ["--jirl.hidden-size", "16", "--jirl.batch-size", "16", "--jirl.learning-starts", "30"]  # a small agent for `deploy.jetracer train` in tests
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

torch.set_num_threads(1)

# Saved spaces that differ from Pendulum-v1's, each with the line a script's loader must refuse it with:
# an upper bound alone, a lower bound alone, and bounds for two actions, which would broadcast against
# Pendulum's one
OTHER_PENDULUM_SPACES = [
    ({"action_high": [3.0]}, "checkpoint action bounds differ from this env's Box(-2.0, 2.0, (1,), float32)"),
    ({"action_low": [-3.0]}, "checkpoint action bounds differ from this env's Box(-2.0, 2.0, (1,), float32)"),
    ({"action_low": [-2.0, -2.0], "action_high": [2.0, 2.0]}, "checkpoint expects 3 observations and 2 actions (Pendulum-v1); this env has 3 and 1"),
]


def readme_section(heading: str) -> str:
    """The README's text under the line `heading` (`## Baselines`), up to the next heading of its level or above."""
    level = len(heading) - len(heading.lstrip("#"))
    text = (ROOT / "README.md").read_text().split(f"\n{heading}\n", 1)[1]
    return re.split(rf"\n#{{1,{level}}} ", text, maxsplit=1)[0]


def figure_value(figure: str) -> float:
    """A number as the documents print it: `2,000`, `10k` and `−10` (with a minus sign) read as numbers."""
    return float(figure.replace(",", "").replace("−", "-").replace("k", "e3"))


def figures_stated(text: str, pattern: str) -> list[tuple[float, ...]]:
    """The numbers that each match of `pattern` captures in a document's `text`, its lines joined by single
    spaces (read by `figure_value`); the document must still say it."""
    flat = " ".join(text.split())
    matches = [tuple(figure_value(g) for g in m.groups()) for m in re.finditer(pattern, flat)]
    assert matches, f"the document no longer says {pattern!r}"
    return matches


def printed_regret(stdout: str) -> tuple[float, ...]:
    """The baseline regret a script prints when its training ends, once: (episode form, per step)."""
    (regret,) = figures_stated(stdout, r"baseline regret \(\w+\): ([\d,.]+) in the episode form, ([\d,.]+) per step")
    return regret


def table_cells(row: str) -> list[str]:
    """The cells of a Markdown table's row, `| a | b |` -> ["a", "b"]."""
    return [cell.strip() for cell in row.strip("|").split("|")]


def markdown_tables(text: str) -> list[tuple[int, list[str], list[list[str]]]]:
    """Each Markdown table in `text`: the line its header is on (from 1), the header's cells and its rows'
    cells, bold marks dropped."""
    found, lines, start = [], text.replace("**", "").splitlines(), None
    for number, line in enumerate([*lines, ""], 1):
        if line.startswith("|") and start is None:
            start = number
        elif not line.startswith("|") and start is not None:
            header, _, *rows = lines[start - 1 : number - 1]
            found.append((start, table_cells(header), [table_cells(row) for row in rows]))
            start = None
    return found


def refusal(call, *args) -> str:
    """The message of the ValueError that `call(*args)` must raise."""
    with pytest.raises(ValueError) as raised:
        call(*args)
    return str(raised.value)


def load_script(name: str):
    """Import ROOT/name.py under its own name (its `__main__` block does not run)."""
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, ROOT / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses with postponed annotations look their module up here
    spec.loader.exec_module(module)
    return module


@pytest.fixture(autouse=True)
def signal_handlers_restored(request):
    """Every test leaves SIGINT and SIGTERM as it found them. The scripts' training loops and the car's
    sessions catch both while they run, in-process too, and must give them back when they end."""
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    yield
    after = {sig: signal.getsignal(sig) for sig in before}
    for sig, handler in before.items():  # so that one leak fails one test, not every later one
        signal.signal(sig, handler)
    assert after == before, f"{request.node.name} left the handlers {after} in place of {before}"


@pytest.fixture(scope="session")
def sac():
    return load_script("sac_continuous")


def small_checkpoint(sac, path: Path, env_id: str = "Pendulum-v1", **args):
    """A 16-unit checkpoint for env_id written by sac_continuous.py's save_checkpoint, with `args` among
    its Args; returns its actor."""
    env = sac.make_env(env_id, 0)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    actor, qf = sac.Actor(obs_dim, act_dim, 16), sac.SoftQNetwork(obs_dim, act_dim, 16)
    sac.save_checkpoint(str(path), env_id, env, actor, qf, sac.Args(hidden_size=16, **args))
    env.close()
    return actor


class FullDisk(io.FileIO):
    """A file on a disk with `room` bytes left: the write that reaches past it stores what fits, then
    raises ENOSPC, as the OS does."""

    room = 4096

    def write(self, data) -> int:
        data = memoryview(data).cast("B")
        if self.tell() + len(data) > self.room:
            super().write(data[: max(0, self.room - self.tell())])
            raise OSError(errno.ENOSPC, "No space left on device")
        return super().write(data)


def overflow_the_actor(weights: dict) -> None:
    """A SAC actor's weights (named as in its state dict), made finite weights whose mean and log-std are NaN
    on every input: every unit of fc1 at 2 after the ReLU; fc2's weights at 3e38, so that each of its units
    sums positive terms beyond float32, +inf in any order; each head's weights +1 and -1 in turn, so that
    its terms are +inf and -inf, whose sum is NaN in any order, fused multiply-adds included. (Finite
    terms of both signs that overflow would not do: a chain of fused multiply-adds keeps the sign of the
    first to overflow, and whether a CPU's kernels sum in such a chain differs from CPU to CPU.)"""
    with torch.no_grad():
        weights["fc1.weight"].zero_()
        weights["fc1.bias"].fill_(2.0)
        weights["fc2.weight"].fill_(3e38)
        weights["fc2.bias"].zero_()
        for head in ("fc_mean", "fc_logstd"):
            w = weights[f"{head}.weight"]
            w.copy_(torch.where(torch.arange(w.shape[1]) % 2 == 0, 1.0, -1.0).expand_as(w))
    assert all(bool(torch.isfinite(w).all()) for w in weights.values())


def overflow_the_mean(weights: dict) -> None:
    """A SAC actor's weights made finite weights whose mean is +inf on every input and whose log-std stays
    finite: every unit of fc2 at 2 after the ReLU, and the mean head's weights at 3e38, so that it sums
    positive terms beyond float32, +inf in any order. (Its action, tanh of the mean, is finite.)"""
    with torch.no_grad():
        weights["fc2.weight"].zero_()
        weights["fc2.bias"].fill_(2.0)
        weights["fc_mean.weight"].fill_(3e38)
    assert all(bool(torch.isfinite(w).all()) for w in weights.values())


def overflow_the_policy_mean(mean: list) -> None:
    """PPO's and TRPO's `actor_mean` parameters (0.weight, 0.bias, 2.weight, 2.bias, 4.weight, 4.bias),
    made finite weights whose mean is +inf: every unit of the second layer at tanh(2) = 0.96, and the last
    layer's weights at 3e38, so that its products of 2.9e38 sum beyond float32."""
    with torch.no_grad():
        mean[2].zero_()
        mean[3].fill_(2.0)
        mean[4].fill_(3e38)


def fill_the_disk_for(monkeypatch, name: str) -> None:
    """open(path, "wb") of a file whose name matches the regular expression gives a FullDisk; every other
    open is the real one."""
    real_open = builtins.open

    def open_(file, mode="r", *args, **kwargs):
        if re.fullmatch(name, os.path.basename(file)) and mode == "wb":
            return FullDisk(file, "wb")
        return real_open(file, mode, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", open_)


@pytest.fixture
def writers_closed(monkeypatch):
    """A run that ends at set-up leaves its TensorBoard writer open, which is harmless in a process of its
    own; in-process, its thread would write to runs/ relative to a directory the test has left. Closed
    here, before monkeypatch changes back. Yields the writers made, for a test that reads their logs first."""
    opened = []

    class Recorded(tensorboard.SummaryWriter):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            opened.append(self)

    monkeypatch.setattr(tensorboard, "SummaryWriter", Recorded)
    yield opened
    assert opened, "the run made no writer through the patched class"
    for writer in opened:
        writer.close()
