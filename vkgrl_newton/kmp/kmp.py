"""Kernelized Movement Primitives: mean (eq. 3.29), covariance (eq. 3.37) and the
null-space KMP / KGRL prediction (eq. 4.36), written literally for clarity.

Notation (thesis chapters 3.2-4.2): N reference points s_i with GMR mean mu_i (O) and
covariance Sigma_i (O x O); K = [k(s_i, s_j) I_O] (NO x NO, time-major: index i*O + d);
Sigma = blockdiag(Sigma_1..Sigma_N); mu = stacked mu_i (NO); k* = [k(s*, s_i) I_O] (O x NO).

Kernel: k(s_i, s_j) = exp(-l (s_i - s_j)^2). l multiplies the squared distance (the KGRL
author's and Huang's convention), so it is an inverse squared length scale.

These functions build the full NO x NO matrices and solve with a float64 Cholesky
factorization; condition numbers reach 1e6 with millimetre-level demo spread, which float32
cannot carry. They are the reference implementation: the per-step tables of `tables.py` are
the fast path and are tested against `ns_kmp_predict`.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = [
    "rbf_kernel",
    "kmp_mean",
    "kmp_covariance",
    "ns_kmp_predict",
    "validate_reference",
]


def _f64(x, name: str) -> torch.Tensor:
    try:
        return torch.as_tensor(x, dtype=torch.float64).detach().cpu()
    except (TypeError, ValueError, RuntimeError) as e:
        raise ValueError(f"{name}: not convertible to a float64 tensor ({e})") from None


def _check_positive(name: str, value: float) -> float:
    value = float(value)
    if not value > 0.0 or value != value or value == float("inf"):
        raise ValueError(f"{name} must be a finite number > 0, got {value}")
    return value


def _check_nonnegative(name: str, value: float) -> float:
    value = float(value)
    if not value >= 0.0 or value == float("inf"):
        raise ValueError(f"{name} must be a finite number >= 0, got {value}")
    return value


def rbf_kernel(s_a, s_b, l: float) -> torch.Tensor:
    """Scalar kernel matrix k(s_a[i], s_b[j]) = exp(-l (s_a[i] - s_b[j])^2), shape (len(s_a), len(s_b))."""
    s_a = _f64(s_a, "s_a").reshape(-1)
    s_b = _f64(s_b, "s_b").reshape(-1)
    d = s_a[:, None] - s_b[None, :]
    return torch.exp(-l * d * d)


def validate_reference(s_ref, mu_ref, sigma_ref):
    """Check and convert a KMP reference: s_ref (N,), mu_ref (N, O) or None, sigma_ref (N, O, O)
    symmetric positive definite. Returns float64 tensors; raises ValueError naming the argument.
    """
    s_ref = _f64(s_ref, "s_ref")
    sigma_ref = _f64(sigma_ref, "sigma_ref")
    if s_ref.ndim != 1 or s_ref.shape[0] == 0:
        raise ValueError(f"s_ref must have shape (N,) with N >= 1, got {tuple(s_ref.shape)}")
    n = s_ref.shape[0]
    if sigma_ref.ndim != 3 or sigma_ref.shape[0] != n or sigma_ref.shape[1] != sigma_ref.shape[2] or sigma_ref.shape[1] == 0:
        raise ValueError(f"sigma_ref must have shape (N={n}, O, O), got {tuple(sigma_ref.shape)}")
    o = sigma_ref.shape[1]
    checked = {"s_ref": s_ref, "sigma_ref": sigma_ref}
    if mu_ref is not None:
        mu_ref = _f64(mu_ref, "mu_ref")
        if mu_ref.shape != (n, o):
            raise ValueError(f"mu_ref must have shape (N={n}, O={o}), got {tuple(mu_ref.shape)}")
        checked["mu_ref"] = mu_ref
    for name, t in checked.items():
        if not torch.isfinite(t).all():
            raise ValueError(f"{name} contains NaN or inf")
    asym = (sigma_ref - sigma_ref.transpose(-1, -2)).abs().amax()
    # relative to the covariances' own scale: millimetre spread means entries of 1e-8 m^2
    if asym > 1e-9 * float(sigma_ref.abs().amax()):
        raise ValueError(f"sigma_ref must be symmetric (max |S - S^T| = {float(asym):.3g})")
    _, info = torch.linalg.cholesky_ex(sigma_ref)
    bad = torch.nonzero(info).reshape(-1)
    if bad.numel() > 0:
        raise ValueError(
            f"sigma_ref must be positive definite; {bad.numel()} of {n} covariances are not "
            f"(first at index {int(bad[0])})"
        )
    return s_ref, mu_ref, sigma_ref


def _block_diag(sigma: torch.Tensor) -> torch.Tensor:
    return torch.block_diag(*sigma.unbind(0))


def _kron_eye(k: torch.Tensor, o: int) -> torch.Tensor:
    return torch.kron(k, torch.eye(o, dtype=k.dtype))


def _cholesky(matrix: torch.Tensor, what: str) -> torch.Tensor:
    chol, info = torch.linalg.cholesky_ex(matrix)
    if int(info) != 0:
        raise ValueError(f"{what} is not positive definite (Cholesky failed at pivot {int(info)})")
    return chol


def kmp_mean(s_star, s_ref, mu_ref, sigma_ref, lam: float, l: float) -> torch.Tensor:
    """KMP mean E[eta(s*)] = k* (K + lam Sigma)^-1 mu (eq. 3.29) at each query; returns (M, O)."""
    lam = _check_positive("lam", lam)
    l = _check_positive("l", l)
    if mu_ref is None:
        raise ValueError("mu_ref is required: the reference means (N, O)")
    s_ref, mu_ref, sigma_ref = validate_reference(s_ref, mu_ref, sigma_ref)
    s_star = _f64(s_star, "s_star").reshape(-1)
    o = mu_ref.shape[1]
    big_k = _kron_eye(rbf_kernel(s_ref, s_ref, l), o)
    chol = _cholesky(big_k + lam * _block_diag(sigma_ref), "K + lam*Sigma")
    alpha = torch.cholesky_solve(mu_ref.reshape(-1, 1), chol)  # (NO, 1)
    k_star = _kron_eye(rbf_kernel(s_star, s_ref, l), o)  # (MO, NO)
    return (k_star @ alpha).reshape(-1, o)


def kmp_covariance(s_star, s_ref, sigma_ref, lam: float, l: float) -> torch.Tensor:
    """KMP covariance D[eta(s*)] = (N/lam) (k(s*,s*) - k* (K + lam Sigma)^-1 k*^T) (eq. 3.37); (M, O, O).

    N is the number of reference points. Huang's code uses a separate lam for the covariance
    (lam_c, about 60); pass that here.
    """
    lam = _check_positive("lam", lam)
    l = _check_positive("l", l)
    s_ref, _, sigma_ref = validate_reference(s_ref, None, sigma_ref)
    s_star = _f64(s_star, "s_star").reshape(-1)
    n, o = sigma_ref.shape[0], sigma_ref.shape[1]
    big_k = _kron_eye(rbf_kernel(s_ref, s_ref, l), o)
    chol = _cholesky(big_k + lam * _block_diag(sigma_ref), "K + lam*Sigma")
    out = []
    for s in s_star.unbind(0):
        k_star = _kron_eye(rbf_kernel(s.reshape(1), s_ref, l), o)  # (O, NO)
        k_ss = _kron_eye(rbf_kernel(s.reshape(1), s.reshape(1), l), o)  # (O, O)
        d = (n / lam) * (k_ss - k_star @ torch.cholesky_solve(k_star.T, chol))
        out.append(0.5 * (d + d.T))
    return torch.stack(out)


def _ns_kmp_from_blocks(k_star, big_k, k_hat_star, big_k_hat, k_under, mu, sigma_blk, xi, lam, beta):
    """Eq. 4.30 with alpha = 0, given the kernel blocks (all O-expanded matrices):

    eta = k* A mu + (beta/gamma) (k_hat* - k* A K_hat) K_under^-1 xi,  A = (K + gamma Sigma)^-1.

    k_star (O, NO), big_k (NO, NO), k_hat_star (O, O), big_k_hat (NO, O), k_under (O, O),
    mu (NO,), sigma_blk (NO, NO), xi (O,). Kept separate from the kernel choice so that the
    kernelized formula can be checked against an explicit-feature (primal) computation.
    """
    gamma = lam + beta
    chol = _cholesky(big_k + gamma * sigma_blk, "K + (lam+beta)*Sigma")
    mean = k_star @ torch.cholesky_solve(mu.reshape(-1, 1), chol).reshape(-1)
    projector = k_hat_star - k_star @ torch.cholesky_solve(big_k_hat, chol)
    return mean + (beta / gamma) * projector @ torch.linalg.solve(k_under, xi)


def ns_kmp_predict(s_star, xi, s_hat, s_ref, mu_ref, sigma_ref, lam, beta, l):
    """KGRL prediction of thesis eq. 4.36 for one query: returns eta of shape (O,).

        eta(s*) = k* A mu + (beta / gamma) (k_hat* - k* A K_hat) xi,
        A = (K + gamma Sigma)^-1,  gamma = lam + beta,

    with k* = [k(s*, s_i) I_O]_i (O x NO), K_hat = [k(s_i, s_hat) I_O]_i stacked (NO x O),
    k_hat* = k(s*, s_hat) I_O, and the squared-exponential kernel k(a, b) = exp(-l (a - b)^2)
    (for which K_under = k(s_hat, s_hat) I = I in eq. 4.30).

    Args:
        s_star: query input (normalized time), a scalar.
        xi: null-space action (O,), in the units of eta divided by those of Sigma (see tables.py).
        s_hat: input at which xi acts; KGRL uses s_hat = s_star.
        s_ref: (N,) reference inputs; mu_ref (N, O); sigma_ref (N, O, O) symmetric positive definite.
        lam: KMP regularization lambda > 0.  beta: null-space weight >= 0 (0 gives the plain
        KMP mean with lam).  l: kernel parameter > 0 (multiplies the squared distance).

    Inputs may be numpy arrays or torch tensors; the computation runs in float64 on the CPU
    with a Cholesky factorization. The result is a float64 numpy array if mu_ref is a numpy
    array, else a float64 torch tensor.
    """
    as_numpy = isinstance(mu_ref, np.ndarray)
    lam = _check_positive("lam", lam)
    beta = _check_nonnegative("beta", beta)
    l = _check_positive("l", l)
    s_ref, mu_ref, sigma_ref = validate_reference(s_ref, mu_ref, sigma_ref)
    o = mu_ref.shape[1]
    xi = _f64(xi, "xi")
    if xi.shape != (o,):
        raise ValueError(f"xi must have shape (O={o},), got {tuple(xi.shape)}")
    if not torch.isfinite(xi).all():
        raise ValueError("xi contains NaN or inf")
    s_star = _f64(s_star, "s_star").reshape(-1)
    s_hat = _f64(s_hat, "s_hat").reshape(-1)
    if s_star.numel() != 1 or s_hat.numel() != 1:
        raise ValueError(f"s_star and s_hat must be scalars, got {s_star.numel()} and {s_hat.numel()} values")
    eta = _ns_kmp_from_blocks(
        k_star=_kron_eye(rbf_kernel(s_star, s_ref, l), o),
        big_k=_kron_eye(rbf_kernel(s_ref, s_ref, l), o),
        k_hat_star=_kron_eye(rbf_kernel(s_star, s_hat, l), o),
        big_k_hat=_kron_eye(rbf_kernel(s_ref, s_hat, l), o),
        k_under=_kron_eye(rbf_kernel(s_hat, s_hat, l), o),
        mu=mu_ref.reshape(-1),
        sigma_blk=_block_diag(sigma_ref),
        xi=xi,
        lam=lam,
        beta=beta,
    )
    return eta.numpy() if as_numpy else eta
