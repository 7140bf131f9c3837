"""The training loops: SAC's (sac, kgrl and the vision variants) and rsl-rl PPO's, each read top
to bottom, with the logging, throughput counters and checkpoints they share (`Loop`).

A loop returns None when the run's transitions are done and an exit code when a stop signal
(Ctrl-C, SIGTERM, SIGHUP: signals.stop_signals_as_interrupts) ended it; then the run has been
checkpointed and `--resume` continues it.
"""

from __future__ import annotations

import contextlib
import math
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from ..results.curves import CurveWriter
from ..signals import describe, exit_code

__all__ = ["Loop", "sac_loop", "ppo_loop", "rng_state", "restore_rng", "CURVE_EPISODE_KEYS"]

CURVE_EPISODE_KEYS = ("episode_reward", "success_rate", "success_rate_any", "mean_contact_force",
                      "peak_contact_force", "time_to_first_success_s")  # the env's episode log -> curves.jsonl


class Loop:
    """What a training loop (sac_loop, ppo_loop) works with, and the timings it keeps for the summary."""

    def __init__(self, *, cfg, env, step_fn, agent, counters: dict, writer, curves: CurveWriter, bar, checkpoint,
                 ckpt_path: Path, log, time_obs: bool, env_steps0: int, grad0: int, rollout_policy=None,
                 action_path=None, keep=None):
        self.cfg, self.env, self.agent, self.counters = cfg, env, agent, counters
        self.step_fn = step_fn  # env.step, or the KGRL action path's step
        # the KGRL action path (its query phase is a policy input with the time action); None: delta pose
        self.action_path = action_path
        self.writer, self.curves, self.bar, self.log = writer, curves, bar, log
        self.checkpoint = checkpoint  # checkpoint(pending_update=False, snapshot=None)
        self.ckpt_path, self.time_obs = ckpt_path, time_obs
        # --keep-at: keep(n, snapshot=None) writes the policy at n; the counts still ahead
        self.keep = keep
        self.keep_ahead = [n for n in cfg.keep_at if n > counters["transitions"]]
        # acts instead of the agent in its first prior_rollouts transitions (SACConfig.prior_rollouts_policy)
        self.rollout_policy = rollout_policy
        self.env_steps0, self.grad0 = env_steps0, grad0  # where this session's throughput counts from
        self.env_time = self.update_time = 0.0
        self.t_session = time.perf_counter()
        self.first_transition_unix = time.time()  # a sweep's overhead: scheduled -> first env step (sweep.py)
        self.t_start = time.perf_counter()  # wall time not yet in counters["wall_s"]
        self.status: dict[str, float] = {}  # the progress bar's postfix

    def timed_step(self, actions):
        t = time.perf_counter()
        result = self.step_fn(actions)
        return result, time.perf_counter() - t

    def wall_s(self) -> float:
        return self.counters["wall_s"] + time.perf_counter() - self.t_start

    def bank_wall_time(self) -> None:
        """Move the wall time since the last call into counters (before a checkpoint)."""
        self.counters["wall_s"] += time.perf_counter() - self.t_start
        self.t_start = time.perf_counter()

    def after_step(self, extras: dict) -> None:
        """Count one batched env step; log an ended episode (tensorboard, curves.jsonl, the bar)."""
        counters, writer, env = self.counters, self.writer, self.env
        counters["transitions"] += env.num_envs
        counters["env_steps"] += 1
        if "episode" in extras:
            ep = extras["episode"]
            counters["episodes"] += 1
            step = counters["transitions"]
            writer.add_scalar("episode/reward", ep["episode_reward"], step)
            writer.add_scalar("episode/success_rate", ep["success_rate"], step)
            writer.add_scalar("episode/success_rate_any", ep["success_rate_any"], step)
            writer.add_scalar("episode/mean_contact_force", ep["mean_contact_force"], step)
            writer.add_scalar("episode/peak_contact_force", ep["peak_contact_force"], step)
            if not math.isnan(ep["time_to_first_success_s"]):
                writer.add_scalar("episode/time_to_first_success_s", ep["time_to_first_success_s"], step)
            writer.add_scalar("perf/env_steps_per_s", (counters["env_steps"] - self.env_steps0) * env.num_envs
                              / max(self.env_time, 1e-9), step)
            if self.update_time > 0:
                writer.add_scalar("perf/grad_steps_per_s", (self.agent.num_updates - self.grad0) / self.update_time,
                                  step)
            writer.add_scalar("perf/physics_resets", env.physics_resets_total, step)
            writer.add_scalar("perf/ik_failures", env.ik_failures_total, step)
            writer.add_scalar("perf/contact_overflows", env.contact_overflows_total, step)
            self.curves.append(transitions=step, **{k: float(ep[k]) for k in CURVE_EPISODE_KEYS}, wall_s=self.wall_s())
            self.status.update(success=ep["success_rate"], reward=ep["episode_reward"], force=ep["mean_contact_force"])
        self.bar.update(env.num_envs)
        if self.status:
            self.bar.set_postfix({k: f"{v:.3g}" for k, v in self.status.items()}, refresh=False)

    def keep_missed(self, transitions_per_step: int) -> None:
        """A resumed run's --keep-at counts at or behind its checkpoint whose file is missing (a stop came between
        the step that reached the count and its kept file, or the count is new on --resume): the checkpoint is the
        policy at the first step at or past such a count when that step is its last one (kept now); an older count
        is said, not kept under a wrong name."""
        at = self.counters["transitions"]
        for n in self.cfg.keep_at:
            if n <= at and not self.cfg.kept_path(n).exists():
                if n > at - transitions_per_step:
                    self.keep(n)
                else:
                    self.log(f"note: --keep-at {n} is behind this run's checkpoint ({at} transitions) and was not kept "
                             "before it: not kept")

    def keep_due(self, snapshot: dict | None = None) -> None:
        """Keep the policy at each --keep-at count this step reached (before any checkpoint of the step; a count
        leaves the list once its file is written, so a stop while writing keeps it on resume)."""
        while self.keep_ahead and self.counters["transitions"] >= self.keep_ahead[0]:
            self.keep(self.keep_ahead[0], snapshot)
            self.keep_ahead.pop(0)

    def stopped(self, e: BaseException, snapshot: dict | None = None, pending_update: bool = False) -> int:
        """Ctrl-C / SIGTERM: checkpoint (the run now, or `snapshot`), close the logs, say how to go on."""
        self.bank_wall_time()
        if snapshot is not None:  # the wall time spent since counts, though its partial work is redone
            snapshot["counters"]["wall_s"] = self.counters["wall_s"]
        self.checkpoint(pending_update, snapshot)
        self.bar.close()
        self.writer.close()
        at = (snapshot or {"counters": self.counters})["counters"]["transitions"]
        # the command's one line on a stop, on stderr as every command's (its log may be stdout or silent)
        print(f"train/run.py: {describe(e)}; checkpoint at {at} transitions in {self.ckpt_path} (--resume continues)",
              file=sys.stderr)
        return exit_code(e)


def sac_loop(loop: Loop, payload: dict | None) -> int | None:
    """SAC (sac, kgrl, vision_*): a transition per world per step into the replay buffer, updates as
    SACConfig says. None when done, an exit code when stopped by a signal (checkpointed)."""
    import torch

    from ..envs.evaluation import kgrl_observation, policy_observation
    from ..envs.history import ObservationHistory

    cfg, env, agent, counters = loop.cfg, loop.env, loop.agent, loop.counters
    history = None  # envs.history with --obs-history (made at the first input)
    # Overlapped loop (--overlap): env step k+1 runs in a worker thread while the main thread runs the
    # update due after step k; the action of step k+1 is drawn before that update, i.e. from the
    # policy after update k-1 (a one-update lag). The order of every draw from the agent's and the
    # env's generators is fixed, so a seed gives the same run whatever the threads' timing.
    overlap = (str(env.device) == "cpu") if cfg.overlap is None else cfg.overlap
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="env-step") if overlap else None
    pending_update = bool(payload.get("pending_update", False)) if payload is not None else False
    future = None

    def run_update() -> None:
        t = time.perf_counter()
        losses = agent.update()
        loop.update_time += time.perf_counter() - t
        if counters["env_steps"] % 10 == 0:
            for k, v in losses.items():
                loop.writer.add_scalar(f"train/{k}", v, counters["transitions"])
        loop.status["alpha"] = losses.get("alpha", float("nan"))

    obs = env.get_observations()
    last_ckpt = counters["transitions"] // cfg.checkpoint_every
    if payload is not None:
        loop.keep_missed(env.num_envs)
    not_terminal = torch.zeros(env.num_envs, device=env.tdev)  # the `terminated` flags, all 0
    loop.t_start = time.perf_counter()
    if payload is None:  # resumable from its first moment (a sweep's retry of a killed trial)
        loop.checkpoint()
    try:
        while counters["transitions"] < cfg.total_steps:
            x_raw = kgrl_observation(policy_observation(obs, loop.time_obs), loop.action_path)
            if cfg.obs_history and history is None:
                history = ObservationHistory(env.num_envs, x_raw.shape[-1], agent.action_dim, cfg.obs_history, env.tdev)
            x = history.stack(x_raw, env.step_index) if history is not None else x_raw
            a = agent.explore(x)
            if loop.rollout_policy is not None and agent.num_transitions < agent.cfg.prior_rollouts:
                a = loop.rollout_policy.actions(env, obs)
                if a.shape[-1] < agent.action_dim:  # the time action's a_t = 0: the prior's own pace
                    a = torch.cat([a, a.new_zeros(a.shape[0], agent.action_dim - a.shape[-1])], -1)
            if pool is not None:
                future = pool.submit(loop.timed_step, a)
                if pending_update:  # the update due after the previous step, while this one runs
                    run_update()
                    pending_update = False
                (next_obs, reward, dones, extras), dt = future.result()  # a worker's exception surfaces here
                future = None
            else:
                (next_obs, reward, dones, extras), dt = loop.timed_step(a)
            loop.env_time += dt
            x_next = kgrl_observation(_bootstrap_inputs(next_obs, dones, extras, loop.time_obs), loop.action_path,
                                      final=True)  # (the query where each world's step left it)
            if history is not None:  # this step's (input, action) joins the history the next input carries
                history.push(x_raw, a)
                x_next = history.stack(x_next)  # (a reset world's history is cleared at its next input)
            _store(agent, x, a, reward, x_next, extras,
                   not_terminal, *_privileged_inputs(obs, next_obs, dones, extras))
            obs = next_obs
            loop.after_step(extras)
            loop.keep_due()  # (the policy before the update due after this step, in either loop order)
            if pool is not None:
                pending_update = agent.update_due()  # runs during the next env step
            elif agent.update_due():
                run_update()
            if counters["transitions"] // cfg.checkpoint_every > last_ckpt:
                last_ckpt = counters["transitions"] // cfg.checkpoint_every
                loop.bank_wall_time()
                loop.checkpoint(pending_update)
        if pending_update:  # the last step's update: as many gradient steps as the serial loop
            run_update()
            pending_update = False
    except KeyboardInterrupt as e:
        if future is not None:  # let the worker finish its env step (its transition is dropped)
            with contextlib.suppress(BaseException):
                future.result()
        return loop.stopped(e, pending_update=pending_update)
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
    loop.bank_wall_time()
    loop.checkpoint()
    loop.bar.close()
    return None


def _bootstrap_inputs(next_obs, dones, extras: dict, time_obs: bool):
    """The policy inputs a transition bootstraps from: the next observation, or for a world whose
    episode timed out the observation it ended in (the env has already reset it)."""
    import torch

    from ..envs.evaluation import policy_observation

    x_next = policy_observation(next_obs, time_obs)
    if "final_observations" in extras:  # time-outs bootstrap from the state they ended in
        final = policy_observation(extras["final_observations"], time_obs)
        x_next = torch.where(dones.unsqueeze(-1), final, x_next)
    return x_next


def _privileged_inputs(obs, next_obs, dones, extras: dict) -> tuple:
    """(priv, next_priv) for an asymmetric critic: the `critic` group beyond the `policy` part, of obs
    and of the state each transition bootstraps from (as _bootstrap_inputs); () without the group."""
    if "critic" not in obs.keys():
        return ()
    import torch

    def priv(o):
        return o["critic"][:, o["policy"].shape[-1]:]

    p_next = priv(next_obs)
    if "final_observations" in extras:
        p_next = torch.where(dones.unsqueeze(-1), priv(extras["final_observations"]), p_next)
    return priv(obs), p_next


def _store(agent, x, a, reward, x_next, extras: dict, not_terminal, *priv) -> None:
    """Episodes end by time-out only: nothing is terminal; blown-up worlds' rows are dropped (the env
    has counted them on the host already: no extra sync on the common path). priv: (priv, next_priv)
    of a privileged critic, or nothing."""
    if extras["log"]["/physics_resets"] == 0:
        agent.add(x, a, reward, x_next, not_terminal, *priv)
    else:
        keep = ~extras["physics_resets"]
        agent.add(x[keep], a[keep], reward[keep], x_next[keep], not_terminal[keep], *(p[keep] for p in priv))


def ppo_loop(loop: Loop, payload: dict | None) -> int | None:
    """rsl-rl's PPO (ppo, kgrl_ppo): OnPolicyRunner.learn's loop (num_steps_per_env steps of every
    world, the returns, one PPO update) with this project's logging and checkpoints. A checkpoint
    holds the run at an update's end; a stop in mid-rollout saves the last update's end (the
    partial rollout is collected again on resume). None when done, an exit code when stopped."""
    import copy

    import torch

    cfg, env, agent, counters = loop.cfg, loop.env, loop.agent, loop.counters
    alg = agent.alg
    if agent.cfg.get("check_for_nan", True):  # as OnPolicyRunner: a ValueError naming what holds the NaN
        from rsl_rl.utils import check_nan
    else:
        check_nan = None

    def snapshot() -> dict:
        return {"agent": copy.deepcopy(agent.state_dict()), "counters": dict(counters), "rng": rng_state(env)}

    obs = env.get_observations().to(agent.device)
    alg.train_mode()
    last_ckpt = counters["transitions"] // cfg.checkpoint_every
    if payload is not None:
        loop.keep_missed(env.num_envs * agent.num_steps_per_env)
    loop.t_start = time.perf_counter()
    if payload is None:
        loop.checkpoint()
    at_update = snapshot()
    try:
        while counters["transitions"] < cfg.total_steps:
            with torch.inference_mode():
                for _ in range(agent.num_steps_per_env):
                    actions = alg.act(obs)
                    (obs, rewards, dones, extras), dt = loop.timed_step(actions.to(env.tdev))
                    loop.env_time += dt
                    obs, rewards, dones = obs.to(agent.device), rewards.to(agent.device), dones.to(agent.device)
                    # one host read for the NaN test (rsl-rl's check_nan reads each tensor), its message on a hit
                    if check_nan is not None and bool(torch.stack(
                            [torch.isnan(v).any() for v in (*obs.values(), rewards)]).any()):
                        check_nan(obs, rewards, dones)
                    # episodes end by time-out (extras["time_outs"]: PPO bootstraps them) or by a blow-up
                    # (the env reset and counted that world; PPO takes it as terminal)
                    alg.process_env_step(obs, rewards, dones, extras)
                    loop.after_step(extras)
                alg.compute_returns(obs)
            t = time.perf_counter()
            losses = alg.update()
            agent.iterations += 1
            loop.update_time += time.perf_counter() - t
            step = counters["transitions"]
            for k, v in losses.items():
                loop.writer.add_scalar(f"train/{k}", v, step)
            loop.writer.add_scalar("train/learning_rate", alg.learning_rate, step)
            loop.writer.add_scalar("train/action_std", float(alg.get_policy().output_std.detach().mean()), step)
            loop.status["std"] = float(alg.get_policy().output_std.detach().mean())
            loop.bank_wall_time()
            at_update = snapshot()
            loop.keep_due(at_update)
            if counters["transitions"] // cfg.checkpoint_every > last_ckpt:
                last_ckpt = counters["transitions"] // cfg.checkpoint_every
                loop.checkpoint(snapshot=at_update)
    except KeyboardInterrupt as e:
        return loop.stopped(e, snapshot=at_update)
    loop.checkpoint(snapshot=at_update)
    loop.bar.close()
    return None


def rng_state(env) -> dict:
    import torch

    state = {"torch": torch.get_rng_state(), "env_torch": env.generator.get_state()}
    if str(env.tdev).startswith("cuda"):  # rsl-rl's PPO samples actions and minibatches from the device's generator
        state["cuda"] = torch.cuda.get_rng_state(env.tdev)
    return state


def restore_rng(state: dict, env) -> None:
    import torch

    torch.set_rng_state(state["torch"])
    env.generator.set_state(state["env_torch"])  # (older checkpoints also hold an unused "env_numpy")
    if "cuda" in state and str(env.tdev).startswith("cuda"):
        torch.cuda.set_rng_state(state["cuda"], env.tdev)
