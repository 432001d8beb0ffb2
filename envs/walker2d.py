"""Walker2DBulletEnv-v0's baseline: a SAC actor after a short training, run deterministically.

The paper's Walker-2D baseline was a SAC policy stopped early (about 1.59 reward per step against
about 2.2 for SAC at the end of training). Ours is made the same way with ``sac_continuous.py``; its
actor's weights ship beside this file with the command that trained them, and run with torch alone:
the action is tanh of the Gaussian's mean, mapped to the env's units.

    python -m envs.walker2d export runs/<run>/walker_baseline.cleanrl_model --command "<how it was trained>"
    python -m envs.baselines --env-id Walker2DBulletEnv-v0 --episodes 10
"""

from __future__ import annotations

import argparse
import reprlib
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

WEIGHTS = Path(__file__).with_name("walker2d_baseline.pt")
WEIGHTS_FORMAT = "jirl-policy-weights-v1"
# the SAC checkpoints whose actor this module can read (v2 changed only how the critics are stored)
SAC_CHECKPOINT_FORMATS = ("jirl-sac-checkpoint-v1", "jirl-sac-checkpoint-v2")


class MeanPolicy(nn.Module):
    """The deterministic half of sac_continuous.py's Actor (same layer names, so its weights load)."""

    def __init__(self, obs_dim: int, act_dim: int, hidden_size: int):
        super().__init__()
        self.fc1 = nn.Linear(obs_dim, hidden_size)
        self.fc2 = nn.Linear(hidden_size, hidden_size)
        self.fc_mean = nn.Linear(hidden_size, act_dim)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """tanh(mean): the action in [-1, 1]."""
        return torch.tanh(self.fc_mean(F.relu(self.fc2(F.relu(self.fc1(obs))))))


def _read(path: Path) -> dict[str, Any]:
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as err:  # torch raises many types for a damaged file; keep the first sentence (the rest advises weights_only=False)
        cause = (str(err).strip().splitlines() or ["the file ends early"])[0].split(". ")[0]
        raise ValueError(f"{path} is not readable policy weights ({type(err).__name__}: {cause})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path} is not a policy weights file")
    return data


def _require(data: dict[str, Any], keys: tuple[str, ...], path: Path, what: str) -> None:
    """ValueError naming what a file with the right format tag lacks (a KeyError would come later), or
    the first value in it that no export or sac_continuous.py writes: torch would refuse it later with a
    traceback, and NaN weights would act as a baseline that fails."""
    missing = [key for key in keys if key not in data]
    if missing:
        raise ValueError(f"{path} is a damaged {what}: it has no {', '.join(missing)}")
    low, high = data["action_low"], data["action_high"]
    checks = [
        ("obs_dim", type(data["obs_dim"]) is int and data["obs_dim"] > 0),
        ("hidden_size", type(data["hidden_size"]) is int and data["hidden_size"] > 0),
        ("action_low", isinstance(low, (list, tuple)) and len(low) > 0 and all(type(x) in (int, float) for x in low)),
        ("action_high", isinstance(high, (list, tuple)) and isinstance(low, (list, tuple)) and len(high) == len(low) and all(type(x) in (int, float) for x in high)),
    ]
    checks += [(key, isinstance(data[key], dict)) for key in ("metadata", "args") if key in keys]
    checks += [
        (key, isinstance(data[key], dict) and all(type(k) is str and torch.is_tensor(w) and bool(torch.isfinite(w).all()) for k, w in data[key].items()))
        for key in ("policy", "actor")
        if key in keys
    ]
    for key, fits in checks:
        if not fits and key in ("policy", "actor") and isinstance(data[key], dict):
            named = all(type(k) is str and torch.is_tensor(w) for k, w in data[key].items())
            raise ValueError(f"{path} is a damaged {what}: its {key} holds {'a NaN or infinite weight' if named else 'an entry that is not a named tensor'}")
        if not fits:
            raise ValueError(f"{path} is a damaged {what}: its {key} is {reprlib.repr(data[key])}")


def load_policy(path: Path = WEIGHTS) -> tuple[MeanPolicy, np.ndarray, np.ndarray, dict[str, Any]]:
    """(policy, action low, action high, metadata) from a file written by `export`; ValueError if it is not one."""
    data = _read(Path(path))
    if data.get("format") != WEIGHTS_FORMAT:
        raise ValueError(f"{path} is not a {WEIGHTS_FORMAT} file")
    _require(data, ("obs_dim", "action_low", "action_high", "hidden_size", "policy", "metadata"), path, f"{WEIGHTS_FORMAT} file")
    policy = MeanPolicy(data["obs_dim"], len(data["action_low"]), data["hidden_size"])
    try:
        policy.load_state_dict(data["policy"])
    except RuntimeError as err:  # torch's message runs over several lines: keep it on one
        raise ValueError(f"{path}: the weights do not fit the stated sizes: {' '.join(str(err).split())}") from None
    low, high = (np.asarray(data[key], dtype=np.float32) for key in ("action_low", "action_high"))
    return policy.eval(), low, high, data["metadata"]


class Walker2DBaseline:
    """baseline(obs) -> the trained policy's deterministic action, in the env's units.

    The policy runs in float64 and its action is rounded to float32, so that every CPU gives the same
    action: float32 products differ in their last bits between CPUs (AVX2 or AVX-512 kernels), and the
    walker's 1,000 steps grow such a difference into another episode, or a fall.
    """

    def __init__(self, path: Path = WEIGHTS):
        self.policy, self.low, self.high, self.metadata = load_policy(path)
        self.policy.double()
        self.obs_dim = self.policy.fc1.in_features

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Observation, shape (obs_dim,) -> action float32 in env units, within the saved action bounds (6 torques)."""
        obs = np.asarray(obs, dtype=np.float32)
        if obs.shape != (self.obs_dim,):
            raise ValueError(f"the Walker2D baseline expects {self.obs_dim} observations, got shape {obs.shape}")
        with torch.inference_mode():
            action = self.policy(torch.from_numpy(obs).double().unsqueeze(0))[0].numpy().astype(np.float32)
        return self.low + (action + 1.0) * 0.5 * (self.high - self.low)


def export(checkpoint: Path, out: Path = WEIGHTS, **metadata: Any) -> None:
    """Keep only what acting needs from a sac_continuous.py checkpoint (its actor's mean path)."""
    data = _read(Path(checkpoint))
    if data.get("format") not in SAC_CHECKPOINT_FORMATS:
        raise ValueError(f"{checkpoint} is not a sac_continuous.py checkpoint ({', '.join(SAC_CHECKPOINT_FORMATS)})")
    _require(data, ("env_id", "obs_dim", "hidden_size", "action_low", "action_high", "actor", "args"), checkpoint, "sac_continuous.py checkpoint")
    policy = {k: v for k, v in data["actor"].items() if not k.startswith("fc_logstd.")}
    weights = {
        "format": WEIGHTS_FORMAT,
        "env_id": data["env_id"],
        "obs_dim": data["obs_dim"],
        "hidden_size": data["hidden_size"],
        "action_low": data["action_low"],
        "action_high": data["action_high"],
        "policy": policy,
        "metadata": {"seed": data["args"].get("seed"), "total_timesteps": data["args"].get("total_timesteps"), **metadata},
    }
    try:
        MeanPolicy(data["obs_dim"], len(data["action_low"]), data["hidden_size"]).load_state_dict(policy)
    except RuntimeError as err:  # torch's message runs over several lines: keep it on one
        raise ValueError(f"{checkpoint}: the actor's weights do not fit the stated sizes: {' '.join(str(err).split())}") from None
    tmp = Path(f"{out}.tmp")  # written whole, then renamed: a write that fails leaves the old weights as they were
    try:
        with open(tmp, "wb") as file:
            torch.save(weights, file)
        tmp.replace(out)
    except BaseException as err:
        tmp.unlink(missing_ok=True)  # a full disk stays full of half a file otherwise
        if isinstance(err, RuntimeError) and isinstance(err.__context__, OSError):
            err = err.__context__  # torch's zip writer reports a failed write as "unexpected pos"
        if isinstance(err, OSError):
            raise OSError(err.errno, f"cannot write {out}: {err.strerror}") from None
        raise


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Export a SAC checkpoint's actor as the Walker2D baseline's weights.")
    sub = parser.add_subparsers(dest="cmd", required=True)
    exp = sub.add_parser("export", help="write the policy weights file from a sac_continuous.py checkpoint")
    exp.add_argument("checkpoint", type=Path)
    exp.add_argument("--out", type=Path, default=WEIGHTS)
    exp.add_argument("--command", default="", help="the command that trained the checkpoint, kept in the file")
    exp.add_argument("--commit", default="", help="the commit it was trained at")
    args = parser.parse_args(argv)
    try:
        export(args.checkpoint, args.out, command=args.command, commit=args.commit)
    except (ValueError, OSError) as err:  # a missing checkpoint, a full disk
        parser.exit(2, f"error: {err}\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
