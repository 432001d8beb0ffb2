"""Create any environment the scripts accept, including this project's own ids."""

from __future__ import annotations

from typing import Any

import gymnasium as gym

# Env ids that need an extra import to be registered, by prefix of the id.
_LAZY_REGISTRATIONS = {
    "BulletEnv-v": "pybullet_envs_gymnasium",  # Walker2DBulletEnv-v0 and its siblings
}


if "JetRacerTrack-v0" not in gym.registry:
    # 2000 steps at 20 Hz: 100 s, several laps of the default track
    gym.register("JetRacerTrack-v0", entry_point="envs.jetracer_track:JetRacerTrackEnv", max_episode_steps=2000)


def _register_lazily(env_id: str) -> None:
    for marker, module in _LAZY_REGISTRATIONS.items():
        if marker in env_id and env_id not in gym.registry:
            try:
                __import__(module)
            except ImportError as err:
                raise ValueError(f"env id {env_id!r} needs {module}, which does not import: {err}") from None


def make_env(env_id: str, seed: int | None = None, render_mode: str | None = None, **kwargs: Any) -> gym.Env:
    """Make ``env_id`` with Gymnasium's default wrappers (TimeLimit included).

    ``seed`` seeds the action space (for random warm-up actions); episodes are seeded by the
    caller through ``env.reset(seed=...)``. ``kwargs`` go to the env's constructor (e.g. ``track``,
    ``randomize_lighting`` for JetRacerTrack-v0). Raises ``ValueError`` with a one-line message for an
    unknown id.
    """
    module, sep, name = env_id.partition(":")
    if sep and (not module or module.startswith(".") or not name or sep in name):  # gym.make would fail with a bare ValueError or TypeError
        raise ValueError(f"env id {env_id!r} must be a registered id or look like 'module:Env-v0' (an absolute module name, one colon)")
    _register_lazily(env_id)
    if render_mode is not None:  # only when asked for: an env whose constructor has no render_mode still works
        kwargs["render_mode"] = render_mode
    try:
        env = gym.make(env_id, **kwargs)
    except gym.error.DependencyNotInstalled as err:  # a known id whose simulator is missing
        raise ValueError(f"env id {env_id!r} needs a package that is not installed: {err}") from None
    except ImportError as err:  # `module:Env-v0` whose module, or one its env needs, does not import
        raise ValueError(f"env id {env_id!r} needs a module that does not import: {err}") from None
    except gym.error.Error as err:
        raise ValueError(f"unknown env id {env_id!r}: {err}") from None
    except ValueError as err:  # the env refusing its settings: say which env
        raise ValueError(f"cannot make env {env_id!r}: {err}") from None
    if seed is not None:
        env.action_space.seed(seed)
    return env
