"""The asymmetric (privileged) critic: the critics read the actor's observation plus the env's privileged
state, the actor never does (checked on the tensors each network receives); the env's `critic` group
against a float64 computation of the same state; the run's option and its refusals."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from vkgrl_newton.agents.sac import SAC, CriticEnsemble, Actor
from vkgrl_newton.agents.sac_config import make_sac_config

OBS, ACT, PRIV = 5, 3, 4
MARK = 100.0  # privileged columns live at >= MARK, observations in [-3, 3]: any leak is visible


def _agent(**overrides) -> SAC:
    cfg = make_sac_config("thesis", hidden_dims=(16, 16), batch_size=32, buffer_size=2000, learning_starts=0,
                          policy_delay=1, obs_normalization=False, cpu_matmul="torch", **overrides)
    return SAC(OBS, ACT, cfg, "cpu", seed=0, priv_dim=PRIV)


def _fill(agent: SAC, n: int = 256) -> None:
    g = torch.Generator().manual_seed(1)
    for _ in range(n // 16):
        obs, nxt = (torch.rand(16, OBS, generator=g) * 6 - 3 for _ in range(2))
        priv, nxt_priv = (MARK + torch.rand(16, PRIV, generator=g) for _ in range(2))
        agent.add(obs, torch.rand(16, ACT, generator=g) * 2 - 1, torch.rand(16, generator=g), nxt,
                  torch.zeros(16), priv, nxt_priv)


def _record_inputs(monkeypatch) -> dict:
    seen = {"actor": [], "critic": []}
    real_actor, real_critic = Actor.forward, CriticEnsemble.forward

    def actor_forward(self, obs):
        seen["actor"].append(obs.detach().clone())
        return real_actor(self, obs)

    def critic_forward(self, obs, action, frozen=False):
        seen["critic"].append(obs.detach().clone())
        return real_critic(self, obs, action, frozen)

    monkeypatch.setattr(Actor, "forward", actor_forward)
    monkeypatch.setattr(CriticEnsemble, "forward", critic_forward)
    return seen


def test_the_critics_read_the_privileged_inputs_and_the_actor_never_does(monkeypatch):
    agent = _agent()
    _fill(agent)
    seen = _record_inputs(monkeypatch)
    agent.update(4)
    agent.act(torch.rand(7, OBS) * 6 - 3)
    agent.explore(torch.rand(7, OBS) * 6 - 3)
    assert len(seen["actor"]) >= 8 and len(seen["critic"]) >= 12  # critic, target and frozen critic calls
    for x in seen["actor"]:
        assert x.shape[-1] == OBS and bool((x.abs() <= 3).all())  # observations only
    n, stored = len(agent.buffer), agent.buffer.data
    rows = {tuple(r) for r in torch.cat([stored["obs"][:n], stored["next_obs"][:n]]).tolist()}
    priv_rows = {tuple(r) for r in torch.cat([stored["priv"][:n], stored["next_priv"][:n]]).tolist()}
    for x in seen["critic"]:
        assert x.shape[-1] == OBS + PRIV
        obs_part, priv_part = x[:, :OBS], x[:, OBS:]
        assert bool((obs_part.abs() <= 3).all()) and bool((priv_part >= MARK).all())
        # each row is a stored transition's observation beside its own privileged state
        for o, p in zip(obs_part.tolist(), priv_part.tolist()):
            assert tuple(o) in rows and tuple(p) in priv_rows
    assert stored["priv"].shape[-1] == PRIV


def test_the_privileged_state_is_normalized_apart_and_checkpointed():
    cfg = make_sac_config("thesis", hidden_dims=(16, 16), batch_size=32, buffer_size=2000, learning_starts=0,
                          cpu_matmul="torch")
    agent, plain = SAC(OBS, ACT, cfg, "cpu", seed=0, priv_dim=PRIV), SAC(OBS, ACT, cfg, "cpu", seed=0)
    g = torch.Generator().manual_seed(2)
    obs, priv = torch.randn(64, OBS, generator=g), MARK + torch.randn(64, PRIV, generator=g)
    agent.add(obs, torch.zeros(64, ACT), torch.zeros(64), obs, torch.zeros(64), priv, priv)
    plain.add(obs, torch.zeros(64, ACT), torch.zeros(64), obs, torch.zeros(64))
    torch.testing.assert_close(agent.normalize(obs), plain.normalize(obs), rtol=0, atol=0)  # obs stats untouched
    p64 = priv.double()
    want = (p64 - p64.mean(0)) / (p64.std(0, unbiased=False) + cfg.obs_norm_eps)  # rsl-rl's running stats, one batch
    # rsl-rl's float32 running mean and variance of 64 rows near 100 (relative rounding ~1e-7 per term, summed over
    # 64: ~1e-5 of the std); 1e-4 bounds it
    torch.testing.assert_close(agent.normalize_priv(priv).double(), want, rtol=1e-4, atol=1e-4)
    state = agent.state_dict()
    again = SAC(OBS, ACT, cfg, "cpu", seed=5, priv_dim=PRIV)
    again.load_state_dict(state)
    torch.testing.assert_close(again.normalize_priv(priv), agent.normalize_priv(priv), rtol=0, atol=0)
    assert torch.equal(again.buffer.data["next_priv"][:64], priv)


def test_refusals():
    with pytest.raises(ValueError, match="prior_anchor with a privileged critic"):
        _agent(prior_anchor=True)
    agent = _agent()
    with pytest.raises(ValueError, match="give priv and next_priv"):
        agent.add(torch.zeros(2, OBS), torch.zeros(2, ACT), torch.zeros(2), torch.zeros(2, OBS), torch.zeros(2))
    plain = SAC(OBS, ACT, make_sac_config("thesis", hidden_dims=(8,), cpu_matmul="torch"), "cpu")
    with pytest.raises(ValueError, match="priv_dim=0"):
        plain.add(torch.zeros(2, OBS), torch.zeros(2, ACT), torch.zeros(2), torch.zeros(2, OBS), torch.zeros(2),
                  torch.zeros(2, PRIV), torch.zeros(2, PRIV))


def test_the_envs_critic_group_is_the_policys_plus_the_privileged_state(peg_env):
    """AssemblyEnv.privileged_state against float64 frames from the env's own poses (scipy's rotations)."""
    from vkgrl_newton.envs.assembly_env import PRIVILEGED_OBS_DIM

    env = peg_env
    cfg = env.cfg
    env.cfg = dataclasses.replace(cfg, privileged_obs=True)
    try:
        obs = env.get_observations()
    finally:
        env.cfg = cfg
    assert "critic" not in env.get_observations().keys()  # only when asked
    policy, critic = obs["policy"], obs["critic"]
    assert critic.shape == (env.num_envs, policy.shape[-1] + PRIVILEGED_OBS_DIM)
    assert torch.equal(critic[:, :policy.shape[-1]], policy)
    priv = critic[:, policy.shape[-1]:].double().numpy()
    tcp_p, tcp_q = (t.double().numpy() for t in env.tcp_pose())
    held_p, held_q = (t.double().numpy() for t in env.held_pose())
    tcp_r, held_r = Rotation.from_quat(tcp_q), Rotation.from_quat(held_q)  # scipy's (x, y, z, w), as ours
    in_hand_q = (tcp_r.inv() * held_r).as_quat()
    got_q = priv[:, 9:13]
    got_q = got_q * np.sign((got_q * in_hand_q).sum(-1, keepdims=True))  # q and -q are one rotation
    # the env's float32 differences and rotation of positions < 1 m against float64 of the same float32 poses:
    # a few roundings of 6e-8 m (quaternions: of 6e-8); 1e-6 m (1e-5 for the quaternion) bounds them
    np.testing.assert_allclose(priv[:, 0:3], held_p - env.target_base_w.double().numpy(), atol=1e-6)
    np.testing.assert_allclose(priv[:, 3:6], tcp_p - env.fixed_tip_w.double().numpy(), atol=1e-6)
    np.testing.assert_allclose(priv[:, 6:9], tcp_r.inv().apply(held_p - tcp_p), atol=1e-6)
    np.testing.assert_allclose(got_q, in_hand_q, atol=1e-5)
    np.testing.assert_allclose(priv[:, 13:16], env.force_smoothed_w.double().numpy(), atol=1e-6)
    # the held peg hangs below the fingertips, roughly along the TCP's axis (a sanity check of the frame)
    assert np.all(np.abs(priv[:, 6:8]) < 0.01)


def _resolve(argv):
    from vkgrl_newton.run.config import build_parser
    from vkgrl_newton.run.resolve import resolve

    untimed = [] if "ppo" in argv else ["--cpu-matmul", "torch"]  # (no timing of the auto choice here)
    return resolve(build_parser(), [*argv, "--device", "cpu", *untimed])


def test_the_run_option_is_recorded_and_refused_where_it_cannot_hold(tmp_path):
    from vkgrl_newton.run.config import ConfigError

    cfg = _resolve(["--method", "sac", "--privileged-critic", "--run-dir", str(tmp_path / "a")]).config
    assert cfg.privileged_critic and cfg.meta()["privileged_critic"] is True
    assert "privileged_critic" not in _resolve(["--method", "sac", "--run-dir", str(tmp_path / "b")]).config.meta()
    with pytest.raises(ConfigError, match="--privileged-critic is for the SAC methods"):
        _resolve(["--method", "ppo", "--privileged-critic", "--run-dir", str(tmp_path / "c")])
    with pytest.raises(ConfigError, match="add --sac prior_anchor=false"):  # the quick kgrl recipe anchors
        _resolve(["--method", "kgrl", "--privileged-critic", "--run-dir", str(tmp_path / "d")])
    kgrl = _resolve(["--method", "kgrl", "--privileged-critic", "--sac", "prior_anchor=false",
                     "--run-dir", str(tmp_path / "e")]).config
    assert kgrl.privileged_critic and not kgrl.sac.prior_anchor


@pytest.mark.slow
def test_a_privileged_critic_run_trains_resumes_and_evaluates(tmp_path, wp_cpu):
    from scripts import TINY_RUN, load_script
    from vkgrl_newton.agents.checkpoint import load_checkpoint

    run_py = load_script("run")
    run_dir = tmp_path / "priv"
    tiny = TINY_RUN
    assert run_py.main(["--method", "sac", "--privileged-critic", "--run-dir", str(run_dir), "--total-steps", "24",
                        "--eval-episodes", "1", *tiny]) == 0
    assert json.loads((run_dir / "config.json").read_text())["privileged_critic"] is True
    ckpt = load_checkpoint(run_dir / "checkpoints" / "last.pt")
    buf = ckpt["agent"]["buffer"]
    assert buf["priv"].shape == (24, 16) and torch.isfinite(buf["next_priv"]).all()
    assert ckpt["agent"]["critic"]["weights.0"].shape[1] == ckpt["meta"]["obs_dim"] + 16 + 4  # obs + priv + action
    assert run_py.main(["--run-dir", str(run_dir), "--resume", "--total-steps", "32", "--eval-episodes", "0",
                        "--no-progress"]) == 0
    assert load_checkpoint(run_dir / "checkpoints" / "last.pt")["counters"]["transitions"] == 32
