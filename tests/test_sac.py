"""Tests of the Soft Actor-Critic agent (vkgrl_newton.agents.sac) on the CPU, against float64
references written independently of the agent: numerical integration of the squashed density,
explicit per-critic MLPs, the Bellman target from its formula, Polyak interpolation."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
import torch

from vkgrl_newton.agents import (
    SAC,
    SAC_PRESETS,
    CriticEnsemble,
    ReplayBuffer,
    SACConfig,
    make_sac_config,
    soft_update_,
    squashed_log_prob,
)

# small nets: one intra-op thread is fast and immune to a busy second core (conftest.py)
pytestmark = pytest.mark.usefixtures("torch_one_thread")


SMALL = dict(hidden_dims=(32, 32), batch_size=16, learning_starts=32, buffer_size=512, gradient_steps=4)


U32 = 2.0 ** -24  # float32's unit roundoff


def small_agent(obs_dim=3, action_dim=2, seed=0, **overrides) -> SAC:
    return SAC(obs_dim, action_dim, make_sac_config("thesis", **{**SMALL, **overrides}), "cpu", seed)


def fill(agent: SAC, steps: int, n: int = 16, seed: int = 0) -> None:
    g = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        obs = torch.randn(n, agent.obs_dim, generator=g) * 3 + 1
        act = torch.rand(n, agent.action_dim, generator=g) * 2 - 1
        agent.add(obs, act, torch.randn(n, generator=g), torch.randn(n, agent.obs_dim, generator=g),
                  torch.rand(n, generator=g) < 0.2)


# ------------------------------------------------------------------------------ float64 references
def elu(x):
    return np.where(x > 0, x, np.expm1(np.minimum(x, 0)))


def np_mlp(x, layers):
    """layers: list of (W (in, out), b (out,)); ELU between, none after the last."""
    for i, (w, b) in enumerate(layers):
        x = x @ w + b
        x = elu(x) if i < len(layers) - 1 else x
    return x


def actor_layers(agent):
    lin = [m for m in agent.actor.modules() if isinstance(m, torch.nn.Linear)]
    return [(m.weight.detach().double().numpy().T, m.bias.detach().double().numpy()) for m in lin]


def critic_layers(critic: CriticEnsemble, i: int):
    return [(w[i].detach().double().numpy(), b[i, 0].detach().double().numpy())
            for w, b in zip(critic.weights, critic.biases)]


def gauss_logpdf(x, mean, std):
    return -0.5 * ((x - mean) / std) ** 2 - np.log(std) - 0.5 * np.log(2 * np.pi)


# ------------------------------------------------------------------------------ tests
def test_act_and_update_shapes():
    agent = small_agent()
    obs = torch.randn(16, 3) * 100  # large inputs must still give actions in [-1, 1]
    assert not agent.ready()
    fill(agent, 1)
    assert not agent.ready()  # 16 < learning_starts = 32
    fill(agent, 2)
    assert agent.ready() and agent.update_due()
    for det in (False, True):
        a = agent.act(obs, deterministic=det)
        assert a.shape == (16, 2) and a.dtype == torch.float32
        assert torch.isfinite(a).all() and a.abs().max() <= 1.0
    r = agent.random_actions(16)
    assert r.shape == (16, 2) and r.abs().max() <= 1.0 and r.std() > 0.3
    stats = agent.update()
    assert set(stats) == {"critic_loss", "actor_loss", "alpha_loss", "alpha", "q_mean", "entropy"}
    assert all(isinstance(v, float) and math.isfinite(v) for v in stats.values())
    assert agent.num_updates == 4
    assert math.isfinite(agent.update(num_gradient_steps=1)["actor_loss"])  # update 4: actor (policy_delay 4)
    stats = agent.update(num_gradient_steps=3)  # updates 5, 6, 7: critic only
    assert agent.num_updates == 8 and math.isnan(stats["actor_loss"]) and math.isfinite(stats["critic_loss"])


def test_squashed_log_prob_against_numerical_density():
    mean, std = 0.3, 0.8
    # Reference density of a = tanh(u), u ~ N(mean, std): p_u(atanh a) |d atanh(a)/da|, derivative by
    # central differences, all float64.
    a = np.linspace(-1, 1, 400_001)[1:-1]
    h = 1e-7
    datanh = (np.arctanh(a + h) - np.arctanh(a - h)) / (2 * h)
    ref_logp = gauss_logpdf(np.arctanh(a), mean, std) + np.log(datanh)
    u = torch.from_numpy(np.arctanh(a))
    ours = squashed_log_prob(u[:, None], torch.tensor([mean], dtype=torch.float64),
                             torch.tensor([math.log(std)], dtype=torch.float64)).numpy()
    inner = np.abs(a) < 0.999  # finite differences lose digits right at the edge
    # float64 both sides; the reference's central difference has truncation ~h^2 |d3 atanh| / 6 and
    # cancellation ~eps |atanh(a)| / h ~ 1e-9 relative (|a| < 0.999), <~1e-6 in the log: atol 1e-5 bounds it
    np.testing.assert_allclose(ours[inner], ref_logp[inner], atol=1e-5)
    # the trapezoid rule on 4e5 points (error ~ h^2 f'' ~ 1e-11) misses the two tails beyond |a| = 1 - 5e-6,
    # whose mass is P(|u| > atanh(1 - 5e-6) ~ 6.4) < 1e-9: 1e-4 is a loose bound on both
    assert abs(np.trapezoid(np.exp(ours), a) - 1.0) < 1e-4

    # 3-D: the log-prob is the sum of per-dimension 1-D log-probs
    rng = np.random.default_rng(0)
    m, ls, u3 = rng.normal(size=3), rng.normal(size=3) * 0.3, rng.normal(size=(5, 3)) * 2
    per_dim = gauss_logpdf(u3, m, np.exp(ls)) - np.log(1 - np.tanh(u3) ** 2)
    got = squashed_log_prob(*(torch.from_numpy(x) for x in (u3, m, ls))).numpy()
    np.testing.assert_allclose(got, per_dim.sum(-1), rtol=1e-10)  # float64, ~10 roundings: ~1e-15

    # float32, far in the tail where log(1 - tanh(u)^2) is -inf in float32: still exact
    u_big = torch.tensor([[15.0, -12.0]])
    got32 = squashed_log_prob(u_big, torch.zeros(1, 2), torch.zeros(1, 2))
    ref = gauss_logpdf(np.array([15.0, -12.0]), 0, 1) + 2 * np.log(np.cosh([15.0, -12.0]))
    assert torch.isfinite(got32).all()
    # float32 result of ~110: the stable log(1 - tanh^2) and the Gaussian term, ~10 roundings: <= ~10 u32 (6e-7)
    np.testing.assert_allclose(got32.item(), ref.sum(), rtol=16 * U32)


def test_critic_loss_matches_float64_target():
    agent = small_agent(obs_dim=3, action_dim=2, hidden_dims=(8, 8), obs_normalization=False)
    with torch.no_grad():  # make the target differ from the online critic, so a swap would show
        for p in agent.critic_target.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=torch.Generator().manual_seed(1)))
    g = torch.Generator().manual_seed(2)
    obs, next_obs = torch.randn(4, 3, generator=g), torch.randn(4, 3, generator=g)
    action, reward = torch.rand(4, 2, generator=g) * 2 - 1, torch.randn(4, generator=g)
    # The caller's convention: terminated = dones & ~time_outs. Row 0 timed out (bootstraps),
    # row 1 terminated (no bootstrap), rows 2-3 are mid-episode.
    dones, time_outs = torch.tensor([1, 1, 0, 0]).bool(), torch.tensor([1, 0, 0, 0]).bool()
    terminated = (dones & ~time_outs).float()
    alpha = torch.tensor(0.3)
    rng_state = agent.generator.get_state()
    loss, q, target = agent.critic_loss(obs, action, reward, next_obs, terminated, alpha)

    # float64 reference, with the same standard-normal draw the agent makes for a'
    eps = torch.randn((4, 2), generator=torch.Generator().set_state(rng_state)).double().numpy()
    out = np_mlp(next_obs.double().numpy(), actor_layers(agent))
    mean, log_std = out[:, :2], np.clip(out[:, 2:], -20, 2)
    u = mean + np.exp(log_std) * eps
    next_a = np.tanh(u)
    next_logp = (gauss_logpdf(u, mean, np.exp(log_std)) - np.log(1 - np.tanh(u) ** 2)).sum(-1)
    sa_next = np.concatenate([next_obs.double().numpy(), next_a], -1)
    q_next = np.min([np_mlp(sa_next, critic_layers(agent.critic_target, i))[:, 0] for i in range(2)], axis=0)
    r, d = reward.double().numpy(), terminated.double().numpy()
    ref_target = r + 0.99 * (1 - d) * (q_next - 0.3 * next_logp)
    sa = np.concatenate([obs.double().numpy(), action.double().numpy()], -1)
    ref_q = np.stack([np_mlp(sa, critic_layers(agent.critic, i))[:, 0] for i in range(2)])
    ref_loss = 0.5 * ((ref_q - ref_target) ** 2).mean(1).sum()

    # float32 networks of 3 layers of <= 8-term dot products (gamma_8 ~ 5e-7 of the summed magnitudes per
    # layer, any order or FMA, on any CPU) plus exp/tanh/log (~1 ulp each): <~ 3e-6 of magnitudes O(1);
    # rtol 1e-5, atol 1e-5 (1e-6 for q, whose inputs are exact float32 values) bound that with margin
    np.testing.assert_allclose(target.numpy(), ref_target, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(q.detach().numpy(), ref_q, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(loss.item(), ref_loss, rtol=1e-5)
    # terminated: r + gamma * 0 * (...) is r exactly (any finite bootstrap value: 0 * x = +-0, r + 0 = r)
    assert target[1].item() == reward[1].item()
    assert abs(target[0].item() - reward[0].item()) > 1e-3  # time-out: bootstraps


@pytest.mark.parametrize("target_entropy, direction", [(-50.0, -1), (50.0, +1)])
def test_entropy_temperature_moves_towards_target(target_entropy, direction):
    agent = small_agent(target_entropy=target_entropy, policy_delay=1)
    fill(agent, 4)
    stats = agent.update(8)
    assert -50 < stats["entropy"] < 50  # so the sign of (entropy - target) is known
    # d loss / d log_alpha = entropy - target: alpha must fall when entropy > target, rise otherwise
    assert math.copysign(1.0, stats["alpha"] - 1.0) == direction  # init_alpha 1.0
    assert stats["alpha"] == pytest.approx(agent.log_alpha.exp().item())


def test_critic_ensemble_equals_separate_critics():
    cfg = SACConfig(hidden_dims=(16, 8), n_critics=3)
    ens = CriticEnsemble(5 + 2, cfg, torch.Generator().manual_seed(0)).double()
    g = torch.Generator().manual_seed(1)
    obs, act = torch.randn(11, 5, generator=g, dtype=torch.float64), torch.rand(11, 2, generator=g, dtype=torch.float64)
    got = ens(obs, act)
    assert got.shape == (3, 11)
    for i in range(3):
        seq = torch.nn.Sequential(torch.nn.Linear(7, 16), torch.nn.ELU(), torch.nn.Linear(16, 8), torch.nn.ELU(),
                                  torch.nn.Linear(8, 1)).double()
        lins = [m for m in seq if isinstance(m, torch.nn.Linear)]
        with torch.no_grad():
            for lin, w, b in zip(lins, ens.weights, ens.biases):
                lin.weight.copy_(w[i].T)
                lin.bias.copy_(b[i, 0])
        # float64, two code paths (batched matmul vs nn.Linear): <= 16-term sums, ~3 layers: ~1e-14 at most
        torch.testing.assert_close(got[i], seq(torch.cat([obs, act], -1))[:, 0], rtol=1e-12, atol=1e-12)
    assert not torch.allclose(got[0], got[1])  # the critics are initialized independently


def _forward_and_grads(agent: SAC, dtype: torch.dtype) -> dict[str, torch.Tensor]:
    """Q of both critics, the actor's outputs and every gradient a gradient step uses."""
    g = torch.Generator().manual_seed(1)
    obs = torch.randn(37, agent.obs_dim, generator=g).to(dtype)
    act = (torch.rand(37, agent.action_dim, generator=g) * 2 - 1).to(dtype).requires_grad_(True)
    q = agent.critic(obs, act)
    (q * torch.linspace(-1, 2, q.numel()).to(dtype).view_as(q)).sum().backward()
    out = {"q": q.detach(), "dq/da": act.grad.clone()}
    out.update({f"critic.{i}": p.grad.clone() for i, p in enumerate(agent.critic.parameters())})
    frozen_act = act.detach().clone().requires_grad_(True)  # the actor's loss: d/da only
    agent.critic(obs, frozen_act, frozen=True).sum().backward()
    out["frozen dq/da"] = frozen_act.grad
    for i, p in enumerate(agent.critic.parameters()):  # frozen: no critic weight gradient added
        assert torch.equal(p.grad, out[f"critic.{i}"])
    mean, log_std = agent.actor(obs)
    (mean.square().sum() + (log_std * 0.3).sum()).backward()
    out.update({"mean": mean.detach(), "log_std": log_std.detach()})
    out.update({f"actor.{i}": p.grad.clone() for i, p in enumerate(agent.actor.parameters())})
    return out


def test_onednn_layers_match_the_float64_torch_networks():
    """The CPU's oneDNN layers (agents/dense.py) against float64 F.linear/baddbmm: forward and
    every gradient (weights, biases, the shared critic input, the frozen critic's d/da)."""
    from vkgrl_newton.agents.dense import onednn_available

    if not onednn_available():
        pytest.skip("this torch has no oneDNN linear")
    fast = small_agent(obs_dim=5, action_dim=3, seed=3, n_critics=3, cpu_matmul="onednn")
    assert fast.actor.matmul == fast.critic.matmul == "onednn"
    ref = small_agent(obs_dim=5, action_dim=3, seed=3, n_critics=3, cpu_matmul="torch")
    assert ref.actor.matmul == "torch"
    ref.actor.double(), ref.critic.double()
    got, want = _forward_and_grads(fast, torch.float32), _forward_and_grads(ref, torch.float64)
    assert got.keys() == want.keys()
    for k in want:
        # float32 chains of <= 4 layers of <= 40-term dot products (and their transposes):
        # rounding error <= ~4 * 40 * 2^-24 ~ 1e-5 of the magnitudes summed (observed ~1e-7)
        scale = want[k].abs().max().item()
        torch.testing.assert_close(got[k].double(), want[k], rtol=0, atol=1e-5 * max(scale, 1.0), msg=k)
    with pytest.raises(ValueError, match="cpu_matmul='mkl'.*onednn.*torch"):
        make_sac_config("quick", cpu_matmul="mkl")


def test_polyak_update_is_tau_interpolation():
    g = torch.Generator().manual_seed(0)
    target = [torch.randn(4, 3, generator=g), torch.randn(7, generator=g)]
    online = [torch.randn(4, 3, generator=g), torch.randn(7, generator=g)]
    ref = [t.double() + 0.005 * (o.double() - t.double()) for t, o in zip(target, online)]
    bounds = [4 * U32 * torch.maximum(t.double().abs(), o.double().abs()) for t, o in zip(target, online)]
    soft_update_(target, online, 0.005)
    # float32 lerp t + tau (o - t): a subtraction, a product, a sum (or FMA), each <= u of a value <= 2 max(|t|, |o|)
    # (was atol 1e-6, no origin: ~2 ulps of the largest draws)
    for t, r, b in zip(target, ref, bounds):
        assert bool(((t.double() - r).abs() <= b).all())

    # inside the agent: after one gradient step, target = old target + tau (new online - old target)
    agent = small_agent(tau=0.1)
    fill(agent, 3)
    with torch.no_grad():
        for p in agent.critic_target.parameters():
            p.add_(1.0)
    old = [p.detach().double().clone() for p in agent.critic_target.parameters()]
    agent.update(1)
    for t_old, t_new, o_new in zip(old, agent.critic_target.parameters(), agent.critic.parameters()):
        want = t_old + 0.1 * (o_new.double() - t_old)
        bound = 4 * U32 * torch.maximum(t_old.abs(), o_new.double().abs())  # as above (was atol 1e-6)
        assert bool(((t_new.double() - want).abs() <= bound).all())


def test_replay_buffer_wraparound_and_sampling():
    def rows(values):
        v = torch.tensor(values, dtype=torch.float32)
        return v[:, None], torch.stack([v, -v], 1), 10 * v, v[:, None] + 0.5, (v % 2 == 0)

    buf = ReplayBuffer(5, 1, 2, "cpu")
    for start in range(0, 12, 3):
        buf.add(*rows(range(start, start + 3)))
    assert len(buf) == 5 and buf.ptr == 12 % 5
    assert sorted(buf.data["obs"][:, 0].tolist()) == [7, 8, 9, 10, 11]  # the newest 5
    b = buf.sample(500, torch.Generator().manual_seed(0))
    assert set(b.obs[:, 0].tolist()) == {7, 8, 9, 10, 11}
    # every field of a sampled row comes from the same transition
    torch.testing.assert_close(b.action, torch.cat([b.obs, -b.obs], 1))
    torch.testing.assert_close(b.reward, 10 * b.obs[:, 0])
    torch.testing.assert_close(b.next_obs, b.obs + 0.5)
    torch.testing.assert_close(b.terminated, (b.obs[:, 0] % 2 == 0).float())

    buf.add(*rows(range(100, 107)))  # more rows than capacity in one add: the last 5 survive
    assert sorted(buf.data["obs"][:, 0].tolist()) == [102, 103, 104, 105, 106]

    part = ReplayBuffer(10, 1, 2, "cpu")
    part.add(*rows([0, 1, 2]))
    b = part.sample(2000, torch.Generator().manual_seed(1))
    assert set(b.obs[:, 0].tolist()) == {0, 1, 2}  # only filled rows
    state = part.state_dict()
    assert state["obs"].shape[0] == 3  # only the filled part is stored
    other = ReplayBuffer(10, 1, 2, "cpu")
    other.load_state_dict(state)
    other.add(*rows([3]))
    assert other.data["obs"][:4, 0].tolist() == [0, 1, 2, 3] and len(other) == 4


def test_obs_normalization_from_env_batches_only():
    agent = small_agent()
    g = torch.Generator().manual_seed(3)
    all_obs = []
    for _ in range(4):
        obs = torch.randn(16, 3, generator=g) * torch.tensor([1.0, 5.0, 0.1]) + torch.tensor([2.0, -3.0, 0.0])
        all_obs.append(obs)
        agent.add(obs, torch.zeros(16, 2), torch.zeros(16), obs + 50, torch.zeros(16))  # next_obs never counted
    x = torch.cat(all_obs).double()
    # float32 running statistics over 4 batches of 16 (rsl-rl's update: batch mean, weighted sums): ~10
    # roundings of values <= |mean| + 3 std ~ 20, i.e. <~ 1e-5 absolute and relative; the std goes through
    # a variance and a sqrt, so 1e-4 relative (both bound the float32 rounding, not the sampling)
    torch.testing.assert_close(agent.normalizer.mean.double(), x.mean(0), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(agent.normalizer.std.double(), x.std(0, unbiased=False), rtol=1e-4, atol=1e-5)
    before = agent.normalizer.state_dict()
    seen = []
    critic_loss = agent.critic_loss

    def spy(obs, action, reward, next_obs, *rest):
        seen.append((obs, next_obs))
        return critic_loss(obs, action, reward, next_obs, *rest)

    agent.critic_loss = spy
    agent.update(2)
    assert all(torch.equal(before[k], v) for k, v in agent.normalizer.state_dict().items())
    # the losses see normalized obs and next_obs: de-normalized, every row is a stored raw row
    raw = torch.cat(all_obs)
    for obs_n, next_n in seen:
        for z, stored in ((obs_n, raw), (next_n, raw + 50)):
            back = agent.normalizer.inverse(z)
            dist = (back[:, None, :] - stored[None]).abs().amax(-1).min(1).values
            # normalize then invert in float32: ~4 roundings of values <= |x| + |mean|: ~1e-6 of the
            # magnitude; 1e-4 of it keeps rows apart (distinct rows differ by far more)
            assert dist.max() < 1e-4 * stored.abs().max()
    # act() feeds the normalized observation to the actor
    obs = all_obs[0][:5]
    z = (obs - agent.normalizer.mean) / (agent.normalizer.std + 1e-2)
    torch.testing.assert_close(agent.act(obs, deterministic=True), torch.tanh(agent.actor(z)[0]))


def test_state_dict_round_trip_continues_identically():
    def step(agent, k):
        fill(agent, 1, seed=100 + k)
        out = agent.update(3)
        return out, agent.act(torch.ones(4, 3))

    a = small_agent(seed=0)
    fill(a, 3)
    for k in range(2):
        step(a, k)
    blob = io.BytesIO()
    torch.save(a.state_dict(), blob)
    blob.seek(0)
    b = small_agent(seed=123)  # different init and generator: everything must come from the checkpoint
    b.load_state_dict(torch.load(blob, weights_only=False))
    # bitwise: the same computation on the same machine and thread count, from the same state (across CPUs
    # the float32 values differ in their last bits, but a and b always run side by side here)
    for k in range(2, 5):
        (sa, aa), (sb, ab) = step(a, k), step(b, k)
        np.testing.assert_equal(sa, sb)  # exact, NaN == NaN (no actor step in some calls)
        assert torch.equal(aa, ab)
    for pa, pb in zip(a.state_dict()["actor"].values(), b.state_dict()["actor"].values()):
        assert torch.equal(pa, pb)
    for mod in ("critic", "critic_target"):
        for pa, pb in zip(getattr(a, mod).parameters(), getattr(b, mod).parameters()):
            assert torch.equal(pa, pb)
    assert torch.equal(a.log_alpha, b.log_alpha)
    assert (a.num_transitions, a.num_env_steps, a.num_updates) == (b.num_transitions, b.num_env_steps, b.num_updates)


def test_learns_contextual_bandit():
    """r = -||a - 0.5 tanh(obs)||^2, one-step episodes: clearly better than random in ~400 steps."""
    cfg = make_sac_config("quick", hidden_dims=(64, 64), batch_size=128, lr=3e-3, learning_starts=256,
                          policy_delay=1, init_alpha=0.05, buffer_size=10_000)
    agent = SAC(2, 2, cfg, "cpu", seed=0)
    g = torch.Generator().manual_seed(0)

    def reward(obs, act):
        return -(act - 0.5 * torch.tanh(obs)).square().sum(-1)

    for _ in range(40):
        obs = torch.randn(32, 2, generator=g)
        act = agent.act(obs) if agent.ready() else agent.random_actions(32)
        agent.add(obs, act, reward(obs, act), obs, torch.ones(32))
        if agent.ready():
            agent.update(12)
    test_obs = torch.randn(2000, 2, generator=g)
    r_policy = reward(test_obs, agent.act(test_obs, deterministic=True)).mean().item()
    r_random = reward(test_obs, torch.rand(2000, 2, generator=g) * 2 - 1).mean().item()
    assert r_random < -0.6
    assert r_policy > -0.05, (r_policy, r_random)  # zero action scores ~ -0.2


def test_presets_and_config_errors():
    t = SAC_PRESETS["thesis"]  # Table 5.3
    assert (t.buffer_size, t.batch_size, t.lr, t.learning_starts, t.train_every, t.gradient_steps) == (
        1_000_000, 256, 4e-4, 5_000, 1, 512)
    assert (t.n_critics, t.hidden_dims, t.activation, t.obs_normalization, t.policy_delay) == (
        2, (512, 256, 128), "elu", True, 4)
    assert make_sac_config("quick", lr=1e-3).lr == 1e-3
    assert make_sac_config("quick", hidden_dims=[8, 4]).hidden_dims == (8, 4)
    with pytest.raises(ValueError, match="preset 'nope'.*quick.*thesis"):
        make_sac_config("nope")
    with pytest.raises(ValueError, match="'bufer_size'.*buffer_size"):
        make_sac_config("quick", bufer_size=10)
    with pytest.raises(ValueError, match="activation.*'gelu'.*elu"):
        make_sac_config("thesis", activation="gelu")
    with pytest.raises(ValueError, match="batch_size"):
        make_sac_config("thesis", batch_size=0)
    with pytest.raises(RuntimeError, match="ready"):
        small_agent().update()
    with pytest.raises(ValueError, match="obs_norm_eps=0.0 must be > 0"):
        make_sac_config("quick", obs_norm_eps=0.0)


def test_obs_norm_eps_is_the_floor_added_to_the_std():
    """(x - mean) / (std + eps) with the configured eps, against float64 statistics."""
    agent = small_agent(obs_dim=2, obs_norm_eps=1e-3)
    g = torch.Generator().manual_seed(4)
    x = torch.randn(256, 2, generator=g) * torch.tensor([0.005, 2.0])  # a 5 mm spread and a wide one
    agent.add(x, torch.zeros(256, 2), torch.zeros(256), x, torch.zeros(256))
    xd = x.double().numpy()
    want = (xd - xd.mean(0)) / (xd.std(0) + 1e-3)  # rsl-rl: the biased (population) variance
    # rsl-rl starts its variance at 1 and updates it as 1 + (var - 1) in float32: an absolute error
    # up to ~2 * 2^-24 in a 2.5e-5 variance, i.e. ~1e-5 in the 5 mm std, ~2e-3 of (std + eps)
    np.testing.assert_allclose(agent.normalize(x).double().numpy(), want, rtol=3e-3, atol=1e-5)
    with_default = small_agent(obs_dim=2)  # rsl-rl's eps 1e-2 squeezes the 5 mm input to ~1/3
    with_default.add(x, torch.zeros(256, 2), torch.zeros(256), x, torch.zeros(256))
    assert with_default.normalize(x)[:, 0].std().item() == pytest.approx(0.005 / 0.015, rel=0.1)


def test_actor_init_std_starts_at_zero_mean_and_that_std():
    cfg = make_sac_config("quick", hidden_dims=(32, 32), actor_init_std=0.1)
    agent = SAC(6, 4, cfg, seed=3)
    obs = torch.randn(512, 6, generator=torch.Generator().manual_seed(0)) * 5.0
    mean, log_std = agent.actor(obs)
    assert mean.abs().max() < 0.05  # ~0 whatever the observation
    assert torch.allclose(log_std.exp(), torch.full_like(log_std, 0.1), rtol=0.05)
    default = SAC(6, 4, make_sac_config("quick", hidden_dims=(32, 32)), seed=3)
    assert default.actor(obs)[0].abs().max() > 0.05  # the option is what makes the difference
    with pytest.raises(ValueError, match="actor_init_std"):
        make_sac_config("quick", actor_init_std=100.0)


def test_warmup_actions_uniform_or_the_untrained_actor():
    obs = torch.randn(4096, 6, generator=torch.Generator().manual_seed(1))
    uniform = SAC(6, 4, make_sac_config("quick", hidden_dims=(32, 32)), seed=0)
    a = uniform.explore(obs)
    assert not uniform.ready() and a.abs().max() <= 1.0
    # U(-1, 1): mean 0, std 1/sqrt(3) per dimension; the sample std of 4096 draws has standard error
    # sqrt((1/5 - 1/9) / 4096) / (2 / sqrt(3)) ~ 0.004: atol 0.02 is 5 standard errors
    np.testing.assert_allclose(a.std(0).numpy(), 1 / math.sqrt(3), atol=0.02)
    policy = SAC(6, 4, make_sac_config("quick", hidden_dims=(32, 32), actor_init_std=0.05, warmup="policy"), seed=0)
    a = policy.explore(obs)
    # tanh(N(0, 0.05^2)): std = 0.05 (1 - O(0.05^2)), mean 0. Sampling: the std's standard error is
    # 0.05 / sqrt(2 * 4096) ~ 1.1 % (rtol 6 %: ~5 SE beyond the 0.5 % tanh bias), the mean's 0.05 / 64 ~ 8e-4
    np.testing.assert_allclose(a.std(0).numpy(), 0.05, rtol=0.06)
    assert a.mean(0).abs().max() < 0.01
    with pytest.raises(ValueError, match="warmup='greedy'.*uniform.*policy"):
        make_sac_config("quick", warmup="greedy")
