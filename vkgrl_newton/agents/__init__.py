"""Reinforcement-learning agents: Soft Actor-Critic (the thesis's learner for SAC and KGRL)."""

from vkgrl_newton.agents.sac import (
    SAC,
    SAC_PRESETS,
    Actor,
    Batch,
    CriticEnsemble,
    ReplayBuffer,
    SACConfig,
    make_sac_config,
    soft_update_,
    squashed_log_prob,
)

__all__ = [
    "SAC",
    "SAC_PRESETS",
    "Actor",
    "Batch",
    "CriticEnsemble",
    "ReplayBuffer",
    "SACConfig",
    "make_sac_config",
    "soft_update_",
    "squashed_log_prob",
]
