"""Tests of the KMP mean (eq. 3.29), covariance (eq. 3.37) and the NS-KMP / KGRL prediction (eq. 4.36)
in vkgrl_newton.kmp.kmp, against independent float64 numpy implementations, closed forms and the
primal (explicit basis-function) formulation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from vkgrl_newton.kmp.kmp import _ns_kmp_from_blocks, kmp_covariance, kmp_mean, ns_kmp_predict, rbf_kernel


def random_spd(rng, d, scale=1.0):
    a = rng.normal(size=(d, d))
    return scale * (a @ a.T / d + 0.2 * np.eye(d))


def reference(seed=0, n=10, o=3, sig_scale=0.1, s=None):
    rng = np.random.default_rng(seed)
    s_ref = np.linspace(0.0, 1.0, n) if s is None else np.asarray(s, dtype=np.float64)
    mu = rng.normal(size=(len(s_ref), o))
    sigma = np.stack([random_spd(rng, o, sig_scale) for _ in range(len(s_ref))])
    return s_ref, mu, sigma


# ---------------------------------------------------------------------------------------
# Independent numpy reference: explicit loops, no kron, np.linalg.solve
# ---------------------------------------------------------------------------------------
def np_k(a, b, l):
    return float(np.exp(-l * (a - b) ** 2))


def np_big_k(s_ref, o, l):
    n = len(s_ref)
    k = np.zeros((n * o, n * o))
    for i in range(n):
        for j in range(n):
            kij = np_k(s_ref[i], s_ref[j], l)
            for d in range(o):
                k[i * o + d, j * o + d] = kij
    return k


def np_k_star(s, s_ref, o, l):
    n = len(s_ref)
    ks = np.zeros((o, n * o))
    for i in range(n):
        kv = np_k(s, s_ref[i], l)
        for d in range(o):
            ks[d, i * o + d] = kv
    return ks


def np_block_diag(sigma):
    n, o, _ = sigma.shape
    out = np.zeros((n * o, n * o))
    for i in range(n):
        out[i * o : (i + 1) * o, i * o : (i + 1) * o] = sigma[i]
    return out


def np_stack_mu(mu):
    n, o = mu.shape
    out = np.zeros(n * o)
    for i in range(n):
        for d in range(o):
            out[i * o + d] = mu[i, d]
    return out


def np_kmp_mean(s_star, s_ref, mu, sigma, lam, l):
    o = mu.shape[1]
    mat = np_big_k(s_ref, o, l) + lam * np_block_diag(sigma)
    alpha = np.linalg.solve(mat, np_stack_mu(mu))
    return np.stack([np_k_star(s, s_ref, o, l) @ alpha for s in np.atleast_1d(s_star)])


def np_kmp_cov(s_star, s_ref, sigma, lam, l):
    n, o, _ = sigma.shape
    mat = np_big_k(s_ref, o, l) + lam * np_block_diag(sigma)
    out = []
    for s in np.atleast_1d(s_star):
        ks = np_k_star(s, s_ref, o, l)
        out.append((n / lam) * (np_k(s, s, l) * np.eye(o) - ks @ np.linalg.solve(mat, ks.T)))
    return np.stack(out)


def np_ns_kmp(s_star, xi, s_hat, s_ref, mu, sigma, lam, beta, l):
    o = mu.shape[1]
    gamma = lam + beta
    mat = np_big_k(s_ref, o, l) + gamma * np_block_diag(sigma)
    ks = np_k_star(s_star, s_ref, o, l)
    k_hat = np_k_star(s_hat, s_ref, o, l).T  # (NO, O)
    mean = ks @ np.linalg.solve(mat, np_stack_mu(mu))
    proj = np_k(s_star, s_hat, l) * np.eye(o) - ks @ np.linalg.solve(mat, k_hat)
    return mean + (beta / gamma) * proj @ xi


def t(x):
    return torch.as_tensor(np.asarray(x), dtype=torch.float64)


def to_np(x):
    return x.numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def ns(s_star, xi, s_hat, s_ref, mu, sigma, lam, beta, l):
    return to_np(ns_kmp_predict(s_star, xi, s_hat, s_ref, mu, sigma, lam, beta, l))


# ---------------------------------------------------------------------------------------
# kmp_mean / kmp_covariance
# ---------------------------------------------------------------------------------------
def test_rbf_kernel_values():
    a, b = np.array([0.0, 0.3, 1.0]), np.array([0.1, 0.5])
    got = rbf_kernel(a, b, 7.0).numpy()
    want = np.array([[np_k(x, y, 7.0) for y in b] for x in a])
    # exp(x) with x = -l d^2 associated differently here and there (<= 2 u64 each side, relative), which
    # exp turns into |x| * 4 u64, plus exp's own <= 1 ulp (2 u64) on each side (torch's SIMD vs numpy's
    # kernel): rtol (4 max|x| + 4) u64 ~ 2.9e-15 (was 1e-15, below that bound for |x| up to 5.7)
    max_x = 7.0 * float(np.max((a[:, None] - b[None, :]) ** 2))
    np.testing.assert_allclose(got, want, rtol=(4 * max_x + 4) * 2.0 ** -53)


def test_kmp_mean_interpolates_reference_as_lam_sigma_vanishes():
    s_ref, mu, sigma = reference(0, n=10, o=3)
    errors = []
    for lam in (1e-1, 1e-3, 1e-5, 1e-8):
        pred = kmp_mean(s_ref, s_ref, mu, sigma, lam, 100.0).numpy()
        errors.append(np.abs(pred - mu).max())
    assert all(a > b for a, b in zip(errors, errors[1:])), errors
    assert errors[0] > 1e-3  # at lam = 0.1 the regularization visibly pulls the mean
    assert errors[-1] < 1e-6, errors


@pytest.mark.parametrize("seed,lam,l", [(0, 0.5, 100.0), (1, 2.0, 30.0), (2, 0.05, 300.0)])
def test_kmp_mean_and_covariance_match_numpy_loops(seed, lam, l):
    s_ref, mu, sigma = reference(seed, n=8, o=3, s=np.sort(np.random.default_rng(seed + 10).uniform(0, 1, 8)))
    s_star = np.array([0.0, 0.13, s_ref[3], 0.5, 0.77, 1.0, 1.3])
    got_m = kmp_mean(s_star, s_ref, mu, sigma, lam, l).numpy()
    want_m = np_kmp_mean(s_star, s_ref, mu, sigma, lam, l)
    assert got_m.shape == (7, 3)
    np.testing.assert_allclose(got_m, want_m, rtol=1e-9, atol=1e-12 * np.abs(want_m).max())
    got_c = kmp_covariance(s_star, s_ref, sigma, lam, l).numpy()
    want_c = np_kmp_cov(s_star, s_ref, sigma, lam, l)
    assert got_c.shape == (7, 3, 3)
    np.testing.assert_allclose(got_c, want_c, rtol=1e-9, atol=1e-9 * np.abs(want_c).max())


def test_kmp_covariance_symmetric_psd():
    s_ref, _, sigma = reference(3, n=12, o=4, sig_scale=0.5)
    s_star = np.linspace(-0.2, 1.2, 29)
    d = kmp_covariance(s_star, s_ref, sigma, 1.5, 50.0)
    assert torch.equal(d, d.transpose(-1, -2))
    ev = torch.linalg.eigvalsh(d)
    assert (ev >= -1e-12 * ev.abs().max()).all()
    assert (ev.amax(-1) > 0).all()
    # far from the data the covariance returns to the prior (N/lam) k(s*, s*) I
    far = kmp_covariance([50.0], s_ref, sigma, 1.5, 50.0)[0].numpy()
    np.testing.assert_allclose(far, (12 / 1.5) * np.eye(4), rtol=1e-12)


@pytest.mark.parametrize("lam", [0.01, 1.0, 30.0])
def test_kmp_covariance_single_point_closed_form(lam):
    rng = np.random.default_rng(4)
    sigma = random_spd(rng, 3, 0.7)[None]
    d = kmp_covariance([0.4], [0.4], sigma, lam, 10.0)[0].numpy()
    want = (1.0 / lam) * (np.eye(3) - np.linalg.inv(np.eye(3) + lam * sigma[0]))
    np.testing.assert_allclose(d, want, rtol=1e-12, atol=1e-14)


# ---------------------------------------------------------------------------------------
# NS-KMP / KGRL prediction
# ---------------------------------------------------------------------------------------
def test_ns_kmp_matches_numpy_loops():
    s_ref, mu, sigma = reference(5, n=9, o=3)
    rng = np.random.default_rng(6)
    for s_star, s_hat in [(0.25, 0.25), (0.4, 0.7), (s_ref[4], s_ref[4]), (1.0, 0.9)]:
        xi = rng.normal(size=3)
        got = ns(s_star, xi, s_hat, s_ref, mu, sigma, 0.7, 3.0, 40.0)
        want = np_ns_kmp(s_star, xi, s_hat, s_ref, mu, sigma, 0.7, 3.0, 40.0)
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)


def test_ns_kmp_xi_zero_is_kmp_mean_with_gamma():
    s_ref, mu, sigma = reference(7, n=10, o=3)
    lam, beta, l = 0.8, 4.0, 20.0
    for s_star in (0.0, 0.33, 0.8, 1.0):
        got = ns(s_star, np.zeros(3), s_star, s_ref, mu, sigma, lam, beta, l)
        want = kmp_mean([s_star], s_ref, mu, sigma, lam + beta, l)[0].numpy()
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
        # and differs from the plain mean with lam (beta really enters as extra regularization)
        plain = kmp_mean([s_star], s_ref, mu, sigma, lam, l)[0].numpy()
        assert np.abs(got - plain).max() > 1e-4


def test_ns_kmp_beta_zero_is_kmp_mean():
    s_ref, mu, sigma = reference(8, n=10, o=3)
    rng = np.random.default_rng(8)
    for s_star in (0.0, 0.47, 1.0):
        xi = rng.normal(size=3) * 10
        got = ns(s_star, xi, s_star, s_ref, mu, sigma, 0.5, 0.0, 20.0)
        want = kmp_mean([s_star], s_ref, mu, sigma, 0.5, 20.0)[0].numpy()
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)


def test_ns_kmp_null_space_term_vanishes_with_sigma():
    """At a reference input with s_hat = s*, the null-space term (beta/gamma)(k(s*,s*) - k* A k*^T) xi
    tends to zero as the covariances shrink (the reference is then fully trusted)."""
    s_ref, mu, sigma = reference(9, n=10, o=3, sig_scale=1.0)
    xi = np.array([1.0, -2.0, 0.5])
    s_star = s_ref[4]
    norms, quads = [], []
    for c in (1e-1, 1e-3, 1e-5, 1e-7):
        term = ns(s_star, xi, s_star, s_ref, mu, c * sigma, 1.0, 4.0, 20.0) - ns(
            s_star, np.zeros(3), s_star, s_ref, mu, c * sigma, 1.0, 4.0, 20.0)
        norms.append(np.linalg.norm(term))
        quads.append(xi @ term)
    assert all(a > b for a, b in zip(norms, norms[1:])), norms
    assert all(a > b for a, b in zip(quads, quads[1:])), quads
    assert norms[-1] < 1e-5 * norms[0] and norms[-1] < 1e-5, norms


def test_ns_kmp_null_space_term_grows_with_sigma():
    s_ref, mu, sigma = reference(10, n=10, o=3, sig_scale=1.0)
    xi = np.array([0.3, 1.0, -0.7])
    norms = []
    for s_star in (s_ref[3], 0.52):  # at a reference input and between two
        norms = []
        for c in (1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0):
            term = ns(s_star, xi, s_star, s_ref, mu, c * sigma, 1.0, 4.0, 20.0) - ns(
                s_star, np.zeros(3), s_star, s_ref, mu, c * sigma, 1.0, 4.0, 20.0)
            norms.append(np.linalg.norm(term))
        assert all(a < b for a, b in zip(norms, norms[1:])), norms
        # bounded by the full null-space weight (beta/gamma) |xi| (k(s*,s*) = 1)
        assert norms[-1] < 4.0 / 5.0 * np.linalg.norm(xi) + 1e-12


@pytest.mark.parametrize("lam,beta", [(1.0, 4.0), (0.1, 30.0), (6.0, 0.5)])
def test_ns_kmp_single_point_closed_form(lam, beta):
    rng = np.random.default_rng(11)
    sigma = random_spd(rng, 3, 0.4)[None]
    mu = rng.normal(size=(1, 3))
    s1 = 0.6
    gamma = lam + beta
    xi = rng.normal(size=3)
    eta_xi = ns(s1, xi, s1, [s1], mu, sigma, lam, beta, 20.0)
    eta_0 = ns(s1, np.zeros(3), s1, [s1], mu, sigma, lam, beta, 20.0)
    gain = (beta / gamma) * (np.eye(3) - np.linalg.inv(np.eye(3) + gamma * sigma[0]))
    np.testing.assert_allclose(eta_xi - eta_0, gain @ xi, rtol=1e-12, atol=1e-14)
    # the mean part: K = I, k* = I  =>  (I + gamma Sigma)^-1 mu
    np.testing.assert_allclose(eta_0, np.linalg.solve(np.eye(3) + gamma * sigma[0], mu[0]), rtol=1e-12)


# ---------------------------------------------------------------------------------------
# Kernelized NS-KMP vs the primal (explicit feature) problem
# ---------------------------------------------------------------------------------------
def bumps(s, b=8, width=0.15):
    c = np.linspace(0.0, 1.0, b)
    return np.exp(-((s - c) ** 2) / (2 * width**2))


def poly(s, b=5):
    return np.array([(s - 0.5) ** k for k in range(b)])


def theta(phi, o):
    """Theta(s) = blockdiag(phi, ..., phi), (B*O, O): Theta^T Theta' = (phi^T phi') I_O."""
    b = len(phi)
    out = np.zeros((b * o, o))
    for d in range(o):
        out[d * b : (d + 1) * b, d] = phi
    return out


@pytest.mark.parametrize("basis", [bumps, poly], ids=["gauss8", "poly5"])
@pytest.mark.parametrize("s_star,s_hat", [(0.3, 0.3), (0.55, 0.2), (0.9, 0.9)])
def test_ns_kmp_kernel_form_matches_primal(basis, s_star, s_hat):
    o, n = 2, 5
    lam, beta = 0.7, 3.0
    gamma = lam + beta
    rng = np.random.default_rng(12)
    s_ref = np.sort(rng.uniform(0, 1, n))
    mu = rng.normal(size=(n, o))
    sigma = np.stack([random_spd(rng, o, 0.3) for _ in range(n)])
    xi = rng.normal(size=o)

    big_phi = np.concatenate([theta(basis(s), o) for s in s_ref], axis=1)  # (BO, NO), time-major columns
    th_star, th_hat = theta(basis(s_star), o), theta(basis(s_hat), o)
    sig_blk = np_block_diag(sigma)
    mu_vec = np_stack_mu(mu)

    # primal: w* = (Phi S^-1 Phi^T + gamma I)^-1 (Phi S^-1 mu + beta w_hat), w_hat = Phi_hat (Phi_hat^T Phi_hat)^-1 xi
    s_inv = np.linalg.inv(sig_blk)
    w_hat = th_hat @ np.linalg.solve(th_hat.T @ th_hat, xi)
    lhs = big_phi @ s_inv @ big_phi.T + gamma * np.eye(big_phi.shape[0])
    w = np.linalg.solve(lhs, big_phi @ s_inv @ mu_vec + beta * w_hat)
    want = th_star.T @ w

    k_under = th_hat.T @ th_hat
    assert abs(k_under[0, 0] - 1.0) > 1e-2  # explicit features: K_under is not the identity
    got = _ns_kmp_from_blocks(
        k_star=t(th_star.T @ big_phi),
        big_k=t(big_phi.T @ big_phi),
        k_hat_star=t(th_star.T @ th_hat),
        big_k_hat=t(big_phi.T @ th_hat),
        k_under=t(k_under),
        mu=t(mu_vec),
        sigma_blk=t(sig_blk),
        xi=t(xi),
        lam=lam,
        beta=beta,
    ).numpy()
    np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-10 * np.abs(want).max())

    # the mean part alone (xi = 0, beta -> 0 in the primal) is the KMP mean of eq. 3.29 with lam
    w0 = np.linalg.solve(big_phi @ s_inv @ big_phi.T + lam * np.eye(big_phi.shape[0]), big_phi @ s_inv @ mu_vec)
    got0 = _ns_kmp_from_blocks(t(th_star.T @ big_phi), t(big_phi.T @ big_phi), t(th_star.T @ th_hat),
                               t(big_phi.T @ th_hat), t(k_under), t(mu_vec), t(sig_blk), t(np.zeros(o)), lam, 0.0)
    np.testing.assert_allclose(got0.numpy(), th_star.T @ w0, rtol=1e-8, atol=1e-10 * np.abs(want).max())


# ---------------------------------------------------------------------------------------
# Input handling
# ---------------------------------------------------------------------------------------
def test_numpy_and_torch_inputs():
    """Any mix of numpy / torch inputs gives the same float64 (O,) result; the return type follows
    mu_ref (numpy array for a numpy mu_ref, torch tensor for a torch one), per the docstring."""
    s_ref, mu, sigma = reference(13, n=6, o=4)
    xi = np.arange(4.0)
    a = ns_kmp_predict(0.4, xi, 0.4, s_ref, mu, sigma, 1.0, 2.0, 20.0)
    b = ns_kmp_predict(t(0.4), t(xi), t([0.4]), t(s_ref), t(mu), t(sigma), 1.0, 2.0, 20.0)
    c = ns_kmp_predict(0.4, t(xi).float(), 0.4, t(s_ref).float(), mu, t(sigma), 1.0, 2.0, 20.0)
    assert isinstance(a, np.ndarray) and a.dtype == np.float64 and a.shape == (4,)
    assert isinstance(b, torch.Tensor) and b.dtype == torch.float64 and b.shape == (4,)
    assert isinstance(c, np.ndarray) and c.dtype == np.float64 and c.shape == (4,)
    np.testing.assert_array_equal(a, b.numpy())
    np.testing.assert_allclose(c, a, rtol=1e-6, atol=1e-7)  # float32 s_ref rounds the inputs
    np.testing.assert_allclose(a, np_ns_kmp(0.4, xi, 0.4, s_ref, mu, sigma, 1.0, 2.0, 20.0), rtol=1e-10)
    m = kmp_mean(np.array([0.4]), t(s_ref), mu, t(sigma), 3.0, 20.0)
    assert isinstance(m, torch.Tensor) and m.shape == (1, 4) and m.dtype == torch.float64
    np.testing.assert_allclose(m[0].numpy(), ns(0.4, np.zeros(4), 0.4, s_ref, mu, sigma, 1.0, 2.0, 20.0),
                               rtol=1e-12)


@pytest.fixture
def ref4():
    return reference(14, n=5, o=3)


def call(ref, **kw):
    s_ref, mu, sigma = ref
    args = dict(s_star=0.5, xi=np.ones(3), s_hat=0.5, s_ref=s_ref, mu_ref=mu, sigma_ref=sigma, lam=1.0, beta=2.0,
                l=20.0)
    args.update(kw)
    return ns_kmp_predict(**args)


def test_bad_shapes(ref4):
    s_ref, mu, sigma = ref4
    with pytest.raises(ValueError, match="s_ref"):
        call(ref4, s_ref=s_ref[:, None])
    with pytest.raises(ValueError, match="s_ref"):
        call(ref4, s_ref=np.zeros(0))
    with pytest.raises(ValueError, match="sigma_ref"):
        call(ref4, s_ref=s_ref[:4])  # N mismatch is reported on sigma_ref
    with pytest.raises(ValueError, match="mu_ref"):
        call(ref4, mu_ref=mu[:, :2])
    with pytest.raises(ValueError, match="mu_ref"):
        call(ref4, mu_ref=mu[:4])
    with pytest.raises(ValueError, match="sigma_ref"):
        call(ref4, sigma_ref=sigma[:, :, :2])
    with pytest.raises(ValueError, match="sigma_ref"):
        call(ref4, sigma_ref=sigma[0])
    with pytest.raises(ValueError, match="xi"):
        call(ref4, xi=np.ones(4))
    with pytest.raises(ValueError, match="xi"):
        call(ref4, xi=np.ones((3, 1)))
    with pytest.raises(ValueError, match="s_star"):
        call(ref4, s_star=[0.1, 0.2])


def test_sigma_not_pd_or_asymmetric(ref4):
    s_ref, mu, sigma = ref4
    bad = sigma.copy()
    w, v = np.linalg.eigh(bad[2])
    w[0] = -0.05
    bad[2] = (v * w) @ v.T
    with pytest.raises(ValueError, match=r"sigma_ref must be positive definite.*index 2"):
        call(ref4, sigma_ref=bad)
    with pytest.raises(ValueError, match="sigma_ref must be positive definite"):
        kmp_mean([0.5], s_ref, mu, bad, 1.0, 20.0)
    with pytest.raises(ValueError, match="sigma_ref must be positive definite"):
        kmp_covariance([0.5], s_ref, bad, 1.0, 20.0)
    asym = sigma.copy()
    asym[1, 0, 2] += 0.01
    with pytest.raises(ValueError, match="sigma_ref must be symmetric"):
        call(ref4, sigma_ref=asym)


@pytest.mark.parametrize("value", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_lam(ref4, value):
    s_ref, mu, sigma = ref4
    with pytest.raises(ValueError, match="lam"):
        call(ref4, lam=value)
    with pytest.raises(ValueError, match="lam"):
        kmp_mean([0.5], s_ref, mu, sigma, value, 20.0)
    with pytest.raises(ValueError, match="lam"):
        kmp_covariance([0.5], s_ref, sigma, value, 20.0)


@pytest.mark.parametrize("value", [0.0, -2.0, float("nan")])
def test_bad_l(ref4, value):
    s_ref, mu, sigma = ref4
    with pytest.raises(ValueError, match=r"^l must"):
        call(ref4, l=value)
    with pytest.raises(ValueError, match=r"^l must"):
        kmp_mean([0.5], s_ref, mu, sigma, 1.0, value)
    with pytest.raises(ValueError, match=r"^l must"):
        kmp_covariance([0.5], s_ref, sigma, 1.0, value)


@pytest.mark.parametrize("value", [-1e-3, -4.0, float("nan"), float("inf")])
def test_bad_beta(ref4, value):
    with pytest.raises(ValueError, match="beta"):
        call(ref4, beta=value)


def test_nan_inputs(ref4):
    s_ref, mu, sigma = ref4
    bad_mu = mu.copy()
    bad_mu[1, 1] = np.nan
    with pytest.raises(ValueError, match="mu_ref contains NaN"):
        call(ref4, mu_ref=bad_mu)
    with pytest.raises(ValueError, match="mu_ref contains NaN"):
        kmp_mean([0.5], s_ref, bad_mu, sigma, 1.0, 20.0)
    bad_s = s_ref.copy()
    bad_s[0] = np.inf
    with pytest.raises(ValueError, match="s_ref contains NaN or inf"):
        call(ref4, s_ref=bad_s)
    with pytest.raises(ValueError, match="xi contains NaN"):
        call(ref4, xi=np.array([0.0, np.nan, 1.0]))
    with pytest.raises(ValueError, match="mu_ref"):
        call(ref4, mu_ref="not numbers")


@pytest.mark.parametrize("scale", [1.0, 1e-6, 1e-8, 1e-10])
def test_asymmetry_check_is_scale_invariant(scale):
    """A covariance with one off-diagonal entry 10% off its mirror is asymmetric in any unit.

    Positions are metres with 0.1-1 mm spread, so covariances of 1e-8..1e-6 m^2 are this project's
    normal scale. (Fails while validate_reference's tolerance is 1e-9 * max(1, max|S|), i.e.
    absolute for |S| < 1: then Cholesky silently reads only the lower triangle.)
    """
    rng = np.random.default_rng(15)
    s_ref = np.linspace(0, 1, 4)
    sigma = np.stack([random_spd(rng, 3) * scale for _ in range(4)])
    sigma[1, 0, 2] *= 1.1
    with pytest.raises(ValueError, match="sigma_ref must be symmetric"):
        ns_kmp_predict(0.5, np.ones(3), 0.5, s_ref, np.zeros((4, 3)), sigma, 1.0, 2.0, 20.0)
