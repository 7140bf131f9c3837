"""Run a policy in the assembly env and write the thesis metrics as JSON.

    python train/evaluate.py --task PegInsert --env factory --action-dim 4 --policy scripted \
        --num-envs 16 --episodes 2 --json runs/eval/peg_factory_4d_scripted.json
    python train/evaluate.py --checkpoint runs/train/PegInsert_kgrl_factory_4d_seed0/checkpoints/last.pt \
        --episodes 2 --video runs/eval/kgrl.gif

Policies: `scripted` (privileged demonstrator, absolute TCP poses through `step_pose`),
`scripted_delta` (the same demonstrator through the SAC action space: what a SAC run's
`--sac prior_rollouts_policy=scripted` rollouts are), `random`
(uniform in [-1, 1]^D) and `zero` (both through the SAC action path `step`), `kmp_prior` (the
KMP prior alone, zeta = 0, fitted as train/run.py does), `kmp_search` (the prior plus a blind spiral
search once the part is blocked, from the observation alone, in a null space with reach floors of its
own: envs.evaluation.KMPSearchPolicy, a baseline of what the KGRL action space holds). `--checkpoint` evaluates a trained
agent deterministically (`--stochastic`: with samples of its actions, as in training); task, method, family, action space and time ablation come from the
checkpoint. Metrics per episode (all worlds end together): success at the episode's last step
(`success_rate`), success at any step (`success_rate_any`), mean contact force (thesis eq. 6.1,
N), peak contact force, time to first success (s, over the episodes that reached it), episode
reward; plus env steps per second and the number of physics resets. `--video` records the task
camera of the first worlds as a GIF. Existing output files are never overwritten.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# light modules only up to the argument checks (no torch, Warp or Newton): --help and argument errors
# answer at once; the heavy modules load in main() once the arguments are checked
from vkgrl_newton._io import atomic_write_text, strict_json  # noqa: E402
from vkgrl_newton.cache import check_run_files  # noqa: E402
from vkgrl_newton.cli_types import device_name, positive_int  # noqa: E402
from vkgrl_newton.results.paired import EVAL_SEED, seed_evaluation  # noqa: E402
from vkgrl_newton.runtime import parse_cli  # noqa: E402
from vkgrl_newton.signals import run_cli  # noqa: E402
from vkgrl_newton.tasks import ACTION_DIMS, FAMILIES, GEOMETRIES, SOLVERS, TASKS, geometry_error  # noqa: E402

POLICIES = ("scripted", "scripted_delta", "random", "zero", "kmp_prior", "kmp_search")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", default="PegInsert", choices=sorted(TASKS))
    ap.add_argument("--env", default="factory", choices=FAMILIES)
    ap.add_argument("--action-dim", type=int, default=6, choices=ACTION_DIMS)
    ap.add_argument("--policy", default="scripted", choices=POLICIES)
    ap.add_argument("--checkpoint", type=Path, default=None, help="a train/run.py checkpoint (replaces --policy)")
    ap.add_argument("--stochastic", action="store_true",
                    help="with --checkpoint: act with samples of the policy (as in training) instead of its mean; "
                         "the draws follow --seed")
    ap.add_argument("--num-envs", type=positive_int, default=16)
    ap.add_argument("--episodes", type=positive_int, default=2)
    ap.add_argument("--seed", type=int, default=0, help="the env's construction and the scripted/random policies' draws")
    ap.add_argument("--eval-seed", type=int, default=EVAL_SEED,
                    help="seeds the evaluation episodes, as train/run.py's --eval-seed: two policies evaluated with one "
                         "eval seed (and the same task, env, action space and worlds) see identical initial states "
                         "(default %(default)s)")
    ap.add_argument("--device", default=None, type=device_name, help="cpu or cuda:0 (default: cuda:0 when present)")
    ap.add_argument("--eager-physics", action="store_true",
                    help="launch the physics kernels one by one instead of one captured graph per control step "
                         "(bitwise the same results, slower: the reference)")
    ap.add_argument("--solver", default="mujoco", choices=SOLVERS)
    ap.add_argument("--geometry", default=None, choices=GEOMETRIES,
                    help="GearMesh/NutThread collision geometry (mesh: tooth/thread meshes, SDFs on CUDA); "
                         "default: the checkpoint's, else primitives (given, it evaluates a policy on the other one)")
    ap.add_argument("--no-time-obs", action="store_true", help="kmp_prior / checkpoint: policy input without time")
    ap.add_argument("--cache-dir", type=Path, default=Path("runs/cache"), help="kmp_prior, kmp_search: demonstrations, tables")
    ap.add_argument("--demos", type=Path, default=None, help="kmp_prior, kmp_search: your own demonstrations")
    ap.add_argument("--kmp-reference", default="gmr", choices=("gmr", "empirical"),
                    help="kmp_prior, kmp_search: the KMP's reference distribution (as train/run.py; a checkpoint's own wins)")
    ap.add_argument("--json", type=Path, default=None, help="output file (never overwritten)")
    ap.add_argument("--video", type=Path, default=None, help="GIF of the task camera (first 4 worlds, tiled)")
    args = parse_cli(ap, argv, device=True)
    for name in ("json", "video"):
        out = getattr(args, name)
        if out is not None and out.exists():
            ap.error(f"--{name} {out} exists; choose another path (results are never overwritten)")

    if args.stochastic and args.checkpoint is None:
        ap.error("--stochastic samples a trained policy's actions: give --checkpoint")
    payload = None
    if args.checkpoint is not None:
        from vkgrl_newton.agents.checkpoint import load_checkpoint

        try:
            payload = load_checkpoint(args.checkpoint)
        except (FileNotFoundError, ValueError) as e:
            ap.error(f"--checkpoint: {e}")
        meta = payload["meta"]
        words = argv if argv is not None else sys.argv[1:]
        given = {a.dest for a in ap._actions for o in a.option_strings
                 if any(w == o or w.startswith(o + "=") for w in words)}
        for name in ("task", "env", "action_dim"):  # the checkpoint says what it is; a different ask is refused
            if name in given and getattr(args, name) != meta[name]:
                ap.error(f"--{name.replace('_', '-')} {getattr(args, name)}: the checkpoint is a {meta['task']} "
                         f"{meta['env']} {meta['action_dim']}D policy; leave --task/--env/--action-dim out with "
                         "--checkpoint")
        args.task, args.env, args.action_dim = meta["task"], meta["env"], meta["action_dim"]
        args.no_time_obs = not meta["time_obs"]
        args.policy = meta["method"]
        if args.geometry is None:
            args.geometry = meta.get("geometry", "primitives")
        if "prior" in meta and args.demos is None:  # the prior the run learned with (--demos overrides)
            try:
                check_run_files(meta, demos=meta["prior"]["demos"])
            except (FileNotFoundError, ValueError) as e:
                ap.error(f"--checkpoint: {e} (--demos FILE evaluates with another prior)")
            args.demos = Path(meta["prior"]["demos"])
    if args.geometry is None:
        args.geometry = "primitives"

    import torch

    from vkgrl_newton.envs.evaluation import (AgentPolicy, KMPPriorPolicy, KMPSearchPolicy, RandomPolicy,
                                                ScriptedDeltaPolicy, ScriptedPolicy, ZeroPolicy, evaluate, write_video)
    from vkgrl_newton.envs.assembly_env import AssemblyEnv, EnvConfig
    from vkgrl_newton.sim.scene import SimConfig

    torch.set_num_threads(1)

    vision = payload["meta"].get("vision") if payload is not None else None
    encoder = None
    if vision is not None:  # a vision_* run: the same frozen encoder it trained with
        from vkgrl_newton.vision.vae import FrozenEncoder, load_vae

        try:
            check_run_files(payload["meta"], vae=vision["vae"])
            vae, _ = load_vae(vision["vae"], expect={"task": args.task})
        except (FileNotFoundError, ValueError) as e:
            ap.error(f"--checkpoint: the run's VAE: {e}")
        encoder = FrozenEncoder(vae)
    if geometry_error(args.task, args.geometry):
        ap.error(f"--{geometry_error(args.task, args.geometry)}")
    cfg = EnvConfig(task=args.task, family=args.env, action_dim=args.action_dim, num_envs=args.num_envs,
                    device=args.device, seed=args.seed, sim=SimConfig(solver=args.solver, geometry=args.geometry),
                    vision_latent_dim=encoder.latent_dim if encoder is not None else 0, graph=not args.eager_physics)
    env = AssemblyEnv(cfg)
    if encoder is not None:
        from vkgrl_newton.envs.camera_latent import CameraLatent

        env.attach_vision(CameraLatent(env, encoder))
    action_path = None
    if args.policy in ("kmp_prior", "kmp_search", "kgrl", "vision_kgrl", "kgrl_ppo"):
        from vkgrl_newton.envs.kgrl_action import KGRLActionPath

        from vkgrl_newton.prepare.prior import load_or_make_prior
        prior = payload["meta"].get("prior", {}) if payload is not None else {}
        tables, _ = load_or_make_prior(args.task, args.action_dim, args.cache_dir, demos=args.demos, device=args.device,
                                       geometry=args.geometry, reference=prior.get("reference", "gmr") if prior else args.kmp_reference,
                                       **{k: prior[k] for k in ("lam", "beta", "l") if k in prior})
        if args.policy != "kmp_search":  # (the search builds its own, with its reach floors)
            action_path = KGRLActionPath(tables, env, reach_floor=1e-3 * prior.get("reach_floor_mm", 0.0),
                                         reach_floor_z=1e-3 * prior.get("reach_floor_z_mm", 0.0))
    if payload is not None:
        meta = payload["meta"]
        if "ppo" in meta:  # run.py --method ppo / kgrl_ppo
            from vkgrl_newton.agents.ppo import PPOAgent

            agent = PPOAgent(env, meta["ppo"], device=str(env.tdev))
        else:
            from vkgrl_newton.agents.sac import SAC, SACConfig

            agent = SAC(meta["obs_dim"], meta["action_dim"], SACConfig(**meta["sac"]), device=env.tdev, seed=args.seed)
        agent.load_state_dict(payload["agent"])
        torch.manual_seed(args.seed)  # PPO samples from torch's global generator, SAC from its own (seed)
        policy = AgentPolicy(agent, action_path, time_obs=meta["time_obs"], deterministic=not args.stochastic)
    else:
        policy = {"scripted": lambda: ScriptedPolicy(seed=args.seed), "random": lambda: RandomPolicy(seed=args.seed),
                  "scripted_delta": lambda: ScriptedDeltaPolicy(seed=args.seed),
                  "zero": ZeroPolicy, "kmp_prior": lambda: KMPPriorPolicy(action_path),
                  "kmp_search": lambda: KMPSearchPolicy.with_floors(tables, env)}[args.policy]()

    frames = camera = None
    if args.video is not None:
        from vkgrl_newton.sim.camera import TASK_CAMERAS, TaskCamera

        frames, camera = [], TaskCamera(env.model, TASK_CAMERAS[args.task], env.num_envs)
    seed_evaluation(env, args.eval_seed)
    result = evaluate(env, policy, args.episodes, video_frames=frames, camera=camera,
                      desc=f"{args.policy} {args.env} {args.action_dim}D")
    result.update(task=args.task, env=args.env, action_dim=args.action_dim, policy=args.policy,
                  num_envs=args.num_envs, device=env.device, solver=args.solver, geometry=args.geometry, seed=args.seed,
                  eval_seed=args.eval_seed, stochastic=args.stochastic,
                  time_obs=not args.no_time_obs, checkpoint=str(args.checkpoint) if args.checkpoint else None)
    if isinstance(policy, KMPSearchPolicy):  # what "kmp_search" meant for this result (its settings may change)
        import dataclasses

        result["search"] = dataclasses.asdict(policy.params)
    print(strict_json({k: v for k, v in result.items() if k != "per_episode"}, indent=2))
    print(f"{result['episodes']} episodes: {args.num_envs} worlds x {args.episodes} per world")
    if args.json is not None:
        atomic_write_text(args.json, strict_json(result, indent=2))  # FileExistsError rather than overwrite
    if frames:
        write_video(args.video, frames)
        print(f"wrote {args.video} ({len(frames)} frames)")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main, "train/evaluate.py"))
