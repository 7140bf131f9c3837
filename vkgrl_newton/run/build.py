"""The one builder: a `RunConfig` -> (encoder, env, action path, agent).

train/run.py, train/evaluate.py (from a checkpoint's configuration) and the gymnasium ids
(run/gym.py) build through these functions, so that the env a policy is evaluated on, or a gym id
hands to another library, is the env run.py trains on: the same task geometry, vision latent,
KMP prior, reference and reach floors. Each step may be called alone (the gym ids build no agent).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .config import RunConfig

__all__ = ["Built", "build", "build_encoder", "build_env", "build_probe", "build_action_path", "build_agent", "build_rollout_policy"]


@dataclass
class Built:
    encoder: object | None  # vision.vae.FrozenEncoder, the vision methods'
    env: object  # envs.assembly_env.AssemblyEnv
    action_path: object | None  # envs.kgrl_action.KGRLActionPath, the kmp methods'
    agent: object | None  # agents.sac.SAC | agents.ppo.PPOAgent
    demos_path: Path | None  # the demonstrations the prior was fitted to

    @property
    def step_fn(self):
        """What one control step of the policy's actions calls: env.step or the KGRL action path's."""
        return self.action_path.step if self.action_path is not None else self.env.step


def build_encoder(cfg: RunConfig, log=print):
    """The frozen VAE encoder of a vision method (the given vae.pt, or the cache's, made on first use:
    prepare.vision); None for the others. The prepare step's errors pass through."""
    if not cfg.method_row.vision:
        return None
    from ..prepare.vision import VISION_PRESETS, load_or_make_encoder

    encoder, _ = load_or_make_encoder(cfg.task, VISION_PRESETS[cfg.preset], cfg.cache_dir, cfg.device,
                                      vae_path=cfg.vae, log=log, progress=cfg.progress)
    if encoder.latent_dim != cfg.latent_dim:
        raise ValueError(f"the VAE's latent has {encoder.latent_dim} dimensions, the vision methods use "
                         f"{cfg.latent_dim} (thesis 5.6)")
    return encoder


def build_env(cfg: RunConfig, encoder=None, solver: str | None = None, probe=None):
    """The batched AssemblyEnv of the configuration, with the encoder's camera latent attached (and with
    vision_probe_obs the near-hole probe: `probe`, or build_probe's when None)."""
    from ..envs.assembly_env import AssemblyEnv, EnvConfig
    from ..sim.scene import SimConfig

    sim = SimConfig(geometry=cfg.geometry) if solver is None else SimConfig(solver=solver, geometry=cfg.geometry)
    env = AssemblyEnv(EnvConfig(task=cfg.task, family=cfg.env, action_dim=cfg.action_dim, num_envs=cfg.num_envs,
                                device=cfg.device, seed=cfg.seed,
                                vision_latent_dim=cfg.vision_width if encoder is not None else 0,
                                sim=sim, graph=not cfg.eager_physics, privileged_obs=cfg.privileged_critic,
                                tcp_velocity_obs=cfg.tcp_velocity_obs, force_obs=cfg.force_obs))
    attach_encoder(env, encoder, probe if probe is not None else build_probe(cfg, encoder))
    return env


def build_probe(cfg: RunConfig, encoder, log=print):
    """--vision-probe-obs: the near-hole probe of the run's (cached) VAE, fitted on first use; else None."""
    if encoder is None or not cfg.vision_probe_obs:
        return None
    from ..prepare.vision import VISION_PRESETS, load_or_make_probe

    probe, path, record = load_or_make_probe(cfg.task, VISION_PRESETS[cfg.preset], cfg.cache_dir, encoder, log=log,
                                             path=cfg.probe, fit=cfg.vision_probe_fit, progress=cfg.progress)
    log(f"near-hole probe loaded: {path} (held-out RMSE, image x / y / z: "
        + " / ".join(f"{v:.2f}" for v in record["held_out_rmse_mm"].values()) + " mm)")
    return probe


def attach_encoder(env, encoder, probe=None) -> None:
    if encoder is not None:
        from ..envs.camera_latent import CameraLatent

        env.attach_vision(CameraLatent(env, encoder, probe=probe))


def build_action_path(cfg: RunConfig, env, log=print):
    """(KGRLActionPath, demonstration path) of a kmp method: the prior (recorded and fitted on first
    use, prepare.prior) with the configuration's reference, parameters, reach floors and base; (None, None)
    for the delta-pose methods."""
    if not cfg.method_row.uses_kmp:
        return None, None
    from ..envs.kgrl_action import KGRLActionPath

    from ..envs.evaluation import base_controller

    tables, demos_path = prior_tables(cfg, log)
    path = KGRLActionPath(tables, env, reach_floor=1e-3 * cfg.reach_floor_mm, reach_floor_z=1e-3 * cfg.reach_floor_z_mm,
                          time_steps=cfg.kgrl_time_action, seat_press=1e-3 * cfg.seat_press_mm)
    # --kgrl-base (None: a = 0 is the prior), --kgrl-residual-scale
    base = base_controller(cfg.kgrl_base, path, cfg.task, search_speed_mm=cfg.kgrl_search_speed_mm,
                           search_press_mm=cfg.kgrl_search_press_mm)
    path.set_base(base, cfg.kgrl_residual_scale)
    return path, demos_path


def prior_tables(cfg: RunConfig, log=print):
    """The KMP tables of the configuration's prior and the demonstrations they come from."""
    from ..prepare.prior import load_or_make_prior

    kw = {"reference": cfg.kmp_reference, **(cfg.kmp_params or {})}
    return load_or_make_prior(cfg.task, cfg.action_dim, cfg.cache_dir, demos=cfg.demos, num_demos=cfg.num_demos,
                              device=cfg.device, geometry=cfg.geometry, log=log, progress=cfg.progress, **kw)


def build_agent(cfg: RunConfig, env):
    """The method's learner for the env's observations: SAC (agents/sac.py) or rsl-rl's PPO."""
    if cfg.method_row.uses_ppo:
        from ..agents.ppo import PPOAgent

        return PPOAgent(env, cfg.ppo, device=str(env.tdev))
    from ..agents.sac import SAC

    from ..envs.assembly_env import PRIVILEGED_OBS_DIM

    return SAC(cfg.obs_dim, cfg.agent_action_dim, cfg.sac, device=env.tdev, seed=cfg.seed,
               priv_dim=PRIVILEGED_OBS_DIM if cfg.privileged_critic else 0)


def build_rollout_policy(cfg: RunConfig, action_path):
    """What acts instead of a SAC agent in its first prior_rollouts transitions (SACConfig.prior_rollouts_policy):
    the prior's blind search, the scripted demonstrator through the SAC action space, or None (the agent
    itself, whose a = 0 is the prior for the kmp methods)."""
    rollouts = getattr(cfg.sac, "prior_rollouts_policy", "prior")  # (PPO runs have no SACConfig)
    if rollouts == "search":
        from ..envs.evaluation import KMPSearchPolicy

        return KMPSearchPolicy(action_path)  # within the run's own reach floors
    if rollouts == "scripted":
        from ..envs.evaluation import ScriptedDeltaPolicy

        return ScriptedDeltaPolicy(seed=cfg.seed)
    return None


def build(cfg: RunConfig, log=print, with_agent: bool = True) -> Built:
    """Everything a run trains or evaluates with, in the order a run has always built it (the encoder
    first: its preparation may take minutes and fails before a simulation is built)."""
    encoder = build_encoder(cfg, log)
    env = build_env(cfg, encoder)
    action_path, demos_path = build_action_path(cfg, env, log)
    agent = build_agent(cfg, env) if with_agent else None
    return Built(encoder, env, action_path, agent, demos_path)
