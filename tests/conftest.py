"""Shared test helpers: load an algorithm script as a module without running its main block."""

import importlib.util
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

torch.set_num_threads(1)


def load_script(name: str):
    """Import ROOT/name.py under its own name (its `__main__` block does not run)."""
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, ROOT / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses with postponed annotations look their module up here
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def sac():
    return load_script("sac_continuous")


def small_checkpoint(sac, path: Path):
    """A 16-unit Pendulum-v1 checkpoint written by sac_continuous.py's save_checkpoint; returns its actor."""
    env = sac.make_env("Pendulum-v1", 0)
    actor, qf = sac.Actor(3, 1, 16), sac.SoftQNetwork(3, 1, 16)
    sac.save_checkpoint(str(path), "Pendulum-v1", env, actor, qf, sac.Args(hidden_size=16))
    env.close()
    return actor
