"""Reinforcement-learning agents: Soft Actor-Critic (the thesis's learner for SAC and KGRL).

The names below load on first use (PEP 562), so that `vkgrl_newton.agents.sac_config` (plain
data, no torch) can be imported by a command line before it has parsed its arguments.
"""

import importlib

_LAZY = {name: "vkgrl_newton.agents.sac" for name in (
    "SAC", "Actor", "Batch", "CriticEnsemble", "ReplayBuffer", "soft_update_", "squashed_log_prob")}
_LAZY.update({name: "vkgrl_newton.agents.sac_config" for name in ("SAC_PRESETS", "SACConfig", "make_sac_config")})

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'vkgrl_newton.agents' has no attribute {name!r}")
