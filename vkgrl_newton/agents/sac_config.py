"""The SAC configuration as plain data (thesis Table 5.3 and this project's presets).

A module of its own, importing no torch, so that the command lines can parse and check every
`--sac FIELD=VALUE` before anything heavy is imported (agents/sac.py uses it).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

WARMUPS = ("uniform", "policy")
LOG_STD_BOUNDS = ("clamp", "tanh")
ROLLOUT_POLICIES = ("prior", "search", "scripted")  # SACConfig.prior_rollouts_policy
ACTIVATION_NAMES = ("elu", "relu", "tanh")
MATMUL_BACKENDS = ("onednn", "torch")  # agents/dense.py
CPU_MATMUL_CHOICES = ("auto", *MATMUL_BACKENDS)  # "auto": the faster here, agents/matmul_backend.py


@dataclass(frozen=True)
class SACConfig:
    buffer_size: int = 1_000_000
    batch_size: int = 256
    lr: float = 4e-4
    # Counted in env transitions summed over worlds (one batched step of N worlds adds N), as
    # SB3/SBX count num_timesteps; until then `explore` gives the warm-up actions.
    learning_starts: int = 5_000
    # Warm-up actions before learning_starts: "uniform" in [-1, 1] (SB3/SBX, the thesis's code),
    # or "policy": the untrained actor's samples (with actor_init_std, a small cloud around a = 0;
    # for KGRL that is the KMP prior, where uniform actions throw the part ~7 mm off the prior).
    warmup: str = "uniform"
    train_every: int = 1  # batched env steps between two `update` calls
    gradient_steps: int = 512  # per `update` call
    n_critics: int = 2
    hidden_dims: tuple[int, ...] = (512, 256, 128)
    activation: str = "elu"
    obs_normalization: bool = True
    # rsl-rl EmpiricalNormalization's eps: inputs are (x - mean) / (std + eps), so a dimension
    # whose spread is below eps is not blown up to unit scale. rsl-rl's default 1e-2 squeezes
    # KGRL's TCP offsets (std 6-9 mm) to ~0.4 (docs/log/benchmarks.md).
    obs_norm_eps: float = 1e-2
    # Decoupled weight decay of AdamW for actor and critics. 1e-4 is optax.adamw's default,
    # which the thesis used through SBX (torch's default would be 1e-2). log_alpha uses plain
    # Adam, as in SBX: decaying it would pull alpha towards 1.
    weight_decay: float = 1e-4
    policy_delay: int = 4  # critic updates per actor + temperature update
    gamma: float = 0.99
    tau: float = 0.005  # Polyak rate; targets move after every critic update, as in SBX
    init_alpha: float = 1.0
    target_entropy: float | None = None  # None -> -dim(A)
    # Hard clamp to [-20, 2] as SB3/SBX (the thesis's code); CleanRL's [-5, 2] is tighter.
    log_std_min: float = -20.0
    log_std_max: float = 2.0
    # None: the default init (std ~1 at the start). A number: the actor starts at mean 0 with this
    # std (pre-tanh) whatever the observation, as RSL-RL-SAC's small-sigma init: for KGRL a = 0 is
    # the prior, and std ~1 explores ~7 mm around it against a 0.06 mm clearance (docs/log/benchmarks.md)
    actor_init_std: float | None = None
    # How log_std is kept in [log_std_min, log_std_max]: "clamp" (SB3/SBX, the thesis's code: no
    # gradient beyond the bounds, so a std pushed to the bound stays there) or "tanh" (CleanRL,
    # SpinningUp: log_std_min + (max - min) (tanh(x) + 1) / 2, a gradient everywhere; with a tight
    # bound the std can shrink again once the entropy target asks for it).
    log_std_bound: str = "clamp"
    # IBRL (Hu et al. 2024) with the prior as the reference policy, for KGRL where a = 0 is the KMP
    # prior: when acting and in the critic's target, take a = 0 instead of the actor's action
    # where the critics (min over the ensemble) value a = 0 more. Off in the thesis.
    prior_anchor: bool = False
    # Actor and temperature updates wait until the buffer holds a rewarded transition (the critic
    # trains from learning_starts on): before that the critic's action gradient has no signal and
    # only moves the policy away from where it started (a = 0, the prior, for KGRL). Off in the thesis.
    actor_after_reward: bool = False
    # A penalty prior_reg * |tanh(mean)|^2 in the actor's loss: pulls the deterministic action
    # toward a = 0 (the prior, for KGRL) where the critic's action gradient is weak; the weight is
    # in units of Q (rewards of 1 per successful step). 0: none (thesis).
    prior_reg: float = 0.0
    # LayerNorm after every hidden layer of the critics (RLPD, SERL): bounds Q's extrapolation to
    # actions the data does not cover. Off in the thesis.
    critic_layer_norm: bool = False
    # RLPD's symmetric sampling: this fraction of every minibatch comes from the prior buffer (the
    # prior's own rollouts, prior_rollouts below), the rest from the online buffer; 0: one buffer (thesis).
    prior_ratio: float = 0.0
    # The first prior_rollouts transitions act with prior_rollouts_policy (below; by default a = 0
    # exactly, for KGRL the prior's own rollouts), counted in the run's transitions like any other, and
    # with prior_ratio > 0 are kept in the prior buffer for good: a critic that always sees the prior's
    # actions knows their value.
    prior_rollouts: int = 0
    # Who acts in those first transitions: "prior" (a = 0, as above) or "search" (KGRL: the prior plus
    # a blind spiral search once the part is blocked, envs.evaluation.KMPSearchPolicy, through the
    # run's own action path; it needs z reach, --kgrl-reach-floor-z). A deviation: scripted data beyond
    # the demonstrations, so that the buffer holds blocked parts that were searched for and seated.
    # "scripted" is for the SAC methods (sac, vision_sac), which have no prior: the scripted demonstrator
    # through the SAC action space (envs.evaluation.ScriptedDeltaPolicy), RLPD's demonstrations kept in
    # the second buffer (prior_ratio). A deviation from the thesis's SAC, which learns from its own data.
    # "search" and "scripted" keep per-world state that a checkpoint does not hold: a run resumed inside
    # its first prior_rollouts transitions restarts them from where each world is (those episodes differ).
    prior_rollouts_policy: str = "prior"
    # Behaviour cloning on the prior buffer's rows of every actor minibatch (for sac with
    # prior_rollouts_policy="scripted": the demonstrator's actions; for KGRL: a = 0 or the search's):
    # the actor's loss gains bc_weight * mean|Q| * E_prior |tanh(mean(s)) - a|^2. Scaled by the
    # critic's magnitude (detached), as TD3+BC (Fujimoto & Gu 2021) balances the two, so that one
    # weight fits any reward scale: 0.4 is their alpha = 2.5. Needs prior_ratio > 0. 0: none (thesis, RLPD).
    bc_weight: float = 0.0
    # Matmul library on a CPU device (agents/dense.py): "onednn" (AVX-512 on AMD and Intel),
    # "torch" (MKL; its AVX2 path on AMD) or "auto", the faster of the two on this machine, timed once
    # and kept (agents/matmul_backend.py); a run records the one that ran. Not a hyperparameter:
    # float32 last bits differ.
    cpu_matmul: str = "auto"

    def __post_init__(self) -> None:
        object.__setattr__(self, "hidden_dims", tuple(int(h) for h in self.hidden_dims))
        if self.warmup not in WARMUPS:
            raise ValueError(f"SACConfig.warmup={self.warmup!r}; allowed: {list(WARMUPS)}")
        if self.cpu_matmul not in CPU_MATMUL_CHOICES:
            raise ValueError(f"SACConfig.cpu_matmul={self.cpu_matmul!r}; allowed: {list(CPU_MATMUL_CHOICES)}")
        if self.activation not in ACTIVATION_NAMES:
            raise ValueError(f"SACConfig.activation={self.activation!r}; allowed: {sorted(ACTIVATION_NAMES)}")
        if self.prior_rollouts < 0:
            raise ValueError(f"SACConfig.prior_rollouts={self.prior_rollouts!r} must be >= 0")
        if self.prior_rollouts_policy not in ROLLOUT_POLICIES:
            raise ValueError(f"SACConfig.prior_rollouts_policy={self.prior_rollouts_policy!r}; allowed: "
                             f"{list(ROLLOUT_POLICIES)}")
        if self.prior_rollouts_policy != "prior" and self.prior_rollouts == 0:
            raise ValueError(f"SACConfig.prior_rollouts_policy={self.prior_rollouts_policy!r} acts in the first "
                             f"prior_rollouts transitions: give prior_rollouts > 0")
        if self.prior_ratio > 0 and self.prior_rollouts == 0:
            raise ValueError("SACConfig.prior_ratio > 0 samples the prior buffer: give prior_rollouts > 0 to fill it")
        for name in ("buffer_size", "batch_size", "train_every", "gradient_steps", "n_critics", "policy_delay"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"SACConfig.{name}={getattr(self, name)!r} must be >= 1")
        if not self.hidden_dims or min(self.hidden_dims) < 1:
            raise ValueError(f"SACConfig.hidden_dims={self.hidden_dims!r} must be non-empty positive ints")
        if not self.log_std_min < self.log_std_max:
            raise ValueError("SACConfig.log_std_min must be < log_std_max")
        if self.actor_init_std is not None and not (
                math.exp(self.log_std_min) <= self.actor_init_std <= math.exp(self.log_std_max)):
            raise ValueError(f"SACConfig.actor_init_std={self.actor_init_std!r} must be None or within "
                             f"[exp(log_std_min), exp(log_std_max)]")
        for name, lo, hi in (("tau", 0.0, 1.0), ("gamma", 0.0, 1.0)):
            if not lo < getattr(self, name) <= hi:
                raise ValueError(f"SACConfig.{name}={getattr(self, name)!r} must be in ({lo}, {hi}]")
        if not self.init_alpha > 0 or not self.lr > 0:
            raise ValueError("SACConfig.init_alpha and SACConfig.lr must be > 0")
        if self.log_std_bound not in LOG_STD_BOUNDS:
            raise ValueError(f"SACConfig.log_std_bound={self.log_std_bound!r}; allowed: {list(LOG_STD_BOUNDS)}")
        if not 0.0 <= self.prior_ratio < 1.0:
            raise ValueError(f"SACConfig.prior_ratio={self.prior_ratio!r} must be in [0, 1)")
        for name in ("lr", "init_alpha", "obs_norm_eps", "weight_decay", "log_std_min", "log_std_max", "gamma", "tau",
                     "prior_reg", "prior_ratio", "bc_weight"):
            if not math.isfinite(float(getattr(self, name))):
                raise ValueError(f"SACConfig.{name}={getattr(self, name)!r} must be finite")
        if not self.bc_weight >= 0:
            raise ValueError(f"SACConfig.bc_weight={self.bc_weight!r} must be >= 0")
        if self.bc_weight > 0 and self.prior_ratio == 0:
            raise ValueError("SACConfig.bc_weight > 0 clones the prior buffer's actions: give prior_ratio > 0 "
                             "(and prior_rollouts) so that minibatches hold them")
        if not self.prior_reg >= 0:
            raise ValueError(f"SACConfig.prior_reg={self.prior_reg!r} must be >= 0")
        if self.weight_decay < 0:
            raise ValueError(f"SACConfig.weight_decay={self.weight_decay!r} must be >= 0")
        if self.buffer_size < self.batch_size:
            raise ValueError(f"SACConfig.buffer_size={self.buffer_size} must be >= batch_size={self.batch_size}")
        if not self.obs_norm_eps > 0:
            raise ValueError(f"SACConfig.obs_norm_eps={self.obs_norm_eps!r} must be > 0")


SAC_PRESETS: dict[str, SACConfig] = {
    "thesis": SACConfig(),  # Table 5.3; gamma, tau, alpha, entropy target, log_std bounds: SBX defaults
    # A 2-core CPU, 16 worlds: a smaller net, an early start and 16 gradient steps per batched env
    # step (update-to-data ratio 1): measured against 32 (ratio 2) on kgrl seeds 0-1 it learned at
    # least as well at equal transitions (success 0.34 / 0.03 against 0.09 / 0.00) in ~0.8x the
    # wall, and it balances the learner against the env for the overlapped loop (docs/log/benchmarks.md).
    "quick": SACConfig(
        buffer_size=200_000, hidden_dims=(256, 256), learning_starts=1_024, gradient_steps=16, policy_delay=2
    ),
}


def make_sac_config(preset: str = "thesis", **overrides: object) -> SACConfig:
    """A preset with some fields replaced; ValueError names an unknown preset or field."""
    if preset not in SAC_PRESETS:
        raise ValueError(f"unknown SAC preset {preset!r}; allowed: {sorted(SAC_PRESETS)}")
    fields = {f.name for f in dataclasses.fields(SACConfig)}
    for name in overrides:
        if name not in fields:
            raise ValueError(f"unknown SACConfig field {name!r}; allowed: {sorted(fields)}")
    return dataclasses.replace(SAC_PRESETS[preset], **overrides)
