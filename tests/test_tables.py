"""Tests of the per-step KGRL tables (vkgrl_newton.kmp.tables) and the cached prior (prior.py):
every table entry against the reference implementation ns_kmp_predict on the same GMR window."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from vkgrl_newton.kmp.demos import synthetic_demos
from vkgrl_newton.kmp.gmr import fit_gmm, gmr
from vkgrl_newton.kmp.kmp import ns_kmp_predict
from vkgrl_newton.kmp.pose import eta_to_pose, reference_quat
from vkgrl_newton.kmp.prior import load_or_fit_prior
from vkgrl_newton.kmp.tables import KMPTables, build_kmp_tables, control_grid, reference_window, tables_path_for

LAM, BETA, L = 1.0, 4.0, 20.0
AX4 = [0, 1, 2, 5]
# zeta scale of the action weights (Table 5.4): w_pos ~ 150-250, w_rot ~ 10-25
XI_SCALE = np.array([150.0, 150.0, 150.0, 15.0, 15.0, 15.0])


def to_np(x):
    return x.numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


@pytest.fixture(scope="module")
def peg_gmm():
    d = synthetic_demos("PegInsert", 6, action_dim=6, seed=0)
    return fit_gmm(d.s, d.eta, n_components=5, seed=0)


@pytest.fixture(scope="module")
def peg_tables(peg_gmm):
    return build_kmp_tables(peg_gmm, 1.0 / 150.0, 15, LAM, BETA, L, action_dim=6)


@pytest.fixture(scope="module")
def nut_gmm():
    d = synthetic_demos("NutThread", 6, action_dim=6, seed=0)
    return fit_gmm(d.s, d.eta, n_components=5, seed=0)


def reference_prediction(gmm, dt, horizon, n, xi, axes=None, lam=LAM, beta=BETA, l=L):
    window = reference_window(dt, horizon)[n]
    mu, sigma = gmr(gmm, window)
    if axes is not None:
        mu, sigma = mu[:, axes], sigma[:, axes][:, :, axes]
    return to_np(ns_kmp_predict(window[0], xi, window[0], window, mu, sigma, lam, beta, l))


def check_steps(tables, gmm, dt, horizon, steps, seed):
    rng = np.random.default_rng(seed)
    mean, gain = tables.mean.numpy(), tables.gain.numpy()
    worst = 0.0
    for n in steps:
        xi = rng.normal(size=6) * XI_SCALE
        want = reference_prediction(gmm, dt, horizon, n, xi)
        got = mean[n] + gain[n] @ xi
        scale = max(1.0, np.abs(want).max())
        err = np.abs(got - want).max() / scale
        worst = max(worst, err)
        assert err < 1e-9, (n, got, want)
        # the mean alone is the xi = 0 prediction
        np.testing.assert_allclose(mean[n], reference_prediction(gmm, dt, horizon, n, np.zeros(6)),
                                   rtol=0, atol=1e-9)
    return worst


# ---------------------------------------------------------------------------------------
# tables vs ns_kmp_predict
# ---------------------------------------------------------------------------------------
def test_tables_match_ns_kmp_every_step_peg(peg_tables, peg_gmm):
    t = peg_tables
    assert t.mean.shape == (151, 6) and t.gain.shape == (151, 6, 6)
    assert t.mean.dtype == torch.float64 and t.gain.dtype == torch.float64
    assert t.n_steps == 150
    check_steps(t, peg_gmm, 1.0 / 150.0, 15, range(151), seed=0)
    # the null-space gain is a real, non-trivial matrix (symmetric here since s_hat = s*)
    assert np.abs(t.gain.numpy()).max() > 1e-7
    np.testing.assert_allclose(t.gain.numpy(), t.gain.transpose(1, 2).numpy(), rtol=0,
                               atol=1e-12 * np.abs(t.gain.numpy()).max())


def test_tables_match_ns_kmp_nut_thread(nut_gmm):
    dt, h = 1.0 / 225.0, 25
    t = build_kmp_tables(nut_gmm, dt, h, LAM, BETA, L, action_dim=6)
    assert t.mean.shape == (226, 6)
    steps = list(range(0, 196, 13)) + list(range(196, 226))  # a spread plus the last 30 (window clamp)
    check_steps(t, nut_gmm, dt, h, steps, seed=1)


def test_tables_other_parameters(peg_gmm):
    """Different lam/beta/l and a short horizon, including beta = 0 (gain zero) and horizon 0."""
    for lam, beta, l, h in [(0.1, 30.0, 200.0, 5), (6.0, 0.0, 2.0, 15), (1.0, 4.0, 20.0, 0)]:
        t = build_kmp_tables(peg_gmm, 1.0 / 150.0, h, lam, beta, l)
        rng = np.random.default_rng(2)
        for n in (0, 70, 140, 150):
            xi = rng.normal(size=6) * XI_SCALE
            want = reference_prediction(peg_gmm, 1.0 / 150.0, h, n, xi, lam=lam, beta=beta, l=l)
            np.testing.assert_allclose(t.mean[n].numpy() + t.gain[n].numpy() @ xi, want, rtol=0,
                                       atol=1e-9 * max(1.0, np.abs(want).max()))
        if beta == 0.0:
            assert torch.all(t.gain == 0)


# ---------------------------------------------------------------------------------------
# window and grid
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("dt,h", [(1.0 / 150.0, 15), (1.0 / 225.0, 25), (0.1, 3)])
def test_reference_window_clamp(dt, h):
    w = reference_window(dt, h)
    n_steps = round(1.0 / dt)
    assert w.shape == (n_steps + 1, h + 1) and w.dtype == torch.float64
    assert (w <= 1.0).all()
    grid = control_grid(dt)
    # IEEE-only float64 (one division; below, a product and a sum): the same bits on any CPU, <= ~3 u64 of 1
    np.testing.assert_allclose(grid.numpy(), np.arange(n_steps + 1) / n_steps, rtol=0, atol=1e-15)
    assert grid[0] == 0.0 and grid[-1] == 1.0
    torch.testing.assert_close(w[:, 0], grid, rtol=0, atol=0)
    # independent: s_n + j dt clamped, from integers
    want = np.minimum(np.arange(n_steps + 1)[:, None] + np.arange(h + 1)[None, :], n_steps) / n_steps
    np.testing.assert_allclose(w.numpy(), want, rtol=0, atol=1e-15)
    for n in range(n_steps - h, n_steps + 1):
        k = n_steps - n  # index of the first point that reaches s = 1
        assert torch.all(w[n, k:] == 1.0), (n, w[n])
        assert torch.all(w[n, :k] < 1.0)
    assert torch.all(w[-1] == 1.0)
    assert torch.all(w[: n_steps - h, -1] < 1.0)


def test_predict_eta_clamps_step_index(peg_tables):
    t = peg_tables
    rng = np.random.default_rng(3)
    zeta = torch.as_tensor(rng.normal(size=(4, 6)) * XI_SCALE)
    idx = torch.tensor([t.n_steps + 5, t.n_steps, 10_000, -3])
    out = t.predict_eta(idx, zeta)
    last = t.mean[-1] + torch.einsum("ij,ej->ei", t.gain[-1], zeta)
    # two float64 matmul paths (batched vs one matrix: MKL/BLAS kernels chosen per CPU), each within
    # gamma_7 ~ 7 u64 of S = |m| + |B||zeta| (was atol 1e-15, no origin: ~S u64 * 9 for S ~ 1)
    u64 = 2.0 ** -53
    s_last = t.mean[-1].abs() + torch.einsum("ij,ej->ei", t.gain[-1].abs(), zeta.abs())
    torch.testing.assert_close(out[:3], last[:3], rtol=0, atol=float(14 * u64 * s_last[:3].max()))
    s_first = t.mean[0].abs() + t.gain[0].abs() @ zeta[3].abs()
    torch.testing.assert_close(out[3], t.mean[0] + t.gain[0] @ zeta[3], rtol=0, atol=float(14 * u64 * s_first.max()))
    # float32 zeta: result in float32
    out32 = t.predict_eta(torch.tensor([3]), zeta[:1].float())
    assert out32.dtype == torch.float32
    # float32: m, B, zeta rounded (u32 each) and a 7-term float32 sum (7 u32): <= 9 u32 S; bound 16 u32 S
    # (was rtol 1e-5, atol 1e-6, no origin)
    s3 = t.mean[3].abs() + t.gain[3].abs() @ zeta[0].abs()
    torch.testing.assert_close(out32.double(), t.predict_eta(torch.tensor([3]), zeta[:1]), rtol=0,
                               atol=float(16 * 2.0 ** -24 * s3.max()))


# ---------------------------------------------------------------------------------------
# 4D mode
# ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def gear4():
    d = synthetic_demos("GearMesh", 6, action_dim=4, seed=1)
    gmm = fit_gmm(d.s, d.eta, n_components=4, seed=0)
    return gmm, build_kmp_tables(gmm, 1.0 / 150.0, 15, LAM, BETA, L, action_dim=4)


def test_4d_tables_embedding(gear4):
    gmm, t = gear4
    assert t.action_dim == 4
    assert torch.all(t.gain[:, 3:5, :] == 0) and torch.all(t.gain[:, :, 3:5] == 0)
    assert torch.all(t.mean[:, 3:5] == 0)
    # roll and pitch stay at the reference whatever zeta is
    zeta = torch.full((1, 6), 100.0, dtype=torch.float64)
    assert torch.all(t.predict_eta(torch.tensor([40]), zeta)[0, 3:5] == 0)
    rng = np.random.default_rng(4)
    idx = torch.tensor(AX4)
    for n in (0, 37, 90, 140, 150):
        sub_gain = t.gain[n][idx[:, None], idx[None, :]].numpy()
        xi = rng.normal(size=4) * XI_SCALE[AX4]
        want = reference_prediction(gmm, 1.0 / 150.0, 15, n, xi, axes=AX4)
        want0 = reference_prediction(gmm, 1.0 / 150.0, 15, n, np.zeros(4), axes=AX4)
        np.testing.assert_allclose(t.mean[n, AX4].numpy(), want0, rtol=0, atol=1e-9)
        np.testing.assert_allclose(t.mean[n, AX4].numpy() + sub_gain @ xi, want, rtol=0,
                                   atol=1e-9 * max(1.0, np.abs(want).max()))
        # gain columns one by one
        for j in range(4):
            e = np.zeros(4)
            e[j] = 1.0
            col = reference_prediction(gmm, 1.0 / 150.0, 15, n, e, axes=AX4) - want0
            np.testing.assert_allclose(sub_gain[:, j], col, rtol=1e-6, atol=1e-12)


def test_4d_subblock_close_to_6d_when_roll_pitch_constant(gear4):
    """Sanity check: with 4D demos the roll/pitch outputs are constant (variance ~reg_covar, no
    coupling), so the (x, y, z, rz) block of the 6D tables nearly equals the separately computed 4D
    tables. (The exact 4D check is test_4d_tables_embedding.)"""
    gmm, t4 = gear4
    t6 = build_kmp_tables(gmm, 1.0 / 150.0, 15, LAM, BETA, L, action_dim=6)
    idx = torch.tensor(AX4)
    g4 = t4.gain[:, idx[:, None], idx[None, :]]
    g6 = t6.gain[:, idx[:, None], idx[None, :]]
    torch.testing.assert_close(g4, g6, rtol=1e-3, atol=1e-3 * float(g6.abs().max()))
    torch.testing.assert_close(t4.mean[:, AX4], t6.mean[:, AX4], rtol=0, atol=1e-6)


# ---------------------------------------------------------------------------------------
# pose output
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("psi_ref", [0.0, math.radians(-40.0)])
def test_predict_pose_matches_eta_to_pose(peg_tables, psi_ref):
    t = peg_tables
    rng = np.random.default_rng(5)
    e = 64
    idx = torch.as_tensor(rng.integers(0, t.n_steps + 10, e))
    zeta = torch.as_tensor(rng.uniform(-1, 1, (e, 6)) * XI_SCALE)
    target = torch.as_tensor(rng.normal(size=(e, 3)) * 0.1)
    q_ref = reference_quat(psi_ref).expand(e, 4)
    pos, quat = t.predict_pose(idx, zeta, target, q_ref)
    eta = t.predict_eta(idx, zeta)
    pos_ref, quat_ref = eta_to_pose(eta, target, psi_ref)
    assert pos.dtype == torch.float64 and quat.shape == (e, 4)
    # the same torch ops on the same eta in one process (same machine): equal but for a batch-dependent
    # kernel choice; 1e-15 (~9 u64 of values <= 1) bounds one 4-term product's rounding on each side
    torch.testing.assert_close(pos, pos_ref, rtol=0, atol=1e-15)
    torch.testing.assert_close(quat, quat_ref, rtol=0, atol=1e-15)
    torch.testing.assert_close(quat.norm(dim=-1), torch.ones(e, dtype=torch.float64), rtol=0, atol=1e-14)


# ---------------------------------------------------------------------------------------
# persistence and the cached prior
# ---------------------------------------------------------------------------------------
def test_save_load_round_trip(peg_tables, tmp_path):
    t = KMPTables(**{**peg_tables.__dict__, "source_sha256": "ab" * 32})
    path = t.save(tmp_path / "deep" / "tables.npz")
    back = KMPTables.load(path)
    assert torch.equal(back.mean, t.mean) and torch.equal(back.gain, t.gain)
    assert (back.dt, back.horizon, back.lam, back.beta, back.l, back.action_dim, back.source_sha256) == (
        t.dt, t.horizon, t.lam, t.beta, t.l, t.action_dim, t.source_sha256)
    assert torch.equal(back.gmm.weights, t.gmm.weights)
    assert torch.equal(back.gmm.means, t.gmm.means)
    assert torch.equal(back.gmm.covariances, t.gmm.covariances)
    assert sorted(p.name for p in path.parent.iterdir()) == ["tables.npz"]
    # empty hash round-trips too
    back2 = KMPTables.load(peg_tables.save(tmp_path / "t2.npz"))
    assert back2.source_sha256 == ""


def test_load_missing_key(peg_tables, tmp_path):
    path = peg_tables.save(tmp_path / "tables.npz")
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files if k != "gain"}
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    with pytest.raises(ValueError, match=r"missing keys \['gain'\]"):
        KMPTables.load(bad)
    arrays["format_version"] = np.int64(99)
    arrays["gain"] = peg_tables.gain.numpy()
    np.savez(tmp_path / "v99.npz", **arrays)
    with pytest.raises(ValueError, match="format"):
        KMPTables.load(tmp_path / "v99.npz")


def test_load_or_fit_prior_cache(tmp_path):
    demo_path = tmp_path / "peg.npz"
    synthetic_demos("PegInsert", 3, action_dim=6, seed=0).save(demo_path)
    kw = dict(action_dim=6, n_components=2)

    t1, path, rebuilt = load_or_fit_prior(demo_path, **kw)
    assert rebuilt and path == tables_path_for(demo_path, 6) and path.exists()
    assert path.name == "peg.kmp6d.npz"
    assert (t1.dt, t1.horizon) == (1.0 / 150.0, 15) and t1.gmm.n_components == 2
    mtime = path.stat().st_mtime_ns

    t2, _, rebuilt = load_or_fit_prior(demo_path, **kw)
    assert not rebuilt
    assert path.stat().st_mtime_ns == mtime
    assert torch.equal(t2.mean, t1.mean) and torch.equal(t2.gain, t1.gain)

    # a different demonstration set under the same name: rebuilt, and different tables
    demo_path.unlink()
    synthetic_demos("PegInsert", 3, action_dim=6, seed=1).save(demo_path)
    t3, _, rebuilt = load_or_fit_prior(demo_path, **kw)
    assert rebuilt and t3.source_sha256 != t1.source_sha256
    assert not torch.equal(t3.mean, t1.mean)

    # a different beta: rebuilt with that beta
    t4, _, rebuilt = load_or_fit_prior(demo_path, beta=2.0, **kw)
    assert rebuilt and t4.beta == 2.0
    # same demos and seed, so the same GMM; only beta differs
    assert torch.equal(t4.gmm.means, t3.gmm.means) and torch.equal(t4.gmm.covariances, t3.gmm.covariances)
    direct = build_kmp_tables(t3.gmm, 1.0 / 150.0, 15, LAM, 2.0, L, action_dim=6)
    assert torch.equal(t4.gain, direct.gain) and torch.equal(t4.mean, direct.mean)
    assert not torch.equal(t4.gain, t3.gain)
    _, _, rebuilt = load_or_fit_prior(demo_path, beta=2.0, **kw)
    assert not rebuilt

    # 4D tables are cached separately, beside the 6D ones, which stay valid
    t5, path4, rebuilt = load_or_fit_prior(demo_path, action_dim=4, beta=2.0, n_components=2)
    assert rebuilt and path4.name == "peg.kmp4d.npz" and t5.action_dim == 4
    assert torch.all(t5.gain[:, 3:5] == 0)
    _, _, rebuilt = load_or_fit_prior(demo_path, beta=2.0, **kw)
    assert not rebuilt
    _, _, rebuilt = load_or_fit_prior(demo_path, action_dim=4, beta=2.0, n_components=2)
    assert not rebuilt
    # a different number of GMM components: rebuilt
    t6, _, rebuilt = load_or_fit_prior(demo_path, action_dim=6, beta=2.0, n_components=3)
    assert rebuilt and t6.gmm.n_components == 3

    # a corrupt cache file is rebuilt rather than trusted
    _, _, rebuilt = load_or_fit_prior(demo_path, action_dim=6, beta=2.0, n_components=3)
    assert not rebuilt
    path.write_bytes(b"garbage")
    _, _, rebuilt = load_or_fit_prior(demo_path, action_dim=6, beta=2.0, n_components=3)
    assert rebuilt
    assert KMPTables.load(path).gmm.n_components == 3  # and the cache is valid again


def test_load_or_fit_prior_rebuilds_for_other_seed(tmp_path):
    """The cache is documented as reused only with the same parameters; the GMM seed is one of them
    (different seeds give different k-means inits and, here, different mixtures)."""
    demo_path = tmp_path / "peg.npz"
    demos = synthetic_demos("PegInsert", 3, action_dim=6, seed=0)
    demos.save(demo_path)
    load_or_fit_prior(demo_path, n_components=2, seed=0)
    t, _, rebuilt = load_or_fit_prior(demo_path, n_components=2, seed=1)
    expected = fit_gmm(demos.s, demos.eta, n_components=2, seed=1)
    assert not torch.equal(expected.means, fit_gmm(demos.s, demos.eta, n_components=2, seed=0).means)
    assert rebuilt, "tables fitted with seed 0 were returned for seed 1"
    assert torch.equal(t.gmm.means, expected.means)


@pytest.mark.parametrize(
    "kw,match",
    [
        (dict(action_dim=5), "action_dim"),
        (dict(dt=0.3), "dt"),
        (dict(dt=0.0), "dt"),
        (dict(lam=0.0), "lam"),
        (dict(lam=-1.0), "lam"),
        (dict(beta=-1.0), "beta"),
        (dict(l=0.0), "l must"),
        (dict(horizon=-1), "horizon"),
        (dict(horizon=2.5), "horizon"),
    ],
)
def test_build_bad_parameters(peg_gmm, kw, match):
    args = dict(dt=1.0 / 150.0, horizon=15, lam=LAM, beta=BETA, l=L, action_dim=6)
    args.update(kw)
    with pytest.raises(ValueError, match=match):
        build_kmp_tables(peg_gmm, **args)


def test_build_rejects_non_6d_gmm():
    rng = np.random.default_rng(0)
    gmm = fit_gmm(rng.uniform(size=200), rng.normal(size=(200, 3)), n_components=1)
    with pytest.raises(ValueError, match="6D"):
        build_kmp_tables(gmm, 1.0 / 150.0, 15, LAM, BETA, L)
