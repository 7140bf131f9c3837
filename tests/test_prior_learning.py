"""Learning beyond the KMP prior (issue 28): the paired evaluation and the SAC options that keep the
prior (a = 0 for KGRL), each against an independent reference: exact enumeration of the bootstrap,
brute-force choices, a float64 LayerNorm critic, counted sampling."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
import torch

from vkgrl_newton.agents.sac import SAC, make_sac_config, squashed_log_prob
from vkgrl_newton.results.paired import paired_gain, seed_evaluation, world_outcomes

pytestmark = pytest.mark.usefixtures("torch_one_thread")

SMALL = dict(hidden_dims=(16, 16), batch_size=16, learning_starts=16, buffer_size=512, gradient_steps=4)


def agent(obs_dim=3, action_dim=2, seed=0, **overrides) -> SAC:
    return SAC(obs_dim, action_dim, make_sac_config("quick", **{**SMALL, **overrides}), "cpu", seed)


# ------------------------------------------------------------------------------ paired evaluation
def test_paired_gain_against_the_exact_bootstrap_distribution():
    a, b = np.array([1.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.0])
    d = a - b  # 1, 0, 0
    exact = np.sort([np.mean(d[list(i)]) for i in itertools.product(range(3), repeat=3)])  # 27 resamples
    g = paired_gain(a, b, reps=200_000, seed=3)
    assert g["mean"] == pytest.approx(1 / 3) and g["n_pairs"] == 3
    assert (g["a_mean"], g["b_mean"]) == (pytest.approx(2 / 3), pytest.approx(1 / 3))
    # the exact distribution's 2.5 / 97.5 % quantiles (its inverse CDF over the 27 equally likely
    # resamples): P(mean = 0) = 8/27, P(mean = 1) = 1/27 > 2.5 %, so the interval is [0, 1]; the
    # Monte Carlo percentile lands on the same atoms
    assert g["ci_low"] == pytest.approx(np.percentile(exact, 2.5, method="inverted_cdf"), abs=1e-9) == 0.0
    assert g["ci_high"] == pytest.approx(np.percentile(exact, 97.5, method="inverted_cdf"), abs=1e-9) == 1.0
    # NaN marks an episode that did not count: dropped pairwise; identical outcomes: a zero interval
    g = paired_gain([1, np.nan, 0, 1], [1, 1, np.nan, 1])
    assert g["n_pairs"] == 2 and g["mean"] == g["ci_low"] == g["ci_high"] == 0.0
    empty = paired_gain([np.nan], [1.0])
    assert empty["mean"] is None and json.loads(json.dumps(empty))["n_pairs"] == 0
    with pytest.raises(ValueError, match="same episodes"):
        paired_gain([1, 0], [1, 0, 1])


def test_world_outcomes_flatten_rounds_then_worlds():
    result = {"per_episode": [{"world_success": [1.0, 0.0]}, {"world_success": [float("nan"), 1.0]}]}
    np.testing.assert_array_equal(world_outcomes(result), [1.0, 0.0, np.nan, 1.0])


def test_an_evaluation_seed_gives_bitwise_the_same_initial_states(peg_env):
    """What two policies see after seed_evaluation with one seed, whatever ran before: identical
    initial states and target-frame noise; another seed, other ones."""
    env = peg_env

    def snapshot():
        obs = env.get_observations()["policy"].clone()
        return obs, env.target_frame_pos_w.clone(), env.fixed_pos_w.clone(), env.fixed_yaw.clone()

    g = torch.Generator().manual_seed(0)
    for _ in range(3):  # one "policy" moves the arm around
        env.step(torch.rand(env.num_envs, env.num_actions, generator=g) * 2 - 1)
    seed_evaluation(env, 123)
    first = snapshot()
    for _ in range(5):  # another policy, another history
        env.step(-torch.rand(env.num_envs, env.num_actions, generator=g))
    seed_evaluation(env, 123)
    again = snapshot()
    for x, y in zip(first, again):
        assert torch.equal(x, y)
    seed_evaluation(env, 124)
    assert not torch.equal(snapshot()[1], first[1])


# ------------------------------------------------------------------------------ exploration options
def test_tanh_log_std_bound_has_a_gradient_at_and_beyond_its_limits():
    soft = agent(log_std_bound="tanh", log_std_max=-1.2, actor_init_std=0.1)
    hard = agent(log_std_max=-1.2, actor_init_std=0.1)
    obs = torch.randn(64, 3, generator=torch.Generator().manual_seed(0))
    for a, bounded in ((soft, True), (hard, False)):
        with torch.no_grad():
            a.actor.head.bias[2:] = 5.0  # raw log_std far above the upper bound
        _, log_std = a.actor(obs)
        assert log_std.max() <= -1.2 + 1e-6
        log_std.sum().backward()
        grad = a.actor.head.bias.grad[2:]
        assert (grad.abs() > 0).all() if bounded else (grad == 0).all()
    # the soft bound starts at the asked std like the clamp does
    fresh = agent(log_std_bound="tanh", log_std_max=-1.2, actor_init_std=0.1)
    _, log_std = fresh.actor(obs)
    np.testing.assert_allclose(log_std.exp().detach().numpy(), 0.1, rtol=0.02)
    lo, hi = -20.0, -1.2  # the map itself: lo + (hi - lo) (tanh(x) + 1) / 2
    x = torch.tensor([-3.0, 0.0, 3.0], dtype=torch.float64)
    want = lo + (hi - lo) * (np.tanh(x.numpy()) + 1) / 2
    fresh.actor.soft_bound = True
    assert fresh.actor.raw_log_std(float(want[1])) == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(ValueError, match="log_std_bound='soft'.*clamp.*tanh"):
        make_sac_config("quick", log_std_bound="soft")


class QuadraticCritic(torch.nn.Module):
    """Q_i(s, a) = -|a - c_i(s)|^2 + i: a known best action per state; min over i is critic 0's."""

    def __init__(self, centre):
        super().__init__()
        self.centre = centre

    def forward(self, obs, action, frozen=False):
        q = -(action - self.centre(obs)).square().sum(-1)
        return torch.stack([q, q + 1.0])


def test_prior_anchor_takes_a_zero_where_the_critics_value_it_more():
    a = agent(prior_anchor=True)
    obs = torch.randn(256, 3, generator=torch.Generator().manual_seed(1))
    centre = lambda o: 0.5 * torch.tanh(o[:, :2])  # noqa: E731
    critic = QuadraticCritic(centre)
    action = torch.rand(256, 2, generator=torch.Generator().manual_seed(2)) * 2 - 1
    chosen = a.anchored(critic, obs, action)
    c = centre(obs).double()
    zero_better = (c.square().sum(-1) < (action.double() - c).square().sum(-1))  # brute force, float64
    assert 0 < int(zero_better.sum()) < 256
    assert torch.equal(chosen[zero_better], torch.zeros_like(chosen[zero_better]))
    assert torch.equal(chosen[~zero_better], action[~zero_better])
    # act() (exploring and deterministic) goes through the same choice with the agent's own critics
    a.critic = critic
    det = a.act(obs, deterministic=True)
    assert torch.equal(det, a.anchored(critic, a.normalize(obs), torch.tanh(a.actor(a.normalize(obs))[0])))


def test_prior_anchor_target_bootstraps_from_the_better_action():
    """The critic's target with the anchor: r + gamma (max(Q'(s', a_pi), Q'(s', 0)) - alpha log pi(a_pi)),
    the entropy term of the policy's own sample whichever action is taken (log pi(0) of a policy that
    has moved away from 0 would be an unbounded bonus)."""
    a = agent(prior_anchor=True, gamma=0.9)
    centre = lambda o: torch.where(o[:, :1] > 0, 0.0, 0.9) * torch.ones(o.shape[0], 2)  # noqa: E731
    a.critic_target = QuadraticCritic(centre)
    g = torch.Generator().manual_seed(5)
    obs, next_obs = torch.randn(512, 3, generator=g), torch.randn(512, 3, generator=g)
    reward, term = torch.rand(512, generator=g), torch.zeros(512)
    state = a.generator.get_state()
    _, _, target = a.critic_loss(obs, torch.zeros(512, 2), reward, next_obs, term, torch.tensor(0.5))
    a.generator.set_state(state)  # replay the draw the target made
    mean, log_std = a.actor(next_obs)
    u = mean + log_std.exp() * torch.randn(mean.shape, generator=a.generator)
    c = centre(next_obs).double()
    q_pi = -(torch.tanh(u).double() - c).square().sum(-1)
    q_0 = -c.square().sum(-1)
    log_pi = squashed_log_prob(u.double(), mean.double(), log_std.double())
    want = (reward.double() + 0.9 * (torch.maximum(q_pi, q_0) - 0.5 * log_pi)).detach()
    # float32 target (a 3-layer MLP's Q and the log-prob, each ~K u32 relative per layer, K <= 256) against the same
    # terms in float64 from the same draw: 1e-5 relative / absolute bounds that with ~5x margin on either CPU
    np.testing.assert_allclose(target.double().numpy(), want.numpy(), rtol=1e-5, atol=1e-5)
    # states whose critic centre is at 0 take a = 0; those centred at 0.9 mostly the policy's sample
    assert (q_0 > q_pi)[next_obs[:, 0] > 0].all() and (q_0 < q_pi)[next_obs[:, 0] <= 0].any()


def test_actor_waits_for_the_first_reward():
    a = agent(actor_after_reward=True, policy_delay=1)
    g = torch.Generator().manual_seed(0)

    def add(r):
        a.add(torch.randn(16, 3, generator=g), torch.rand(16, 2, generator=g) * 2 - 1, torch.full((16,), r),
              torch.randn(16, 3, generator=g), torch.zeros(16))

    add(0.0)
    before = [p.detach().clone() for p in a.actor.parameters()]
    critic_before = [p.detach().clone() for p in a.critic.parameters()]
    stats = a.update()
    assert all(torch.equal(x, y) for x, y in zip(before, a.actor.parameters()))  # no actor step
    assert any(not torch.equal(x, y) for x, y in zip(critic_before, a.critic.parameters()))  # the critic learns
    assert math.isnan(stats["actor_loss"]) and stats["alpha"] == 1.0
    add(1.0)
    a.update()
    assert any(not torch.equal(x, y) for x, y in zip(before, a.actor.parameters()))
    restored = agent(actor_after_reward=True, policy_delay=1)
    restored.load_state_dict(a.state_dict())
    assert restored.rewarded


def test_prior_rollouts_fill_their_buffer_and_batches_take_the_ratio():
    a = agent(prior_rollouts=32, prior_ratio=0.25, batch_size=16)
    obs = torch.randn(16, 3)
    assert torch.equal(a.explore(obs), torch.zeros(16, 2))  # the prior's own actions: a = 0 exactly
    for tag in (1.0, 1.0, 0.0, 0.0, 0.0):  # 32 prior transitions (tag 1), then 48 online (tag 0)
        act = a.explore(obs)
        a.add(torch.full((16, 3), tag), act, torch.zeros(16), torch.zeros(16, 3), torch.zeros(16))
    assert len(a.prior_buffer) == 32 and len(a.buffer) == 80
    assert a.explore(obs).abs().sum() > 0  # after the rollouts, the actor's samples
    b = a.sample(steps=50, batch_size=16)
    tags = b.obs[:, 0].view(50, 16)
    # each minibatch: the last round(0.25 * 16) = 4 rows from the prior buffer (all tag 1); the
    # online rows come from all 80 (32 tag 1, 48 tag 0): about 40 % ones among them
    assert (tags[:, 12:] == 1.0).all()
    online_ones = float(tags[:, :12].mean())
    assert 0.3 < online_ones < 0.5
    with pytest.raises(ValueError, match="prior_rollouts > 0"):
        make_sac_config("quick", prior_ratio=0.5)
    with pytest.raises(ValueError, match="prior_ratio=1.0"):
        make_sac_config("quick", prior_ratio=1.0, prior_rollouts=8)


def test_layer_norm_critic_against_a_float64_reference():
    a = agent(obs_dim=3, action_dim=2, critic_layer_norm=True, cpu_matmul="torch")
    with torch.no_grad():  # non-trivial per-critic scales and shifts
        for g_, h_ in zip(a.critic.ln_scales, a.critic.ln_shifts):
            g_.uniform_(0.5, 1.5, generator=torch.Generator().manual_seed(1))
            h_.uniform_(-0.2, 0.2, generator=torch.Generator().manual_seed(2))
    obs, act = torch.randn(32, 3), torch.rand(32, 2) * 2 - 1
    q = a.critic(obs, act).double().detach().numpy()
    x0 = torch.cat([obs, act], -1).double().numpy()
    ws = [w.detach().double().numpy() for w in a.critic.weights]
    bs = [b.detach().double().numpy() for b in a.critic.biases]
    gs = [g_.detach().double().numpy() for g_ in a.critic.ln_scales]
    hs = [h_.detach().double().numpy() for h_ in a.critic.ln_shifts]
    for i in range(2):
        x = x0
        for k in range(len(ws)):
            x = x @ ws[k][i] + bs[k][i]
            if k < len(ws) - 1:
                mu, var = x.mean(-1, keepdims=True), x.var(-1, keepdims=True)
                x = (x - mu) / np.sqrt(var + 1e-5) * gs[k][i] + hs[k][i]
                x = np.where(x > 0, x, np.expm1(np.minimum(x, 0)))
        # float32 matmuls (K <= 256 terms, gamma_K ~ 1.5e-5 worst case) plus a layer norm's mean, variance and
        # sqrt per layer against float64: 1e-4 relative covers the worst-case bound, atol 1e-5 the Q values near 0
        np.testing.assert_allclose(q[i], x[:, 0], rtol=1e-4, atol=1e-5)
    # the oneDNN path computes the same network
    b = agent(obs_dim=3, action_dim=2, critic_layer_norm=True)
    b.critic.load_state_dict(a.critic.state_dict())
    np.testing.assert_allclose(b.critic(obs, act).detach().numpy(), q, rtol=1e-4, atol=1e-5)


# ------------------------------------------------------------------------------ the prior's fit
def _on_grid_brute_force(demos, dt):
    """Each demonstration's eta at s_n = n dt by hand: the bracketing samples, linear in s."""
    n_steps = int(round(1 / dt))
    out = np.zeros((demos.num_demos, n_steps + 1, 6))
    for d, (s, eta) in enumerate(demos.split()):
        for n in range(n_steps + 1):
            t = n / n_steps
            j = min(max(int(np.searchsorted(s, t, side="right")) - 1, 0), len(s) - 2)
            w = 0.0 if s[j + 1] == s[j] else (t - s[j]) / (s[j + 1] - s[j])
            out[d, n] = (1 - w) * eta[j] + w * eta[j + 1]
    return out


def test_prior_fit_is_measured_against_the_demonstrations():
    from vkgrl_newton.kmp.demos import synthetic_demos
    from vkgrl_newton.kmp.prior import fit_prior, format_prior_fit, prior_fit
    from vkgrl_newton.kmp.tables import EmpiricalReference, control_grid
    from vkgrl_newton.tasks import get_task

    demos = synthetic_demos("PegInsert", 6, action_dim=6, seed=2)
    dt = get_task("PegInsert").kmp_dt
    ref = _on_grid_brute_force(demos, dt)
    mean, sd = ref.mean(0), ref.std(0, ddof=1)
    emp = EmpiricalReference(demos, dt, ridge=0.0)
    mu, sigma = emp(control_grid(dt))
    np.testing.assert_allclose(mu.numpy(), mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.sqrt(np.diagonal(sigma.numpy(), axis1=1, axis2=2)), sd, rtol=1e-9, atol=1e-15)
    with pytest.raises(ValueError, match="control grid"):
        emp(torch.tensor([0.5 * dt]))
    for reference in ("gmr", "empirical"):
        tables = fit_prior(demos, 4, reference=reference)
        fit = prior_fit(tables, demos)
        assert tables.reference == reference and fit["reference"] == reference
        np.testing.assert_allclose(fit["mean_error"], tables.mean.numpy()[:, :3] - mean[:, :3], atol=1e-12)
        np.testing.assert_allclose(fit["demo_sd"], sd[:, :3], rtol=1e-9)
        assert fit["max_abs_error_mm"] == pytest.approx(1e3 * np.abs(fit["mean_error"]).max(0))
        assert "max |m[n] - their mean|" in format_prior_fit(fit)
    # the empirical reference's sd is the demonstrations' own, and its prior follows their mean
    assert fit["sd_ratio_max"] == pytest.approx([1.0] * 3) and fit["sd_ratio_min"] == pytest.approx([1.0] * 3)
    assert max(fit["max_abs_error_mm"]) < 0.5
    with pytest.raises(ValueError, match="reference='spline'"):
        fit_prior(demos, 4, reference="spline")


def test_empirical_tables_are_cached_apart_and_reloaded(tmp_path):
    from vkgrl_newton.kmp.demos import synthetic_demos
    from vkgrl_newton.kmp.prior import load_or_fit_prior

    path = synthetic_demos("PegInsert", 4, action_dim=6, seed=1).save(tmp_path / "demos.npz")
    gmr_t, gmr_path, _ = load_or_fit_prior(path, 4)
    emp_t, emp_path, rebuilt = load_or_fit_prior(path, 4, reference="empirical")
    assert rebuilt and emp_path.name == "demos.kmp4d_empirical.npz" and gmr_path.name == "demos.kmp4d.npz"
    again, _, rebuilt = load_or_fit_prior(path, 4, reference="empirical")
    assert not rebuilt and again.reference == "empirical" and torch.equal(again.mean, emp_t.mean)
    assert not torch.equal(gmr_t.mean, emp_t.mean)


def test_prior_reg_adds_the_mean_penalty_and_pulls_toward_zero():
    a = agent(prior_reg=2.5)
    obs = torch.randn(64, 3, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        a.actor.head.bias[:2] = torch.tensor([0.8, -0.4])  # a mean away from 0
    state = a.generator.get_state()
    loss, _ = a.actor_loss(obs, torch.tensor(0.2))
    a.generator.set_state(state)
    plain = agent()  # the same networks without the penalty, on the same draw
    plain.actor.load_state_dict(a.actor.state_dict())
    plain.critic.load_state_dict(a.critic.state_dict())
    plain.generator.set_state(state)
    base, _ = plain.actor_loss(obs, torch.tensor(0.2))
    mean = a.actor(obs)[0].detach().double()
    want = 2.5 * torch.tanh(mean).square().sum(-1).mean()
    # the difference of two float32 losses cancels: its error is bounded by a few u32 of the losses' own size
    # (16 u32 (|loss| + |base|)), plus the penalty's float32 rounding (16 u32 |want|), not relative to the difference
    bound = 16 * 2.0**-24 * (abs(float(loss)) + abs(float(base)) + abs(float(want)))
    assert float((loss - base).detach()) == pytest.approx(float(want), rel=0, abs=bound)
    # with a flat critic (its last layer zeroed) and alpha = 0 the penalty is the whole loss: its
    # gradient on the mean's bias is 2.5 * d|tanh m|^2/dm = 5 tanh(m) (1 - tanh(m)^2), toward a = 0
    with torch.no_grad():
        a.critic.weights[-1].zero_()
        a.critic.biases[-1].zero_()
    a.actor.zero_grad()
    a.actor_loss(obs, torch.tensor(0.0))[0].backward()
    g = a.actor.head.bias.grad[:2].double()
    t = torch.tanh(mean)
    # float32 autograd through tanh and a mean over the batch (~log2(batch) u32 each) against float64: rtol 1e-4
    np.testing.assert_allclose(g.numpy(), (5.0 * t * (1 - t.square())).mean(0).numpy(), rtol=1e-4)
    assert g[0] > 0 and g[1] < 0
    with pytest.raises(ValueError, match="prior_reg=-1.0"):
        make_sac_config("quick", prior_reg=-1.0)


def test_seat_press_lowers_z_from_the_seat_on_by_a_hand_computed_ramp():
    """with_seat_press (--kgrl-seat-press): m[n] z minus press * clip((n - n0 + 1) / 10, 0, 1), n0 the first row
    within 1 mm of the last z, found here by a plain loop; x, y, rotation and the gains (the null space) untouched."""
    from vkgrl_newton.kmp.demos import synthetic_demos
    from vkgrl_newton.kmp.prior import fit_prior
    from vkgrl_newton.kmp.tables import with_seat_press

    tables = fit_prior(synthetic_demos("PegInsert", 6, action_dim=6, seed=2), 4)
    press = 5e-3
    pressed = with_seat_press(tables, press)
    z = tables.mean[:, 2].numpy()
    n0 = next(n for n in range(len(z)) if abs(z[n] - z[-1]) < 1e-3)
    assert 0 < n0 < len(z) - 10  # the synthetic descent arrives before the end: the ramp is exercised whole
    want = np.array([z[n] - press * min(max((n - n0 + 1) / 10.0, 0.0), 1.0) for n in range(len(z))])
    # float64 both ways: one multiply and one subtract per row (~2 ulp of a ~0.03 m value, ~1e-17 m)
    np.testing.assert_allclose(pressed.mean[:, 2].numpy(), want, rtol=0, atol=1e-15)
    assert pressed.mean[n0 - 1, 2] == tables.mean[n0 - 1, 2] and pressed.mean[-1, 2] < tables.mean[-1, 2] - 0.99 * press
    np.testing.assert_array_equal(np.delete(pressed.mean.numpy(), 2, axis=1), np.delete(tables.mean.numpy(), 2, axis=1))
    assert torch.equal(pressed.gain, tables.gain) and with_seat_press(tables, 0.0) is tables
    for bad in (-1e-3, math.nan, math.inf):
        with pytest.raises(ValueError, match="seat press"):
            with_seat_press(tables, bad)


def test_reach_floor_lifts_short_axes_by_brute_force_over_the_action_corners():
    """Every corner of [-1, 1]^4 (the extremes of a linear map) moves x and y by at least the floor;
    axes already past it, the other axes and the prior's mean (a = 0) are untouched."""
    from vkgrl_newton.kmp.demos import synthetic_demos
    from vkgrl_newton.kmp.prior import fit_prior
    from vkgrl_newton.kmp.tables import null_space_reach, with_reach_floor
    from vkgrl_newton.tasks import get_task

    spec = get_task("PegInsert")
    w = np.array([spec.w_pos] * 3 + [spec.w_rot] * 3)
    tables = fit_prior(synthetic_demos("PegInsert", 6, action_dim=6, seed=2), 4)
    floor = 2e-3
    lifted = with_reach_floor(tables, floor, w)
    corners = np.array(list(itertools.product((-1.0, 1.0), repeat=4)))  # (16, 4) in (x, y, z, yaw)
    zeta = np.zeros((len(corners), 6))
    zeta[:, [0, 1, 2, 5]] = corners * w[[0, 1, 2, 5]]

    def brute_reach(gain):  # (S, 6): the largest |B[n] zeta| of an axis over the corners
        return np.abs(np.einsum("sij,cj->sci", gain.numpy(), zeta)).max(1)

    before, after = brute_reach(tables.gain), brute_reach(lifted.gain)
    # float64 throughout (tables, brute force and floor): each reach is a sum of 4-6 products, so the two
    # orders of summation differ by ~6 ulp (~1e-15 relative); rtol 1e-12 / 1e-9 leave 3-6 orders of
    # margin on either CPU, atol 1e-15 m covers the rows whose reach is ~0 (rx, ry in 4D)
    np.testing.assert_allclose(null_space_reach(tables.gain, w).numpy(), before, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(after[:, :2], np.maximum(before[:, :2], floor), rtol=1e-9, atol=1e-15)
    assert (before[:, :2] < floor).any() and (before[:, :2] > floor).any()  # both cases are exercised
    np.testing.assert_array_equal(after[:, 2:], before[:, 2:])
    assert torch.equal(lifted.mean, tables.mean) and with_reach_floor(tables, 0.0, w) is tables
    # z alone (--kgrl-reach-floor-z): z lifted, x, y and the rest untouched (the float64 bounds above)
    floor_z = 0.5 * float(before[:, 2].max())  # a floor some rows pass and some do not
    after_z = brute_reach(with_reach_floor(tables, floor_z, w, axes=(2,)).gain)
    np.testing.assert_allclose(after_z[:, 2], np.maximum(before[:, 2], floor_z), rtol=1e-9, atol=1e-15)
    assert (before[:, 2] < floor_z).any() and (before[:, 2] > floor_z).any()
    np.testing.assert_array_equal(np.delete(after_z, 2, axis=1), np.delete(before, 2, axis=1))
    for bad in (-1e-3, math.nan, math.inf):
        with pytest.raises(ValueError, match="reach floor"):
            with_reach_floor(tables, bad, w)


def test_cached_evaluation_computes_once_per_key_and_restores_nan(tmp_path):
    from vkgrl_newton.results.paired import cached_evaluation

    calls = []

    def compute():
        calls.append(1)
        return {"success_rate": 0.25, "time_to_first_success_s": math.nan,
                "per_episode": [{"world_success": [1.0, math.nan], "world_contact_force": [0.5, 2.0]}]}

    key = {"task": "PegInsert", "eval_seed": 10_000}
    first, reused = cached_evaluation(tmp_path, key, compute, log=lambda m: None)
    again, reused_again = cached_evaluation(tmp_path, key, compute, log=lambda m: None)
    assert (reused, reused_again, len(calls)) == (False, True, 1)
    assert again["success_rate"] == 0.25 and math.isnan(again["time_to_first_success_s"])
    assert again["per_episode"][0]["world_contact_force"] == [0.5, 2.0]
    assert math.isnan(again["per_episode"][0]["world_success"][1])
    (file,) = (tmp_path / "evaluations").glob("*.json")
    json.loads(file.read_text(), parse_constant=lambda c: pytest.fail(f"bare {c} in the cache file"))
    cached_evaluation(tmp_path, {**key, "eval_seed": 1}, compute, log=lambda m: None)  # another input: evaluated
    assert len(calls) == 2
    file.write_text("{ damaged")
    _, reused = cached_evaluation(tmp_path, key, compute, log=lambda m: None)
    assert not reused and len(calls) == 3 and json.loads(file.read_text())["result"]["success_rate"] == 0.25


def test_cached_evaluation_is_per_processor(tmp_path, monkeypatch):
    """An evaluation made on one CPU is not reused on a CPU of another model (their float32 rounding seats other
    episodes): the cache keys on runtime.processor_name of the key's device, and the stored key names it."""
    import vkgrl_newton.runtime as runtime
    from vkgrl_newton.results.paired import cached_evaluation

    calls = []

    def compute():
        calls.append(1)
        return {"success_rate": float(len(calls))}

    key = {"task": "PegInsert", "device": "cpu"}
    zen3, zen4 = "AMD EPYC (family 25 model 1)", "AMD EPYC (family 25 model 17)"
    monkeypatch.setattr(runtime, "processor_name", lambda device: zen4)
    first, _ = cached_evaluation(tmp_path, key, compute, log=lambda m: None)
    monkeypatch.setattr(runtime, "processor_name", lambda device: zen3)
    other, reused = cached_evaluation(tmp_path, key, compute, log=lambda m: None)
    assert (first["success_rate"], other["success_rate"], reused) == (1.0, 2.0, False)
    again, reused = cached_evaluation(tmp_path, key, compute, log=lambda m: None)
    assert (again["success_rate"], reused, len(calls)) == (2.0, True, 2)
    stored = sorted(json.loads(f.read_text())["key"]["processor"] for f in (tmp_path / "evaluations").glob("*.json"))
    assert stored == [zen3, zen4]


def test_processor_name_tells_cpu_models_apart(tmp_path, monkeypatch):
    """A cloud CPU's model name is masked ("AMD EPYC" on a Zen 3 and a Zen 4 alike): processor_name adds
    /proc/cpuinfo's family and model numbers (read here from a file in that format), keeps the name alone where
    there are none, and names a CUDA device by the GPU."""
    import types

    import warp as wp

    import vkgrl_newton.runtime as runtime

    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: AuthenticAMD\ncpu family\t: 25\nmodel\t\t: 17\n"
                    "model name\t: AMD EPYC\n\nprocessor\t: 1\ncpu family\t: 99\nmodel\t\t: 99\n")
    assert runtime._cpuinfo_fields("cpu family", "model", path=str(info)) == {"cpu family": "25", "model": "17"}
    assert runtime._cpuinfo_fields("model", path=str(tmp_path / "none")) == {}
    monkeypatch.setattr(runtime, "cpu_model", lambda: "AMD EPYC")
    for numbers, name in (({"cpu family": "25", "model": "1"}, "AMD EPYC (family 25 model 1)"),
                          ({"cpu family": "25", "model": "17"}, "AMD EPYC (family 25 model 17)"),
                          ({}, "AMD EPYC")):
        monkeypatch.setattr(runtime, "_cpuinfo_fields", lambda *names, n=numbers: n)
        assert runtime.processor_name("cpu") == name
    monkeypatch.setattr(wp, "get_device", lambda d: types.SimpleNamespace(name=f"NVIDIA H100 as {d}"))
    assert runtime.processor_name("cuda:0") == "NVIDIA H100 as cuda:0"


def test_behaviour_cloning_term_against_a_float64_computation():
    """actor_loss with the prior buffer's actions adds bc_weight * mean|Q| * mean |tanh(mean) - a|^2
    over the last rows alone (TD3+BC's scaling), on the same draw of the policy's sample."""
    a = agent(prior_rollouts=32, prior_ratio=0.25, bc_weight=0.4, cpu_matmul="torch")
    obs, alpha = torch.randn(16, 3, generator=torch.Generator().manual_seed(5)), torch.tensor(0.2)
    demo = torch.tensor([[0.5, -0.25]] * 4)  # the actions of the last 4 rows
    state = a.generator.get_state()
    plain, _ = a.actor_loss(obs, alpha)
    a.generator.set_state(state)
    with_bc, _ = a.actor_loss(obs, alpha, demo)
    a.generator.set_state(state)  # the same draw, by hand in float64
    mean, log_std = (t.double() for t in a.actor(obs))
    u = mean + log_std.exp() * torch.randn(mean.shape, generator=a.generator).double()
    q = a.critic(obs, torch.tanh(u).float()).detach().double().min(dim=0).values
    want = 0.4 * q.abs().mean() * (torch.tanh(mean[-4:]) - demo.double()).square().sum(-1).mean()
    assert float(want.detach()) > 1e-3  # a term that is there
    # float32 loss terms of magnitude ~|Q|: a few ulps of each, summed over 16 rows
    assert float((with_bc - plain).detach()) == pytest.approx(float(want.detach()), rel=1e-4, abs=1e-5)
    with pytest.raises(ValueError, match="bc_weight > 0 clones"):
        make_sac_config("quick", bc_weight=0.4)
    with pytest.raises(ValueError, match="bc_weight=-1"):
        make_sac_config("quick", bc_weight=-1.0, prior_rollouts=8, prior_ratio=0.5)


def test_behaviour_cloning_pulls_the_actor_to_the_prior_buffers_actions():
    """The update clones the prior buffer's rows and only those: with the demonstrator at d and the
    online data at -d (rewards alike), the deterministic action on the demonstration states ends near d,
    for d = +0.6 and for d = -0.6, whichever way the critic's own extrapolation leans."""
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(128, 3, generator=g)
    for d in (0.6, -0.6):
        a = agent(prior_rollouts=64, prior_ratio=0.5, bc_weight=2.0, policy_delay=1, gradient_steps=300,
                  init_alpha=0.01, learning_starts=64)
        for k in range(8):  # 4 batches of demonstrations (d), then 4 online batches (-d)
            act = torch.full((16, 2), d if k < 4 else -d)
            a.add(obs[16 * k:16 * (k + 1)], act, torch.ones(16), obs[16 * k:16 * (k + 1)], torch.zeros(16))
        a.update()
        final = a.act(obs[:64], deterministic=True)
        assert (final - d).abs().max() < 0.15, (d, final)


def test_agent_policy_acts_with_the_mean_or_with_samples(capsys):
    """evaluate.py --stochastic: AgentPolicy(deterministic=False) acts with the agent's own samples
    (its generator's draws, as in training), the default with tanh of the mean."""
    from vkgrl_newton.envs.evaluation import AgentPolicy

    class Echo:  # an env whose step returns the action it was given
        def step(self, action):
            return action

    a = agent()
    obs = torch.randn(8, 3, generator=torch.Generator().manual_seed(3))
    mean = AgentPolicy(a).step(Echo(), obs)
    assert torch.equal(mean, a.act(obs, deterministic=True))
    state = a.generator.get_state()
    sampled = AgentPolicy(a, deterministic=False).step(Echo(), obs)
    a.generator.set_state(state)
    assert torch.equal(sampled, a.act(obs)) and not torch.allclose(sampled, mean)
    from scripts import load_script

    with pytest.raises(SystemExit):  # a policy of its own has no samples to draw
        load_script("evaluate").main(["--stochastic", "--device", "cpu"])
    assert "--stochastic samples a trained policy's actions: give --checkpoint" in capsys.readouterr().err
