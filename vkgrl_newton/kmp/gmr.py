"""GMM over (s, eta) and Gaussian Mixture Regression, thesis eqs. 3.3-3.9 and 4.2-4.3.

The joint density of normalized time s and the O-dimensional pose eta is fitted with
scikit-learn's `GaussianMixture` (full covariances, fixed seed). GMR conditions it on s,
batched over query points, and moment-matches the conditional mixture into one Gaussian
per query (law of total covariance, eq. 3.9), giving the KMP reference (mu(s), Sigma(s)).

Scaling: positions are metres with millimetre spread, rotations are radians. sklearn's
`reg_covar` is an absolute diagonal term, which at 1e-6 would swamp a 1 mm (1e-6 m^2)
variance. So the fit runs on per-dimension standardized data and the mixture is mapped
back exactly (means and covariances transform affinely); `reg_covar` then acts relative
to each dimension's overall spread.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["GMM", "fit_gmm", "gmr", "DEFAULT_N_COMPONENTS", "DEFAULT_JITTER"]

# The KGRL author's code fits 7 components (sklearn, reg 1e-6, random_state 0); the thesis
# gives no number. 5-8 is the usual range for a single insertion skill.
DEFAULT_N_COMPONENTS = 7
# Added to every GMR covariance (Huang's GMR.m adds 1e-8 I) so that Sigma(s) stays PD.
DEFAULT_JITTER = 1e-10


@dataclass(frozen=True)
class GMM:
    """A Gaussian mixture over x = (s, eta): weights (C,), means (C, 1+O), covariances (C, 1+O, 1+O).

    Input dimension 0 is the normalized time s; dimensions 1.. are the outputs eta. float64 torch.
    """

    weights: torch.Tensor
    means: torch.Tensor
    covariances: torch.Tensor

    def __post_init__(self):
        c = self.weights.shape[0]
        d = self.means.shape[-1]
        if self.weights.ndim != 1 or self.means.shape != (c, d) or self.covariances.shape != (c, d, d):
            raise ValueError(
                "GMM: expected weights (C,), means (C, D), covariances (C, D, D); got "
                f"{tuple(self.weights.shape)}, {tuple(self.means.shape)}, {tuple(self.covariances.shape)}"
            )
        if d < 2:
            raise ValueError(f"GMM: dimension D = {d}; need the input s and at least one output")

    @property
    def n_components(self) -> int:
        return self.weights.shape[0]

    @property
    def output_dim(self) -> int:
        return self.means.shape[-1] - 1


def fit_gmm(
    s,
    eta,
    n_components: int = DEFAULT_N_COMPONENTS,
    seed: int = 0,
    reg_covar: float = 1e-6,
    max_iter: int = 500,
) -> GMM:
    """Fit the joint GMM p(s, eta) (eq. 4.2) to stacked demonstration samples.

    s: (T,) normalized time of every sample of every demonstration; eta: (T, O).
    Deterministic for a fixed seed (sklearn k-means init with random_state=seed).
    """
    from sklearn.mixture import GaussianMixture

    s = np.asarray(s, dtype=np.float64)
    eta = np.asarray(eta, dtype=np.float64)
    if s.ndim != 1 or eta.ndim != 2 or eta.shape[0] != s.shape[0]:
        raise ValueError(f"fit_gmm: expected s (T,) and eta (T, O); got s {s.shape}, eta {eta.shape}")
    if s.shape[0] == 0:
        raise ValueError("fit_gmm: no samples (empty demonstrations)")
    if n_components < 1:
        raise ValueError(f"fit_gmm: n_components must be >= 1, got {n_components}")
    if s.shape[0] < n_components * (eta.shape[1] + 2):
        raise ValueError(
            f"fit_gmm: {s.shape[0]} samples are too few for {n_components} full-covariance components "
            f"in {eta.shape[1] + 1} dimensions; record more demonstrations or lower n_components"
        )
    x = np.concatenate([s[:, None], eta], axis=1)
    if not np.all(np.isfinite(x)):
        raise ValueError("fit_gmm: demonstrations contain NaN or inf")
    offset = x.mean(axis=0)
    scale = x.std(axis=0)
    # A dimension that never varies (e.g. roll in 4D demos) keeps unit scale; its variance is
    # then reg_covar alone, a tiny but positive number.
    scale = np.where(scale > 1e-12, scale, 1.0)
    gm = GaussianMixture(
        n_components=n_components,
        covariance_type="full",
        reg_covar=reg_covar,
        max_iter=max_iter,
        random_state=seed,
    )
    gm.fit((x - offset) / scale)
    means = gm.means_ * scale + offset
    covs = gm.covariances_ * scale[None, :, None] * scale[None, None, :]
    return GMM(
        weights=torch.as_tensor(gm.weights_, dtype=torch.float64),
        means=torch.as_tensor(means, dtype=torch.float64),
        covariances=torch.as_tensor(covs, dtype=torch.float64),
    )


def gmr(gmm: GMM, s_query, jitter: float = DEFAULT_JITTER) -> tuple[torch.Tensor, torch.Tensor]:
    """Condition the GMM on time: mu(s) (N, O) and Sigma(s) (N, O, O), eqs. 3.4-3.9.

    s_query: (N,) normalized times. float64 throughout; responsibilities via log-sum-exp so
    that queries far from every component do not underflow to 0/0.
    """
    s = torch.as_tensor(s_query, dtype=torch.float64).reshape(-1)
    mu_x = gmm.means[:, 0]  # (C,)
    mu_y = gmm.means[:, 1:]  # (C, O)
    s_xx = gmm.covariances[:, 0, 0]  # (C,)
    s_yx = gmm.covariances[:, 1:, 0]  # (C, O)
    s_yy = gmm.covariances[:, 1:, 1:]  # (C, O, O)

    dx = s[:, None] - mu_x[None, :]  # (N, C)
    # log pi_k N(s | mu_x, Sigma_xx), eq. 3.7
    log_p = torch.log(gmm.weights)[None, :] - 0.5 * (dx * dx / s_xx + torch.log(2.0 * math.pi * s_xx))
    h = torch.softmax(log_p, dim=1)  # (N, C)

    gain = s_yx / s_xx[:, None]  # Sigma_yx Sigma_xx^-1, (C, O)
    mu_k = mu_y[None] + dx[..., None] * gain[None]  # eq. 3.4, (N, C, O)
    cov_k = s_yy - gain[:, :, None] * s_yx[:, None, :]  # eq. 3.5, (C, O, O)

    mu = torch.einsum("nc,nco->no", h, mu_k)  # eq. 3.8
    d = mu_k - mu[:, None, :]
    sigma = torch.einsum("nc,cij->nij", h, cov_k) + torch.einsum("nc,nci,ncj->nij", h, d, d)  # eq. 3.9
    sigma = 0.5 * (sigma + sigma.transpose(-1, -2))
    sigma = sigma + jitter * torch.eye(sigma.shape[-1], dtype=sigma.dtype)
    return mu, sigma
