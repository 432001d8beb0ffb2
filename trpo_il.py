# TRPO (Schulman et al. 2015) started from a policy that imitates the baseline: TRPO+IL, the JIRL paper's
# main comparison method (Sec. V.B, Table I). One file, CleanRL's shape (CleanRL has no TRPO); logs the same
# baseline regret as the SAC scripts.
# Run: python trpo_il.py --env-id Pendulum-v1 --total-timesteps 100000
import copy
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
import torch.optim as optim
import tyro
from torch.distributions import kl_divergence
from torch.distributions.normal import Normal
from torch.utils.tensorboard import SummaryWriter

try:  # this repository's env ids and baselines; absent when the script is copied alone
    from envs import get_baseline as project_baseline
    from envs import make_env as project_make_env
except ImportError:
    project_baseline = project_make_env = None

CHECKPOINT_FORMAT = "jirl-gaussian-checkpoint-v1"
CHECKPOINT_KEYS = ("env_id", "obs_dim", "action_low", "action_high", "hidden_size", "agent", "obs_mean", "obs_var", "args")  # what save_checkpoint writes besides the format
EVAL_SEED_OFFSET = 1_000_000  # evaluation episodes (and the baseline's) never reuse a training reset seed
EPISODE_LIMIT = 100_000  # steps: an episode still running after this many is in an env without a time limit
IL_SEED_OFFSET = 2_000_000  # the imitation phase's baseline episodes neither

# RL Zoo's tuned TRPO hyperparameters (rl-baselines3-zoo, hyperparams/trpo.yml), one env here:
# num_steps = n_envs * n_steps keeps the same batch; unnamed fields keep sb3-contrib's defaults.
DEFAULTS = dict(num_steps=2048, gamma=0.99, n_critic_updates=10, norm_obs=False, norm_reward=False)
TUNED = {
    "Pendulum-v1": DEFAULTS | dict(gamma=0.9, n_critic_updates=15),
    "LunarLanderContinuous-v3": DEFAULTS | dict(n_critic_updates=20, norm_obs=True, norm_reward=True),
}


@dataclass
class Args:
    """TRPO+IL: a policy cloned from the baseline, then trained by TRPO. An algorithm option left at None takes
    RL Zoo's tuned value for --env-id, else a generic default, as its help lists."""

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

    # Algorithm specific arguments
    env_id: str = "Pendulum-v1"
    """the id of the environment (any Gymnasium env with a Box action space)"""
    total_timesteps: int = 100_000
    """env steps of the RL phase in whole rollouts: rounded down to a multiple of --num-steps, at least one (the imitation phase's steps come on top, logged as il/env_steps)"""
    learning_rate: float = 1e-3
    """the learning rate of the value function's optimizer (the policy step is set by --max-kl)"""
    num_steps: Optional[int] = None
    """env steps per rollout (2048: RL Zoo's 2 envs x 1024)"""
    gamma: Optional[float] = None
    """the discount factor gamma (Pendulum 0.9, else 0.99)"""
    gae_lambda: float = 0.95
    """the lambda of generalized advantage estimation"""
    norm_adv: bool = True
    """toggles advantages normalization"""
    max_kl: float = 0.01
    """trust region: the largest mean KL(pi_old || pi_new) a policy step may reach"""
    cg_max_steps: int = 15
    """conjugate gradient iterations solving F x = g"""
    cg_damping: float = 0.1
    """damping added to the Fisher-vector product, F + damping I"""
    line_search_shrinking_factor: float = 0.8
    """the backtracking line search multiplies the step by this after each rejection"""
    line_search_max_iter: int = 10
    """steps the line search tries before keeping the old policy"""
    n_critic_updates: Optional[int] = None
    """epochs fitting the value function per rollout (Pendulum 15, Lunar Lander 20, else 10)"""
    critic_batch_size: int = 128
    """minibatch of the value function's epochs"""
    norm_obs: Optional[bool] = None
    """normalize observations by running statistics, saved in the checkpoint (on for Lunar Lander)"""
    norm_reward: Optional[bool] = None
    """scale rewards by the running standard deviation of the discounted return (on for Lunar Lander)"""
    hidden_size: int = 64
    """units in each of the two hidden layers of actor and critic"""

    # Imitation phase
    il_steps: int = 20_000
    """env steps of baseline rollouts for imitation (90 % fit, 10 % held out)"""
    il_target_mse: float = 1e-3
    """stop behaviour cloning once the held-out action MSE (policy units) is below this"""
    il_patience: int = 20
    """... or after this many epochs without a better held-out MSE"""
    il_max_epochs: int = 500
    """... or after this many epochs"""
    il_batch_size: int = 256
    """minibatch of behaviour cloning and value pretraining"""
    il_lr: float = 1e-3
    """learning rate of behaviour cloning and value pretraining"""
    il_init_std: float = 0.2
    """the cloned policy's exploration std (policy units) when RL starts"""
    il_value_epochs: int = 50
    """epochs fitting the value function to the baseline's discounted returns"""

    # Baseline regret
    baseline: str = ""
    """baseline controller as module:function returning env-unit actions; empty: this project's baseline for env_id"""
    regret_estimator: Literal["auto", "paired", "unpaired", "off"] = "auto"
    """paired: a shadow env runs the baseline from each training episode's reset seed; unpaired: the baseline's mean reward per step; auto: paired when the env reproduces a seeded reset"""
    baseline_eval_episodes: int = 10
    """episodes measuring the baseline's mean return and reward per step (the unpaired estimator)"""

    def __post_init__(self) -> None:
        """Out-of-range values end the parse with a message naming each flag (tyro prints it); None
        fields are filled with tuned values later and checked only when set."""
        rules = [
            ("exp_name", bool(self.exp_name) and os.path.basename(self.exp_name) == self.exp_name, "a name, not empty and not a path"),
            ("seed", 0 <= self.seed < 2**32, "in [0, 2**32)"),  # numpy's global seed
            ("torch_threads", self.torch_threads >= 1, ">= 1"),
            ("eval_episodes", self.eval_episodes >= 1, ">= 1"),
            ("total_timesteps", self.total_timesteps >= 1, ">= 1"),
            ("learning_rate", 0.0 < self.learning_rate < math.inf, "> 0"),
            ("num_steps", self.num_steps is None or self.num_steps >= (2 if self.norm_adv else 1), ">= 2 with --norm-adv (advantages are divided by their std), else >= 1"),
            ("gamma", self.gamma is None or 0.0 <= self.gamma <= 1.0, "in [0, 1]"),
            ("gae_lambda", 0.0 <= self.gae_lambda <= 1.0, "in [0, 1]"),
            ("max_kl", 0.0 < self.max_kl < math.inf, "> 0"),
            ("cg_max_steps", self.cg_max_steps >= 1, ">= 1"),
            ("cg_damping", 0.0 <= self.cg_damping < math.inf, ">= 0"),
            ("line_search_shrinking_factor", 0.0 < self.line_search_shrinking_factor < 1.0, "in (0, 1)"),
            ("line_search_max_iter", self.line_search_max_iter >= 1, ">= 1"),
            ("n_critic_updates", self.n_critic_updates is None or self.n_critic_updates >= 1, ">= 1"),
            ("critic_batch_size", self.critic_batch_size >= 1, ">= 1"),
            ("hidden_size", self.hidden_size >= 1, ">= 1"),
            ("il_steps", self.il_steps >= 1, ">= 1"),
            ("il_target_mse", 0.0 <= self.il_target_mse < math.inf, ">= 0"),
            ("il_patience", self.il_patience >= 1, ">= 1"),
            ("il_max_epochs", self.il_max_epochs >= 1, ">= 1"),
            ("il_batch_size", self.il_batch_size >= 1, ">= 1"),
            ("il_lr", 0.0 < self.il_lr < math.inf, "> 0"),
            ("il_init_std", 0.0 < self.il_init_std < math.inf, "> 0"),
            ("il_value_epochs", self.il_value_epochs >= 1, ">= 1"),
            ("baseline_eval_episodes", self.baseline_eval_episodes >= 1, ">= 1"),
        ]  # comparisons with NaN are False, so NaN fails every rule
        problems = [f"--{name.replace('_', '-')} must be {rule}, got {getattr(self, name)}" for name, ok, rule in rules if not ok]
        if problems:
            raise ValueError("; ".join(problems))


def resolve_hyperparameters(args: Args) -> Args:
    """Fill every None field with RL Zoo's tuned value for the env, else the generic default."""
    tuned = TUNED.get(args.env_id, DEFAULTS)
    for name, value in tuned.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    return args


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
        raise ValueError(f"{env_id} has an unbounded action space {env.action_space}; actions are scaled into bounds")
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
    """Policy actions live in [-1, 1] (samples are clipped there); the env's in [low, high]."""
    return low + (np.clip(action, -1.0, 1.0) + 1.0) * 0.5 * (high - low)


def to_policy_units(action: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """The baseline speaks env units; everything stored or compared is in [-1, 1]. A dimension whose
    bounds are equal holds one value, 0 here (not 0/0 = NaN)."""
    span = high - low
    fraction = np.divide(np.asarray(action, dtype=np.float64) - low, span, out=np.full(np.shape(action), 0.5), where=span > 0)
    return np.clip(2.0 * fraction - 1.0, -1.0, 1.0)


def flat_grad(y: torch.Tensor, params: list, **kwargs) -> torch.Tensor:
    return torch.cat([g.reshape(-1) for g in torch.autograd.grad(y, params, **kwargs)])


def conjugate_gradient(matrix_vector: Callable, b: torch.Tensor, max_steps: int, residual_tol: float = 1e-10) -> torch.Tensor:
    """Approximately solve A x = b for symmetric positive-definite A, given only x -> A x."""
    x = torch.zeros_like(b)
    r, p = b.clone(), b.clone()
    rr = r @ r
    for _ in range(max_steps):
        if rr < residual_tol:  # b (or the residual) is already ~0
            break
        ap = matrix_vector(p)
        alpha = rr / (p @ ap)
        x += alpha * p
        r -= alpha * ap
        new_rr = r @ r
        p = r + (new_rr / rr) * p
        rr = new_rr
    return x


class RunningMeanStd:
    """Running mean and variance of observations (Chan et al.'s parallel update)."""

    def __init__(self, shape: tuple[int, ...]):
        self.mean, self.var, self.count = np.zeros(shape), np.ones(shape), 1e-4

    def update(self, x: np.ndarray) -> None:
        x = np.asarray(x, dtype=np.float64).reshape(-1, *self.mean.shape)
        batch_mean, batch_var, n = x.mean(0), x.var(0), x.shape[0]
        delta, total = batch_mean - self.mean, self.count + n
        self.mean = self.mean + delta * n / total
        self.var = (self.var * self.count + batch_var * n + delta**2 * self.count * n / total) / total
        self.count = total

    def normalize(self, x: np.ndarray) -> np.ndarray:
        return np.clip((x - self.mean) / np.sqrt(self.var + 1e-8), -10.0, 10.0).astype(np.float32)


def layer_init(layer: nn.Linear, std: float = np.sqrt(2), bias_const: float = 0.0) -> nn.Linear:
    torch.nn.init.orthogonal_(layer.weight, std)
    torch.nn.init.constant_(layer.bias, bias_const)
    return layer


class Agent(nn.Module):
    """Gaussian policy with a state-independent log-std, and a separate value network."""

    def __init__(self, obs_dim: int, act_dim: int, hidden_size: int):
        super().__init__()
        self.critic = nn.Sequential(
            layer_init(nn.Linear(obs_dim, hidden_size)),
            nn.Tanh(),
            layer_init(nn.Linear(hidden_size, hidden_size)),
            nn.Tanh(),
            layer_init(nn.Linear(hidden_size, 1), std=1.0),
        )
        self.actor_mean = nn.Sequential(
            layer_init(nn.Linear(obs_dim, hidden_size)),
            nn.Tanh(),
            layer_init(nn.Linear(hidden_size, hidden_size)),
            nn.Tanh(),
            layer_init(nn.Linear(hidden_size, act_dim), std=0.01),
        )
        self.actor_logstd = nn.Parameter(torch.zeros(1, act_dim))

    def get_value(self, x: torch.Tensor) -> torch.Tensor:
        return self.critic(x)

    def get_action_and_value(self, x: torch.Tensor, action: Optional[torch.Tensor] = None):
        action_mean = self.actor_mean(x)
        # unchecked: a NaN that an update makes is found after the update (`divergence`), not as torch's error mid-update
        probs = Normal(action_mean, self.actor_logstd.expand_as(action_mean).exp(), validate_args=False)
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action).sum(1), probs.entropy().sum(1), self.critic(x)

    def divergence(self) -> str:
        """What makes the agent unusable after an update ('' when nothing), for the line that ends the run:
        the parts that hold a NaN or an infinity (a step or a reward too large diverged), or a log-std
        whose standard deviation is 0 or infinite. The rollout then only ever samples a checked policy."""
        parts = {"the policy's mean": self.actor_mean.parameters(), "the policy's log-std": [self.actor_logstd], "the critic": self.critic.parameters()}
        names = [name for name, tensors in parts.items() if not all(torch.isfinite(t).all() for t in tensors)]
        if names:
            return "NaN or infinite weights in " + (" and ".join([", ".join(names[:-1]), names[-1]]) if len(names) > 1 else names[0])
        std = self.actor_logstd.exp()
        if not ((std > 0) & torch.isfinite(std)).all():
            return f"a policy standard deviation of 0 or infinity (log-std {self.actor_logstd.tolist()[0]})"
        return ""


def policy_params(agent: "Agent") -> list:
    return list(agent.actor_mean.parameters()) + [agent.actor_logstd]


def policy_distribution(agent: "Agent", obs: torch.Tensor) -> Normal:
    mean = agent.actor_mean(obs)
    # unchecked: the line search rejects a trial step to a NaN, zero or infinite standard deviation (its KL is not <= max_kl)
    return Normal(mean, agent.actor_logstd.expand_as(mean).exp(), validate_args=False)


def fisher_vector_product(agent: "Agent", obs: torch.Tensor, vector: torch.Tensor, damping: float) -> torch.Tensor:
    """(F + damping I) v, with F the Hessian of the mean KL(pi_old || pi) at pi = pi_old (double backprop)."""
    params = policy_params(agent)
    new = policy_distribution(agent, obs)
    old = Normal(new.loc.detach(), new.scale.detach())
    kl = kl_divergence(old, new).sum(1).mean()
    grads = flat_grad(kl, params, create_graph=True)
    return flat_grad(grads @ vector, params) + damping * vector


def trpo_step(agent: "Agent", obs, actions, old_logprobs, advantages, args: "Args") -> dict:
    """One natural-gradient policy step, accepted by a backtracking line search only if the mean KL
    stays within --max-kl and the surrogate objective improves; otherwise the policy is unchanged."""
    params = policy_params(agent)
    with torch.no_grad():
        old = policy_distribution(agent, obs)
        old = Normal(old.loc.clone(), old.scale.clone())

    def surrogate() -> torch.Tensor:
        ratio = torch.exp(policy_distribution(agent, obs).log_prob(actions).sum(1) - old_logprobs)
        return (ratio * advantages).mean()

    objective = surrogate()
    gradient = flat_grad(objective, params)
    step_direction = conjugate_gradient(lambda v: fisher_vector_product(agent, obs, v, args.cg_damping), gradient, args.cg_max_steps)
    curvature = step_direction @ fisher_vector_product(agent, obs, step_direction, args.cg_damping)  # s^T F s
    result = {"objective": objective.item(), "kl": 0.0, "step_fraction": 0.0, "accepted": False}
    if not (torch.isfinite(curvature) and curvature > 0):  # no ascent direction (e.g. all advantages 0)
        return result
    full_step = torch.sqrt(2.0 * args.max_kl / curvature) * step_direction  # KL ~ s^T F s / 2 = max_kl
    start = torch.nn.utils.parameters_to_vector(params).detach()
    with torch.no_grad():
        for i in range(args.line_search_max_iter):
            fraction = args.line_search_shrinking_factor**i
            torch.nn.utils.vector_to_parameters(start + fraction * full_step, params)
            kl = kl_divergence(old, policy_distribution(agent, obs)).sum(1).mean().item()
            new_objective = surrogate().item()
            if kl <= args.max_kl and new_objective > objective.item():
                return result | {"objective": new_objective, "kl": kl, "step_fraction": fraction, "accepted": True}
        torch.nn.utils.vector_to_parameters(start, params)
    return result


def collect_baseline_data(env: gym.Env, baseline: Callable, steps: int, seed: int, gamma: float) -> dict:
    """At least `steps` env steps of whole baseline episodes: observations, actions in policy units,
    discounted returns-to-go, the running discounted returns that --norm-reward scales by, and the
    episodes' returns."""
    low, high = env.action_space.low, env.action_space.high
    obs_list, action_list, return_list, running_list, episode_returns, episode = [], [], [], [], [], 0
    while len(obs_list) < steps:
        if hasattr(baseline, "reset"):
            baseline.reset()
        obs, _ = env.reset(seed=seed + IL_SEED_OFFSET + episode)
        rewards, done, discounted_return = [], False, 0.0
        while not done:
            action = ask_baseline(baseline, obs)
            if action is None:
                raise ValueError("the baseline returned None (it only intervenes); imitation needs its actions everywhere")
            action = check_baseline_action(action, env.action_space)
            obs_list.append(obs)
            action_list.append(to_policy_units(action, low, high))
            obs, reward, terminated, truncated, _ = env.step(action)
            rewards.append(float(reward))
            discounted_return = discounted_return * gamma + rewards[-1]  # as --norm-reward accumulates it
            running_list.append(discounted_return)
            done = terminated or truncated
            if not done and len(rewards) == EPISODE_LIMIT:  # a baseline that never fails would run for ever
                raise ValueError(f"the baseline's episode from reset seed {seed + IL_SEED_OFFSET + episode} did not end within"
                                 f" {EPISODE_LIMIT:,} steps; imitation needs whole episodes: give the env a time limit (max_episode_steps)")
        returns_to_go, running = np.zeros(len(rewards)), 0.0
        for t in reversed(range(len(rewards))):  # Monte Carlo; a truncated tail is cut short, not bootstrapped
            running = rewards[t] + gamma * running
            returns_to_go[t] = running
        return_list.extend(returns_to_go)
        episode_returns.append(sum(rewards))
        episode += 1
    largest = float(np.max(np.abs(return_list)))
    if largest > float(np.finfo(np.float32).max):  # stored as float32 it would be infinite, and a value fitted to it NaN
        raise ValueError(f"the baseline's discounted returns reach {largest:.3g}, beyond float32's range; scale the env's rewards down")
    return {
        "obs": np.asarray(obs_list, dtype=np.float32),
        "actions": np.asarray(action_list, dtype=np.float32),
        "returns": np.asarray(return_list, dtype=np.float32),
        "running_returns": np.asarray(running_list),
        "episode_returns": episode_returns,
    }


def imitate(agent: Agent, obs: np.ndarray, actions: np.ndarray, returns: np.ndarray, args: Args, writer, rng) -> dict:
    """Behaviour cloning of the policy mean with held-out early stopping, then the exploration std,
    then the value function fitted to the baseline's returns (so the first update is not destructive)."""
    n = len(obs)
    if n < 2:  # an env of one-step episodes with --il-steps 1: nothing left to fit once a step is held out
        raise ValueError(f"imitation needs at least 2 baseline steps (one is held out), got {n}; raise --il-steps")
    order = rng.permutation(n)
    held_out, fit = order[: max(1, n // 10)], order[max(1, n // 10) :]
    x, y, g = torch.from_numpy(obs), torch.from_numpy(actions), torch.from_numpy(returns).unsqueeze(1)
    optimizer = optim.Adam(agent.actor_mean.parameters(), lr=args.il_lr)
    best_mse, best_state, stale, epoch = float("inf"), None, 0, 0
    for epoch in range(1, args.il_max_epochs + 1):
        for start in range(0, len(fit), args.il_batch_size):
            idx = fit[start : start + args.il_batch_size]
            bc_loss = ((agent.actor_mean(x[idx]) - y[idx]) ** 2).mean()
            optimizer.zero_grad()
            bc_loss.backward()
            optimizer.step()
        rng.shuffle(fit)
        with torch.no_grad():
            mse = ((agent.actor_mean(x[held_out]) - y[held_out]) ** 2).mean().item()
        writer.add_scalar("il/bc_loss", bc_loss.item(), epoch)
        writer.add_scalar("il/action_mse", mse, epoch)
        if mse < best_mse:
            best_mse, best_state, stale = mse, {k: v.clone() for k, v in agent.actor_mean.state_dict().items()}, 0
        else:
            stale += 1
        if best_mse < args.il_target_mse or stale >= args.il_patience:
            break
    if best_state is None:  # every held-out MSE was NaN: nothing to keep
        raise ValueError("behaviour cloning gave no finite held-out action error (non-finite observations, or --il-lr too large)")
    agent.actor_mean.load_state_dict(best_state)
    with torch.no_grad():
        agent.actor_logstd.fill_(float(np.log(args.il_init_std)))

    value_optimizer = optim.Adam(agent.critic.parameters(), lr=args.il_lr)
    for _ in range(args.il_value_epochs):
        for start in range(0, n, args.il_batch_size):
            idx = order[start : start + args.il_batch_size]
            value_loss = ((agent.critic(x[idx]) - g[idx]) ** 2).mean()
            value_optimizer.zero_grad()
            value_loss.backward()
            value_optimizer.step()
        rng.shuffle(order)
    diverged = agent.divergence()
    if diverged:  # found here, not as the cloned policy's unloadable checkpoint or the first update's NaN
        raise ValueError(f"imitation diverged: {diverged}")
    writer.add_scalar("il/value_loss", value_loss.item(), 0)
    return {"epochs": epoch, "action_mse": best_mse, "value_loss": value_loss.item()}


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


def save_checkpoint(path: str, env_id: str, env: gym.Env, agent: Agent, obs_rms: Optional[RunningMeanStd], args: Args) -> None:
    """Weights, observation statistics, spaces and hyperparameters."""
    write_checkpoint(
        path,
        {
            "format": CHECKPOINT_FORMAT,
            "env_id": env_id,
            "obs_dim": int(env.observation_space.shape[0]),
            "action_low": env.action_space.low.tolist(),
            "action_high": env.action_space.high.tolist(),
            "hidden_size": args.hidden_size,
            "agent": agent.state_dict(),
            "obs_mean": None if obs_rms is None else torch.from_numpy(obs_rms.mean),
            "obs_var": None if obs_rms is None else torch.from_numpy(obs_rms.var),
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
    """The first value no sound checkpoint holds, named, or None: torch (numpy, for the observation
    statistics) would refuse such a value later with a traceback of its own, and NaN weights would pass
    for a diverged env."""

    def statistic(x: object) -> bool:  # a running mean or variance of the observations
        return isinstance(x, torch.Tensor) and x.is_floating_point() and x.shape == (checkpoint["obs_dim"],) and bool(torch.isfinite(x).all())

    low, high, weights, mean, var = (checkpoint[key] for key in ("action_low", "action_high", "agent", "obs_mean", "obs_var"))
    normalized = mean is not None or var is not None  # both None: saved without observation normalization
    fits = {
        "obs_dim": type(checkpoint["obs_dim"]) is int and checkpoint["obs_dim"] > 0,
        "hidden_size": type(checkpoint["hidden_size"]) is int and checkpoint["hidden_size"] > 0,
        "action_low": isinstance(low, (list, tuple)) and len(low) > 0 and all(type(x) in (int, float) for x in low),
        "action_high": isinstance(high, (list, tuple)) and isinstance(low, (list, tuple)) and len(high) == len(low) and all(type(x) in (int, float) for x in high),
        "agent": isinstance(weights, dict) and all(type(k) is str and torch.is_tensor(w) and bool(torch.isfinite(w).all()) for k, w in weights.items()),
        "obs_mean": statistic(mean) if normalized else True,
        "obs_var": statistic(var) and bool((var >= 0).all()) if normalized else True,
    }
    field = next((field for field, ok in fits.items() if not ok), None)
    if field == "agent" and isinstance(weights, dict):  # NaN: a damaged file, or a training that diverged
        named = all(type(k) is str and torch.is_tensor(w) for k, w in weights.items())
        return f"its {field} holds {'a NaN or infinite weight' if named else 'an entry that is not a named tensor'}"
    return None if field is None else f"its {field} is {reprlib.repr(checkpoint[field])}"


def evaluate(path: str, env_id: str, episodes: int, seed: int) -> list[float]:
    """Returns of the checkpoint's mean action, episode i reset with seed + EVAL_SEED_OFFSET + i."""
    env = make_env(env_id, seed)
    checkpoint = load_checkpoint(path)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    if checkpoint["obs_dim"] != obs_dim or len(checkpoint["action_low"]) != act_dim:
        raise ValueError(f"checkpoint expects {checkpoint['obs_dim']} observations and {len(checkpoint['action_low'])} actions ({checkpoint['env_id']}); this env has {obs_dim} and {act_dim}")
    if not np.allclose(checkpoint["action_low"], env.action_space.low) or not np.allclose(checkpoint["action_high"], env.action_space.high):
        raise ValueError(f"checkpoint action bounds differ from this env's {env.action_space}")
    agent = Agent(obs_dim, act_dim, checkpoint["hidden_size"])
    try:
        agent.load_state_dict(checkpoint["agent"])
    except RuntimeError as err:  # torch's message runs over several lines: keep it on one
        raise ValueError(f"checkpoint weights do not fit: {' '.join(str(err).split())}") from None
    obs_rms = None
    if checkpoint["obs_mean"] is not None:
        obs_rms = RunningMeanStd((obs_dim,))
        obs_rms.mean, obs_rms.var = checkpoint["obs_mean"].numpy(), checkpoint["obs_var"].numpy()
    low, high = env.action_space.low, env.action_space.high
    returns = []
    for i in range(episodes):
        obs, _ = env.reset(seed=seed + EVAL_SEED_OFFSET + i)
        episode_return, done, steps = 0.0, False, 0
        while not done:
            x = obs_rms.normalize(obs) if obs_rms is not None else obs.astype(np.float32)
            with torch.inference_mode():
                action = agent.actor_mean(torch.from_numpy(x).unsqueeze(0))[0].numpy()
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
    args = resolve_hyperparameters(tyro.cli(Args))
    sys.path.append(os.getcwd())  # `module:...` in --env-id and --baseline may name a module in the current directory; last, so it shadows nothing installed
    batch_size = args.num_steps
    num_iterations = max(1, args.total_timesteps // batch_size)
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
    rng = np.random.default_rng(args.seed)

    # env setup; bad input ends here with one line, before anything is written
    try:
        env = make_env(args.env_id, args.seed, args.capture_video, run_name)
        baseline = load_baseline(args.baseline, args.env_id)
        if baseline is None:
            raise ValueError(f"TRPO+IL imitates a baseline and {args.env_id} has none; pass --baseline module:function")
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
    agent = Agent(obs_dim, act_dim, args.hidden_size)
    shadow_env = make_env(args.env_id, args.seed)  # runs the baseline beside the training env

    # Imitation phase: the baseline acts, so these steps carry no regret; they are counted apart
    try:
        data = collect_baseline_data(shadow_env, baseline, args.il_steps, args.seed, args.gamma)
    except ValueError as err:
        raise SystemExit(f"{args.exp_name}: error: {err}")
    obs_rms = RunningMeanStd((obs_dim,)) if args.norm_obs else None
    if obs_rms is not None:
        obs_rms.update(data["obs"])
    il_obs = obs_rms.normalize(data["obs"]) if obs_rms is not None else data["obs"]
    return_rms, value_targets = RunningMeanStd(()), data["returns"]
    if args.norm_reward:  # RL's reward scale starts from the baseline's steps, and the value is fitted in its units
        return_rms.update(data["running_returns"])
        value_targets = (value_targets / np.sqrt(return_rms.var + 1e-8)).astype(np.float32)
        writer.add_scalar("il/reward_scale", float(np.sqrt(return_rms.var + 1e-8)), 0)
    try:
        il = imitate(agent, il_obs, data["actions"], value_targets, args, writer, rng)
    except ValueError as err:
        raise SystemExit(f"{args.exp_name}: error: {err}")
    writer.add_scalar("il/env_steps", len(data["obs"]), 0)
    print(f"imitation: {len(data['obs'])} baseline steps, {il['epochs']} epochs, held-out action MSE {il['action_mse']:.2e}")

    # Baseline measurement on the evaluation seeds, so it compares with eval/episodic_return
    estimator, baseline_reward_per_step, baseline_seconds = "off", 0.0, 0.0
    if args.regret_estimator != "off":
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
    if args.save_model:  # the cloned policy, evaluated like the final one
        os.makedirs(f"runs/{run_name}", exist_ok=True)
        il_path = f"runs/{run_name}/{args.exp_name}_cloned.cleanrl_model"
        try:
            save_checkpoint(il_path, args.env_id, env, agent, obs_rms, args)
        except OSError as err:  # a full disk: say so in one line, not as torch's traceback
            raise SystemExit(f"{args.exp_name}: error: cannot save the model to {il_path}: {err.strerror or err}") from None
        try:
            il_returns = evaluate(il_path, args.env_id, args.eval_episodes, args.seed)
        except ValueError as err:  # the cloned model is saved; only its evaluation failed
            raise SystemExit(f"{args.exp_name}: error: {err}")
        writer.add_scalar("il/eval_return", float(np.mean(il_returns)), 0)
        print(f"cloned policy: mean return {np.mean(il_returns):.1f}")

    value_optimizer = optim.Adam(agent.critic.parameters(), lr=args.learning_rate)

    # ALGO Logic: Storage setup
    obs_buf = torch.zeros((args.num_steps, obs_dim))
    actions = torch.zeros((args.num_steps, act_dim))
    logprobs = torch.zeros(args.num_steps)
    rewards = torch.zeros(args.num_steps)
    dones = torch.zeros(args.num_steps)
    values = torch.zeros(args.num_steps)
    discounted_return = 0.0  # for --norm-reward

    # TRY NOT TO MODIFY: start the game
    global_step = 0
    start_time = time.time()
    episode, episode_rewards = 0, []
    videos = VideoTracker(wandb_run, run_name) if wandb_run is not None and args.capture_video else None
    try:
        raw_obs, _ = env.reset(seed=args.seed)
    except ValueError as err:  # a NaN, or an exception of the env's own (CheckedEnv)
        raise SystemExit(f"{args.exp_name}: error: {err}")
    if estimator == "paired":
        t0 = time.time()
        try:
            baseline_first_obs, baseline_rewards = baseline_rollout(shadow_env, baseline, args.seed)
        except ValueError as err:
            raise SystemExit(f"{args.exp_name}: error: {err}")
        baseline_seconds += time.time() - t0
        if not np.array_equal(baseline_first_obs, raw_obs):  # the env ignores its reset seed: pairing is impossible
            if args.regret_estimator == "paired":
                raise SystemExit(f"{args.exp_name}: error: {args.env_id} does not reproduce a seeded reset; use --regret-estimator unpaired")
            estimator = "unpaired"
    if estimator != "off":
        print(f"baseline regret estimator: {estimator}")
        writer.add_text("baseline_regret_estimator", estimator)

    def observe(raw: np.ndarray) -> torch.Tensor:
        if obs_rms is None:
            return torch.as_tensor(raw, dtype=torch.float32)
        return torch.from_numpy(obs_rms.normalize(raw))

    next_obs = observe(raw_obs)
    next_done = 0.0
    stop = StopRequest()  # from here Ctrl-C, SIGTERM, or an env, a baseline or the logs failing ends the training, keeping what was learnt
    sound, diverged = None, ""  # (step, agent, observation statistics) before the last update, as the agent acted through the rollout; what diverged
    for iteration in range(1, num_iterations + 1):
        if writer.failure and stop.reason is None:  # the logs failed: end as for a failing env
            stop.end(f"{args.exp_name}: error: {writer.failure}", 1)
        if stop.reason is not None:
            break
        for step in range(0, args.num_steps):
            global_step += 1
            obs_buf[step] = next_obs
            dones[step] = next_done

            # ALGO LOGIC: action logic
            with torch.no_grad():
                action, logprob, _, value = agent.get_action_and_value(next_obs.unsqueeze(0))
                values[step] = value.flatten()
            if not math.isfinite(sum(action.tolist()[0])):  # finite weights whose mean overflows float32: end before the env gets it (action[0].tolist() costs 5 µs more)
                diverged = "the policy's mean overflowed"
                stop.end(f"{args.exp_name}: error: the training diverged: {diverged}", 1)
                break
            actions[step] = action[0]
            logprobs[step] = logprob[0]

            # TRY NOT TO MODIFY: execute the game and log data.
            try:
                raw_obs, reward, terminated, truncated, _ = env.step(to_env_units(action[0].numpy(), low, high))
            except ValueError as err:  # a diverged simulation (its NaN never reaches the rollout) or a failing env: keep the model
                stop.end(f"{args.exp_name}: error: {err}", 1)
                break
            episode_rewards.append(float(reward))
            if obs_rms is not None:
                obs_rms.update(raw_obs)
            if args.norm_reward:
                discounted_return = discounted_return * args.gamma + reward
                return_rms.update(np.array([discounted_return]))
                reward = reward / np.sqrt(return_rms.var + 1e-8)
            if truncated and not terminated:
                # Bootstrap through time-limit truncation: the cut-off future is worth V(s_T)
                with torch.no_grad():
                    reward += args.gamma * agent.get_value(observe(raw_obs).unsqueeze(0)).item()
            rewards[step] = float(reward)
            next_done = float(terminated or truncated)

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
                episode, episode_rewards, discounted_return = episode + 1, [], 0.0
                try:
                    raw_obs, _ = env.reset(seed=args.seed + episode)
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
            next_obs = observe(raw_obs)
        if stop.reason is not None:  # the env failed, or a signal came, during the rollout: no update from it
            break
        if args.save_model:  # kept for an update that diverges, which would leave nothing worth saving
            sound = (global_step, {k: v.clone() for k, v in agent.state_dict().items()}, copy.deepcopy(obs_rms))

        # bootstrap value if not done
        with torch.no_grad():
            next_value = agent.get_value(next_obs.unsqueeze(0)).reshape(1)
            advantages = torch.zeros_like(rewards)
            lastgaelam = 0
            for t in reversed(range(args.num_steps)):
                if t == args.num_steps - 1:
                    nextnonterminal = 1.0 - next_done
                    nextvalues = next_value
                else:
                    nextnonterminal = 1.0 - dones[t + 1]
                    nextvalues = values[t + 1]
                delta = rewards[t] + args.gamma * nextvalues * nextnonterminal - values[t]
                advantages[t] = lastgaelam = delta + args.gamma * args.gae_lambda * nextnonterminal * lastgaelam
            returns = advantages + values

        # Optimizing the policy: one trust-region step on the whole rollout
        b_advantages = advantages
        if args.norm_adv:
            b_advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
        step = trpo_step(agent, obs_buf, actions, logprobs, b_advantages, args)
        with torch.no_grad():
            entropy = policy_distribution(agent, obs_buf).entropy().sum(1).mean().item()

        # Fitting the value function with its own optimizer
        b_inds = np.arange(batch_size)
        for epoch in range(args.n_critic_updates):
            rng.shuffle(b_inds)
            for start in range(0, batch_size, args.critic_batch_size):
                mb_inds = b_inds[start : start + args.critic_batch_size]
                v_loss = 0.5 * ((agent.get_value(obs_buf[mb_inds]).view(-1) - returns[mb_inds]) ** 2).mean()
                value_optimizer.zero_grad()
                v_loss.backward()
                value_optimizer.step()

        diverged = agent.divergence()
        if diverged:  # the update diverged: end here, before a rollout samples its policy or its NaN is logged
            stop.end(f"{args.exp_name}: error: the training diverged: {diverged}", 1)
            break
        y_pred, y_true = values.numpy(), returns.numpy()
        var_y = np.var(y_true)
        explained_var = np.nan if var_y == 0 else 1 - np.var(y_true - y_pred) / var_y

        # TRY NOT TO MODIFY: record rewards for plotting purposes
        writer.add_scalar("losses/value_loss", v_loss.item(), global_step)
        writer.add_scalar("losses/policy_objective", step["objective"], global_step)
        writer.add_scalar("losses/kl", step["kl"], global_step)
        writer.add_scalar("losses/step_fraction", step["step_fraction"], global_step)
        writer.add_scalar("losses/line_search_accepted", float(step["accepted"]), global_step)
        writer.add_scalar("losses/entropy", entropy, global_step)
        writer.add_scalar("losses/explained_variance", explained_var, global_step)
        sps = int(global_step / (time.time() - start_time))
        print("SPS:", sps)
        writer.add_scalar("charts/SPS", sps, global_step)
        writer.add_scalar("charts/baseline_rollout_seconds", baseline_seconds, global_step)

    stop.restore()  # a signal from here on (saving, evaluating) acts at once
    rolled_back = sound[0] if diverged and sound is not None else None
    if rolled_back is not None:  # the agent from before the update that diverged is saved, not the diverged one
        agent.load_state_dict(sound[1])
        obs_rms = sound[2]  # the statistics of the rollout it acted through, not moved by the one that overflowed it
    if stop.reason is not None:
        saving = "; saving the model" + (f" of step {rolled_back:,}, the last sound one," if rolled_back is not None else "") + " without evaluating it"
        print(f"{stop.reason}: training stopped at step {global_step:,} of {num_iterations * batch_size:,}" + (saving if args.save_model else ""), file=sys.stderr)
    if estimator != "off":  # what the run cost against the baseline: the measure of the paper's Table I
        print(f"baseline regret ({estimator}): {baseline_regret:,.1f} in the episode form, {baseline_regret_per_step:,.1f} per step")
    if args.save_model:
        model_path = f"runs/{run_name}/{args.exp_name}.cleanrl_model"
        try:
            save_checkpoint(model_path, args.env_id, env, agent, obs_rms, args)
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
    shadow_env.close()
    writer.close()
    if wandb_run is not None:  # after the writer's last record, with the status the run exits with (run in-process, wandb would not see it)
        finish_tracking(wandb_run, stop.status if stop.reason is not None else int(bool(writer.failure)))
    if stop.reason is not None:
        sys.exit(stop.status)
    if writer.failure:  # in the last step's or the evaluation's logs; the model is saved and evaluated
        raise SystemExit(f"{args.exp_name}: error: {writer.failure}")
