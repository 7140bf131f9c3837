"""A run from its configuration to its metrics.json: build, log, loop, evaluate, write.

    from vkgrl_newton.run import RunConfig, train
    rc = train(config)            # config: run.resolve's, or a RunConfig of your own

A run directory holds config.json, curves.jsonl, tb/, checkpoints/last.pt and metrics.json
(train/run.py's docstring). A stop signal at any phase keeps what was finished (the cache's
entries whole, the checkpoint of what was trained), prints one line on stderr naming the phase
and what it kept (docs/cli.md, Signals) and returns the signal's exit code; a finished run's
earlier result is kept beside a longer one.
"""

from __future__ import annotations

import hashlib
import json
import sys
import time

from .._io import atomic_write_text, strict_json
from ..results.curves import CurveWriter
from ..results.paired import cached_evaluation, format_gain, paired_gain, seed_evaluation, world_outcomes
from ..runtime import processor_name
from ..signals import describe, exit_code, stop_line, where
from .build import Built, build_action_path, build_agent, build_encoder, build_env, build_probe, build_rollout_policy
from .config import SEARCH_SETTINGS, RunConfig
from .loops import Loop, ppo_loop, restore_rng, rng_state, sac_loop

__all__ = ["train", "final_evaluation", "prior_evaluation_key", "paired_line", "run_meta_with_files"]


def train(cfg: RunConfig, payload: dict | None = None, torch_threads: int | None = None, log=None) -> int:
    """Train (or, with the checkpoint's `payload`, continue) the run of `cfg`; 0 when done, 2 when its
    prerequisites cannot be made, a signal's exit code when stopped."""
    import torch
    from tqdm import tqdm

    if torch_threads:
        torch.set_num_threads(torch_threads)
    torch.manual_seed(cfg.seed)
    log = log or tqdm.write
    log(f"train/run.py: {cfg.method} {cfg.task} {cfg.env} {cfg.action_dim}D on device {cfg.device} -> {cfg.run_dir}")
    built = _build(cfg, log)
    if isinstance(built, int):
        return built
    meta = run_meta_with_files(cfg, built)
    if payload is not None:
        for key in ("prior", "vision"):
            if key in payload["meta"] and payload["meta"][key] != meta.get(key):
                raise SystemExit(f"train/run.py: --resume: the run's {key} was {payload['meta'][key]}, "
                                 f"now {meta.get(key)}")
    counters = {"transitions": 0, "env_steps": 0, "episodes": 0, "wall_s": 0.0}
    made_dir = not cfg.run_dir.exists()
    loop = None
    try:
        if payload is not None:
            built.agent.load_state_dict(payload["agent"])
            counters.update(payload["counters"])
            restore_rng(payload["rng"], built.env)
            log(f"resumed {cfg.run_dir} at {counters['transitions']} transitions")
        else:
            cfg.run_dir.mkdir(parents=True, exist_ok=True)
            atomic_write_text(cfg.run_dir / "config.json", strict_json({**meta, **cfg.plan(), "device": cfg.device},
                                                                       indent=2))
        loop = _make_loop(cfg, built, meta, counters, payload, log)
        rc = (ppo_loop if cfg.method_row.uses_ppo else sac_loop)(loop, payload)
        if rc is not None:  # stopped by a signal: checkpointed, nothing evaluated
            return rc
        return _finish(cfg, built, meta, loop, payload, log)
    except KeyboardInterrupt as e:  # outside the loops' and the evaluation's own handling (starting, writing)
        if loop is not None:
            loop.bar.close()  # (before the line: else printed after it)
            loop.writer.close()
        if cfg.ckpt_path.is_file():
            then = f"the checkpoint {cfg.ckpt_path} is kept (--resume continues)"
        else:  # stopped before its first checkpoint: its files would only make the next run refuse the directory
            _remove_unstarted_run(cfg.run_dir, made_dir)
            then = "stopped before its first checkpoint: what it wrote is removed; run again to start it"
        print(stop_line("train/run.py", e, then), file=sys.stderr)
        return exit_code(e)


def _remove_unstarted_run(run_dir, made_dir: bool) -> None:
    """A fresh run's files (resolve refused a directory that held any of them), and its directory if it made it."""
    import shutil

    from .config import RUN_FILES

    for name in RUN_FILES:
        path = run_dir / name
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        elif path.exists():
            path.unlink()
    if made_dir and run_dir.is_dir() and not any(run_dir.iterdir()):
        run_dir.rmdir()


def _build(cfg: RunConfig, log) -> Built | int:
    """The run's objects (run.build), or the exit code when the vision prerequisites cannot be made."""
    try:
        try:
            encoder = build_encoder(cfg, log)
            probe = build_probe(cfg, encoder, log)  # (--vision-probe-obs; else None)
        except (FileExistsError, FileNotFoundError, ValueError) as e:
            print(f"train/run.py: the vision prerequisites: {e}", file=sys.stderr)
            return 2
        env = build_env(cfg, encoder, probe=probe)
        action_path, demos_path = build_action_path(cfg, env, log)
        agent = build_agent(cfg, env)
    except KeyboardInterrupt as e:  # the prepare phases say what they kept (signals.phase); nothing of the run yet
        print(stop_line("train/run.py", e, "nothing of the run is written yet; run again to continue"), file=sys.stderr)
        return exit_code(e)
    return Built(encoder, env, action_path, agent, demos_path)


def run_meta_with_files(cfg: RunConfig, built: Built) -> dict:
    """cfg.meta() plus exactly what the run learns from: the prior's file and parameters, the VAE's hash."""
    meta = cfg.meta()
    if built.action_path is not None:
        from ..prepare.prior import prior_record

        meta["prior"] = prior_record(built.action_path.tables, built.demos_path, **cfg.prior_table_changes)
    if built.encoder is not None:
        from ..cache import file_sha256

        meta["vision"]["vae_sha256"] = file_sha256(meta["vision"]["vae"])
        if cfg.vision_probe_obs:  # the probe it read the latent through (made by build_env)
            meta["vision"]["probe"] = str(cfg.probe_path())
            meta["vision"]["probe_sha256"] = file_sha256(cfg.probe_path())
    return meta


def _make_loop(cfg: RunConfig, built: Built, meta: dict, counters: dict, payload: dict | None, log) -> Loop:
    from torch.utils.tensorboard import SummaryWriter
    from tqdm import tqdm

    from ..agents.checkpoint import save_checkpoint

    agent, env = built.agent, built.env

    def checkpoint(pending_update: bool = False, snapshot: dict | None = None) -> None:
        """The run as it is now, or as `snapshot` (agent, counters, rng) holds it."""
        snapshot = snapshot or {"agent": agent.state_dict(), "counters": counters, "rng": rng_state(env)}
        save_checkpoint(cfg.ckpt_path, {"meta": meta, "counters": dict(snapshot["counters"]),
                                        "agent": snapshot["agent"],
                                        "pending_update": pending_update,  # overlapped loop: due, not yet run
                                        "rng": snapshot["rng"], "plan": cfg.plan()})

    def keep(n: int, snapshot: dict | None = None) -> None:
        """--keep-at n: the policy now (or `snapshot`'s), as a checkpoint without the replay buffer."""
        state = (snapshot["agent"] if snapshot is not None else
                 agent.state_dict(include_buffer=False) if hasattr(agent, "buffer") else agent.state_dict())
        at = dict((snapshot or {"counters": counters})["counters"])
        save_checkpoint(cfg.kept_path(n), {"meta": meta, "counters": at, "agent": state, "pending_update": False,
                                           "rng": rng_state(env), "plan": cfg.plan()})
        log(f"kept the policy at {at['transitions']} transitions: {cfg.kept_path(n)} (--keep-at {n})")

    # a resumed run drops what was logged after its checkpoint (as curves.jsonl does): the events at
    # the checkpoint's own count were logged before it was written, so they stay (an update pending at
    # the checkpoint, or an interrupted final evaluation, logs a second point at that count on resume)
    writer = SummaryWriter(str(cfg.run_dir / "tb"), purge_step=counters["transitions"] + 1 if payload else None)
    curves = CurveWriter(cfg.run_dir, resume_at=counters["transitions"] if payload else None)
    if built.action_path is not None and cfg.method_row.takes_recipe:
        log(f"KGRL recipe {cfg.kgrl_recipe}: reach floors x, y {cfg.reach_floor_mm:g} mm, "
            f"z {cfg.reach_floor_z_mm:g} mm (--kgrl-recipe, docs/cli.md)")
        if cfg.sac.prior_rollouts >= cfg.total_steps:
            log(f"note: the first {cfg.sac.prior_rollouts} transitions act with the prior "
                f"(--sac prior_rollouts), all of this run's {cfg.total_steps}: every training episode is the "
                "prior's; the learner acts only in the final evaluation")
    rollout_policy = build_rollout_policy(cfg, built.action_path)
    if getattr(cfg.sac, "prior_rollouts_policy", "prior") == "scripted":
        kept = (f"kept in a second buffer sampled at prior_ratio={cfg.sac.prior_ratio:g}"
                if cfg.sac.prior_ratio > 0 else "in the one replay buffer (prior_ratio=0)")
        log(f"the first {cfg.sac.prior_rollouts} transitions act with the scripted demonstrator through "
            f"the SAC action space (--sac prior_rollouts_policy=scripted), {kept}")
    # the bar last: a stop before the Loop holds it would leave it open, printed after the stop's line
    bar = tqdm(total=cfg.total_steps, initial=counters["transitions"], unit="tr", disable=not cfg.progress,
               desc=f"{cfg.method} {cfg.task} {cfg.env} {cfg.action_dim}D")
    return Loop(cfg=cfg, env=env, step_fn=built.step_fn, agent=agent, counters=counters, writer=writer, curves=curves,
                bar=bar, checkpoint=checkpoint, ckpt_path=cfg.ckpt_path, log=log, time_obs=cfg.time_obs,
                env_steps0=counters["env_steps"], grad0=agent.num_updates, rollout_policy=rollout_policy,
                action_path=built.action_path, keep=keep)


def _summary(loop: Loop, payload: dict | None) -> dict:
    counters, env, agent = loop.counters, loop.env, loop.agent
    return {"transitions": counters["transitions"], "env_steps": counters["env_steps"],
            "episodes": counters["episodes"], "gradient_steps": agent.num_updates, "wall_s": counters["wall_s"],
            # whole loop (env, acting, buffer, updates) vs the env and action path alone
            "loop_transitions_per_s": (counters["env_steps"] - loop.env_steps0) * env.num_envs
            / max(time.perf_counter() - loop.t_session, 1e-9),
            "train_env_steps_per_s": (counters["env_steps"] - loop.env_steps0) * env.num_envs
            / max(loop.env_time, 1e-9),
            "grad_steps_per_s": ((agent.num_updates - loop.grad0) / loop.update_time if loop.update_time > 0
                                 else float("nan")),
            "physics_resets": env.physics_resets_total, "ik_failures": env.ik_failures_total,
            "contact_overflows": env.contact_overflows_total, "first_transition_unix": loop.first_transition_unix,
            "resumed": payload is not None}


def _finish(cfg: RunConfig, built: Built, meta: dict, loop: Loop, payload: dict | None, log) -> int:
    """The final evaluation, then metrics.json (a finished run's earlier result kept beside it)."""
    summary = _summary(loop, payload)
    writer, counters = loop.writer, loop.counters
    metrics: dict = {}
    try:
        if cfg.eval_episodes:
            metrics = final_evaluation(cfg, built.env, built.agent, built.action_path)
            for k in ("success_rate", "mean_contact_force", "time_to_first_success_s", "mean_episode_reward"):
                writer.add_scalar(f"eval/{k}", metrics[k], counters["transitions"])
            if "prior_eval" in metrics:
                writer.add_scalar("eval/prior_success_rate", metrics["prior_eval"]["success_rate"],
                                  counters["transitions"])
    except KeyboardInterrupt as e:  # the checkpoint holds the whole run: --resume evaluates it again
        writer.close()
        print(f"train/run.py: {describe(e)} during the final evaluation{where(e)}; the trained checkpoint "
              f"{cfg.ckpt_path} is kept (--resume evaluates)", file=sys.stderr)
        return exit_code(e)
    writer.close()
    result = {**metrics, **meta, "device": built.env.device, "processor": processor_name(built.env.device),
              "checkpoint": str(cfg.ckpt_path), "training": summary}
    result.pop("sac", None)
    result.pop("ppo", None)
    if hasattr(built.agent, "cpu_matmul"):  # the SAC products' library that ran (config.json: the SACConfig's)
        result["cpu_matmul"] = built.agent.cpu_matmul
    _write_results(cfg, meta, result, log)
    shown = {k: result[k] for k in ("success_rate", "mean_contact_force", "time_to_first_success_s",
                                    "mean_episode_reward") if k in result}
    log(f"done: {strict_json(shown)} -> {cfg.run_dir / 'metrics.json'}")
    if "paired_gain" in result:
        log(paired_line(result))
    return 0


def _write_results(cfg: RunConfig, meta: dict, result: dict, log) -> None:
    run_dir = cfg.run_dir
    metrics_path = run_dir / "metrics.json"
    if metrics_path.exists():  # a finished run trained further: its earlier result stays beside the new one
        earlier = json.loads(metrics_path.read_text()).get("training", {}).get("transitions", "earlier")
        for name in ("metrics", "config"):  # config.json: the plan (total_steps) it was run to
            aside = run_dir / f"{name}_at_{earlier}.json"
            if not aside.exists():
                (run_dir / f"{name}.json").rename(aside)
                log(f"the earlier {name}.json -> {aside}")
    # the plan the run was finished to (a resume may have changed --total-steps or the evaluation)
    atomic_write_text(run_dir / "config.json", strict_json({**meta, **cfg.plan(), "device": cfg.device}, indent=2),
                      overwrite=True)
    atomic_write_text(metrics_path, strict_json(result, indent=2), overwrite=True)  # the run's own file


def final_evaluation(cfg: RunConfig, env, agent, action_path) -> dict:
    """The trained policy (deterministic) on the evaluation episodes of the eval seed; a KGRL run's
    prior (a = 0) on the same episodes ("prior_eval"), and the paired gain of the policy over it."""
    from ..envs.evaluation import AgentPolicy, KMPPriorPolicy, evaluate

    seed_evaluation(env, cfg.eval_seed)
    policy = AgentPolicy(agent, action_path, cfg.time_obs, obs_history=cfg.obs_history)
    metrics = evaluate(env, policy, cfg.eval_episodes, progress=cfg.progress, desc="final evaluation")
    metrics["eval_seed"] = cfg.eval_seed
    if action_path is not None:
        def evaluate_prior() -> dict:
            seed_evaluation(env, cfg.eval_seed)
            return evaluate(env, KMPPriorPolicy(action_path), cfg.eval_episodes, progress=cfg.progress,
                            desc="the prior, same episodes")

        prior, _ = cached_evaluation(cfg.cache_dir, prior_evaluation_key(cfg, env, action_path), evaluate_prior,
                                     log=print)
        metrics["prior_eval"] = {k: v for k, v in prior.items() if k != "per_episode"}
        metrics["prior_eval"]["per_episode"] = [{k: e[k] for k in ("world_success", "world_contact_force")}
                                                for e in prior["per_episode"]]
        metrics["paired_gain"] = {
            "success_rate": paired_gain(world_outcomes(metrics), world_outcomes(prior), seed=cfg.eval_seed),
            "mean_contact_force": paired_gain(world_outcomes(metrics, "world_contact_force"),
                                              world_outcomes(prior, "world_contact_force"), seed=cfg.eval_seed)}
    return metrics


def paired_line(metrics: dict) -> str:
    """One line: the policy's success, its a = 0's on the same episodes (the prior, or the base controller that
    --kgrl-base names), and the paired gain."""
    g = metrics["paired_gain"]["success_rate"]
    base = metrics.get("kgrl_base", "prior")
    a0 = "the prior" if base == "prior" else f"its a = 0 (the {base} controller)"
    return (f"success {metrics['success_rate']:.3f}, {a0} {metrics['prior_eval']['success_rate']:.3f} on the same "
            f"{g['n_pairs']} episodes: " + format_gain("gain", g))


def prior_evaluation_key(cfg: RunConfig, env, action_path) -> dict:
    """Every input of the evaluation of a = 0 on the run's evaluation episodes (results.paired.cached_evaluation): the
    same for every training seed and variant of the configuration that leaves a = 0 alone. With --kgrl-base a = 0 is
    the base controller, which steers through the null space (its gain: the reach floors); centre_latent's episodes
    also depend on the VAE and the probe it reads the camera through. --force-obs draws its noise from the generator
    of the episodes' resets."""
    key = {"what": "kgrl prior evaluation", "task": cfg.task, "env": cfg.env, "action_dim": cfg.action_dim,
           "num_envs": env.num_envs, "device": str(env.device), "geometry": cfg.geometry,
           "eager_physics": bool(cfg.eager_physics), "vision_latent_dim": env.cfg.vision_latent_dim,
           "eval_seed": cfg.eval_seed, "eval_episodes": cfg.eval_episodes,
           "prior_mean_sha256": hashlib.sha256(action_path.tables.mean.numpy().tobytes()).hexdigest(),
           "kgrl_base": cfg.kgrl_base}
    if cfg.force_obs:  # its noise comes from the generator that draws the episodes' resets
        key["force_obs"] = True
    if cfg.kgrl_base != "prior":  # a base steers through the null space: the gain (the reach floors) decides it too
        key["prior_gain_sha256"] = hashlib.sha256(action_path.tables.gain.numpy().tobytes()).hexdigest()
    for name in SEARCH_SETTINGS:  # the blind base's spiral search
        if getattr(cfg, name) is not None:
            key[name] = getattr(cfg, name)
    if cfg.kgrl_base == "centre_latent":
        from ..cache import file_sha256

        key.update(vae_sha256=file_sha256(cfg.vae_path()), probe_sha256=file_sha256(cfg.probe_path()))
    return key
