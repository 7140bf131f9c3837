"""Which per-episode draws decide whether the KMP prior (a = 0) seats the peg? 128 episodes."""
import torch, numpy as np
from vkgrl_newton.runtime import configure_warp
configure_warp()
from vkgrl_newton.envs.assembly_env import AssemblyEnv, EnvConfig
from vkgrl_newton.envs.kgrl_action import KGRLActionPath
from vkgrl_newton.prepare.prior import load_or_make_prior
from vkgrl_newton.results.paired import seed_evaluation
torch.set_num_threads(1)
env = AssemblyEnv(EnvConfig(task="PegInsert", family="factory", action_dim=4, num_envs=16, device="cpu", seed=0))
tables, _ = load_or_make_prior("PegInsert", 4, "runs/cache", device="cpu", log=lambda m: None)
path = KGRLActionPath(tables, env)
seed_evaluation(env, 10000)
rows = []
for r in range(8):
    held_p, _ = env.held_pose(); tcp_p, _ = env.tcp_pose()
    in_hand = (held_p - tcp_p)[:, :2].clone()          # world xy of the peg relative to the TCP
    obs_noise = (env.target_frame_pos_w - env.fixed_tip_w)[:, :2].clone()
    for t in range(env.max_episode_length):
        obs, rew, dones, extras = path.step(torch.zeros(16, 4))
    succ = env.last_episode_success_any.clone()
    for i in range(16):
        rows.append((*in_hand[i].tolist(), *obs_noise[i].tolist(), bool(succ[i])))
a = np.array(rows)
np.save("/tmp/diag/prior_fail.npy", a)
s = a[:, 4].astype(bool)
print("episodes", len(a), "success", s.mean())
# the error the prior makes laterally: it aims at the observed target with the TCP, so the peg lands at
# true_hole + obs_noise + in_hand (+ the prior's own mean offset)
err = a[:, 0:2] + a[:, 2:4]
for name, v in (("in_hand x", a[:, 0]), ("in_hand y", a[:, 1]), ("noise x", a[:, 2]), ("noise y", a[:, 3]),
                ("err x", err[:, 0]), ("err y", err[:, 1])):
    print(f"{name:10s} sd {1e3*v.std():.2f} mm | success mean {1e3*v[s].mean():+.2f} sd {1e3*v[s].std():.2f} | fail mean {1e3*v[~s].mean():+.2f} sd {1e3*v[~s].std():.2f}")
bins = np.array([0, 0.5, 1, 1.5, 2, 3, 5, 10]) * 1e-3
d = np.linalg.norm(err + np.array([tables.mean[100, 0].item(), tables.mean[100, 1].item()]), axis=1)
d0 = np.linalg.norm(err, axis=1)
for name, dd in (("|err|", d0), ("|err + m|", d)):
    idx = np.digitize(dd, bins)
    print(name, [(f"<{1e3*bins[k]:.1f}mm", int((idx == k).sum()), round(float(s[idx == k].mean()), 2) if (idx == k).any() else None) for k in range(1, len(bins))])
