"""The camera controller's own frames, for a near-hole probe that is right where it steers (--vision-probe-fit
closed_loop, issue 40).

The image-set probe (prepare.vision.load_or_make_probe) is fitted on the frames of the VAE's image set: the scripted
demonstrator with command noise and random actions. The camera controller (--kgrl-base centre_latent's a = 0,
envs.evaluation.base_controller) steers by it where those frames are few: blocked on the fixed part, a millimetre or
two off the hole. There its error on world x was 0.94 mm RMSE (PegInsert, 128 episodes), against 0.55 mm on the image
set's held-out frames (docs/results/probe_closed_loop_40). `collect_closed_loop_frames` runs that controller, steering
by the image-set probe, on episodes of their own (CLOSED_LOOP_SEED, never the studies' eval seed) and returns every
control step's latent and privileged geometry; the probe is then fitted on the image set and these frames together
(the states the controller visits labelled in simulation, as DAgger aggregates the learner's own states).
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["CLOSED_LOOP_SEED", "CLOSED_LOOP_ROUNDS", "collect_closed_loop_frames"]

# the episodes' eval seed (results.paired.seed_evaluation): not 10 000, every study's evaluation episodes
CLOSED_LOOP_SEED = 20_000
CLOSED_LOOP_ROUNDS = 8  # x 16 worlds: 128 episodes, ~19 000 frames (~5 min on one core here)


@torch.no_grad()
def collect_closed_loop_frames(task: str, encoder, probe, cache_dir, num_envs: int = 16,
                               rounds: int = CLOSED_LOOP_ROUNDS, eval_seed: int = CLOSED_LOOP_SEED, env=None,
                               tables=None, log=print, progress: bool = True) -> dict:
    """The camera controller (base_controller "centre_latent" in the ceiling's floored null space, Factory 4D, the
    task's cached prior) steering by `probe` (vision.probe.ProbeMLP) over `encoder`'s latent, on `rounds` x worlds
    episodes of `eval_seed`. Returns float64 arrays, one row per world per control step, read before the step:
    "z" (n, d_z) the latent, "geometry" (n, 13) vision.dataset.GEOMETRY_COLUMNS (held part, fixed tip, the optical
    frame), "round" (n,) int, and "success" (rounds * worlds,) bool per episode. `env`: an AssemblyEnv to use
    (tests share theirs; its vision slot is replaced by this encoder's and the probe's); `tables`: the prior's KMP
    tables to use (None: the task's cached Factory 4D prior, prepare.prior.load_or_make_prior)."""
    from tqdm import tqdm

    from ..envs.assembly_env import AssemblyEnv, EnvConfig
    from ..envs.camera_latent import LATERAL_DIM, CameraLatent
    from ..envs.evaluation import KMPCentrePolicy, base_controller, task_search_params
    from ..results.paired import seed_evaluation
    from .prior import load_or_make_prior

    device = str(encoder.fc_mu.weight.device)
    width = encoder.latent_dim + LATERAL_DIM
    if env is None:
        env = AssemblyEnv(EnvConfig(task=task, family="factory", action_dim=4, num_envs=num_envs, device=device,
                                    seed=0, vision_latent_dim=width))
    elif env.cfg.vision_latent_dim != width:
        raise ValueError(f"collect_closed_loop_frames: the env's vision slot is {env.cfg.vision_latent_dim} wide, "
                         f"the latent and the probe's estimate need {width}")
    env.attach_vision(CameraLatent(env, encoder, probe=probe))
    if tables is None:
        tables, _ = load_or_make_prior(task, 4, cache_dir, device=str(env.tdev), log=log, progress=progress)
    path = KMPCentrePolicy.floored_path(tables, env, task_search_params(task))
    policy = base_controller("centre_latent", path, task)
    camera = env.vision_source.camera
    z, geometry, round_of, success = [], [], [], []
    seed_evaluation(env, eval_seed)
    obs = env.get_observations()
    bar = tqdm(total=rounds * env.max_episode_length, disable=not progress, desc="closed-loop frames", unit="step")
    for k in range(rounds):
        if bool((env.episode_length_buf != 0).any()):  # a world that blew up was reset alone: its clock is off the
            env.reset()  # others', and a round must be one episode in every world (the rest of this seed's draws move)
            obs = env.get_observations()
        while True:
            latent = env.current_vision_latent()[:, :-LATERAL_DIM]
            hand = env.hand_pose()
            z.append(latent.double().cpu())
            geometry.append(torch.cat((env.held_pose()[0], env.fixed_tip_w, camera.optical_poses_w(*hand)),
                                      -1).double().cpu())
            round_of.append(torch.full((env.num_envs,), k))
            obs, _, _, extras = policy.step(env, obs)
            bar.update()
            if "episode" in extras:  # the time-out ends every world's episode together (a blown world's alone: NaN)
                # (NaN: a world that blew up mid-episode, not counted: not a success)
                success.append(np.asarray(extras["episode"]["world_success"], np.float64) == 1.0)
                break
    bar.close()
    out = {"z": torch.cat(z).numpy(), "geometry": torch.cat(geometry).numpy(), "round": torch.cat(round_of).numpy(),
           "success": np.concatenate(success)}
    log(f"closed-loop frames: {len(out['z'])} from {rounds * env.num_envs} episodes of eval seed {eval_seed}, the "
        f"camera controller seated {int(out['success'].sum())}")
    return out

