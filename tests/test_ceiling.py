"""tools/ceiling.py's failure categories on constructed episode records (no physics), and the privileged oracle
policy (envs.evaluation.KMPOraclePolicy) against a float64 computation of eta = m[n] + G[n] zeta."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from vkgrl_newton.tools.ceiling import (BLOWN_OFFSET, CATEGORIES, CEILING_GEOMETRY, DESCENT, PRESS_MIN, REST_BAND, SEAT_HAIR,
                                        category_counts, classify)


def rec(task="PegInsert", **kw) -> dict:
    """A failed episode resting on the face 2 mm off the axis, grasp unchanged; kw overrides (lengths in mm)."""
    g = CEILING_GEOMETRY[task]
    r = {"task": task, "success": False, "success_any": False, "height_final_mm": 1e3 * g.rest_height,
         "lateral_final_mm": 1e3 * g.catch + 1.0, "offset_change_xy_mm": 0.1}
    r.update(kw)
    return r


def test_thresholds_come_from_the_part_geometry():
    peg = CEILING_GEOMETRY["PegInsert"]
    assert peg.catch == pytest.approx(0.057e-3 + 0.75e-3)  # radial clearance + chamfer
    assert peg.rest_height == pytest.approx(0.025) and peg.entry_depth == pytest.approx(0.75e-3)
    assert peg.success_z == pytest.approx(1e-3) and peg.success_xy == pytest.approx(2.5e-3)
    gear = CEILING_GEOMETRY["GearMesh"]
    assert gear.catch == pytest.approx(0.2e-3 + 0.5e-3) and gear.rest_height == pytest.approx(0.020)
    assert gear.success_z == pytest.approx(1e-3)
    nut = CEILING_GEOMETRY["NutThread"]
    assert nut.rest_height == pytest.approx(3e-3) and nut.success_z == pytest.approx(0.75e-3)
    assert nut.catch == pytest.approx(0.25e-3 + 1.5e-3) and nut.entry_depth == pytest.approx(1.5e-3)


@pytest.mark.parametrize("task", sorted(CEILING_GEOMETRY))
def test_one_record_per_category(task):
    g = CEILING_GEOMETRY[task]
    mm = lambda m: 1e3 * m  # noqa: E731
    cases = {
        "success": rec(task, success=True, success_any=True, height_final_mm=0.1, lateral_final_mm=0.05),
        "seated_then_lost": rec(task, success_any=True),
        "seated_but_test_missed": rec(task, height_final_mm=mm(g.success_z) + 0.1, lateral_final_mm=0.1),
        "tilted_or_slipped_in_grasp": rec(task, offset_change_xy_mm=mm(g.catch) + 0.2, landing_lateral_mm=0.1),
        "jammed_in_hole": rec(task, height_final_mm=mm(g.rest_height - g.entry_depth) - 0.2, lateral_final_mm=0.1,
                              press_final_mm=5.0, descent_last_mm=0.1),
        "held_above_seat": rec(task, height_final_mm=mm(g.rest_height - g.entry_depth) - 0.2, lateral_final_mm=0.1,
                               press_final_mm=0.5),
        "time_out_inserting": rec(task, height_final_mm=mm(g.rest_height) - 0.1, lateral_final_mm=0.1,
                                  descent_last_mm=1.0),
        "jammed_on_chamfer": rec(task, lateral_final_mm=mm(g.catch) - 0.1),
        "time_out_searching": rec(task),
        "other": rec(task, blown=True),
    }
    assert set(cases) == set(CATEGORIES)
    for want, r in cases.items():
        assert classify(r) == want, (want, r)
    counts = category_counts([{**r, "category": classify(r)} for r in cases.values()])
    assert counts == {c: 1 for c in CATEGORIES}


def test_boundaries():
    g = CEILING_GEOMETRY["PegInsert"]
    mm = lambda m: 1e3 * m  # noqa: E731
    eps = 1e-6  # mm
    # the hair: seated within SEAT_HAIR of the test's height, centred
    assert classify(rec(height_final_mm=mm(g.success_z + SEAT_HAIR) - eps, lateral_final_mm=0.0)) == "seated_but_test_missed"
    assert classify(rec(height_final_mm=mm(g.success_z + SEAT_HAIR) + eps, lateral_final_mm=0.0)) == "jammed_in_hole"
    # centring by a hair: seated but 2.6 mm off (the test wants < 2.5 mm)
    assert classify(rec(height_final_mm=0.0, lateral_final_mm=mm(g.success_xy + SEAT_HAIR) - eps)) == "seated_but_test_missed"
    assert classify(rec(height_final_mm=0.0, lateral_final_mm=mm(g.success_xy + SEAT_HAIR) + eps)) == "jammed_in_hole"
    # the grasp: an in-hand change up to the catch is not a slip; beyond BLOWN_OFFSET the part has left the hand
    assert classify(rec(offset_change_xy_mm=mm(g.catch) - eps, landing_lateral_mm=0.1)) == "time_out_searching"
    assert classify(rec(offset_change_xy_mm=mm(g.catch) + eps, landing_lateral_mm=0.1)) == "tilted_or_slipped_in_grasp"
    # ... only where it was aimed within the catch (on landing or at the end): pressed beside the entry, the miss first
    assert classify(rec(offset_change_xy_mm=2.5, landing_lateral_mm=mm(g.catch) + eps)) == "time_out_searching"
    assert classify(rec(offset_change_xy_mm=2.5, landing_lateral_mm=None)) == "time_out_searching"
    assert classify(rec(offset_change_xy_mm=2.5, landing_lateral_mm=mm(g.catch) - eps)) == "tilted_or_slipped_in_grasp"
    assert classify(rec(offset_change_xy_mm=2.5, lateral_final_mm=mm(g.catch) - eps,
                        height_final_mm=19.0)) == "tilted_or_slipped_in_grasp"  # steered over the hole, tilted, jammed
    assert classify(rec(offset_change_xy_mm=mm(BLOWN_OFFSET) + eps)) == "other"
    assert classify(rec(height_final_mm=float("nan"))) == "other"
    # still descending over the last steps: time ran out while inserting (above the rest band: not yet in contact)
    assert classify(rec(lateral_final_mm=0.1, descent_last_mm=1e3 * DESCENT + eps)) == "time_out_inserting"
    assert classify(rec(lateral_final_mm=0.1, descent_last_mm=1e3 * DESCENT - eps)) == "jammed_on_chamfer"
    assert classify(rec(height_final_mm=mm(g.rest_height + REST_BAND) + eps, descent_last_mm=5.0)) == "time_out_searching"
    # inside and not seated: held there by the command (press under PRESS_MIN), or pressed and jammed
    assert classify(rec(height_final_mm=5.0, press_final_mm=1e3 * PRESS_MIN - eps)) == "held_above_seat"
    assert classify(rec(height_final_mm=5.0, press_final_mm=1e3 * PRESS_MIN + eps)) == "jammed_in_hole"
    assert classify(rec(height_final_mm=5.0, press_final_mm=-3.0)) == "held_above_seat"  # commanded above the TCP
    # the entry's foot: below it the part is inside
    foot = mm(g.rest_height - g.entry_depth)
    assert classify(rec(height_final_mm=foot - eps, lateral_final_mm=0.3)) == "jammed_in_hole"
    assert classify(rec(height_final_mm=foot + eps, lateral_final_mm=0.3)) == "jammed_on_chamfer"
    # on the entry: within the catch jammed, beyond it beside the hole; above the rest band: not touching
    assert classify(rec(lateral_final_mm=mm(g.catch) - eps)) == "jammed_on_chamfer"
    assert classify(rec(lateral_final_mm=mm(g.catch) + eps)) == "time_out_searching"
    assert classify(rec(height_final_mm=mm(g.rest_height + REST_BAND) + eps, lateral_final_mm=0.1)) == "time_out_searching"
    # success first, then seated at some step
    assert classify(rec(success=True, success_any=True, blown=True)) == "success"
    assert classify(rec(success_any=True, offset_change_xy_mm=50.0)) == "seated_then_lost"


def fake_env(num_envs: int, seed: int = 0):
    from vkgrl_newton.rotations import quat_from_euler_xyz
    from vkgrl_newton.tasks import get_task

    g = torch.Generator().manual_seed(seed)
    spec = get_task("PegInsert")
    yaw = torch.rand(num_envs, generator=g) * 2 * math.pi
    env = SimpleNamespace(
        task=spec, num_envs=num_envs, num_actions=4, max_episode_length=spec.episode_steps, tdev=torch.device("cpu"),
        device="cpu", step_index=torch.zeros(num_envs, dtype=torch.int32),
        target_frame_pos_w=(torch.rand(num_envs, 3, generator=g) - 0.5),
        ref_quat_w=quat_from_euler_xyz(torch.full_like(yaw, math.pi), torch.zeros_like(yaw), yaw).float().contiguous(),
        episode_length_buf=torch.zeros(num_envs, dtype=torch.long),
        target_base_w=torch.rand(num_envs, 3, generator=g), held_p=torch.zeros(num_envs, 3))
    env.held_pose = lambda: (env.held_p, torch.zeros(num_envs, 4))
    return env


def test_oracle_policy_steers_by_the_true_lateral_error(wp_cpu):
    """Two worlds blocked 20 mm above the prior's seat from step 30: a = 0 until the search's n_min, then x, y of
    eta = the TCP's minus 1.5 x the held part's true lateral error (float64 reference), z 1 mm below the TCP;
    one drops 1.5 mm at step 80 (beyond the oracle's 1 mm settle): x, y frozen, z the prior's."""
    from vkgrl_newton.envs.evaluation import ORACLE_GAIN, ORACLE_PARAMS, KMPOraclePolicy
    from vkgrl_newton.kmp.demos import synthetic_demos
    from vkgrl_newton.kmp.prior import fit_prior

    tables = fit_prior(synthetic_demos("PegInsert", 6, action_dim=6, seed=0), action_dim=4)
    env = fake_env(2)
    p = ORACLE_PARAMS
    assert p.settle_mm == 1.0 and ORACLE_GAIN == 1.5
    policy = KMPOraclePolicy.with_floors(tables, env)
    mean = policy.path.tables.mean.numpy()
    gain = policy.path.tables.gain.numpy()
    w = np.full(3, env.task.w_pos)
    high = mean[-1, 2] + 20e-3
    lateral = np.array([[1.2e-3, -0.7e-3], [0.4e-3, 0.9e-3]])
    env.held_p[:, :2] = env.target_base_w[:, :2] + torch.from_numpy(lateral).float()
    drop_at, checked, held = 80, 0, None
    for n in range(120):
        env.episode_length_buf.fill_(n)
        rel = mean[[n, n], :3].copy()  # x, y follow the prior's; z held 20 mm over the seat from step 30
        if n >= 30:
            rel[:, 2] = high
        if n >= drop_at:
            rel[1, 2] = high - 1.5e-3
        obs = torch.zeros(2, 8)
        obs[:, 1:4] = torch.from_numpy(rel).float()
        a = policy.actions(env, {"policy": obs}).double().numpy()
        assert np.all(a[:, 3] == 0)
        if n < p.n_min:
            assert np.all(a == 0), n
            continue
        eta = mean[n, :3] + np.einsum("ij,ej->ei", gain[n][:3, :3], a[:, :3] * w)
        rel32 = obs[:, 1:4].double().numpy()
        lat32 = (env.held_p - env.target_base_w)[:, :2].double().numpy()
        want = np.c_[rel32[:, :2] - 1.5 * lat32, rel32[:, 2] - 1e-3]
        for e in range(2) if n < drop_at else range(1):
            # within the floored reach: eta as wanted. Error: the policy's float32 solve of B a = want - m
            # (|want| ~ 0.05 m, B's condition ~1e2: ~1e2 x 6e-8 x 0.05 m ~ 3e-7 m) and float32 a; 1e-6 m bounds it
            if np.all(np.abs(a[e, :3]) < 1):
                np.testing.assert_allclose(eta[e], want[e], atol=1e-6)
                checked += 1
            else:  # clipped: toward it
                zeta = np.linalg.solve(gain[n][:3, :3], want[e] - mean[n, :3])
                assert np.all(np.sign(a[e, :3]) == np.sign(zeta)), n
        if n >= drop_at:
            if held is None:
                held = want[1, :2].copy()
            want1 = np.r_[held, mean[n, 2]]
            if np.all(np.abs(a[1, :3]) < 1):  # (the same float32 solve's error as above)
                np.testing.assert_allclose(eta[1], want1, atol=1e-6)
                checked += 1
    assert policy.found.tolist() == [False, True] and checked > 40


def test_noisy_oracle_steers_by_the_lateral_error_plus_a_bias_held_per_episode(wp_cpu):
    """lateral_noise_mm sigma: x, y of eta = the TCP's minus 1.5 x (true lateral error + b), b drawn at each episode's
    start, held through it, redrawn at the next; b ~ N(0, sigma^2) per axis (sample moments over 4 096 worlds);
    sigma 0 steers as the plain oracle."""
    from vkgrl_newton.envs.evaluation import KMPOraclePolicy
    from vkgrl_newton.kmp.demos import synthetic_demos
    from vkgrl_newton.kmp.prior import fit_prior

    tables = fit_prior(synthetic_demos("PegInsert", 6, action_dim=6, seed=0), action_dim=4)
    for bad in (-1.0, math.inf, math.nan):
        with pytest.raises(ValueError, match="lateral_noise_mm"):
            KMPOraclePolicy.with_floors(tables, fake_env(2), lateral_noise_mm=bad)
    E, sigma = 4096, 0.8
    env = fake_env(E)
    noisy = KMPOraclePolicy.with_floors(tables, env, lateral_noise_mm=sigma, noise_seed=3)
    plain = KMPOraclePolicy.with_floors(tables, env)
    mean = noisy.path.tables.mean.numpy()
    env.held_p[:, :2] = env.target_base_w[:, :2] + 1e-3 * (torch.rand(E, 2) - 0.5)
    high = mean[-1, 2] + 20e-3
    biases = []
    assert noisy.params.n_min == 60
    gain = noisy.path.tables.gain.numpy()
    w = np.full(3, env.task.w_pos)
    for episode in range(2):
        for n in (0, 1, 70, 71):  # held 20 mm over the seat from step 1: blocked at 70 (n_min 60), steering at once
            env.episode_length_buf.fill_(n)
            rel = np.repeat(mean[[n], :3], E, 0)
            rel[:, 2] = high if n >= 1 else rel[:, 2]
            obs = torch.zeros(E, 8)
            obs[:, 1:4] = torch.from_numpy(rel).float()
            a = noisy.actions(env, {"policy": obs}).double().numpy()
            plain.actions(env, {"policy": obs})
            b = noisy.bias.numpy().copy()
            if n == 0:
                biases.append(b)
            np.testing.assert_array_equal(b, biases[-1])  # held through the episode
            lat = (env.held_p - env.target_base_w)[:, :2].double().numpy()
            if n >= 70:
                assert bool((noisy.since == 70).all())
                r32 = obs[:, 1:3].double().numpy()
                want = r32 - 1.5 * (lat + b)
                np.testing.assert_allclose(noisy._last[0][:, :2].numpy(), want, atol=1e-12)
                np.testing.assert_allclose(plain._last[0][:, :2].numpy(), r32 - 1.5 * lat, atol=1e-12)
                # the action applied: eta's x, y as wanted where within reach. Error: a is float32 (|a| <= 1, 6e-8
                # relative) mapped through G's ~1e2-conditioned rows onto |want| ~ 0.05 m: ~3e-7 m; 1e-6 m bounds it
                eta = mean[n, :3] + np.einsum("ij,ej->ei", gain[n][:3, :3], a[:, :3] * w)
                inside = np.all(np.abs(a[:, :3]) < 1, axis=1)
                assert inside.sum() > E // 2
                np.testing.assert_allclose(eta[inside, :2], want[inside], atol=1e-6)
    assert not np.any(biases[0] == biases[1])  # redrawn at the next start
    for b in biases:  # sample sd within 4.5 of its own standard errors (sigma / sqrt(2 E) ~ 1.1 %); mean likewise
        np.testing.assert_allclose(b.std(0), 1e-3 * sigma, rtol=4.5 / math.sqrt(2 * E))
        assert np.all(np.abs(b.mean(0)) < 4.5 * 1e-3 * sigma / math.sqrt(E))
    assert np.all(plain.bias.numpy() == 0)
    # the inside take-over holds x, y at the TCP's less 1.5 (e + b) as well
    env2 = fake_env(2)
    inside = KMPOraclePolicy.with_floors(tables, env2, push_mm=3.0, inside_mm=24.25, lateral_noise_mm=sigma)
    obs = torch.zeros(2, 8)
    obs[:, 1:4] = torch.from_numpy(mean[[0, 0], :3]).float()
    inside.actions(env2, {"policy": obs})  # step 0: the bias drawn
    env2.episode_length_buf.fill_(110)
    d = np.array([[0.05e-3, -0.02e-3, 2.0e-3], [0.0, 0.0, 24.5e-3]])
    env2.held_p[:] = env2.target_base_w + torch.from_numpy(d).float()
    inside.actions(env2, {"policy": obs})
    dd = (env2.held_p - env2.target_base_w)[0, :2].double().numpy()
    b = inside.bias.numpy()[0]
    assert inside.found.tolist() == [True, False] and np.all(b != 0)
    np.testing.assert_allclose(inside.held[0].numpy(), obs[0, 1:3].double().numpy() - 1.5 * (dd + b), atol=1e-12)


def test_centre_policy_is_blind_and_steers_the_tcp_over_the_observed_target(wp_cpu):
    """KMPCentrePolicy reads the observation only (the privileged poses raise): once blocked, x, y of eta = the TCP's
    minus 1.5 x its own x, y relative to the observed target (float64 reference; the search's blocked test); after a
    1.5 mm drop (its 1 mm settle) x, y frozen and z push_mm below the prior's seat."""
    from vkgrl_newton.envs.evaluation import KMPCentrePolicy
    from vkgrl_newton.kmp.demos import synthetic_demos
    from vkgrl_newton.kmp.prior import fit_prior

    tables = fit_prior(synthetic_demos("PegInsert", 6, action_dim=6, seed=0), action_dim=4)
    env = fake_env(2)

    def privileged():
        raise AssertionError("a blind policy read a privileged pose")

    env.held_pose = privileged
    env.target_base_w = env.held_p = None
    policy = KMPCentrePolicy.with_floors(tables, env, push_mm=3.0)
    p = policy.params
    mean, gain = policy.path.tables.mean.numpy(), policy.path.tables.gain.numpy()
    w = np.full(3, env.task.w_pos)
    high = mean[-1, 2] + 20e-3
    off = np.array([[1.1e-3, -0.6e-3], [-0.3e-3, 0.8e-3]])  # the TCP off the observed target, x, y
    drop_at, checked, held = 80, 0, None
    for n in range(120):
        env.episode_length_buf.fill_(n)
        rel = np.c_[off, np.full(2, high if n >= 30 else mean[n, 2])]
        if n >= drop_at:
            rel[1, 2] = high - 1.5e-3
        obs = torch.zeros(2, 8)
        obs[:, 1:4] = torch.from_numpy(rel).float()
        a = policy.actions(env, {"policy": obs}).double().numpy()
        if n < p.n_min:
            assert np.all(a == 0), n
            continue
        r32 = obs[:, 1:4].double().numpy()
        want = np.c_[r32[:, :2] - 1.5 * r32[:, :2], r32[:, 2] - 1e-3]
        if n >= drop_at:
            held = want[1, :2].copy() if held is None else held
            want[1] = np.r_[held, mean[n, 2] - 3e-3]
        eta = mean[n, :3] + np.einsum("ij,ej->ei", gain[n][:3, :3], a[:, :3] * w)
        for e in range(2):
            if np.all(np.abs(a[e, :3]) < 1):  # float32 a through G (condition ~1e2) on |want| ~ 0.05 m: ~3e-7 m
                np.testing.assert_allclose(eta[e], want[e], atol=1e-6)
                checked += 1
    assert policy.found.tolist() == [False, True] and checked > 40
    # spiral: the search's spiral about the observed target, led by track x the lag (float64, from the closed form)
    spiral = KMPCentrePolicy.with_floors(tables, env, push_mm=3.0, spiral=True)
    for n in range(p.n_min, p.n_min + 30):
        env.episode_length_buf.fill_(n)
        obs = torch.zeros(2, 8)
        obs[:, 1:4] = torch.from_numpy(np.c_[off, np.full(2, high)]).float()
        spiral.actions(env, {"policy": obs})
        k = n - spiral.since.numpy()
        b = p.pitch_mm * 1e-3 / (2 * math.pi)
        th = np.sqrt(2 * p.speed_mm * 1e-3 * k / b)
        s = b * th[:, None] * np.c_[np.cos(th), np.sin(th)]
        np.testing.assert_allclose(spiral._last[0][:, :2].numpy(), s + p.track * (s - obs[:, 1:3].double().numpy()),
                                   atol=1e-12)
    assert spiral.since.tolist() == [p.n_min, p.n_min]


def test_the_camera_estimate_steers_the_oracle_and_the_centre_policy(wp_cpu):
    """lateral_estimate in place of the truth: the oracle's x, y of eta = the TCP's minus 1.5 (estimate + b), with the
    estimate read once a step (it renders) and the true lateral error never used for x, y; the inside take-over holds
    x, y at the TCP's less 1.5 x the estimate; KMPCentrePolicy steers by it with no privileged read, and refuses it
    beside the spiral."""
    from vkgrl_newton.envs.evaluation import KMPCentrePolicy, KMPOraclePolicy
    from vkgrl_newton.kmp.demos import synthetic_demos
    from vkgrl_newton.kmp.prior import fit_prior

    tables = fit_prior(synthetic_demos("PegInsert", 6, action_dim=6, seed=0), action_dim=4)
    E = 4
    env = fake_env(E)
    env.held_p[:, :2] = env.target_base_w[:, :2] + 1e-3  # the truth: +1 mm on x and y in every world
    est = torch.tensor([[0.3e-3, -0.2e-3], [-0.9e-3, 0.4e-3], [0.0, 0.0], [1.1e-3, 1.3e-3]], dtype=torch.float64)
    calls = []

    def estimate(e):
        calls.append(int(e.episode_length_buf[0]))
        return est

    def blocked_at_70(policy):
        """Steps 0, 1, 70, 71 held 20 mm over the seat from step 1 (n_min 60: blocked at 70); the wanted x, y at 70
        and at 71 against the TCP's less 1.5 x the estimate."""
        mean = policy.path.tables.mean.numpy()
        for n in (0, 1, 70, 71):
            env.episode_length_buf.fill_(n)
            rel = np.repeat(mean[[n], :3], E, 0)
            rel[:, 2] = mean[-1, 2] + 20e-3 if n >= 1 else rel[:, 2]
            obs = torch.zeros(E, 8)
            obs[:, 1:4] = torch.from_numpy(rel).float()
            policy.actions(env, {"policy": obs})
            if n >= 70:
                r32 = obs[:, 1:3].double().numpy()
                np.testing.assert_allclose(policy._last[0][:, :2].numpy(), r32 - 1.5 * est.numpy(), atol=1e-12)
        return mean

    oracle = KMPOraclePolicy.with_floors(tables, env, lateral_estimate=estimate)
    mean = blocked_at_70(oracle)
    assert calls == [0, 1, 70, 71]  # once a step
    # the take-over of a part found inside unblocked: x, y at the TCP's less 1.5 x the estimate
    env2 = fake_env(2)
    inside = KMPOraclePolicy.with_floors(tables, env2, push_mm=3.0, inside_mm=24.25, lateral_estimate=lambda e: est[:2])
    env2.episode_length_buf.fill_(110)
    env2.held_p[:] = env2.target_base_w + torch.tensor([[0.05e-3, -0.02e-3, 2.0e-3], [0.0, 0.0, 24.5e-3]])
    obs = torch.zeros(2, 8)
    obs[:, 1:4] = torch.from_numpy(mean[[110, 110], :3]).float()
    inside.actions(env2, {"policy": obs})
    assert inside.found.tolist() == [True, False]
    np.testing.assert_allclose(inside.held[0].numpy(), obs[0, 1:3].double().numpy() - 1.5 * est[0].numpy(), atol=1e-12)
    # the centre policy: nothing privileged, x, y of eta = the TCP's minus 1.5 x the estimate once blocked

    def privileged():
        raise AssertionError("the centre policy read a privileged pose")

    env.held_pose = privileged
    blocked_at_70(KMPCentrePolicy.with_floors(tables, env, push_mm=3.0, lateral_estimate=estimate))
    with pytest.raises(ValueError, match="spiral and lateral_estimate"):
        KMPCentrePolicy.with_floors(tables, env, spiral=True, lateral_estimate=estimate)


def test_the_latent_lateral_estimate_turns_the_probe_into_the_world_and_scores_near_hole_frames():
    """lateral_from_image: the probe's image-frame vector (fixed tip minus held) turned into the world by the camera's
    optical pose and negated (scipy's rotation as the reference); LatentLateral's score counts only the near-hole
    frames (the held part within 10 mm, xy, and less than 20 mm above the tip)."""
    from scipy.spatial.transform import Rotation

    from vkgrl_newton.envs.camera_latent import LatentLateral
    from vkgrl_newton.vision.probe import lateral_from_image

    E = 5
    rng = np.random.default_rng(0)
    q = Rotation.random(E, random_state=1).as_quat()  # xyzw
    d_image = 1e-3 * rng.normal(size=(E, 3))
    out = lateral_from_image(torch.from_numpy(d_image), torch.from_numpy(q)).numpy()
    np.testing.assert_allclose(out, -Rotation.from_quat(q).apply(d_image)[:, :2], atol=1e-15)
    # the probe's own target, relative_in_image (R^T (tip - held)), comes back as the held part minus the tip, x, y
    from vkgrl_newton.vision.probe import relative_in_image

    g = np.zeros((E, 13))
    g[:, 0:6] = rng.normal(size=(E, 6))
    g[:, 9:13] = q
    back = lateral_from_image(torch.from_numpy(relative_in_image(g)), torch.from_numpy(q)).numpy()
    np.testing.assert_allclose(back, g[:, 0:2] - g[:, 3:5], atol=1e-12)
    held = rng.normal(size=(E, 3))
    tip = held.copy()
    tip[:, :2] -= 1e-3 * np.array([[1, 0], [0, 2], [3, 0], [0, 0], [40, 0]])  # world 4 40 mm away: not near
    tip[:, 2] -= np.array([5e-3, 5e-3, 5e-3, 30e-3, 5e-3])  # world 3 30 mm above: not near
    env = SimpleNamespace(held_pose=lambda: (torch.from_numpy(held).float(), None),
                          fixed_tip_w=torch.from_numpy(tip).float())
    est = LatentLateral.__new__(LatentLateral)  # (its __init__ builds a real camera)
    est.sq, est.count = torch.zeros(2, dtype=torch.float64), torch.zeros((), dtype=torch.float64)
    assert est.rmse_mm() == {"x": None, "y": None, "frames": 0}
    est.score(env, torch.from_numpy(out))
    truth = (torch.from_numpy(held).float() - torch.from_numpy(tip).float()).double().numpy()[:, :2]
    score = est.rmse_mm()
    assert score["frames"] == 3
    # the same float64 operations on the same float32-rounded poses, summed in another order: ~1e-15 relative, so
    # 1e-9 holds on any CPU (no float32 step differs between the two sides)
    np.testing.assert_allclose([score["x"], score["y"]], 1e3 * np.sqrt(((out[:3] - truth[:3]) ** 2).mean(0)), rtol=1e-9)


def test_the_probe_in_torch_is_the_fitted_probe():
    """ProbeMLP(NearHoleRegressor.state()) reproduces scikit-learn's predictions (MLP and affine; float64: to
    rounding), and in float32 to float32's rounding of ~1e-3 m outputs."""
    from vkgrl_newton.vision.probe import NearHoleRegressor, ProbeMLP

    rng = np.random.default_rng(1)
    z = rng.normal(size=(300, 16))
    g = np.zeros((300, 13))
    g[:, 12] = 1.0
    g[:, 3:6] = 1e-3 * np.tanh(z[:, :3] + z[:, 3:6] ** 2)
    g[:, 2] = -1e-3
    for model in ("mlp", "linear"):
        reg = NearHoleRegressor(z, g, model=model)
        probe = ProbeMLP(reg.state())
        np.testing.assert_allclose(probe(torch.from_numpy(z)).numpy(), reg(z), rtol=0, atol=1e-15)
        # float32 input and weights' rounding (6e-8 relative) through a few 64-wide layers on ~1e-3 m: < 1e-8 m
        np.testing.assert_allclose(probe(torch.from_numpy(z).float()).double().numpy(), reg(z), rtol=0, atol=1e-8)


def test_the_near_hole_regressor_fits_only_near_hole_frames_and_recovers_a_linear_map():
    """NearHoleRegressor (linear model): where the image-frame target is an exact affine map of the latent on the
    near-hole frames, the fit recovers it (float64 least squares' error); far frames with other labels do not pull it;
    a latent of the wrong width is refused."""
    from vkgrl_newton.vision.probe import NearHoleRegressor, near_hole_mask, relative_in_image

    rng = np.random.default_rng(0)
    n, d = 400, 6
    z = rng.normal(size=(n, d))
    A, c = rng.normal(size=(d, 3)), rng.normal(size=3)
    g = np.zeros((n, 13))
    g[:, 12] = 1.0  # the identity camera rotation: image frame = world
    g[:, 3:6] = 1e-3 * (z @ A + c)  # fixed tip; held at 0: the target is the tip itself
    g[:, 2] = -1e-3  # the held part 1 mm below the tip: inside the 20 mm band
    g[np.arange(n) % 4 == 0, 0] = 0.05  # a quarter 50 mm away on x: outside the near-hole mask, labels off the map
    near = near_hole_mask(g)
    assert 0.5 * n < near.sum() < 0.75 * n + 1
    reg = NearHoleRegressor(z, g, model="linear")
    assert reg.num_fit == int(near.sum())
    # the map recovered on the near frames (ridge 1e-6 of the standardized inputs: ~1e-9 m of shrinkage)
    np.testing.assert_allclose(reg(z)[near], relative_in_image(g)[near], atol=1e-8)
    with pytest.raises(ValueError, match="columns"):
        reg(z[:, :3])


def test_oracle_takes_over_a_part_that_went_in_unblocked(wp_cpu):
    """inside_mm: a world whose part is found inside (true height above seated under inside_mm) without having been
    blocked is settled at once: x, y held at the TCP's less 1.5 e, z the TCP's less the true height less push_mm."""
    from vkgrl_newton.envs.evaluation import KMPOraclePolicy
    from vkgrl_newton.kmp.demos import synthetic_demos
    from vkgrl_newton.kmp.prior import fit_prior

    tables = fit_prior(synthetic_demos("PegInsert", 6, action_dim=6, seed=0), action_dim=4)
    env = fake_env(2)
    policy = KMPOraclePolicy.with_floors(tables, env, push_mm=3.0, inside_mm=24.25)
    mean, gain = policy.path.tables.mean.numpy(), policy.path.tables.gain.numpy()
    n = 110
    env.episode_length_buf.fill_(n)
    d = np.array([[0.05e-3, -0.02e-3, 2.0e-3], [0.0, 0.0, 24.5e-3]])  # world 0 inside 2 mm above its seat, 1 above
    env.held_p[:] = env.target_base_w + torch.from_numpy(d).float()
    obs = torch.zeros(2, 8)
    obs[:, 1:4] = torch.from_numpy(mean[[n, n], :3]).float()
    a = policy.actions(env, {"policy": obs}).double().numpy()
    assert policy.found.tolist() == [True, False] and np.all(a[1] == 0)
    rel = obs[0, 1:4].double().numpy()
    dd = (env.held_p - env.target_base_w)[0].double().numpy()
    want = np.r_[rel[:2] - 1.5 * dd[:2], rel[2] - dd[2] - 3e-3]
    eta = mean[n, :3] + gain[n][:3, :3] @ (a[0, :3] * env.task.w_pos)
    assert np.all(np.abs(a[0, :3]) < 1)
    np.testing.assert_allclose(eta, want, atol=1e-6)  # the float32 solve's error, as in the test above


def test_oracle_mesh_yaw_turns_the_gear_to_a_gap(wp_cpu):
    """mesh_pitch (GearMesh): once on, the yaw of eta is the meshing yaw's: the nearest TCP yaw at which the held
    gear's yaw (the TCP's plus its in-hand offset) less the fixed part's is a multiple of the pitch."""
    from vkgrl_newton.envs.evaluation import KMPOraclePolicy
    from vkgrl_newton.kmp.demos import synthetic_demos
    from vkgrl_newton.kmp.pose import pose_to_eta
    from vkgrl_newton.kmp.prior import fit_prior
    from vkgrl_newton.rotations import euler_xyz_from_quat, quat_from_euler_xyz, quat_mul

    tables = fit_prior(synthetic_demos("PegInsert", 6, action_dim=6, seed=0), action_dim=4)
    env = fake_env(2)
    pitch = 2 * math.pi / 19
    policy = KMPOraclePolicy.with_floors(tables, env, push_mm=3.0, inside_mm=24.25, mesh_pitch=pitch)
    tcp_yaw = torch.tensor([0.10, -0.05])
    off = torch.tensor([0.07, -0.12])  # the gear's yaw in the hand
    env.fixed_yaw = torch.tensor([0.2, 0.05])
    tcp_q = quat_from_euler_xyz(torch.full((2,), math.pi), torch.zeros(2), tcp_yaw)
    flip = torch.tensor((0.0, 1.0, 0.0, 0.0)).expand(2, 4)
    held_q = quat_mul(quat_from_euler_xyz(torch.full((2,), math.pi), torch.zeros(2), tcp_yaw + off), flip)
    env.tcp_p = env.target_frame_pos_w + torch.tensor([0.0, 0.0, 0.03])
    env.tcp_pose = lambda: (env.tcp_p, tcp_q)
    env.held_pose = lambda: (env.held_p, held_q)
    held_off = euler_xyz_from_quat(held_q.double())[2] - tcp_yaw.double()  # as the env's frames read it
    goal = policy.mesh_yaw(env)
    gear = goal + torch.atan2(torch.sin(held_off), torch.cos(held_off)) - env.fixed_yaw.double()
    k = gear / pitch
    # float64 throughout (goal from the same float64 yaws): residues of a few ulp of angles ~1 rad, ~1e-15; 1e-9 bounds
    # them on any CPU (libm's atan2/sin/cos differ by an ulp at most)
    assert torch.allclose(k, k.round(), atol=1e-9) and bool(((goal - tcp_yaw.double()).abs() <= pitch / 2 + 1e-9).all())
    n = 110  # both worlds inside: on
    env.episode_length_buf.fill_(n)
    env.held_p[:] = env.target_base_w + torch.tensor([0.0, 0.0, 2e-3])
    mean, gain = policy.path.tables.mean.numpy(), policy.path.tables.gain.numpy()
    obs = torch.zeros(2, 8)
    obs[:, 1:4] = torch.from_numpy(mean[[n, n], :3]).float()
    a = policy.actions(env, {"policy": obs}).double().numpy()
    q_goal = quat_from_euler_xyz(torch.full((2,), math.pi), torch.zeros(2), goal.float()).double()
    rz = pose_to_eta(env.tcp_p.double(), q_goal, env.target_frame_pos_w.double(), env.task.psi_ref)[:, 5].numpy()
    ax = [0, 1, 2, 5]
    w = np.array([env.task.w_pos] * 3 + [env.task.w_rot])
    unclipped = 0
    for e in range(2):
        eta = mean[n, ax] + gain[n][np.ix_(ax, ax)] @ (a[e] * w)
        if np.all(np.abs(a[e]) < 1):
            # the policy's float32 solve (B's condition ~1e2 x 6e-8 x |want| <= ~0.5 rad: 3e-6 rad) and the float32
            # goal quaternion (~1e-7 rad); 1e-5 rad bounds them
            np.testing.assert_allclose(eta[3], rz[e], atol=1e-5)
            unclipped += 1
        else:
            assert a[e, 3] != 0
    assert unclipped >= 1


def test_the_ceiling_table_is_the_committed_ceiling_runs():
    """results/ceiling_table.csv (what the learning curves draw) against the JSONs of docs/results/ceiling_40 it
    transcribes: each row's successes, episodes, eval seed and worlds recounted from the per-episode records."""
    import json
    from pathlib import Path

    from vkgrl_newton.results.ceiling import ceiling_levels, load_ceiling

    root = Path(__file__).resolve().parents[1] / "docs" / "results" / "ceiling_40"
    rows = load_ceiling()
    assert {r.task for r in rows} == {"PegInsert", "GearMesh", "NutThread"}
    for r in rows:
        data = json.loads((root / r.source).read_text())
        records = data["controllers"][r.controller]["records"]
        assert (data["task"], data["env"], data["action_dim"], data["eval_seed"], data["num_envs"]) == \
            (r.task, r.env, r.action_dim, r.eval_seed, r.num_envs)
        assert (sum(bool(e["success"]) for e in records), len(records)) == (r.successes, r.episodes), r
        assert len(records) == data["num_envs"] * data["episodes_per_world"]
    assert [c.controller for c in ceiling_levels("PegInsert", "factory", 4, 10000, 16)] == ["scripted", "oracle", "search"]
    assert ceiling_levels("PegInsert", "factory", 4, 10001, 16) == [] and ceiling_levels("PegInsert", "forge", 4, 10000, 16) == []
