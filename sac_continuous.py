# Soft Actor-Critic (Haarnoja et al. 2018) for continuous actions, in one file, CleanRL's shape.
# Logs the baseline regret of the JIRL paper (Definition 1) so every method is measured alike.
# Run: python sac_continuous.py --env-id Pendulum-v1 --total-timesteps 20000
from __future__ import annotations  # the JIRL script also runs on the car's Python 3.8 (deploy/)

import errno
import importlib
import io
import math
import os
import random
import re
import reprlib
import signal
import stat
import sys
import threading
import time
import traceback
from dataclasses import dataclass
from types import FrameType
from typing import Callable, Literal, Optional

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import torch.optim as optim
import tyro
from torch.utils.tensorboard import SummaryWriter

try:  # this repository's env ids and baselines; absent when the script is copied alone
    from envs import get_baseline as project_baseline
    from envs import make_env as project_make_env
except ImportError:
    project_baseline = project_make_env = None

CHECKPOINT_FORMAT = "jirl-sac-checkpoint-v2"  # v2: the twin critics as one ensemble "qf"
CHECKPOINT_KEYS = ("env_id", "obs_dim", "action_low", "action_high", "hidden_size", "actor", "qf", "args")  # what save_checkpoint writes besides the format
EVAL_SEED_OFFSET = 1_000_000  # evaluation episodes (and the baseline's) never reuse a training reset seed
EPISODE_LIMIT = 100_000  # steps: an episode still running after this many is in an env without a time limit
FUSED_ADAM = tuple(int(v) for v in torch.__version__.split(".")[:2]) >= (2, 4)  # fused Adam runs on CPU from torch 2.4 (the car may have older)


@dataclass
class Args:
    """Soft Actor-Critic on a Gymnasium env with a Box action space, logging its baseline regret against a baseline
    controller (the env's own in envs/, or --baseline)."""

    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """the name of this experiment"""
    seed: int = 1
    """seed of the experiment; training episode e starts from env.reset(seed=seed + e)"""
    torch_threads: int = 1
    """torch CPU threads (2 threads collapse when another process shares a 2-core machine)"""
    track: bool = False
    """whether to mirror the run to Weights and Biases: its TensorBoard logs, Args, this script and the videos (needs wandb; WANDB_MODE=offline keeps it on disk)"""
    wandb_project_name: str = "jirl"
    """the Weights and Biases project of --track"""
    wandb_entity: Optional[str] = None
    """the Weights and Biases entity (a user or a team) of --track; None: your account's default entity"""
    capture_video: bool = False
    """whether to record videos of the agent to `videos/{run_name}` (needs moviepy)"""
    save_model: bool = False
    """whether to save a checkpoint to `runs/{run_name}` and evaluate it at the end"""
    eval_episodes: int = 10
    """deterministic evaluation episodes after training (with --save-model)"""
    log_every: int = 100
    """log losses and SPS every this many steps"""

    # Algorithm specific arguments
    env_id: str = "Pendulum-v1"
    """the id of the environment (any Gymnasium env with a Box action space)"""
    total_timesteps: int = 20_000
    """total timesteps of the experiment"""
    buffer_size: int = 1_000_000
    """the replay memory buffer size (no more is allocated than the run can fill)"""
    gamma: float = 0.99
    """the discount factor gamma"""
    tau: float = 0.005
    """target smoothing coefficient"""
    batch_size: int = 256
    """the batch size of samples from the replay memory"""
    learning_starts: int = 5_000
    """timestep to start learning; uniformly random actions before it"""
    hidden_size: int = 256
    """units in each of the two hidden layers of every network (the paper used 64, 256 for Walker2D)"""
    policy_lr: float = 3e-4
    """the learning rate of the policy network optimizer"""
    q_lr: float = 1e-3
    """the learning rate of the Q network optimizer (and of the entropy coefficient)"""
    policy_frequency: int = 2
    """the frequency of training policy (delayed, repeated to keep one actor step per env step)"""
    target_network_frequency: int = 1
    """the frequency of updates for the target networks"""
    alpha: float = 0.2
    """entropy regularization coefficient (initial value with --autotune)"""
    autotune: bool = True
    """automatic tuning of the entropy coefficient"""

    # Baseline regret
    baseline: str = ""
    """baseline controller as module:function returning env-unit actions; empty: this project's baseline for env_id"""
    regret_estimator: Literal["auto", "paired", "unpaired", "off"] = "auto"
    """paired: a shadow env runs the baseline from each training episode's reset seed; unpaired: the baseline's mean reward per step; auto: paired when the env reproduces a seeded reset"""
    baseline_eval_episodes: int = 10
    """episodes measuring the baseline's mean return and reward per step (the unpaired estimator)"""

    def __post_init__(self) -> None:
        """Out-of-range values end the parse with a message naming each flag (tyro prints it)."""
        rules = [
            ("exp_name", bool(self.exp_name) and os.path.basename(self.exp_name) == self.exp_name, "a name, not empty and not a path"),
            ("seed", 0 <= self.seed < 2**32, "in [0, 2**32)"),  # numpy's global seed
            ("torch_threads", self.torch_threads >= 1, ">= 1"),
            ("eval_episodes", self.eval_episodes >= 1, ">= 1"),
            ("log_every", self.log_every >= 1, ">= 1"),
            ("total_timesteps", self.total_timesteps >= 1, ">= 1"),
            ("buffer_size", self.buffer_size >= 1, ">= 1"),
            ("gamma", 0.0 <= self.gamma <= 1.0, "in [0, 1]"),
            ("tau", 0.0 < self.tau <= 1.0, "in (0, 1]"),
            ("batch_size", self.batch_size >= 1, ">= 1"),
            ("learning_starts", self.learning_starts >= 0, ">= 0"),
            ("hidden_size", self.hidden_size >= 1, ">= 1"),
            ("policy_lr", 0.0 < self.policy_lr < math.inf, "> 0"),
            ("q_lr", 0.0 < self.q_lr < math.inf, "> 0"),
            ("policy_frequency", self.policy_frequency >= 1, ">= 1"),
            ("target_network_frequency", self.target_network_frequency >= 1, ">= 1"),
            ("alpha", 0.0 < self.alpha < math.inf, "> 0"),
            ("baseline_eval_episodes", self.baseline_eval_episodes >= 1, ">= 1"),
        ]  # comparisons with NaN are False, so NaN fails every rule
        problems = [f"--{name.replace('_', '-')} must be {rule}, got {getattr(self, name)}" for name, ok, rule in rules if not ok]
        if problems:
            raise ValueError("; ".join(problems))


def kind(err: Exception) -> str:
    """The exception's type as a user would look it up: ValueError, but pybullet.error."""
    module = type(err).__module__
    return type(err).__qualname__ if module == "builtins" else f"{module}.{type(err).__qualname__}"


def raised(err: Exception) -> str:
    """'raised {Type} ({file}, line {n})' for an exception from a user's code (an env, a baseline), after
    printing its traceback: the one line that ends the run then says where it came from."""
    where = traceback.extract_tb(err.__traceback__)[-1]
    traceback.print_exc()
    return f"raised {kind(err)} ({os.path.basename(where.filename)}, line {where.lineno})"


def flaw(obs: np.ndarray, shape: tuple, reward: float = 0.0, terminated: bool = False, truncated: bool = False) -> str:
    """What makes an env's return unusable ('' when nothing): one NaN or infinity learnt from (a
    simulation that diverged) turns every weight to NaN, and an observation of another shape than its
    space's, a reward that is not a number or a flag that is neither True nor False fits no buffer."""
    if obs.shape != shape:
        return f"an observation of shape {obs.shape}, not its space's {shape}"
    try:
        if not np.isfinite(obs).all():
            return "a non-finite observation"
    except TypeError:  # objects or strings
        return f"an observation of dtype {obs.dtype}, not numbers"
    try:
        if not math.isfinite(reward):
            return "a non-finite reward"
    except TypeError:  # None, a string, a reward in an array
        return f"a reward that is not a number ({reward!r:.60})"
    try:
        if terminated in (True, False) and truncated in (True, False):  # also numpy's bools, and 0 and 1
            return ""
    except ValueError:  # several flags in an array
        pass
    return f"flags terminated={terminated!r:.30}, truncated={truncated!r:.30}, where each must be True or False"


class CheckedEnv(gym.Wrapper):
    """The env as the scripts step it: an exception of its own (a simulator that lost its connection,
    hours into a run) and a NaN, an infinity or a malformed observation, reward or flag it returns
    (`flaw`) all come out as a ValueError naming the env and the episode's reset seed, on which the
    training loop ends keeping its model. A failure to close, which follows a simulator's loss, is a
    warning line instead of a second traceback."""

    def __init__(self, env: gym.Env, env_id: str):
        super().__init__(env)
        self.env_id, self.episode = env_id, "an unseeded reset"
        self.shape = env.observation_space.shape  # looked up once: through a stack of wrappers it takes half a microsecond

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        self.episode = "an unseeded reset" if seed is None else f"reset seed {seed}"
        try:
            obs, info = self.env.reset(seed=seed, options=options)
        except Exception as err:
            raise ValueError(f"{self.env_id} {raised(err)} at {self.episode}: {err}") from err
        obs = np.asarray(obs)  # a list, which Gymnasium tolerates, as the networks need it
        what = flaw(obs, self.shape)
        if what:
            raise ValueError(f"{self.env_id} returned {what} at {self.episode}")
        return obs, info

    def step(self, action):
        try:
            obs, reward, terminated, truncated, info = self.env.step(action)
        except Exception as err:
            raise ValueError(f"{self.env_id} {raised(err)} in the episode from {self.episode}: {err}") from err
        obs = np.asarray(obs)
        what = flaw(obs, self.shape, reward, terminated, truncated)
        if what:
            raise ValueError(f"{self.env_id} returned {what} in the episode from {self.episode}")
        return obs, reward, terminated, truncated, info

    def close(self) -> None:
        try:
            self.env.close()
        except Exception as err:  # a simulator gone (what ended the run, maybe) cannot close: the run still ends as it would
            print(f"warning: {self.env_id} failed to close: {kind(err)}: {err}", file=sys.stderr)


def make_env(env_id: str, seed: int, capture_video: bool = False, run_name: str = "") -> gym.Env:
    """One env (no vector wrapper: episodes are reset explicitly, so there is no autoreset to undo)."""
    render = {"render_mode": "rgb_array"} if capture_video else {}  # only when recording: an env whose constructor has no render_mode still works
    if project_make_env is not None:
        env = project_make_env(env_id, seed, **render)
    else:
        module, sep, name = env_id.partition(":")
        if sep and (not module or module.startswith(".") or not name or sep in name):  # gym.make would fail with a bare ValueError or TypeError
            raise ValueError(f"env id {env_id!r} must be a registered id or look like 'module:Env-v0' (an absolute module name, one colon)")
        try:
            env = gym.make(env_id, **render)
        except gym.error.DependencyNotInstalled as err:  # a known id whose simulator is missing
            raise ValueError(f"env id {env_id!r} needs a package that is not installed: {err}") from None
        except ImportError as err:  # `module:Env-v0` whose module, or one its env needs, does not import
            raise ValueError(f"env id {env_id!r} needs a module that does not import: {err}") from None
        except gym.error.Error as err:
            raise ValueError(f"unknown env id {env_id!r}: {err}") from None
        except ValueError as err:  # the env refusing its settings: say which env
            raise ValueError(f"cannot make env {env_id!r}: {err}") from None
        env.action_space.seed(seed)
    if not isinstance(env.action_space, gym.spaces.Box) or len(env.action_space.shape) != 1:
        raise ValueError(f"{env_id} has a {env.action_space} action space; this script needs a flat continuous (Box) one")
    if not np.all(np.isfinite(env.action_space.low) & np.isfinite(env.action_space.high)):
        raise ValueError(f"{env_id} has an unbounded action space {env.action_space}; SAC squashes actions into bounds")
    if not isinstance(env.observation_space, gym.spaces.Box) or len(env.observation_space.shape) != 1:
        raise ValueError(f"{env_id} has observations {env.observation_space}; this script needs a flat Box")
    if capture_video:
        try:  # RecordVideo needs moviepy, and would create videos/ before saying so
            import moviepy  # noqa: F401
        except ImportError:
            raise ValueError("--capture-video needs moviepy (pip install moviepy)") from None
        env = gym.wrappers.RecordVideo(env, f"videos/{run_name}")
    return CheckedEnv(env, env_id)


def load_baseline(spec: str, env_id: str) -> Optional[Callable]:
    """The baseline `module:function` (a class is instantiated), else this project's one for env_id, else None."""
    if spec:
        module_name, sep, attribute = spec.partition(":")
        if not (module_name and sep and attribute) or module_name.startswith(".") or sep in attribute:
            raise ValueError(f"baseline {spec!r} must look like 'module:function' (an absolute module name, one colon)")
        try:  # a ValueError the user's module raises is named with the baseline too
            baseline = getattr(importlib.import_module(module_name), attribute)
        except (ImportError, AttributeError, ValueError) as err:
            raise ValueError(f"cannot load baseline {spec!r}: {err}") from None
        try:
            baseline = baseline() if isinstance(baseline, type) else baseline
        except ValueError as err:  # a class refusing its settings; any other error keeps its traceback
            raise ValueError(f"cannot load baseline {spec!r}: {err}") from None
        if not callable(baseline):
            raise ValueError(f"baseline {spec!r} is a {type(baseline).__name__}, not a function or class")
        return baseline
    if project_baseline is None:
        return None
    try:
        return project_baseline(env_id)
    except ValueError:
        return None


def ask_baseline(baseline: Callable, obs: np.ndarray):
    """The baseline's action at obs. Whatever a baseline raises (a user's controller at a state it was
    not written for) is printed with its traceback and raised again as a ValueError that names it, so
    that a run asking the baseline mid-training ends as for a bad action: keeping its model."""
    try:
        return baseline(obs)
    except Exception as err:
        raise ValueError(f"the baseline {raised(err)}: {err}") from err


def check_baseline_action(action, space: gym.spaces.Box) -> np.ndarray:
    """The baseline's action shaped like the action space (a bare number for a 1-D space is fine) and
    clipped to its bounds, as the agent's always is: the baseline measured is the one that is handed
    control, on envs that do not clip by themselves too. ValueError unless it holds one finite number
    per action dimension (env units)."""
    try:
        values = np.asarray(action, dtype=np.float64)
    except (TypeError, ValueError):
        values = np.array([np.nan])
    if values.size != math.prod(space.shape) or not np.all(np.isfinite(values)):
        raise ValueError(f"the baseline returned {action!r}; expected {math.prod(space.shape)} finite number(s) in env units")
    return np.clip(np.asarray(action).reshape(space.shape), space.low, space.high)


def baseline_rollout(env: gym.Env, baseline: Callable, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """One baseline episode from env.reset(seed=seed): (initial observation, reward of every step).
    env is make_env's, which raises on a NaN: a NaN regret would hide every later episode's."""
    if hasattr(baseline, "reset"):
        baseline.reset()
    obs, _ = env.reset(seed=seed)
    first_obs, rewards, done = obs, [], False
    while not done:
        action = ask_baseline(baseline, obs)
        if action is None:
            raise ValueError("the baseline returned None (it only intervenes), so it cannot be measured; use --regret-estimator off")
        obs, reward, terminated, truncated, _ = env.step(check_baseline_action(action, env.action_space))
        rewards.append(float(reward))
        done = terminated or truncated
        if not done and len(rewards) == EPISODE_LIMIT:  # a baseline that never fails would run for ever
            raise ValueError(f"the baseline's episode from reset seed {seed} did not end within {EPISODE_LIMIT:,} steps;"
                             " give the env a time limit (max_episode_steps) or use --regret-estimator off")
    return first_obs, np.asarray(rewards)


def paired_regret(rewards: np.ndarray, baseline_rewards: np.ndarray) -> tuple[float, float]:
    """Baseline regret of one episode against the baseline's episode from the same initial state.

    Returns (max(0, R^b - R), sum_t max(0, r^b_t - r_t)), the per-step sum being the paper's
    Definition 1; steps align by index and a finished trajectory earns 0 after its end.
    """
    steps = max(len(rewards), len(baseline_rewards))
    r = np.zeros(steps)
    r[: len(rewards)] = rewards
    r_b = np.zeros(steps)
    r_b[: len(baseline_rewards)] = baseline_rewards
    return max(0.0, float(r_b.sum() - r.sum())), float(np.maximum(r_b - r, 0.0).sum())


def unpaired_regret(rewards: np.ndarray, baseline_reward_per_step: float) -> tuple[float, float]:
    """Fallback when episodes cannot be paired: the baseline earns b per step.

    Returns (max(0, b L - R), sum_t max(0, b - r_t)); the per-step form overstates the paired one.
    """
    rewards = np.asarray(rewards, dtype=np.float64)
    b = baseline_reward_per_step
    return max(0.0, b * len(rewards) - float(rewards.sum())), float(np.maximum(b - rewards, 0.0).sum())


def to_env_units(action: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Policy actions live in [-1, 1]; the env's in [low, high]."""
    return low + (action + 1.0) * 0.5 * (high - low)


class ReplayBuffer:
    """Preallocated ring buffer; actions are stored in policy units [-1, 1].

    One row per transition (obs, action, reward, next_obs, terminated) in one array, so sampling a
    batch is one gather; the named fields are views of its columns.
    """

    def __init__(self, capacity: int, obs_dim: int, act_dim: int, seed: int):
        self.capacity, self.size, self.pos = capacity, 0, 0
        self.fields = (obs_dim, act_dim, 1, obs_dim, 1)
        try:
            self.storage = np.zeros((capacity, sum(self.fields)), dtype=np.float32)
        except MemoryError:  # a --buffer-size with a zero too many, say
            raise ValueError(f"a replay buffer of {capacity:,} transitions ({capacity * sum(self.fields) * 4 / 2**30:,.0f} GiB) does not fit in memory") from None
        self.obs, self.actions, self.rewards, self.next_obs, self.terminations = np.split(self.storage, np.cumsum(self.fields)[:-1], axis=1)
        self.rng = np.random.default_rng(seed)

    def add(self, obs, action, reward: float, next_obs, terminated: bool) -> None:
        i = self.pos
        self.obs[i], self.actions[i], self.rewards[i] = obs, action, reward
        self.next_obs[i], self.terminations[i] = next_obs, terminated
        self.pos = (self.pos + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch_size: int) -> tuple[torch.Tensor, ...]:
        """(obs, actions, rewards, next_obs, terminations) of a uniform batch, as column views of one tensor."""
        idx = self.rng.integers(0, self.size, size=batch_size)
        return torch.from_numpy(self.storage[idx]).split(self.fields, dim=1)


class EnsembleLinear(nn.Module):
    """`num` independent nn.Linear layers evaluated by one batched matrix product.

    weight[i] and bias[i] are layer i's, shaped and initialised as nn.Linear's ((out, in), U(+-1/sqrt(in))).
    """

    def __init__(self, num: int, in_features: int, out_features: int):
        super().__init__()
        bound = 1.0 / math.sqrt(in_features)
        self.weight = nn.Parameter(torch.empty(num, out_features, in_features).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(num, 1, out_features).uniform_(-bound, bound))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (batch, in) shared by every member, or (num, batch, in); returns (num, batch, out)."""
        if x.dim() == 2:
            x = x.expand(self.weight.shape[0], *x.shape)
        return torch.baddbmm(self.bias, x, self.weight.transpose(1, 2))


class SoftQNetwork(nn.Module):
    """The twin soft Q-functions as one ensemble: each layer holds Q1's and Q2's weights, so both are
    evaluated by one chain of batched products (half the operations of two networks, same arithmetic)."""

    def __init__(self, obs_dim: int, act_dim: int, hidden_size: int, num_critics: int = 2):
        super().__init__()
        self.fc1 = EnsembleLinear(num_critics, obs_dim + act_dim, hidden_size)
        self.fc2 = EnsembleLinear(num_critics, hidden_size, hidden_size)
        self.fc3 = EnsembleLinear(num_critics, hidden_size, 1)

    def forward(self, x: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """Q1(s, a), Q2(s, a) stacked: (num_critics, batch, 1)."""
        x = torch.cat([x, a], 1)
        x = F.relu(self.fc1(x), inplace=True)  # in place: the products before need their inputs, not outputs
        x = F.relu(self.fc2(x), inplace=True)
        return self.fc3(x)


LOG_STD_MAX = 2
LOG_STD_MIN = -5
HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)
LOG_2 = math.log(2.0)


class Actor(nn.Module):
    """Tanh-squashed Gaussian policy over actions in [-1, 1]."""

    def __init__(self, obs_dim: int, act_dim: int, hidden_size: int):
        super().__init__()
        self.fc1 = nn.Linear(obs_dim, hidden_size)
        self.fc2 = nn.Linear(hidden_size, hidden_size)
        self.fc_mean = nn.Linear(hidden_size, act_dim)
        self.fc_logstd = nn.Linear(hidden_size, act_dim)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = F.relu(self.fc1(x), inplace=True)  # in place: the products before need their inputs, not outputs
        x = F.relu(self.fc2(x), inplace=True)
        mean = self.fc_mean(x)
        log_std = torch.tanh(self.fc_logstd(x))
        log_std = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (log_std + 1)  # From SpinUp / Denis Yarats
        return mean, log_std

    def get_action(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(sampled action, its log-density, deterministic action tanh(mean))."""
        mean, log_std = self(x)
        noise = torch.randn_like(mean)
        x_t = mean + log_std.exp() * noise  # reparameterization trick
        y_t = torch.tanh(x_t)
        # the Gaussian's log-density at x_t, written out (torch.distributions costs more than the math here),
        # then the change of variables through tanh in the stable form log(1 - tanh(x)^2) = 2 (log 2 - x - softplus(-2x))
        log_prob = -0.5 * noise.square() - log_std - HALF_LOG_2PI - 2.0 * (LOG_2 - x_t - F.softplus(-2.0 * x_t))
        return y_t, log_prob.sum(1, keepdim=True), torch.tanh(mean)


def all_finite(part: object) -> bool:
    """Whether every tensor in a part of a state is finite, in the dicts an optimizer's state nests them in."""
    if isinstance(part, dict):
        return all(all_finite(x) for x in part.values())
    return not torch.is_tensor(part) or bool(torch.isfinite(part).all())


PART_NAMES = {"actor": "the actor", "qf": "the critics", "qf_target": "the target critics", "q_optimizer": "the critics' optimizer",
              "actor_optimizer": "the actor's optimizer", "log_alpha": "the entropy coefficient"}  # SoftActorCritic.state_dict()'s, in words


class SoftActorCritic:
    """SAC's networks, optimizers and entropy coefficient, and one gradient step of it (`update`)."""

    def __init__(self, obs_dim: int, act_dim: int, args: Args):
        self.args = args
        self.actor = Actor(obs_dim, act_dim, args.hidden_size)
        self.qf = SoftQNetwork(obs_dim, act_dim, args.hidden_size)
        self.qf_target = SoftQNetwork(obs_dim, act_dim, args.hidden_size)
        self.qf_target.load_state_dict(self.qf.state_dict())
        self.q_params, self.q_target_params = list(self.qf.parameters()), list(self.qf_target.parameters())
        # fused: one kernel per optimizer step instead of a loop over parameters (2.4-2.7x faster on CPU, BENCHMARKS.md)
        self.q_optimizer = optim.Adam(self.q_params, lr=args.q_lr, fused=FUSED_ADAM)
        # Automatic entropy tuning
        self.target_entropy = -float(act_dim)
        self.log_alpha = torch.full((1,), float(np.log(args.alpha)), requires_grad=args.autotune)
        self.alpha = self.log_alpha.exp().detach()
        # the entropy coefficient shares the actor's Adam as a second parameter group (its own learning rate):
        # Adam is per-parameter, so this is the same update as a separate optimizer, one step and backward fewer
        param_groups = [{"params": list(self.actor.parameters()), "lr": args.policy_lr}]
        if args.autotune:
            param_groups.append({"params": [self.log_alpha], "lr": args.q_lr})
        self.actor_optimizer = optim.Adam(param_groups, fused=FUSED_ADAM)

    def update(self, data: tuple[torch.Tensor, ...], step: int) -> dict[str, torch.Tensor]:
        """One critic step (and, every policy_frequency steps, actor and alpha steps); the losses, as tensors."""
        args, alpha = self.args, self.alpha
        b_obs, b_actions, b_rewards, b_next_obs, b_terminations = data
        with torch.no_grad():
            next_state_actions, next_state_log_pi, _ = self.actor.get_action(b_next_obs)
            qf_next_target = self.qf_target(b_next_obs, next_state_actions)  # (2, batch, 1): both target critics
            min_qf_next_target = qf_next_target.min(0).values - alpha * next_state_log_pi
            next_q_value = b_rewards + (1 - b_terminations) * args.gamma * min_qf_next_target

        qf_a_values = self.qf(b_obs, b_actions)
        qf_losses = (qf_a_values - next_q_value).square().mean((1, 2))  # each critic's MSE
        qf_loss = qf_losses.sum()

        # optimize the model
        self.q_optimizer.zero_grad()
        qf_loss.backward()
        self.q_optimizer.step()
        losses = {"qf1_values": qf_a_values[0].mean(), "qf2_values": qf_a_values[1].mean(), "qf1_loss": qf_losses[0],
                  "qf2_loss": qf_losses[1], "qf_loss": qf_loss / 2.0}  # fmt: skip

        if step % args.policy_frequency == 0:  # TD 3 Delayed update support
            self.qf.requires_grad_(False)  # the actor loss needs gradients through the critics, not of them
            for _ in range(args.policy_frequency):  # compensate for the delay by doing 'actor_update_interval' instead of 1
                pi, log_pi, _ = self.actor.get_action(b_obs)
                min_qf_pi = self.qf(b_obs, pi).min(0).values
                actor_loss = ((self.alpha * log_pi) - min_qf_pi).mean()
                losses["actor_loss"] = loss = actor_loss

                if args.autotune:
                    # the actor step's own log-probabilities, as in SB3 (saves a forward pass); the two losses
                    # share no parameter, so one backward of their sum gives each its own gradient
                    alpha_loss = (-self.log_alpha.exp() * (log_pi.detach() + self.target_entropy)).mean()
                    losses["alpha_loss"] = alpha_loss
                    loss = actor_loss + alpha_loss

                self.actor_optimizer.zero_grad()
                loss.backward()
                self.actor_optimizer.step()
                self.alpha = self.log_alpha.exp().detach()
            self.qf.requires_grad_(True)

        # update the target networks
        if step % args.target_network_frequency == 0:
            with torch.no_grad():
                torch._foreach_lerp_(self.q_target_params, self.q_params, args.tau)
        losses["alpha"] = self.alpha
        return losses

    def divergence(self) -> str:
        """The parts whose weights or optimizer moments hold a NaN or an infinity ('' when none): a training
        that diverged (a step or a reward too large), named so in the line that ends the run, and not taken
        for the env's fault, which its NaN action would become (CheckedEnv). The car's training checks the
        same before it saves, as a state holding either would not resume."""
        names = [PART_NAMES[key] for key, part in self.state_dict().items() if not all_finite(part)]
        if not names:
            return ""
        return "NaN or infinite values in " + (" and ".join([", ".join(names[:-1]), names[-1]]) if len(names) > 1 else names[0])

    def state_dict(self) -> dict:
        """Everything needed to resume training: networks, targets, optimizers, entropy coefficient."""
        state = {name: getattr(self, name).state_dict() for name in ("actor", "qf", "qf_target", "q_optimizer", "actor_optimizer")}
        state["log_alpha"] = self.log_alpha.detach().clone()
        return state

    def load_state_dict(self, state: dict) -> None:
        for name in ("actor", "qf", "qf_target", "q_optimizer", "actor_optimizer"):
            getattr(self, name).load_state_dict(state[name])
        # an optimizer's state carries the learning rates it was made with: this run's apply, as its other settings do
        self.q_optimizer.param_groups[0]["lr"] = self.args.q_lr
        for group, lr in zip(self.actor_optimizer.param_groups, (self.args.policy_lr, self.args.q_lr)):  # the actor's, then the entropy coefficient's
            group["lr"] = lr
        with torch.no_grad():
            self.log_alpha.copy_(state["log_alpha"])
        self.alpha = self.log_alpha.exp().detach()


def write_checkpoint(path: str, checkpoint: dict) -> None:
    """torch.save(checkpoint, path). A write that fails (a full disk) raises its OSError and leaves no
    file: half a checkpoint would pass for one until it is loaded."""
    file = open(path, "wb")  # an OSError here (no such folder, no permission) changes nothing
    try:
        with file:
            torch.save(checkpoint, file)
    except BaseException as err:
        if os.path.isfile(path):  # not a device such as /dev/null
            os.remove(path)
        if isinstance(err, RuntimeError) and isinstance(err.__context__, OSError):
            raise err.__context__ from None  # torch reports the OSError as its zip writer's "unexpected pos"
        raise


def save_checkpoint(path: str, env_id: str, env: gym.Env, actor: Actor, qf: SoftQNetwork, args: Args) -> None:
    """Everything needed to rebuild and check the actor: weights, spaces, hyperparameters."""
    write_checkpoint(
        path,
        {
            "format": CHECKPOINT_FORMAT,
            "env_id": env_id,
            "obs_dim": int(env.observation_space.shape[0]),
            "action_low": env.action_space.low.tolist(),
            "action_high": env.action_space.high.tolist(),
            "hidden_size": args.hidden_size,
            "actor": actor.state_dict(),
            "qf": qf.state_dict(),
            "args": vars(args),
        },
    )


def load_checkpoint(path: str) -> dict:
    """Read a checkpoint written by save_checkpoint; ValueError if it is not one."""
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as err:  # torch raises many types for a damaged file; keep the first sentence (the rest advises weights_only=False)
        cause = (str(err).strip().splitlines() or ["the file ends early"])[0].split(". ")[0]
        raise ValueError(f"{path} is not a readable checkpoint ({type(err).__name__}: {cause})") from None
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != CHECKPOINT_FORMAT:
        found = checkpoint.get("format") if isinstance(checkpoint, dict) else None
        if isinstance(found, str) and found.startswith("jirl-"):  # another script's or version's: name it and its run
            run = checkpoint["args"].get("exp_name") if isinstance(checkpoint.get("args"), dict) else None
            origin = f" (from a {run} run)" if isinstance(run, str) else ""
            raise ValueError(f"{path} is a {found} file{origin}, not a {CHECKPOINT_FORMAT} checkpoint")
        raise ValueError(f"{path} is not a {CHECKPOINT_FORMAT} checkpoint")
    missing = [key for key in CHECKPOINT_KEYS if key not in checkpoint]
    if missing:
        raise ValueError(f"{path} is a damaged {CHECKPOINT_FORMAT} checkpoint: it has no {', '.join(missing)}")
    damage = checkpoint_damage(checkpoint)
    if damage is not None:
        raise ValueError(f"{path} is a damaged {CHECKPOINT_FORMAT} checkpoint: {damage}")
    return checkpoint


def checkpoint_damage(checkpoint: dict) -> Optional[str]:
    """The first value no sound checkpoint holds, named, or None: torch would refuse such a value later
    with a traceback of its own, and NaN weights would pass for a diverged env."""
    low, high, weights = checkpoint["action_low"], checkpoint["action_high"], checkpoint["actor"]
    fits = {
        "obs_dim": type(checkpoint["obs_dim"]) is int and checkpoint["obs_dim"] > 0,
        "hidden_size": type(checkpoint["hidden_size"]) is int and checkpoint["hidden_size"] > 0,
        "action_low": isinstance(low, (list, tuple)) and len(low) > 0 and all(type(x) in (int, float) for x in low),
        "action_high": isinstance(high, (list, tuple)) and isinstance(low, (list, tuple)) and len(high) == len(low) and all(type(x) in (int, float) for x in high),
        "actor": isinstance(weights, dict) and all(type(k) is str and torch.is_tensor(w) and bool(torch.isfinite(w).all()) for k, w in weights.items()),
    }
    field = next((field for field, ok in fits.items() if not ok), None)
    if field == "actor" and isinstance(weights, dict):  # NaN: a damaged file, or a training that diverged
        named = all(type(k) is str and torch.is_tensor(w) for k, w in weights.items())
        return f"its {field} holds {'a NaN or infinite weight' if named else 'an entry that is not a named tensor'}"
    return None if field is None else f"its {field} is {reprlib.repr(checkpoint[field])}"


def actor_from_checkpoint(checkpoint: dict, env: gym.Env) -> Actor:
    """The checkpoint's actor, after checking that it was trained on spaces like env's."""
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    if checkpoint["obs_dim"] != obs_dim or len(checkpoint["action_low"]) != act_dim:
        raise ValueError(
            f"checkpoint expects {checkpoint['obs_dim']} observations and {len(checkpoint['action_low'])} actions"
            f" ({checkpoint['env_id']}); this env has {obs_dim} and {act_dim}"
        )
    if not np.allclose(checkpoint["action_low"], env.action_space.low) or not np.allclose(
        checkpoint["action_high"], env.action_space.high
    ):
        raise ValueError(f"checkpoint action bounds differ from this env's {env.action_space}")
    actor = Actor(obs_dim, act_dim, checkpoint["hidden_size"])
    try:
        actor.load_state_dict(checkpoint["actor"])
    except RuntimeError as err:  # torch's message runs over several lines: keep it on one
        raise ValueError(f"checkpoint actor weights do not fit: {' '.join(str(err).split())}") from None
    return actor.eval()


def evaluate(path: str, env_id: str, episodes: int, seed: int) -> list[float]:
    """Returns of the checkpoint's deterministic policy, episode i reset with seed + EVAL_SEED_OFFSET + i."""
    env = make_env(env_id, seed)
    actor = actor_from_checkpoint(load_checkpoint(path), env)
    low, high = env.action_space.low, env.action_space.high
    returns = []
    for i in range(episodes):
        obs, _ = env.reset(seed=seed + EVAL_SEED_OFFSET + i)
        episode_return, done, steps = 0.0, False, 0
        while not done:
            with torch.inference_mode():
                _, _, action = actor.get_action(torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0))
            action = action[0].numpy()
            if not np.isfinite(action).all():  # finite weights whose output overflows float32: not the env's fault, which its NaN would become
                raise ValueError(f"the policy's action at step {steps} of evaluation episode {i} is {action.tolist()}, not finite: its network overflows float32 there")
            obs, reward, terminated, truncated, _ = env.step(to_env_units(action, low, high))
            episode_return += float(reward)
            done, steps = terminated or truncated, steps + 1
            if not done and steps == EPISODE_LIMIT:  # a policy that never fails would run for ever
                raise ValueError(f"evaluation episode {i} did not end within {EPISODE_LIMIT:,} steps; give the env a time limit (max_episode_steps)")
        returns.append(episode_return)
    env.close()
    return returns


def claim_run_dir(run_name: str) -> str:
    """Create runs/{run_name} and return the name; a run that finds it taken (one launched in the same
    second, as a sweep is) takes run_name_2, _3, ...: two runs never share a directory, where TensorBoard
    would merge their curves and one model would overwrite the other."""
    name, n = run_name, 1
    while True:
        os.makedirs(os.path.dirname(f"runs/{name}"), exist_ok=True)  # a namespaced env id ("ns/Env-v0") nests
        try:
            os.mkdir(f"runs/{name}")  # atomic: of two runs making it at once, exactly one succeeds
            return name
        except FileExistsError:
            n += 1
            name = f"{run_name}_{n}"
        except FileNotFoundError:  # a run that ended on bad input removed runs/, empty, in between: again
            pass


def start_tracking(args: Args, run_name: str):
    """The Weights and Biases run of --track, which mirrors the TensorBoard logs of runs/{run_name} (the
    writer is made after it) and keeps Args and this script; ValueError when it cannot start (no wandb,
    no login, no server), before anything is trained. Not monitor_gym: its hook fails at gymnasium 1.x's
    RecordVideo.close (wandb issue 9947), so VideoTracker sends each video once RecordVideo has written it."""
    try:
        import wandb
    except ImportError:
        raise ValueError("--track needs Weights and Biases (pip install wandb)") from None
    if wandb.run is not None:  # an earlier run in this process (runpy, a notebook) that ended on an error, or whose W&B process died
        try:
            wandb.run.finish(exit_code=1)
        except Exception:  # that process is gone; wandb.init starts another
            pass
    wandb.tensorboard.unpatch()  # the earlier run's patch named its own folder
    wandb.tensorboard.patch(root_logdir=f"runs/{run_name}")  # sync_tensorboard=True with the folder named: unnamed, wandb seeks it for 10 s, and no run ends sooner
    try:
        return wandb.init(project=args.wandb_project_name, entity=args.wandb_entity, name=run_name, config=vars(args), save_code=True)
    except wandb.errors.Error as err:  # its message runs over several lines: keep it on one
        raise ValueError(f"--track: Weights and Biases did not start: {' '.join(str(err).split())}") from None


class VideoTracker:
    """Sends the videos of --capture-video to the --track run, each once written: RecordVideo writes
    rl-video-episode-{e}.mp4 when the next episode starts, or when the env closes for an episode still
    running, so send() is called after each reset and after env.close(). One that cannot be sent (W&B's
    process gone, the folder removed) is named in one line and ends the sending, not the training."""

    def __init__(self, run, run_name: str) -> None:
        self.run, self.folder, self.sent, self.failed = run, f"videos/{run_name}", set(), False

    def send(self, global_step: int) -> None:
        if self.failed:
            return
        import wandb

        try:
            written = {int(match[1]) for match in (re.fullmatch(r"rl-video-episode-(\d+)\.mp4", name) for name in os.listdir(self.folder)) if match}
            for episode in sorted(written - self.sent):
                self.run.log({"videos": wandb.Video(f"{self.folder}/rl-video-episode-{episode}.mp4"), "global_step": global_step})
                self.sent.add(episode)
        except Exception as err:  # the run's logs and model do not depend on W&B
            self.failed = True
            print(f"--track: a video could not be sent at step {global_step} ({kind(err)}: {err}); the run goes on, sending no more", file=sys.stderr)


def finish_tracking(run, exit_code: int) -> None:
    """Finish the --track run with the status the run exits with. A W&B process that died during the run
    is named in one line, not a traceback, and leaves that status as it is: the TensorBoard logs and the
    model are whole."""
    import wandb

    try:
        run.finish(exit_code=exit_code)
    except Exception as err:  # wandb's own exit hook would then raise again: tear it down here
        print(f"--track: Weights and Biases did not finish the run ({kind(err)}: {err}); runs/ has its logs", file=sys.stderr)
        try:
            wandb.teardown()
        except Exception:
            pass


class CheckedWriter(SummaryWriter):
    """TensorBoard's SummaryWriter, except that a write that fails (a full disk, a file-size limit) is not
    raised from whichever call comes next, mid-loop, after a traceback from TensorBoard's writing thread:
    it is said once, in `failure`, and later writes are dropped. The loop then ends as for a failing env,
    keeping the model where the disk has room for it."""

    def __init__(self, log_dir: str) -> None:
        self.failure = ""  # why the logs stopped; "" while they are written
        self.other_threads_hook = threading.excepthook
        threading.excepthook = self.thread_failed  # before super() starts the writing thread
        self.checked(super().__init__, log_dir)  # which writes the event file's first record

    def add_scalar(self, *args, **kwargs) -> None:
        self.checked(super().add_scalar, *args, **kwargs)

    def add_text(self, *args, **kwargs) -> None:
        self.checked(super().add_text, *args, **kwargs)

    def close(self) -> None:
        self.checked(super().close)  # which joins the writing thread
        if threading.excepthook == self.thread_failed:  # leave the process as it was found
            threading.excepthook = self.other_threads_hook

    def checked(self, write: Callable, *args, **kwargs) -> None:
        if self.failure:
            return
        try:
            write(*args, **kwargs)
        except OSError as err:  # the thread's error, raised at the first call after it failed
            self.failure = f"cannot write the logs to {self.log_dir}: {err.strerror or err}"

    def thread_failed(self, exc: threading.ExceptHookArgs) -> None:
        """A writing thread's OSError is said by `failure`; any other thread's error as before."""
        if not (isinstance(exc.exc_value, OSError) and type(exc.thread).__module__.startswith("tensorboard.")):
            self.other_threads_hook(exc)


class OutputGuard:
    """sys.stdout or sys.stderr whose reader may go away during a run of hours: a terminal that hung up
    (an ssh session that dropped, for a run under disown or setsid, which gets no SIGHUP, or one whose
    SIGHUP is still on its way) fails every write with EIO; a pipe whose reader ended (`| tee`, killed by
    the hang-up) with EPIPE. Python would raise at the run's next print and lose the run with its model.
    Here the stream's file descriptor is pointed at {folder}/stdout.log or stderr.log instead, as nohup
    would, after a line saying when and why (at /dev/null where there is no folder, or it cannot be
    written), and the run goes on: stopping is SIGHUP's job (StopRequest). Other errors (a full disk)
    are raised as before."""

    guarded = True  # marks a stream already guarded: a run in the same process (runpy) wraps it once

    def __init__(self, stream, name: str = "output", folder: Optional[str] = None) -> None:
        self.stream, self.name, self.folder = stream, name, folder
        if hasattr(stream, "reconfigure"):  # on a pipe, by line as on a terminal: the 8 KB block Python buffers there is lost whole when it meets a dead reader
            stream.reconfigure(line_buffering=True)

    @classmethod
    def install(cls, folder: Optional[str] = None) -> None:
        """Guard sys.stdout and sys.stderr, keeping what they print once their reader has gone in folder."""
        folder = folder and os.path.abspath(folder)
        for name in ("stdout", "stderr"):
            stream = getattr(sys, name)
            if getattr(stream, "guarded", False):  # by an earlier run in this process, maybe another script's copy
                stream.folder = folder
                continue
            try:
                a_file = stat.S_ISREG(os.fstat(stream.fileno()).st_mode)  # a file has no reader to lose
            except (AttributeError, OSError, ValueError):  # no file descriptor (a notebook's, pytest's capsys)
                continue
            if not a_file:
                setattr(sys, name, cls(stream, name, folder))

    def write(self, text: str) -> int:
        try:
            return self.stream.write(text)
        except OSError as err:
            self.lost(err)
            if isinstance(getattr(self.stream, "buffer", None), io.RawIOBase):  # unbuffered (python -u): the text was dropped
                return self.stream.write(text)
            return len(text)  # buffered: the text waits in the buffer for the descriptor's new place

    def writelines(self, lines) -> None:  # the stream's own would call its own write, not this one
        for line in lines:
            self.write(line)

    def flush(self) -> None:
        try:
            self.stream.flush()
        except OSError as err:
            self.lost(err)

    def lost(self, err: OSError) -> None:
        if err.errno not in (errno.EIO, errno.EPIPE):
            raise err
        kept = None
        if self.folder:
            try:
                kept = os.open(os.path.join(self.folder, f"{self.name}.log"), os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
                os.write(kept, f"[{time.strftime('%Y-%m-%d %H:%M:%S')}: the {'terminal' if err.errno == errno.EIO else 'pipe'} of {self.name} went away"
                               f" ({errno.errorcode[err.errno]}); what the run printed from then on follows]\n".encode())
            except OSError:  # the folder removed, a full disk: the output has nowhere to go
                if kept is not None:
                    os.close(kept)
                kept = None
        if kept is None:
            kept = os.open(os.devnull, os.O_WRONLY)
        os.dup2(kept, self.stream.fileno())  # what the stream still holds, and all it is given later, goes there
        os.close(kept)

    def __getattr__(self, name: str):  # fileno, isatty, encoding, buffer: the stream's own
        return getattr(self.stream, name)


class StopRequest:
    """Why the training ends before its last step: Ctrl-C (SIGINT), SIGTERM (`kill`, `timeout`, a
    cluster's time limit) or SIGHUP (the ssh session or terminal it runs in went away), caught so that
    the run ends at the training loop's next turn instead of at once; or an env, a baseline or the logs
    that failed. Either way --save-model still saves what was learnt. The first signal puts the previous
    handlers back, so a second one acts as it always did; after a hang-up, SIGHUP is ignored.
    A signal that comes after the loop that made the request has gone (it crashed in a Python that goes
    on: runpy, IPython's %run) goes to the previous handler at once, instead of waiting for a loop that
    will never read it."""

    def __init__(self) -> None:
        self.reason: Optional[str] = None  # said when the training stops
        self.status = 0  # the run's exit status then
        self.previous: dict = {}
        self.loop_code = sys._getframe(1).f_code  # the code that made this request and runs the training loop
        if threading.current_thread() is not threading.main_thread():  # only the main thread may handle signals
            return
        for sig in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None)):  # no SIGHUP on Windows
            if sig is not None and signal.getsignal(sig) is not signal.SIG_IGN:  # an ignored one stays ignored (Ctrl-C in a script's background job, SIGHUP under nohup)
                self.previous[sig] = signal.signal(sig, self.request)

    def request(self, signum: int, frame: Optional[FrameType]) -> None:
        if frame is not None and not self.running(frame):  # the loop is gone: the signal acts as it did before it
            handler = self.previous.get(signum)
            self.restore()
            if callable(handler):
                handler(signum, frame)  # Python's own raises KeyboardInterrupt
            else:
                signal.raise_signal(signum)  # the default action, back in place
            return
        if signum == getattr(signal, "SIGHUP", None):  # the hung-up terminal's writes fail from here on: OutputGuard
            self.previous[signum] = signal.SIG_IGN  # from here on: a second hang-up (a shell passing it on) is no request to stop at once
        self.end(f"{signal.Signals(signum).name} received", 128 + signum)  # the status a shell gives a process the signal ended

    def end(self, reason: str, status: int) -> None:
        self.reason, self.status = reason, status
        self.restore()

    def running(self, frame: Optional[FrameType]) -> bool:
        """Whether the loop's code is on the stack the signal interrupted."""
        while frame is not None and frame.f_code is not self.loop_code:
            frame = frame.f_back
        return frame is not None

    def restore(self) -> None:
        for sig, handler in self.previous.items():
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)  # None: a handler set outside Python
        self.previous = {}


if __name__ == "__main__":
    args = tyro.cli(Args)
    sys.path.append(os.getcwd())  # `module:...` in --env-id and --baseline may name a module in the current directory; last, so it shadows nothing installed
    try:  # before make_env, whose video folder shares the name
        run_name = claim_run_dir(f"{args.env_id}__{args.exp_name}__{args.seed}__{int(time.time())}")
    except OSError as err:  # a file named runs in the way, no permission, a full disk
        raise SystemExit(f"{args.exp_name}: error: cannot make the run's folder in runs/: {err}")
    OutputGuard.install(f"runs/{run_name}")  # a run whose terminal or pipe is gone trains on, keeping its output there

    # TRY NOT TO MODIFY: seeding
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.torch_threads)

    # env setup; bad input ends here with one line, before anything is written
    try:
        env = make_env(args.env_id, args.seed, args.capture_video, run_name)
        baseline = load_baseline(args.baseline, args.env_id) if args.regret_estimator != "off" else None
        if baseline is None and args.regret_estimator in ("paired", "unpaired"):
            raise ValueError(f"no baseline for {args.env_id}; pass --baseline module:function")
        # no more rows than the run stores
        rb = ReplayBuffer(min(args.buffer_size, args.total_timesteps), env.observation_space.shape[0], env.action_space.shape[0], args.seed)
        wandb_run = start_tracking(args, run_name) if args.track else None  # last: bad input starts no W&B run; before the writer it mirrors
    except BaseException as err:  # bad input, or a crash in a user's env: either way the claimed directory goes, and runs/ if now empty
        os.removedirs(f"runs/{run_name}")
        if isinstance(err, ValueError):
            raise SystemExit(f"{args.exp_name}: error: {err}")
        raise  # anything else keeps its traceback
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    low, high = env.action_space.low, env.action_space.high

    writer = CheckedWriter(f"runs/{run_name}")
    writer.add_text(
        "hyperparameters",
        "|param|value|\n|-|-|\n%s" % ("\n".join([f"|{key}|{value}|" for key, value in vars(args).items()])),
    )

    sac = SoftActorCritic(obs_dim, act_dim, args)
    actor = sac.actor

    rng = np.random.default_rng(args.seed)

    # Baseline measurement on the evaluation seeds, so it compares with eval/episodic_return
    estimator, baseline_reward_per_step, baseline_seconds = "off", 0.0, 0.0
    shadow_env = None  # runs the baseline beside the training env, when needed
    if baseline is not None and args.regret_estimator != "off":
        shadow_env = make_env(args.env_id, args.seed)
        try:
            traces = [baseline_rollout(shadow_env, baseline, args.seed + EVAL_SEED_OFFSET + i)[1] for i in range(args.baseline_eval_episodes)]
        except ValueError as err:
            raise SystemExit(f"{args.exp_name}: error: {err}")
        baseline_return = float(np.mean([t.sum() for t in traces]))
        baseline_reward_per_step = float(sum(t.sum() for t in traces) / sum(len(t) for t in traces))
        writer.add_scalar("charts/baseline_return", baseline_return, 0)
        writer.add_scalar("charts/baseline_reward_per_step", baseline_reward_per_step, 0)
        print(f"baseline: return {baseline_return:.1f}, reward per step {baseline_reward_per_step:.3f}")
        estimator = {"off": "off", "unpaired": "unpaired"}.get(args.regret_estimator, "paired")
    baseline_regret = baseline_regret_per_step = 0.0

    # TRY NOT TO MODIFY: start the game
    start_time = time.time()
    episode, episode_rewards = 0, []
    videos = VideoTracker(wandb_run, run_name) if wandb_run is not None and args.capture_video else None
    try:
        obs, _ = env.reset(seed=args.seed)
    except ValueError as err:  # a NaN, or an exception of the env's own (CheckedEnv)
        raise SystemExit(f"{args.exp_name}: error: {err}")
    if estimator == "paired":
        t0 = time.time()
        try:
            baseline_first_obs, baseline_rewards = baseline_rollout(shadow_env, baseline, args.seed)
        except ValueError as err:
            raise SystemExit(f"{args.exp_name}: error: {err}")
        baseline_seconds += time.time() - t0
        if not np.array_equal(baseline_first_obs, obs):  # the env ignores its reset seed: pairing is impossible
            if args.regret_estimator == "paired":
                raise SystemExit(f"{args.exp_name}: error: {args.env_id} does not reproduce a seeded reset; use --regret-estimator unpaired")
            estimator = "unpaired"
    if baseline is not None:
        print(f"baseline regret estimator: {estimator}")
        writer.add_text("baseline_regret_estimator", estimator)

    if args.learning_starts >= args.total_timesteps:  # allowed (a run of the baseline and an untrained agent), but rarely meant
        print(f"note: --learning-starts {args.learning_starts} is not below --total-timesteps {args.total_timesteps}: the agent is never updated")
    stop = StopRequest()  # from here Ctrl-C, SIGTERM, or an env, a baseline or the logs failing ends the training, keeping what was learnt
    sound, diverged = None, ""  # (step, actor, critics) at the last episode end whose weights were all finite; what diverged
    for global_step in range(args.total_timesteps):
        if writer.failure and stop.reason is None:  # the logs failed: end as for a failing env
            stop.end(f"{args.exp_name}: error: {writer.failure}", 1)
        if stop.reason is not None:
            break
        # ALGO LOGIC: put action logic here
        if global_step < args.learning_starts:
            action = rng.uniform(-1.0, 1.0, size=act_dim).astype(np.float32)
        else:
            with torch.inference_mode():
                action, _, _ = actor.get_action(torch.from_numpy(obs).float().unsqueeze(0))
            action = action[0].numpy()
            if not math.isfinite(sum(action.tolist())):  # a diverged training: end before its NaN acts (numpy's sum here costs 7 µs more)
                diverged = sac.divergence() or "the actor overflowed"
                stop.end(f"{args.exp_name}: error: the training diverged: {diverged}", 1)
                break

        # TRY NOT TO MODIFY: execute the game and log data.
        try:
            next_obs, reward, terminated, truncated, _ = env.step(to_env_units(action, low, high))
        except ValueError as err:  # a diverged simulation (its NaN never reaches the buffer) or a failing env: keep the model
            stop.end(f"{args.exp_name}: error: {err}", 1)
            break
        episode_rewards.append(float(reward))

        # Bootstrap through time-limit truncation: store `terminated`, never `truncated`; next_obs is
        # the true next observation because the env is reset explicitly below, never automatically.
        rb.add(obs, action, reward, next_obs, terminated)
        obs = next_obs

        if terminated or truncated:
            episode_return = float(np.sum(episode_rewards))
            print(f"global_step={global_step}, episodic_return={episode_return:.1f}")
            writer.add_scalar("charts/episodic_return", episode_return, global_step)
            writer.add_scalar("charts/episodic_length", len(episode_rewards), global_step)
            if estimator != "off":
                if estimator == "paired":
                    regret, regret_per_step = paired_regret(np.asarray(episode_rewards), baseline_rewards)
                else:
                    regret, regret_per_step = unpaired_regret(np.asarray(episode_rewards), baseline_reward_per_step)
                baseline_regret += regret
                baseline_regret_per_step += regret_per_step
                writer.add_scalar("charts/baseline_regret", baseline_regret, global_step)
                writer.add_scalar("charts/baseline_regret_per_step", baseline_regret_per_step, global_step)
            if args.save_model:  # kept for a divergence to come, which would leave nothing worth saving
                weights = ({k: v.clone() for k, v in sac.actor.state_dict().items()}, {k: v.clone() for k, v in sac.qf.state_dict().items()})
                if all(bool(torch.isfinite(w).all()) for part in weights for w in part.values()):
                    sound = (global_step, *weights)
            episode, episode_rewards = episode + 1, []
            try:
                obs, _ = env.reset(seed=args.seed + episode)
            except ValueError as err:
                stop.end(f"{args.exp_name}: error: {err}", 1)
                break
            if videos is not None:  # the ended episode's video, if RecordVideo recorded it
                videos.send(global_step)
            if estimator == "paired":
                t0 = time.time()
                try:
                    _, baseline_rewards = baseline_rollout(shadow_env, baseline, args.seed + episode)
                except ValueError as err:  # the baseline or the env failed (a bad action, a NaN, an exception) after hours, maybe: keep the model
                    stop.end(f"{args.exp_name}: error: {err}", 1)
                    break
                baseline_seconds += time.time() - t0

        # ALGO LOGIC: training.
        if global_step >= args.learning_starts:
            losses = sac.update(rb.sample(args.batch_size), global_step)

            if global_step % args.log_every == 0:
                for name, value in losses.items():
                    writer.add_scalar(f"losses/{name}", value.item(), global_step)

        if global_step % args.log_every == 0 and global_step > 0:
            sps = int(global_step / (time.time() - start_time))
            print("SPS:", sps)
            writer.add_scalar("charts/SPS", sps, global_step)
            writer.add_scalar("charts/baseline_rollout_seconds", baseline_seconds, global_step)

    stop.restore()  # a signal from here on (saving, evaluating) acts at once
    rolled_back = sound[0] if diverged and sound is not None else None
    if rolled_back is not None:  # the model of the last episode end before the divergence is saved, not the diverged one
        sac.actor.load_state_dict(sound[1])
        sac.qf.load_state_dict(sound[2])
    if stop.reason is not None:
        saving = "; saving the model" + (f" of step {rolled_back:,}, the last sound one," if rolled_back is not None else "") + " without evaluating it"
        print(f"{stop.reason}: training stopped at step {global_step:,} of {args.total_timesteps:,}" + (saving if args.save_model else ""), file=sys.stderr)
    if estimator != "off":  # what the run cost against the baseline: the measure of the paper's Table I
        print(f"baseline regret ({estimator}): {baseline_regret:,.1f} in the episode form, {baseline_regret_per_step:,.1f} per step")
    if args.save_model:
        model_path = f"runs/{run_name}/{args.exp_name}.cleanrl_model"
        try:
            save_checkpoint(model_path, args.env_id, env, sac.actor, sac.qf, args)
        except OSError as err:  # a full disk: say so in one line, not as torch's traceback
            raise SystemExit(f"{args.exp_name}: error: cannot save the model to {model_path}: {err.strerror or err}") from None
        print(f"model saved to {model_path}")
    if args.save_model and stop.reason is None:  # a stopped run's model is saved, not evaluated
        try:
            episodic_returns = evaluate(model_path, args.env_id, args.eval_episodes, args.seed)
        except ValueError as err:  # the model is saved; only its evaluation failed
            raise SystemExit(f"{args.exp_name}: error: {err}")
        for idx, episodic_return in enumerate(episodic_returns):
            writer.add_scalar("eval/episodic_return", episodic_return, idx)
        print(f"eval: mean return {np.mean(episodic_returns):.1f} over {len(episodic_returns)} episodes")

    env.close()  # RecordVideo writes the video of an unfinished episode here
    if videos is not None:
        videos.send(global_step)
    if shadow_env is not None:
        shadow_env.close()
    writer.close()
    if wandb_run is not None:  # after the writer's last record, with the status the run exits with (run in-process, wandb would not see it)
        finish_tracking(wandb_run, stop.status if stop.reason is not None else int(bool(writer.failure)))
    if stop.reason is not None:
        sys.exit(stop.status)
    if writer.failure:  # in the last step's or the evaluation's logs; the model is saved and evaluated
        raise SystemExit(f"{args.exp_name}: error: {writer.failure}")
