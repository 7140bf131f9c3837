"""Linear probe of a visual latent: how much of the privileged state is linearly readable from it.

Not in the thesis, which judges the VAE by its reconstructions and the RL results; here it is
the check that the encoder mean (eq. 4.49) carries the relative target pose the policy needs.
Per target column, a ridge-regularized affine map latent -> target is fitted (scikit-learn's
Ridge) on the training images and scored on the validation images by

    R^2 = 1 - SS_res / SS_tot,   SS_res = sum (y - y_hat)^2,   SS_tot = sum (y - mean(y))^2

with mean(y) the validation mean (as sklearn's r2_score): 1 is perfect, 0 is no better than the
mean, below 0 worse. A yaw target is whatever columns the caller passes (the angle, or cos and sin).
"""

from __future__ import annotations

import numpy as np
from sklearn.linear_model import LinearRegression, Ridge
from sklearn.metrics import r2_score

__all__ = ["linear_probe"]


def _as_2d(a, name: str) -> np.ndarray:
    a = np.asarray(a.detach().cpu() if hasattr(a, "detach") else a, dtype=np.float64)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2 or not np.isfinite(a).all():
        raise ValueError(f"linear_probe: {name} must be finite (n,) or (n, k), got shape {a.shape}")
    return a


def linear_probe(latent_train, target_train, latent_val, target_val, ridge: float = 1e-3) -> dict[str, np.ndarray]:
    """Fit target ~ latent @ W + b on the training rows; R^2 per target column on the validation rows.

    latent_*: (n, d); target_*: (n, k) or (n,) (numpy arrays or tensors), computed in float64.
    The ridge penalty is `ridge * ||W||^2` against the MEAN squared error (so it does not fade
    as n grows), on the weights only, not the bias. Returns float64 arrays: `r2` (k,) on the
    validation set, `r2_train` (k,), `weight` (d, k), `bias` (k,).
    """
    if not ridge >= 0:
        raise ValueError(f"linear_probe: ridge={ridge!r}; allowed: >= 0")
    zt, yt = _as_2d(latent_train, "latent_train"), _as_2d(target_train, "target_train")
    zv, yv = _as_2d(latent_val, "latent_val"), _as_2d(target_val, "target_val")
    if zt.shape[0] != yt.shape[0] or zv.shape[0] != yv.shape[0]:
        raise ValueError(f"linear_probe: rows differ: latent_train {zt.shape}, target_train {yt.shape}, "
                         f"latent_val {zv.shape}, target_val {yv.shape}")
    if zt.shape[1] != zv.shape[1] or yt.shape[1] != yv.shape[1]:
        raise ValueError(f"linear_probe: columns differ between train {zt.shape, yt.shape} "
                         f"and val {zv.shape, yv.shape}")
    if zt.shape[0] < 2 or zv.shape[0] < 2:
        raise ValueError("linear_probe: needs at least 2 training and 2 validation rows")
    n = zt.shape[0]
    # sklearn's Ridge penalizes alpha ||W||^2 against the SUM of squared errors: alpha = n * ridge;
    # the bias is fitted and not penalized
    model = (Ridge(alpha=n * ridge) if ridge > 0 else LinearRegression()).fit(zt, yt)
    weight, bias = model.coef_.T.copy(), np.asarray(model.intercept_, dtype=np.float64)
    return {"r2": _r2(yv, model.predict(zv)), "r2_train": _r2(yt, model.predict(zt)), "weight": weight, "bias": bias}


def _r2(y: np.ndarray, y_hat: np.ndarray) -> np.ndarray:
    """Per column; nan for a constant column (R^2 undefined there)."""
    r2 = r2_score(y, y_hat, multioutput="raw_values", force_finite=False)
    return np.where(np.isfinite(r2), r2, np.nan)
