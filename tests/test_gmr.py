"""Tests of the GMM fit and Gaussian Mixture Regression (thesis eqs. 3.3-3.9) in vkgrl_newton.kmp.gmr."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from vkgrl_newton.kmp.demos import synthetic_demos
from vkgrl_newton.kmp.gmr import DEFAULT_JITTER, GMM, fit_gmm, gmr


def random_spd(rng, d, scale=1.0):
    a = rng.normal(size=(d, d))
    return scale * (a @ a.T / d + 0.3 * np.eye(d))


def hand_gmm(seed=0, c=3, o=2):
    rng = np.random.default_rng(seed)
    weights = rng.uniform(0.5, 1.5, c)
    weights /= weights.sum()
    means = np.column_stack([np.linspace(0.1, 0.9, c) + rng.normal(0, 0.05, c), rng.normal(0, 2.0, (c, o))])
    covs = np.stack([random_spd(rng, 1 + o) for _ in range(c)])
    covs[:, 0, :] *= 0.2  # time spread ~0.2 (s lives in [0, 1])
    covs[:, :, 0] *= 0.2
    return weights, means, covs


def as_gmm(weights, means, covs):
    return GMM(weights=torch.as_tensor(weights), means=torch.as_tensor(means), covariances=torch.as_tensor(covs))


def log_normal_pdf(x, mean, cov):
    """log N(x | mean, cov) for x (..., D), numpy float64."""
    d = x.shape[-1]
    chol = np.linalg.cholesky(cov)
    z = np.linalg.solve(chol, (x - mean).reshape(-1, d).T).T
    logdet = 2.0 * np.log(np.diag(chol)).sum()
    out = -0.5 * (z * z).sum(-1) - 0.5 * (d * np.log(2 * np.pi) + logdet)
    return out.reshape(x.shape[:-1])


def precision_conditioning(mean, cov, s):
    """Exact Gaussian conditioning on x0 = s via the precision matrix (independent of eqs. 3.4-3.5)."""
    lam = np.linalg.inv(cov)
    lam_yy, lam_ys = lam[1:, 1:], lam[1:, 0]
    cov_c = np.linalg.inv(lam_yy)
    mu_c = mean[1:] - cov_c @ lam_ys * (s - mean[0])
    return mu_c, cov_c


# ---------------------------------------------------------------------------------------
# GMR against brute force
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1])
def test_gmr_matches_quadrature(seed):
    """Conditional mean/covariance of the mixture by summing p(s, y) on a fine 2D grid over y."""
    weights, means, covs = hand_gmm(seed)
    gmm = as_gmm(weights, means, covs)
    s_values = np.array([0.0, 0.35, 0.62, 1.0])
    mu, sigma = gmr(gmm, s_values)
    mu, sigma = mu.numpy(), sigma.numpy()
    for n, s in enumerate(s_values):
        # grid bounds: +-8 std of every component's conditional (computed via the precision matrix)
        cond = [precision_conditioning(means[k], covs[k], s) for k in range(len(weights))]
        lo = np.min([m - 8 * np.sqrt(np.diag(c)) for m, c in cond], axis=0)
        hi = np.max([m + 8 * np.sqrt(np.diag(c)) for m, c in cond], axis=0)
        g0, g1 = np.linspace(lo[0], hi[0], 400), np.linspace(lo[1], hi[1], 400)
        y = np.stack(np.meshgrid(g0, g1, indexing="ij"), axis=-1)  # (400, 400, 2)
        x = np.concatenate([np.full(y.shape[:-1] + (1,), s), y], axis=-1)
        logp = np.stack([np.log(weights[k]) + log_normal_pdf(x, means[k], covs[k]) for k in range(len(weights))])
        p = np.exp(logp - logp.max()).sum(0)
        p /= p.sum()
        m_ref = np.einsum("ij,ijd->d", p, y)
        dy = y - m_ref
        c_ref = np.einsum("ij,ijd,ije->de", p, dy, dy)
        scale = np.sqrt(np.max(np.diag(c_ref)))  # conditional std scale
        np.testing.assert_allclose(mu[n], m_ref, rtol=0, atol=1e-4 * scale)
        np.testing.assert_allclose(sigma[n], c_ref, rtol=0, atol=1e-4 * scale**2)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gmr_single_component_exact(seed):
    weights, means, covs = hand_gmm(seed, c=1, o=3)
    gmm = as_gmm(np.ones(1), means, covs)
    s_values = np.array([-0.5, 0.0, 0.3, 1.0, 2.5])
    mu, sigma = gmr(gmm, s_values)
    mu0, sigma0 = gmr(gmm, s_values, jitter=0.0)
    o = 3
    for n, s in enumerate(s_values):
        m_ref, c_ref = precision_conditioning(means[0], covs[0], s)
        np.testing.assert_allclose(mu[n].numpy(), m_ref, rtol=1e-10, atol=1e-12)
        # gmr adds DEFAULT_JITTER = 1e-10 to the diagonal
        np.testing.assert_allclose(sigma[n].numpy(), c_ref + DEFAULT_JITTER * np.eye(o), rtol=1e-10, atol=1e-13)
        np.testing.assert_allclose(sigma0[n].numpy(), c_ref, rtol=1e-10, atol=1e-13)
    # the jitter is exactly what separates the two: it is added last, so the difference carries one IEEE rounding
    # of |Sigma| <= ~2.2 (<= u64 |Sigma| ~ 2.4e-16, observed 8e-18), the same on any CPU
    np.testing.assert_allclose((sigma - sigma0).numpy(), np.broadcast_to(1e-10 * np.eye(o), sigma.shape), atol=1e-15)


def test_gmr_far_query_does_not_underflow():
    """A query many std from every component: log-sum-exp responsibilities stay finite and the
    nearest component (in Mahalanobis distance along s) dominates."""
    weights, means, covs = hand_gmm(0)
    gmm = as_gmm(weights, means, covs)
    mu, sigma = gmr(gmm, [60.0])
    assert torch.isfinite(mu).all() and torch.isfinite(sigma).all()
    dist = (60.0 - means[:, 0]) ** 2 / covs[:, 0, 0] + np.log(covs[:, 0, 0]) - 2 * np.log(weights)
    k = int(np.argmin(dist))
    m_ref, c_ref = precision_conditioning(means[k], covs[k], 60.0)
    np.testing.assert_allclose(mu[0].numpy(), m_ref, rtol=1e-6)
    np.testing.assert_allclose(sigma[0].numpy(), c_ref + 1e-10 * np.eye(2), rtol=1e-6, atol=1e-9)


def test_gmr_batched_shapes_symmetric_pd():
    weights, means, covs = hand_gmm(3, c=4, o=5)
    gmm = as_gmm(weights, means, covs)
    s = np.linspace(-0.2, 1.2, 37)
    mu, sigma = gmr(gmm, s)
    assert mu.shape == (37, 5) and sigma.shape == (37, 5, 5)
    assert mu.dtype == torch.float64 and sigma.dtype == torch.float64
    assert torch.equal(sigma, sigma.transpose(-1, -2))
    assert (torch.linalg.eigvalsh(sigma) > 0).all()
    # batching does not change the per-query result
    for i in (0, 17, 36):
        m1, s1 = gmr(gmm, s[i : i + 1])
        torch.testing.assert_close(m1[0], mu[i], rtol=1e-13, atol=1e-15)
        torch.testing.assert_close(s1[0], sigma[i], rtol=1e-13, atol=1e-15)
    # a torch tensor or a scalar as the query
    m2, _ = gmr(gmm, torch.tensor(s[5]))
    torch.testing.assert_close(m2[0], mu[5], rtol=1e-13, atol=1e-15)


def test_gmm_dataclass_validates_shapes():
    w, m, c = hand_gmm(0)
    with pytest.raises(ValueError, match="covariances"):
        as_gmm(w, m, c[:, :2, :2])
    with pytest.raises(ValueError, match="at least one output"):
        as_gmm(w, m[:, :1], c[:, :1, :1])
    g = as_gmm(w, m, c)
    assert g.n_components == 3 and g.output_dim == 2


# ---------------------------------------------------------------------------------------
# fit_gmm
# ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def peg_demos():
    return synthetic_demos("PegInsert", 4, action_dim=6, seed=0)


def test_fit_gmm_deterministic(peg_demos):
    a = fit_gmm(peg_demos.s, peg_demos.eta, n_components=3, seed=0)
    b = fit_gmm(peg_demos.s, peg_demos.eta, n_components=3, seed=0)
    assert torch.equal(a.weights, b.weights)
    assert torch.equal(a.means, b.means)
    assert torch.equal(a.covariances, b.covariances)
    assert a.means.dtype == torch.float64 and a.means.shape == (3, 7) and a.covariances.shape == (3, 7, 7)
    np.testing.assert_allclose(a.weights.sum().item(), 1.0, atol=1e-12)


def test_fit_gmm_recovers_single_gaussian():
    rng = np.random.default_rng(42)
    mean = np.array([0.5, 0.02, -0.01, 0.3])
    std = np.array([0.3, 2e-3, 1e-3, 0.05])  # mm-scale positions, radian-scale rotation
    corr = np.array([[1.0, 0.6, -0.3, 0.2], [0.6, 1.0, 0.1, 0.0], [-0.3, 0.1, 1.0, 0.4], [0.2, 0.0, 0.4, 1.0]])
    cov = corr * np.outer(std, std)
    n = 20000
    x = rng.multivariate_normal(mean, cov, size=n)
    g = fit_gmm(x[:, 0], x[:, 1:], n_components=1, seed=0)
    m_fit, c_fit = g.means[0].numpy(), g.covariances[0].numpy()
    # the one-component ML fit is the sample mean / (biased) sample covariance; reg_covar 1e-6 acts
    # on standardized data, i.e. 1e-6 relative to each dimension's variance
    np.testing.assert_allclose(m_fit, x.mean(0), rtol=1e-9, atol=1e-12)
    c_sample = np.cov(x.T, bias=True)
    np.testing.assert_allclose(c_fit, c_sample + 1e-6 * np.diag(np.diag(c_sample)), rtol=1e-7,
                               atol=1e-9 * np.outer(std, std).max())
    # and the truth, within sampling error
    assert np.all(np.abs(m_fit - mean) < 5 * std / np.sqrt(n))
    corr_fit = c_fit / np.outer(np.sqrt(np.diag(c_fit)), np.sqrt(np.diag(c_fit)))
    np.testing.assert_allclose(np.sqrt(np.diag(c_fit)), std, rtol=5 * np.sqrt(0.5 / n))
    np.testing.assert_allclose(corr_fit, corr, atol=5 / np.sqrt(n))


def test_fit_gmm_unit_scale_invariant(peg_demos):
    """Fitting on eta (m) and on 1000*eta (mm) gives the same mixture up to the unit change."""
    s, eta = peg_demos.s, peg_demos.eta
    a = fit_gmm(s, eta, n_components=4, seed=0)
    b = fit_gmm(s, 1000.0 * eta, n_components=4, seed=0)
    d = np.concatenate([[1.0], np.full(6, 1000.0)])  # s keeps its unit
    np.testing.assert_allclose(b.weights.numpy(), a.weights.numpy(), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(b.means.numpy() / d, a.means.numpy(), rtol=1e-6,
                               atol=1e-9 * np.abs(a.means.numpy()).max())
    cb = b.covariances.numpy() / np.outer(d, d)
    ca = a.covariances.numpy()
    # compare in correlation-like units so that entries of very different size are judged alike
    sd = np.sqrt(np.einsum("cii->ci", ca))
    norm = sd[:, :, None] * sd[:, None, :]
    np.testing.assert_allclose(cb / norm, ca / norm, rtol=0, atol=1e-5)
    np.testing.assert_allclose(np.einsum("cii->ci", cb), np.einsum("cii->ci", ca), rtol=1e-5)


def test_fit_gmm_constant_dimension_4d():
    """4D demos have eta[:, 3:5] == 0: the fit must still work and give those dims a tiny variance."""
    d = synthetic_demos("GearMesh", 3, action_dim=4, seed=0)
    g = fit_gmm(d.s, d.eta, n_components=2, seed=0)
    assert torch.isfinite(g.covariances).all()
    np.testing.assert_allclose(g.means[:, 4:6].numpy(), 0.0, atol=1e-15)
    var = torch.diagonal(g.covariances, dim1=-2, dim2=-1)[:, 4:6]
    assert (var > 0).all() and (var < 1e-5).all()
    mu, sigma = gmr(g, np.linspace(0, 1, 11))
    assert (torch.linalg.eigvalsh(sigma) > 0).all()


def test_fit_gmm_bad_inputs():
    rng = np.random.default_rng(0)
    s, eta = rng.uniform(size=100), rng.normal(size=(100, 2))
    with pytest.raises(ValueError, match="no samples"):
        fit_gmm(np.zeros(0), np.zeros((0, 2)), n_components=1)
    with pytest.raises(ValueError, match=r"expected s \(T,\) and eta \(T, O\)"):
        fit_gmm(s, eta[:99], n_components=1)
    with pytest.raises(ValueError, match=r"expected s \(T,\) and eta \(T, O\)"):
        fit_gmm(s[:, None], eta, n_components=1)
    with pytest.raises(ValueError, match=r"expected s \(T,\) and eta \(T, O\)"):
        fit_gmm(s, eta[:, 0], n_components=1)
    bad = eta.copy()
    bad[10, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        fit_gmm(s, bad, n_components=1)
    bad_s = s.copy()
    bad_s[3] = np.inf
    with pytest.raises(ValueError, match="NaN or inf"):
        fit_gmm(bad_s, eta, n_components=1)
    with pytest.raises(ValueError, match="too few"):
        fit_gmm(s[:11], eta[:11], n_components=3)  # 3 components need 3 * (2 + 2) = 12 samples
    with pytest.raises(ValueError, match="n_components"):
        fit_gmm(s, eta, n_components=0)
