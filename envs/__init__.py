"""Environments and baseline controllers shared by the algorithm scripts.

The scripts import this package only for the project's own env ids and baselines; copied alone
into another project, they fall back to ``gymnasium.make`` and ``--baseline module:function``.
"""

from typing import Any

from envs.make import make_env

_FROM_BASELINES = ("BASELINES", "EXPERTS", "get_baseline", "load_baseline", "rollout")
__all__ = ["make_env", *_FROM_BASELINES]


def __getattr__(name: str) -> Any:
    # Imported on first use, so that `python -m envs.baselines` runs the module only once.
    if name in _FROM_BASELINES:
        from envs import baselines

        return getattr(baselines, name)
    raise AttributeError(f"module 'envs' has no attribute {name!r}")
