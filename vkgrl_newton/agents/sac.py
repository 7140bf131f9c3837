"""Soft Actor-Critic (Haarnoja et al. 2018), as trained in the thesis (Table 5.3, SBX).

Read top to bottom: replay buffer, actor, critic ensemble, the agent (the config and its
presets: agents/sac_config.py).
Everything lives on one training device; the N worlds of the simulator are added as one batch.

Time-out convention (the caller's job): `add(obs, action, reward, next_obs, terminated)` takes
`terminated = dones & ~time_outs`, and `next_obs` must be the true final observation of the
episode (before the auto-reset), so a time-out still bootstraps from the state it ended in.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from rsl_rl.modules import EmpiricalNormalization
from torch import nn

from vkgrl_newton.agents.dense import ensemble_linear, ensemble_map, ensemble_stack, linear, resolve_backend
from vkgrl_newton.agents.matmul_backend import choose_cpu_matmul
# the configuration is plain data in a module of its own (no torch: the CLIs parse with it)
from vkgrl_newton.agents.sac_config import (ACTIVATION_NAMES, LOG_STD_BOUNDS, SAC_PRESETS, WARMUPS,  # noqa: F401
                                           SACConfig, make_sac_config)

Tensor = torch.Tensor
ACTIVATIONS: dict[str, type[nn.Module]] = {"elu": nn.ELU, "relu": nn.ReLU, "tanh": nn.Tanh}
assert tuple(ACTIVATIONS) == ACTIVATION_NAMES


# ----------------------------------------------------------------------------- replay buffer
class Batch(NamedTuple):
    obs: torch.Tensor  # (B, obs_dim), raw (normalized by the agent at sample time)
    action: torch.Tensor  # (B, action_dim) in [-1, 1]
    reward: torch.Tensor  # (B,)
    next_obs: torch.Tensor  # (B, obs_dim)
    terminated: torch.Tensor  # (B,) float, 1 = no bootstrap
    priv: torch.Tensor | None = None  # (B, priv_dim): the critic's privileged inputs (an asymmetric critic)
    next_priv: torch.Tensor | None = None  # (B, priv_dim)


class ReplayBuffer:
    """Preallocated circular buffer on the training device, filled N worlds at a time; with priv_dim > 0
    it also holds each transition's privileged critic inputs (priv, next_priv)."""

    def __init__(self, capacity: int, obs_dim: int, action_dim: int, device: torch.device | str,
                 priv_dim: int = 0) -> None:
        self.capacity, self.device = int(capacity), torch.device(device)
        shapes = {"obs": (obs_dim,), "action": (action_dim,), "reward": (), "next_obs": (obs_dim,), "terminated": ()}
        if priv_dim:
            shapes.update(priv=(priv_dim,), next_priv=(priv_dim,))
        self.FIELDS = tuple(shapes)
        # empty, not zeros: a 1M-row buffer costs no time or pages until it is written
        self.data = {k: torch.empty((self.capacity, *s), device=self.device) for k, s in shapes.items()}
        self.ptr = 0  # next row to write
        self.size = 0  # filled rows

    def __len__(self) -> int:
        return self.size

    def add(self, obs: Tensor, action: Tensor, reward: Tensor, next_obs: Tensor, terminated: Tensor,
            priv: Tensor | None = None, next_priv: Tensor | None = None) -> None:
        rows = [obs, action, reward, next_obs, terminated, priv, next_priv][:len(self.FIELDS)]
        if any(x is None for x in rows):
            raise ValueError("this replay buffer holds privileged critic inputs: give priv and next_priv")
        rows = [torch.as_tensor(x, device=self.device).to(torch.float32) for x in rows]
        n = rows[0].shape[0]
        if n > self.capacity:  # only the newest `capacity` rows can survive
            rows, n = [x[-self.capacity :] for x in rows], self.capacity
        idx = (self.ptr + torch.arange(n, device=self.device)) % self.capacity
        for k, x in zip(self.FIELDS, rows):
            self.data[k][idx] = x.reshape(n, *self.data[k].shape[1:])
        self.ptr = (self.ptr + n) % self.capacity
        self.size = min(self.size + n, self.capacity)

    def sample(self, batch_size: int, generator: torch.Generator) -> Batch:
        idx = torch.randint(0, self.size, (batch_size,), generator=generator, device=self.device)
        return Batch(*(self.data[k][idx] for k in self.FIELDS))

    def state_dict(self) -> dict:
        # only the filled part: rows [0, size) are the filled ones whether or not it has wrapped
        return {"capacity": self.capacity, "ptr": self.ptr, "size": self.size,
                **{k: v[: self.size].clone() for k, v in self.data.items()}}

    def load_state_dict(self, state: dict) -> None:
        if int(state["capacity"]) != self.capacity:
            raise ValueError(f"replay buffer capacity {state['capacity']} != {self.capacity}")
        self.ptr, self.size = int(state["ptr"]), int(state["size"])
        for k in self.FIELDS:
            self.data[k][: self.size] = state[k].to(self.device)


# ----------------------------------------------------------------------------- networks
def _init_linear_(weight: torch.Tensor, bias: torch.Tensor, fan_in: int, generator: torch.Generator) -> None:
    """nn.Linear's default distribution U(+-1/sqrt(fan_in)), drawn from our own generator."""
    bound = 1.0 / math.sqrt(fan_in)
    with torch.no_grad():
        nn.init.uniform_(weight, -bound, bound, generator=generator)
        nn.init.uniform_(bias, -bound, bound, generator=generator)


def squashed_log_prob(u: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """log pi(tanh(u)) for u ~ N(mean, exp(log_std)), summed over the action dims.

    Change of variables: log|d tanh(u)/du| = log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)),
    exact and stable for large |u| (no 1e-6 fudge as in SB3).
    """
    gauss = -0.5 * ((u - mean) / log_std.exp()).square() - log_std - 0.5 * math.log(2 * math.pi)
    log_det = 2.0 * (math.log(2.0) - u - F.softplus(-2.0 * u))
    return (gauss - log_det).sum(-1)


class Actor(nn.Module):
    """MLP -> (mean, log_std) of a Gaussian in pre-tanh space; actions are tanh-squashed into [-1, 1]."""

    def __init__(self, obs_dim: int, action_dim: int, cfg: SACConfig, generator: torch.Generator) -> None:
        super().__init__()
        dims, layers = [obs_dim, *cfg.hidden_dims], []
        for i, o in zip(dims[:-1], dims[1:]):
            layers += [nn.Linear(i, o), ACTIVATIONS[cfg.activation]()]
        self.trunk = nn.Sequential(*layers)
        self.head = nn.Linear(dims[-1], 2 * action_dim)  # mean and log_std side by side
        # forward() walks the Linear layers itself (agents/dense.py); the Sequential stays so that
        # the parameters keep their state_dict names (trunk.0, trunk.2, ...) and old checkpoints load
        self.linears = [m for m in self.trunk if isinstance(m, nn.Linear)] + [self.head]
        self.activation = ACTIVATIONS[cfg.activation]()
        self.matmul = "torch"  # agents/dense.py backend; SAC sets it for its device
        self.log_std_bounds = (cfg.log_std_min, cfg.log_std_max)
        self.soft_bound = cfg.log_std_bound == "tanh"
        for m in self.modules():
            if isinstance(m, nn.Linear):
                _init_linear_(m.weight, m.bias, m.in_features, generator)
        if cfg.actor_init_std is not None:  # start at mean 0, std actor_init_std (see SACConfig)
            with torch.no_grad():
                self.head.weight.mul_(1e-3)
                self.head.bias[:action_dim] = 0.0
                self.head.bias[action_dim:] = self.raw_log_std(math.log(cfg.actor_init_std))

    def raw_log_std(self, log_std: float) -> float:
        """The head's output that gives this log_std (the inverse of the bound; inside it, strictly)."""
        if not self.soft_bound:
            return log_std
        lo, hi = self.log_std_bounds
        y = min(max(2.0 * (log_std - lo) / (hi - lo) - 1.0, -1.0 + 1e-6), 1.0 - 1e-6)
        return math.atanh(y)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x, last = obs, len(self.linears) - 1
        for i, m in enumerate(self.linears):  # the trunk's Linear/activation pairs, then the head
            x = linear(x, m.weight, m.bias, self.matmul)
            x = self.activation(x) if i < last else x
        mean, log_std = x.chunk(2, dim=-1)
        lo, hi = self.log_std_bounds
        if self.soft_bound:
            return mean, lo + 0.5 * (hi - lo) * (torch.tanh(log_std) + 1.0)
        return mean, log_std.clamp(lo, hi)

    def sample(self, obs: torch.Tensor, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """Reparameterized action in [-1, 1] and its log-probability."""
        mean, log_std = self(obs)
        u = mean + log_std.exp() * torch.randn(mean.shape, generator=generator, device=mean.device)
        return torch.tanh(u), squashed_log_prob(u, mean, log_std)

    def deterministic(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self(obs)[0])


class CriticEnsemble(nn.Module):
    """n_critics Q(s, a) MLPs evaluated as one batched module: weights (n, in, out), as torch.baddbmm."""

    def __init__(self, in_dim: int, cfg: SACConfig, generator: torch.Generator) -> None:
        super().__init__()
        n, dims = cfg.n_critics, [in_dim, *cfg.hidden_dims, 1]
        self.weights = nn.ParameterList([nn.Parameter(torch.empty(n, i, o)) for i, o in zip(dims[:-1], dims[1:])])
        self.biases = nn.ParameterList([nn.Parameter(torch.empty(n, 1, o)) for o in dims[1:]])
        self.activation = ACTIVATIONS[cfg.activation]()
        self.matmul = "torch"  # agents/dense.py backend; SAC sets it for its device
        for w, b in zip(self.weights, self.biases):
            _init_linear_(w, b, w.shape[1], generator)
        # LayerNorm of every hidden layer (before its activation), a scale and shift per critic
        # (created only when asked, so that older checkpoints keep their keys)
        if cfg.critic_layer_norm:
            self.ln_scales = nn.ParameterList([nn.Parameter(torch.ones(n, 1, o)) for o in dims[1:-1]])
            self.ln_shifts = nn.ParameterList([nn.Parameter(torch.zeros(n, 1, o)) for o in dims[1:-1]])
        else:
            self.ln_scales = self.ln_shifts = None

    def forward(self, obs: torch.Tensor, action: torch.Tensor, frozen: bool = False) -> torch.Tensor:
        """(B, obs_dim), (B, action_dim) -> Q values (n_critics, B).

        frozen: the weights as constants (the actor's loss), so a backward pass computes the
        gradient w.r.t. the action only, never the critics' weight gradients it would discard."""
        weights, biases = self.weights, self.biases
        scales, shifts = self.ln_scales, self.ln_shifts
        if frozen:
            weights, biases = [w.detach() for w in weights], [b.detach() for b in biases]
            if scales is not None:
                scales, shifts = [g.detach() for g in scales], [h.detach() for h in shifts]
        x = torch.cat([obs, action], dim=-1)  # (B, in): shared by the critics, never copied per critic
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(weights, biases)):
            x = ensemble_linear(x, w, b, self.matmul)
            if i < last:
                if scales is not None:
                    x = ensemble_layer_norm(x, scales[i], shifts[i])
                x = ensemble_map(self.activation, x)
        return ensemble_stack(x)


def ensemble_layer_norm(h, scale: torch.Tensor, shift: torch.Tensor):
    """LayerNorm over the features of each member's activations; scale, shift (n, 1, d) per member."""
    d = scale.shape[-1]
    if isinstance(h, torch.Tensor):  # (n, B, d)
        return F.layer_norm(h, (d,)) * scale + shift
    return tuple(F.layer_norm(x, (d,)) * g[0] + c[0] for x, g, c in zip(h, scale, shift))


@torch.no_grad()
def soft_update_(target: list[torch.Tensor], online: list[torch.Tensor], tau: float) -> None:
    """Polyak averaging target <- target + tau (online - target), one fused op over all tensors."""
    torch._foreach_lerp_(target, online, tau)


# ----------------------------------------------------------------------------- the agent
class SAC:
    def __init__(self, obs_dim: int, action_dim: int, config: SACConfig, device: torch.device | str = "cpu",
                 seed: int = 0, priv_dim: int = 0) -> None:
        """priv_dim > 0: an asymmetric critic (Factory's): the critics read the actor's observation plus
        priv_dim privileged inputs (`add(..., priv, next_priv)`), which never reach the actor."""
        self.cfg, self.device = config, torch.device(device)
        self.obs_dim, self.action_dim, self.priv_dim = obs_dim, action_dim, int(priv_dim)
        if self.priv_dim and config.prior_anchor:  # act() would choose between a and 0 by the critic's value
            raise ValueError("SACConfig.prior_anchor with a privileged critic: the anchor chooses the action by "
                             "the critic, which would bring privileged state to the policy; set prior_anchor=False")
        # No global RNG: init_gen (CPU) draws the weights; self.generator (on the device) draws
        # exploration noise, warm-up actions and replay indices, and is checkpointed for resumes.
        init_gen = torch.Generator().manual_seed(seed)
        self.generator = torch.Generator(device=self.device).manual_seed(seed)
        self.actor = Actor(obs_dim, action_dim, config, init_gen).to(self.device)
        self.critic = CriticEnsemble(obs_dim + self.priv_dim + action_dim, config, init_gen).to(self.device)
        # "auto": the faster backend on this machine, kept in the user's cache (a run resolves it
        # before, in its own cache, and records it in its config: agents/matmul_backend.py)
        backend = choose_cpu_matmul(config, obs_dim, action_dim, self.device)
        self.actor.matmul = self.critic.matmul = resolve_backend(backend, self.device)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self._target_params, self._online_params = list(self.critic_target.parameters()), list(self.critic.parameters())
        self.log_alpha = torch.tensor(math.log(config.init_alpha), device=self.device, requires_grad=True)
        self.target_entropy = float(-action_dim if config.target_entropy is None else config.target_entropy)
        # fused: one kernel per parameter tensor instead of ~10 (the for-loop update is ~10 % of a
        # gradient step on a CPU; docs/log/benchmarks.md)
        adamw = dict(lr=config.lr, weight_decay=config.weight_decay, fused=True)
        self.actor_optim = torch.optim.AdamW(self.actor.parameters(), **adamw)
        self.critic_optim = torch.optim.AdamW(self.critic.parameters(), **adamw)
        self.alpha_optim = torch.optim.Adam([self.log_alpha], lr=config.lr, fused=True)
        # Statistics from env batches as they arrive (never from replay samples), applied at use.
        self.normalizer = (EmpiricalNormalization(obs_dim, eps=config.obs_norm_eps).to(self.device)
                           if config.obs_normalization else None)
        self.priv_normalizer = (EmpiricalNormalization(self.priv_dim, eps=config.obs_norm_eps).to(self.device)
                                if config.obs_normalization and self.priv_dim else None)
        self.buffer = ReplayBuffer(config.buffer_size, obs_dim, action_dim, self.device, self.priv_dim)
        # the prior's own rollouts (RLPD's second buffer: the first cfg.prior_rollouts transitions),
        # sampled at cfg.prior_ratio
        self.prior_buffer = (ReplayBuffer(config.buffer_size, obs_dim, action_dim, self.device, self.priv_dim)
                             if config.prior_ratio > 0 else None)
        self.rewarded = False  # a transition with reward > 0 has been added (cfg.actor_after_reward)
        self.num_transitions = 0  # env transitions added, summed over worlds
        self.num_env_steps = 0  # batched `add` calls
        self.num_updates = 0  # critic gradient steps

    @property
    def cpu_matmul(self) -> str:
        """The matmul library the networks run on: "onednn" or "torch" (torch's: MKL on a CPU, cuBLAS on CUDA)."""
        return self.actor.matmul

    # --- acting ------------------------------------------------------------------------------
    def normalize(self, obs: torch.Tensor) -> torch.Tensor:
        return obs if self.normalizer is None else self.normalizer(obs)

    def normalize_priv(self, priv: torch.Tensor) -> torch.Tensor:
        return priv if self.priv_normalizer is None else self.priv_normalizer(priv)

    @torch.no_grad()
    def act(self, obs: torch.Tensor, deterministic: bool = False) -> torch.Tensor:
        """Actions in [-1, 1] for a batch of raw observations (N, obs_dim)."""
        obs = self.normalize(torch.as_tensor(obs, dtype=torch.float32, device=self.device))
        a = self.actor.deterministic(obs) if deterministic else self.actor.sample(obs, self.generator)[0]
        return self.anchored(self.critic, obs, a) if self.cfg.prior_anchor else a

    def anchored(self, critic: "CriticEnsemble", obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """IBRL's choice (cfg.prior_anchor): a = 0 (the prior) where min_i Q_i(s, 0) > min_i Q_i(s, a)."""
        zero = torch.zeros_like(action)
        q = critic(torch.cat([obs, obs]), torch.cat([action, zero])).min(dim=0).values
        q_pi, q_0 = q.chunk(2)
        return torch.where((q_0 > q_pi).unsqueeze(-1), zero, action)

    def random_actions(self, num_envs: int) -> torch.Tensor:
        """Uniform actions in [-1, 1] (SB3/SBX warm-up)."""
        u = torch.rand((num_envs, self.action_dim), generator=self.generator, device=self.device)
        return 2.0 * u - 1.0

    def explore(self, obs: torch.Tensor) -> torch.Tensor:
        """The training loop's action: the stochastic actor once ready(), before that cfg.warmup's."""
        if self.num_transitions < self.cfg.prior_rollouts:
            return torch.zeros((obs.shape[0], self.action_dim), device=self.device)
        if self.ready() or self.cfg.warmup == "policy":
            return self.act(obs)
        return self.random_actions(obs.shape[0])

    # --- data ----------------------------------------------------------------------------------
    def add(self, obs: Tensor, action: Tensor, reward: Tensor, next_obs: Tensor, terminated: Tensor,
            priv: Tensor | None = None, next_priv: Tensor | None = None) -> None:
        """One batched env step of N worlds; terminated = dones & ~time_outs, next_obs = true final obs;
        priv, next_priv: the privileged critic inputs of obs and next_obs (with priv_dim > 0 only)."""
        obs = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
        if self.normalizer is not None:
            self.normalizer.update(obs)
        extra = ()
        if self.priv_dim:
            if priv is None or next_priv is None:
                raise ValueError(f"SAC with a privileged critic (priv_dim={self.priv_dim}): give priv and next_priv")
            priv = torch.as_tensor(priv, dtype=torch.float32, device=self.device)
            if self.priv_normalizer is not None:
                self.priv_normalizer.update(priv)
            extra = (priv, next_priv)
        elif priv is not None:
            raise ValueError("priv given to a SAC without a privileged critic (priv_dim=0)")
        self.buffer.add(obs, action, reward, next_obs, terminated, *extra)
        if self.prior_buffer is not None and self.num_transitions < self.cfg.prior_rollouts:
            self.prior_buffer.add(obs, action, reward, next_obs, terminated, *extra)
        self.num_transitions += obs.shape[0]
        self.num_env_steps += 1
        if self.cfg.actor_after_reward and not self.rewarded:  # one host read per step until the first reward
            self.rewarded = bool((torch.as_tensor(reward) > 0).any())

    def ready(self) -> bool:
        """Enough samples to train: learning_starts transitions and at least one batch."""
        return self.num_transitions >= self.cfg.learning_starts and len(self.buffer) >= self.cfg.batch_size

    def update_due(self) -> bool:
        """ready() and this batched env step is a multiple of train_every."""
        return self.ready() and self.num_env_steps % self.cfg.train_every == 0

    # --- losses --------------------------------------------------------------------------------
    def critic_loss(self, obs: Tensor, action: Tensor, reward: Tensor, next_obs: Tensor, terminated: Tensor,
                    alpha: Tensor, critic_obs: Tensor | None = None,
                    next_critic_obs: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """Soft Bellman residual on normalized obs; returns (loss, Q (n, B), target (B,)). The actor
        reads obs and next_obs; the critics read critic_obs and next_critic_obs (the same unless the
        critic is privileged: obs plus the privileged inputs)."""
        critic_obs = obs if critic_obs is None else critic_obs
        next_critic_obs = next_obs if next_critic_obs is None else next_critic_obs
        with torch.no_grad():
            if self.cfg.prior_anchor:  # IBRL: bootstrap from the better of pi's sample and a = 0
                mean, log_std = self.actor(next_obs)
                u = mean + log_std.exp() * torch.randn(mean.shape, generator=self.generator, device=mean.device)
                zero = torch.zeros_like(u)
                q = self.critic_target(torch.cat([next_critic_obs, next_critic_obs]), torch.cat([torch.tanh(u), zero]))
                q_pi, q_0 = q.min(dim=0).values.chunk(2)
                next_q = torch.maximum(q_0, q_pi)
                # the entropy term of the policy's own sample in both cases: log pi(0 | s') of a policy
                # that has moved away from 0 with a small std is hugely negative, and would add an
                # unbounded bonus to the target exactly where the prior's action is chosen
                next_log_pi = squashed_log_prob(u, mean, log_std)
            else:
                next_action, next_log_pi = self.actor.sample(next_obs, self.generator)
                next_q = self.critic_target(next_critic_obs, next_action).min(dim=0).values
            target = reward + self.cfg.gamma * (1.0 - terminated) * (next_q - alpha * next_log_pi)
        q = self.critic(critic_obs, action)
        loss = 0.5 * (q - target).square().mean(dim=1).sum()  # SB3/SBX: 0.5 sum_i MSE_i
        return loss, q, target

    def actor_loss(self, obs: torch.Tensor, alpha: torch.Tensor, bc_action: torch.Tensor | None = None,
                   critic_obs: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """E[alpha log pi(a|s) - min_i Q_i(s, a)], plus cfg.prior_reg * E|tanh(mean)|^2 (toward a = 0),
        plus, with bc_action (the actions of obs's last len(bc_action) rows, the prior buffer's),
        cfg.bc_weight * mean|Q| * E|tanh(mean) - bc_action|^2 over those rows (TD3+BC's scaling)."""
        mean, log_std = self.actor(obs)  # Actor.sample's draw, with the mean kept for the penalty
        u = mean + log_std.exp() * torch.randn(mean.shape, generator=self.generator, device=mean.device)
        log_pi = squashed_log_prob(u, mean, log_std)
        q = self.critic(obs if critic_obs is None else critic_obs, torch.tanh(u), frozen=True).min(dim=0).values
        loss = (alpha * log_pi - q).mean()
        if self.cfg.prior_reg:
            loss = loss + self.cfg.prior_reg * torch.tanh(mean).square().sum(-1).mean()
        if self.cfg.bc_weight and bc_action is not None and len(bc_action):
            bc = (torch.tanh(mean[-len(bc_action):]) - bc_action).square().sum(-1).mean()
            loss = loss + self.cfg.bc_weight * q.detach().abs().mean() * bc
        return loss, log_pi

    # --- training ------------------------------------------------------------------------------
    def update(self, num_gradient_steps: int | None = None) -> dict[str, float]:
        """num_gradient_steps (default cfg.gradient_steps) critic steps, the actor every policy_delay."""
        if not self.ready():
            raise RuntimeError(f"SAC.update before ready(): {self.num_transitions} transitions, "
                               f"learning_starts={self.cfg.learning_starts}, batch_size={self.cfg.batch_size}")
        cfg = self.cfg
        steps, bs = (cfg.gradient_steps if num_gradient_steps is None else num_gradient_steps), cfg.batch_size
        if steps < 1:
            raise ValueError(f"num_gradient_steps={steps} must be >= 1")
        # All minibatches in one draw and one normalization (stats change only in `add`).
        b = self.sample(steps, bs)
        n_prior = self.prior_rows(bs)  # the last n_prior rows of each minibatch are the prior buffer's
        obs = self.normalize(b.obs).view(steps, bs, -1)
        next_obs = self.normalize(b.next_obs).view(steps, bs, -1)
        action, reward, term = b.action.view(steps, bs, -1), b.reward.view(steps, bs), b.terminated.view(steps, bs)
        critic_obs, next_critic_obs = obs, next_obs
        if self.priv_dim:  # the critics' inputs: the actor's, then the privileged ones
            critic_obs = torch.cat([obs, self.normalize_priv(b.priv).view(steps, bs, -1)], -1)
            next_critic_obs = torch.cat([next_obs, self.normalize_priv(b.next_priv).view(steps, bs, -1)], -1)
        critic_stats, actor_stats = [], []  # device tensors; one sync at the end
        for k in range(steps):
            alpha = self.log_alpha.detach().exp()
            loss_q, q, _ = self.critic_loss(obs[k], action[k], reward[k], next_obs[k], term[k], alpha,
                                            critic_obs[k], next_critic_obs[k])
            self.critic_optim.zero_grad(set_to_none=True)
            loss_q.backward()
            self.critic_optim.step()
            soft_update_(self._target_params, self._online_params, cfg.tau)
            critic_stats.append(torch.stack([loss_q.detach(), q.detach().mean()]))
            if self.num_updates % cfg.policy_delay == 0 and (self.rewarded or not cfg.actor_after_reward):
                loss_pi, log_pi = self.actor_loss(obs[k], alpha, action[k, bs - n_prior:] if n_prior else None,
                                                  critic_obs[k])
                self.actor_optim.zero_grad(set_to_none=True)
                loss_pi.backward()  # actor weights only: the critic is frozen in actor_loss
                self.actor_optim.step()
                # d loss / d log_alpha = entropy - target: alpha falls while entropy is above target
                log_pi = log_pi.detach()
                loss_alpha = -(self.log_alpha * (log_pi + self.target_entropy)).mean()
                self.alpha_optim.zero_grad(set_to_none=True)
                loss_alpha.backward()
                self.alpha_optim.step()
                actor_stats.append(torch.stack([loss_pi.detach(), loss_alpha.detach(), -log_pi.mean()]))
            self.num_updates += 1
        nan = torch.full((3,), float("nan"), device=self.device)
        a_mean = torch.stack(actor_stats).mean(0) if actor_stats else nan
        stats = torch.cat([torch.stack(critic_stats).mean(0), a_mean, self.log_alpha.detach().exp()[None]])
        cl, qm, al, tl, ent, alpha = stats.tolist()
        return {"critic_loss": cl, "actor_loss": al, "alpha_loss": tl, "alpha": alpha, "q_mean": qm, "entropy": ent}

    def prior_rows(self, batch_size: int) -> int:
        """Rows of a minibatch drawn from the prior buffer (the last ones): 0 while it is empty."""
        if self.prior_buffer is None or len(self.prior_buffer) == 0:
            return 0
        return int(round(self.cfg.prior_ratio * batch_size))

    def sample(self, steps: int, batch_size: int) -> Batch:
        """steps x batch_size rows; with a filled prior buffer, round(prior_ratio * batch_size) of
        each minibatch come from it (RLPD's symmetric sampling at 0.5), the rest online."""
        n_prior = self.prior_rows(batch_size)
        if n_prior == 0:
            return self.buffer.sample(steps * batch_size, self.generator)
        online = self.buffer.sample(steps * (batch_size - n_prior), self.generator)
        prior = self.prior_buffer.sample(steps * n_prior, self.generator)
        return Batch(*(None if o is None else
                       torch.cat([o.view(steps, batch_size - n_prior, *o.shape[1:]),
                                  p.view(steps, n_prior, *p.shape[1:])], dim=1).reshape(steps * batch_size,
                                                                                         *o.shape[1:])
                       for o, p in zip(online, prior)))

    # --- checkpoints -----------------------------------------------------------------------------
    def state_dict(self, include_buffer: bool = True) -> dict:
        """Everything a bit-identical resume needs (the buffer can be left out to save space)."""
        state = {
            "actor": self.actor.state_dict(), "critic": self.critic.state_dict(),
            "critic_target": self.critic_target.state_dict(), "log_alpha": self.log_alpha.detach().clone(),
            "actor_optim": self.actor_optim.state_dict(), "critic_optim": self.critic_optim.state_dict(),
            "alpha_optim": self.alpha_optim.state_dict(),
            "normalizer": None if self.normalizer is None else self.normalizer.state_dict(),
            **({"priv_normalizer": self.priv_normalizer.state_dict()} if self.priv_normalizer is not None else {}),
            "counters": (self.num_transitions, self.num_env_steps, self.num_updates),
            "generator": self.generator.get_state(), "config": dataclasses.asdict(self.cfg),
        }
        if include_buffer:
            state["buffer"] = self.buffer.state_dict()
            if self.prior_buffer is not None:
                state["prior_buffer"] = self.prior_buffer.state_dict()
        if self.cfg.actor_after_reward:
            state["rewarded"] = self.rewarded
        return state

    def load_state_dict(self, state: dict) -> None:
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        self.critic_target.load_state_dict(state["critic_target"])
        with torch.no_grad():
            self.log_alpha.copy_(state["log_alpha"])
        self.actor_optim.load_state_dict(state["actor_optim"])
        self.critic_optim.load_state_dict(state["critic_optim"])
        self.alpha_optim.load_state_dict(state["alpha_optim"])
        if self.normalizer is not None:
            self.normalizer.load_state_dict(state["normalizer"])
        if self.priv_normalizer is not None:
            self.priv_normalizer.load_state_dict(state["priv_normalizer"])
        self.num_transitions, self.num_env_steps, self.num_updates = state["counters"]
        self.generator.set_state(state["generator"])
        if "buffer" in state:
            self.buffer.load_state_dict(state["buffer"])
        if "prior_buffer" in state and self.prior_buffer is not None:
            self.prior_buffer.load_state_dict(state["prior_buffer"])
        self.rewarded = bool(state.get("rewarded", False))

