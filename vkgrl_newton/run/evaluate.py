"""train/evaluate.py as a library: a policy (a checkpoint's, or a named baseline) on seeded evaluation
episodes, built through the one builder (run/build.py), so that a checkpoint is evaluated on the env,
encoder (with the camera its VAE was trained on) and prior its run trained with.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from ..cache import check_run_files
from ..results.paired import seed_evaluation
from ..runtime import processor_name
from ..tasks import geometry_error
from .config import SEARCH_SETTINGS, ConfigError, RunConfig
from .methods import METHODS

__all__ = ["POLICIES", "KMP_POLICIES", "checkpoint_config", "evaluation_config", "make_policy", "evaluate_policy"]

POLICIES = ("scripted", "scripted_delta", "random", "zero", "kmp_prior", "kmp_search")
KMP_POLICIES = ("kmp_prior", "kmp_search")  # the baselines on the KMP prior


def checkpoint_config(args, payload: dict, given: set[str]) -> None:
    """A checkpoint says what it is: task, env, action space, method, time input, geometry, prior and
    VAE into `args` (ConfigError where an option asks for another)."""
    meta = payload["meta"]
    for name in ("task", "env", "action_dim"):  # a different ask is refused
        if name in given and getattr(args, name) != meta[name]:
            raise ConfigError(f"--{name.replace('_', '-')} {getattr(args, name)}: the checkpoint is a {meta['task']} "
                              f"{meta['env']} {meta['action_dim']}D policy; leave --task/--env/--action-dim out "
                              "with --checkpoint")
    args.task, args.env, args.action_dim = meta["task"], meta["env"], meta["action_dim"]
    args.cpu_matmul = evaluation_cpu_matmul(args, meta)
    args.no_time_obs = not meta["time_obs"]
    args.policy = meta["method"]
    if args.geometry is None:
        args.geometry = meta.get("geometry", "primitives")
    if "prior" in meta and args.demos is None:  # the prior the run learned with (--demos overrides)
        try:
            check_run_files(meta, demos=meta["prior"]["demos"])
        except (FileNotFoundError, ValueError) as e:
            raise ConfigError(f"--checkpoint: {e} (--demos FILE evaluates with another prior)") from None
        args.demos = Path(meta["prior"]["demos"])
    if "vision" in meta:  # a vision run: the same frozen encoder it trained with
        try:
            check_run_files(meta, vae=meta["vision"]["vae"], probe=meta["vision"].get("probe"))
        except (FileNotFoundError, ValueError) as e:
            raise ConfigError(f"--checkpoint: the run's vision files: {e}") from None


def evaluation_cpu_matmul(args, meta: dict) -> str | None:
    """The matmul library a SAC checkpoint is evaluated on: its own (as it trained, so its results
    repeat), or the one --cpu-matmul names ("auto": this machine's faster one); None for PPO.
    ConfigError where it cannot run here."""
    given = getattr(args, "cpu_matmul", None)
    if "sac" not in meta:
        if given is not None:
            raise ConfigError("--cpu-matmul is for the checkpoints of the SAC methods; this one is rsl-rl PPO's")
        return None
    from ..agents.dense import onednn_available
    from ..agents.matmul_backend import CHOICE_FILE, choose_cpu_matmul
    from ..agents.sac_config import SACConfig

    was = meta["sac"].get("cpu_matmul", "torch")  # (before the field existed: torch's)
    backend = given or was
    if backend == "auto":
        sac = SACConfig(**{**meta["sac"], "cpu_matmul": "auto"})
        backend = choose_cpu_matmul(sac, meta["obs_dim"], meta["action_dim"] + (1 if meta.get("kgrl_time_action") else 0),
                                    args.device,
                                    Path(args.cache_dir) / CHOICE_FILE, log=print)
    if backend == "onednn" and not str(args.device).startswith("cuda") and not onednn_available():
        import torch

        raise ConfigError(f"{'--cpu-matmul onednn' if given else '--checkpoint: the run trained on oneDNN'}, which "
                          f"this torch ({torch.__version__}) does not provide; evaluate with --cpu-matmul torch (its "
                          "float32 last bits, and so some contact outcomes, may differ)")
    return backend


def evaluation_config(args, payload: dict | None) -> RunConfig:
    """The RunConfig whose env, encoder and prior the evaluation builds: the checkpoint's (with this
    command's worlds, seed and device), or for a named policy the delta-pose (or, for the KMP baselines,
    the kgrl) configuration of --task/--env/--action-dim."""
    if args.geometry is None:
        args.geometry = "primitives"
    if geometry_error(args.task, args.geometry):
        raise ConfigError(f"--{geometry_error(args.task, args.geometry)}")
    meta = payload["meta"] if payload is not None else {}
    method = meta.get("method") or ("kgrl" if args.policy in KMP_POLICIES else "sac")
    if args.demos is not None and METHODS[method].uses_kmp:  # missing, damaged or another task's: one line
        from .resolve import check_demos_file

        check_demos_file(args.demos, args.task)
    prior = meta.get("prior", {})
    return RunConfig(task=args.task, method=method, env=args.env, action_dim=args.action_dim, seed=args.seed,
                     num_envs=args.num_envs, preset=meta.get("preset", "quick"), time_obs=not args.no_time_obs,
                     geometry=args.geometry, demos=args.demos,
                     kmp_reference=prior.get("reference", "gmr") if prior else args.kmp_reference,
                     kmp_params={k: prior[k] for k in ("lam", "beta", "l") if k in prior} or None,
                     reach_floor_mm=prior.get("reach_floor_mm", 0.0), reach_floor_z_mm=prior.get("reach_floor_z_mm", 0.0),
                     seat_press_mm=prior.get("seat_press_mm", 0.0),
                     vae=Path(meta["vision"]["vae"]) if "vision" in meta else None,
                     kgrl_time_action=meta.get("kgrl_time_action", 0), kgrl_base=meta.get("kgrl_base", "prior"),
                     kgrl_residual_scale=meta.get("kgrl_residual_scale", 1.0),
                     **{name: meta.get(name) for name in SEARCH_SETTINGS},  # absent: the search's own
                     tcp_velocity_obs=meta.get("tcp_velocity_obs", False),
                     force_obs=meta.get("force_obs", False), vision_probe_obs=meta.get("vision_probe_obs", False),
                     vision_probe_fit=meta.get("vision_probe_fit", "images"),
                     probe=Path(meta["vision"]["probe"]) if "probe" in meta.get("vision", {}) else None,
                     sac=None, ppo=meta.get("ppo"), device=args.device, cache_dir=args.cache_dir, progress=True,
                     eager_physics=bool(args.eager_physics))


def make_policy(args, cfg: RunConfig, built, payload: dict | None):
    """The evaluation policy: the checkpoint's agent (deterministic or sampled), or the named baseline."""
    import torch

    from ..envs.evaluation import (AgentPolicy, KMPPriorPolicy, KMPSearchPolicy, RandomPolicy, ScriptedDeltaPolicy,
                                   ScriptedPolicy, ZeroPolicy)

    if payload is not None:
        meta = payload["meta"]
        if "ppo" in meta:  # run.py's ppo methods
            from ..agents.ppo import PPOAgent

            agent = PPOAgent(built.env, meta["ppo"], device=str(built.env.tdev))
        else:
            from ..agents.sac import SAC, SACConfig

            sac = SACConfig(**{**meta["sac"], "cpu_matmul": args.cpu_matmul or meta["sac"].get("cpu_matmul", "torch")})
            agent = SAC(meta["obs_dim"], cfg.agent_action_dim, sac, device=built.env.tdev, seed=args.seed)
        agent.load_state_dict(payload["agent"])
        torch.manual_seed(args.seed)  # PPO samples from torch's global generator, SAC from its own (seed)
        return AgentPolicy(agent, built.action_path, time_obs=meta["time_obs"], deterministic=not args.stochastic,
                           obs_history=meta.get("obs_history", 0))
    if args.policy == "kmp_prior":
        return KMPPriorPolicy(built.action_path)
    if args.policy == "kmp_search":  # (the search builds its own action path, with its reach floors)
        return KMPSearchPolicy.with_floors(built.tables, built.env)
    return {"scripted": lambda: ScriptedPolicy(seed=args.seed), "random": lambda: RandomPolicy(seed=args.seed),
            "scripted_delta": lambda: ScriptedDeltaPolicy(seed=args.seed), "zero": ZeroPolicy}[args.policy]()


@dataclasses.dataclass
class _Evaluated:
    env: object
    action_path: object | None
    tables: object | None  # kmp_search's prior tables (it floors them itself)


def evaluate_policy(args, payload: dict | None) -> dict:
    """Build (run.build), evaluate on the eval seed's episodes, and return evaluate.py's result dict
    (the frames, when --video, under "_frames")."""
    from ..envs.evaluation import KMPSearchPolicy, evaluate
    from .build import build_action_path, build_encoder, build_env, build_probe, prior_tables

    cfg = evaluation_config(args, payload)
    try:
        encoder = build_encoder(cfg)
    except (FileNotFoundError, ValueError) as e:
        raise ConfigError(f"--checkpoint: the run's VAE: {e}") from None
    try:
        probe = build_probe(cfg, encoder)
    except (FileNotFoundError, ValueError) as e:
        raise ConfigError(f"--checkpoint: the run's near-hole probe: {e}") from None
    env = build_env(cfg, encoder, solver=args.solver, probe=probe)
    search = payload is None and args.policy == "kmp_search"
    action_path = build_action_path(cfg, env)[0] if not search else None
    built = _Evaluated(env, action_path, prior_tables(cfg)[0] if search else None)
    policy = make_policy(args, cfg, built, payload)
    frames = camera = None
    if args.video is not None:
        from ..sim.camera import TASK_CAMERAS, TaskCamera

        frames, camera = [], TaskCamera(env.model, TASK_CAMERAS[args.task], env.num_envs)
    seed_evaluation(env, args.eval_seed)
    result = evaluate(env, policy, args.episodes, video_frames=frames, camera=camera,
                      desc=f"{args.policy} {args.env} {args.action_dim}D")
    result.update(task=args.task, env=args.env, action_dim=args.action_dim, policy=args.policy,
                  num_envs=args.num_envs, device=env.device, processor=processor_name(env.device), solver=args.solver,
                  geometry=args.geometry, seed=args.seed,
                  eval_seed=args.eval_seed, stochastic=args.stochastic,
                  time_obs=not args.no_time_obs, checkpoint=str(args.checkpoint) if args.checkpoint else None)
    if hasattr(getattr(policy, "agent", None), "cpu_matmul"):  # the SAC products' library that ran
        result["cpu_matmul"] = policy.agent.cpu_matmul
    if isinstance(policy, KMPSearchPolicy):  # what "kmp_search" meant for this result (its settings may change)
        result["search"] = dataclasses.asdict(policy.params)
    result["_frames"] = frames
    return result
