"""Record scripted demonstrations in the simulator: the data the KMP prior of KGRL is fitted to.

`record_demonstrations` runs the scripted inserter (scripted.py) until enough successful episodes
are recorded and returns them as a `DemoSet`: the 6D relative TCP pose eta (thesis eqs. 5.21,
5.26-5.29: position relative to the observed target frame, rotation as log(q_ref^-1 q_tcp)) at
every control step over normalized time s = t / T. Only episodes in which the part was seated
at some step (`success_rate_any`) are kept: a demonstration should show the task done.
Used by `train/collect_demos.py` and by `train/run.py`, which records them itself for KGRL.
"""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from ..kmp.demos import DemoSet
from ..kmp.pose import pose_to_eta, unwrap_rotation_vectors
from .assembly_env import AssemblyEnv
from .scripted import ScriptedInserter

__all__ = ["record_demonstrations"]


def record_demonstrations(env: AssemblyEnv, num_demos: int, seed: int = 0, max_episodes: int = 20,
                          progress: bool = True) -> tuple[DemoSet | None, int]:
    """(demonstrations, episodes run); None when fewer than 2 episodes succeeded.

    The env should be 6D (6D demonstrations serve 4D and 6D priors; 4D tables use their
    x, y, z, yaw marginal). Each demonstration covers one full episode, s = 0..1.
    """
    if num_demos < 2:
        raise ValueError(f"num_demos must be >= 2 (a distribution needs several demonstrations), got {num_demos}")
    policy = ScriptedInserter(seed=seed)
    demos: list[np.ndarray] = []
    episodes = 0
    # a with: closed on a stop too (else its last state is printed after the stop's one line)
    with tqdm(total=num_demos, desc=f"{env.cfg.task} demonstrations", unit="demo", disable=not progress) as bar:
        while len(demos) < num_demos and episodes < max_episodes:
            if bool((env.episode_length_buf != 0).any()):
                env.reset()  # a demonstration starts at s = 0 (after a time-out the env is there already)
            policy.reset(env)
            traj = [_eta(env)]
            while True:
                _, _, _, extras = env.step_pose(*policy.act(env))
                if "episode" in extras:
                    break
                traj.append(_eta(env))
            # the env auto-reset the worlds at the time-out; the last pose is the one before it
            success = env.last_episode_success_any.cpu().numpy()
            traj = np.stack(traj, axis=1)  # (E, T, 6)
            for w in np.nonzero(success)[0]:
                if len(demos) < num_demos:
                    eta = traj[w].copy()
                    eta[:, 3:] = unwrap_rotation_vectors(eta[:, 3:])
                    demos.append(eta)
                    bar.update(1)
            episodes += 1
    if len(demos) < 2:
        return None, episodes
    lengths = np.array([d.shape[0] for d in demos], dtype=np.int64)
    s = np.concatenate([np.linspace(0.0, 1.0, n) for n in lengths])
    demo_set = DemoSet(s=s, eta=np.concatenate(demos), demo_lengths=lengths, task=env.cfg.task,
                       psi_ref=env.task.psi_ref, action_dim=env.cfg.action_dim,
                       source=f"scripted:{env.cfg.family}:seed{seed}")
    return demo_set, episodes


def _eta(env: AssemblyEnv) -> np.ndarray:
    tcp_p, tcp_q = env.tcp_pose()
    eta = pose_to_eta(tcp_p.double(), tcp_q.double(), env.target_frame_pos_w.double(), env.task.psi_ref)
    return eta.cpu().numpy()
