"""Probes of a visual latent: how much of the privileged state is readable from it.

Two probes. `linear_probe`, over the whole image set: R^2 of the relative target pose. And
`near_hole_probe`, the one that matters for the policy: on the frames where the held part is
within 1 cm (xy) of the fixed part and less than 2 cm above it (`near_hole_mask`), the fixed
tip's position relative to the held part in the image's frame (`relative_in_image`), predicted
from the latent by an affine map and by a small MLP, as RMSE in mm per axis, next to the 1 mm
observation noise the latent must correct (thesis eq. 5.23) and next to a privileged pixel
baseline: the same regressions from the two parts' pixel centroids, pixel counts and mean 3D
points (shape-index and depth renders, `part_pixel_features`): what the image itself allows.

The whole-range probe:

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
import torch
from sklearn.linear_model import LinearRegression, Ridge
from sklearn.metrics import r2_score

__all__ = ["linear_probe", "near_hole_mask", "relative_in_image", "part_pixel_features", "regression_rmse",
           "regression_errors", "episode_bootstrap_se", "NearHoleRegressor", "ProbeMLP", "lateral_from_image", "near_hole_probe", "NEAR_HOLE_XY", "NEAR_HOLE_HEIGHT", "PROBE_AXES"]

NEAR_HOLE_XY = 0.01  # m: the held part within this horizontal distance of the fixed tip ...
NEAR_HOLE_HEIGHT = 0.02  # m: ... and less than this above it (in contact or inside: below 0)
PROBE_AXES = ("x", "y", "z")  # of the image's frame: +x right, +y down, +z along the optical axis


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


# ----------------------------------------------------------------------------- the near-hole probe
def near_hole_mask(geometry, xy_radius: float = NEAR_HOLE_XY, max_height: float = NEAR_HOLE_HEIGHT) -> np.ndarray:
    """(n,) bool: frames whose held part (its reference point: the bottom that must reach the hole)
    is strictly within `xy_radius` of the fixed tip horizontally and strictly less than
    `max_height` above it. `geometry`: (n, 13) as `vision.dataset.GEOMETRY_COLUMNS`, world frame."""
    g = np.asarray(geometry, dtype=np.float64)
    d = g[:, 0:3] - g[:, 3:6]
    return (np.hypot(d[:, 0], d[:, 1]) < xy_radius) & (d[:, 2] < max_height)


def _rotate_inverse(q_xyzw: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R(q)^T v for unit quaternions (n, 4) xyzw and vectors (n, 3), float64."""
    u, w = -q_xyzw[:, :3], q_xyzw[:, 3:4]  # the conjugate
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def relative_in_image(geometry) -> np.ndarray:
    """(n, 3) float64, m: the fixed tip minus the held part's reference point, in the image's
    (optical) frame of each frame's camera."""
    g = np.asarray(geometry, dtype=np.float64)
    q = g[:, 9:13] / np.linalg.norm(g[:, 9:13], axis=1, keepdims=True)
    return _rotate_inverse(q, g[:, 3:6] - g[:, 0:3])


def part_pixel_features(shape_index: np.ndarray, depth: np.ndarray, ray_dirs: np.ndarray, part_ids) -> np.ndarray:
    """(E, 6) float32 per world: the part's pixel centroid (u right, v down, px; pixel centres at
    k + 0.5), its pixel count, and the mean of its pixels' 3D points depth x direction in the
    optical frame (m). NaN (count 0) where the part is not in view.

    shape_index (E, H, W) integer and depth (E, H, W) ray distance, as `TaskCamera.render_labelled`;
    ray_dirs (H, W, 3) unit directions in the optical frame; part_ids[w]: the shape indices of the
    part in world w."""
    n, h, w = shape_index.shape
    out = np.full((n, 6), np.nan, np.float32)
    vv, uu = np.mgrid[0:h, 0:w]
    for e in range(n):
        mask = np.isin(shape_index[e], np.asarray(part_ids[e]))
        count = int(mask.sum())
        out[e, 2] = count
        if count:
            pts = depth[e][mask].astype(np.float64)[:, None] * ray_dirs[mask]
            out[e, :2] = uu[mask].mean() + 0.5, vv[mask].mean() + 0.5
            out[e, 3:] = pts.mean(axis=0)
    return out


def regression_rmse(x_train, y_train, x_val, y_val, model: str = "linear", seed: int = 0) -> np.ndarray:
    """Fit y ~ f(x) on the training rows, (k,) RMSE per target column on the validation rows
    (`regression_errors` gives the errors themselves)."""
    err = regression_errors(x_train, y_train, x_val, y_val, model, seed)
    return np.sqrt((err ** 2).mean(axis=0))


def regression_errors(x_train, y_train, x_val, y_val, model: str = "linear", seed: int = 0) -> np.ndarray:
    """Fit y ~ f(x) on the training rows; (n_val, k) prediction errors f(x_val) - y_val.

    model "linear": an affine map (inputs standardized, ridge 1e-6 against the mean squared error,
    only so that collinear inputs stay solvable); "mlp": scikit-learn's MLPRegressor, two hidden
    layers of 64 ReLU units on standardized inputs and targets, fitted by L-BFGS (at most 1000
    iterations) with an L2 penalty of 0.1. That solver and penalty were chosen on one image
    set's pixel measurements (PegInsert, 128 px, 1 401 training frames) against Adam with early
    stopping, which stopped short (RMSE 2x the affine map's): the penalty is a fixed setting,
    never tuned on the frames a probe is scored on. Computed in float64."""
    xt, yt = _as_2d(x_train, "x_train"), _as_2d(y_train, "y_train")
    xv, yv = _as_2d(x_val, "x_val"), _as_2d(y_val, "y_val")
    if xt.shape[0] != yt.shape[0] or xv.shape[0] != yv.shape[0] or xt.shape[1] != xv.shape[1]:
        raise ValueError(f"regression_rmse: shapes do not fit: x_train {xt.shape}, y_train {yt.shape}, "
                         f"x_val {xv.shape}, y_val {yv.shape}")
    reg = _fit_regressor(xt, yt, model, seed)
    return _predict(reg, xv).reshape(yv.shape) - yv


def _fit_regressor(xt: np.ndarray, yt: np.ndarray, model: str, seed: int):
    """regression_errors' model (its docstring), fitted on float64 (n, d) inputs and (n, k) targets."""
    from sklearn.compose import TransformedTargetRegressor
    from sklearn.neural_network import MLPRegressor
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    if model == "linear":
        reg = make_pipeline(StandardScaler(), Ridge(alpha=1e-6 * xt.shape[0]))
    elif model == "mlp":
        if xt.shape[0] < 20:
            raise ValueError(f"regression_rmse: model 'mlp' needs at least 20 training rows, got {xt.shape[0]}")
        mlp = MLPRegressor(hidden_layer_sizes=(64, 64), solver="lbfgs", alpha=0.1, max_iter=1000, random_state=seed)
        reg = TransformedTargetRegressor(regressor=make_pipeline(StandardScaler(), mlp), transformer=StandardScaler())
    else:
        raise ValueError(f"regression_rmse: model={model!r}; allowed: 'linear', 'mlp'")
    import warnings

    from sklearn.exceptions import ConvergenceWarning
    from threadpoolctl import threadpool_limits

    # one BLAS thread: the products are small, and with training jobs on the cores OpenBLAS's
    # spinning threads made an MLP fit 10x slower (measured: 50 s against 4.6 s)
    with warnings.catch_warnings(), threadpool_limits(1):
        warnings.simplefilter("ignore", ConvergenceWarning)  # max_iter is a budget here, not an error
        reg.fit(xt, yt if yt.shape[1] > 1 else yt[:, 0])
    return reg


def _predict(reg, x: np.ndarray) -> np.ndarray:
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        return np.asarray(reg.predict(x), dtype=np.float64)


class NearHoleRegressor:
    """The near-hole probe as an estimator a controller can use: fitted on the near-hole frames of an image set
    (`near_hole_mask`), latent (n, d_z) -> the fixed tip minus the held part's origin in the image's frame (n, 3)
    float64, m (`relative_in_image`), by `regression_errors`' model. Privileged labels train it, as a pose
    estimator is trained in simulation; at run time it reads only the latent."""

    def __init__(self, latent, geometry, model: str = "mlp", seed: int = 0) -> None:
        z, g = _as_2d(latent, "latent"), np.asarray(geometry, np.float64)
        if g.ndim != 2 or g.shape[0] != z.shape[0] or g.shape[1] != 13:
            raise ValueError(f"NearHoleRegressor: geometry must be (n, 13) beside latent {z.shape}, got {g.shape}")
        near = near_hole_mask(g)
        self.model, self.num_fit, self.latent_dim = model, int(near.sum()), z.shape[1]
        self._reg = _fit_regressor(z[near], relative_in_image(g[near]), model, seed)

    def __call__(self, latent) -> np.ndarray:
        z = _as_2d(latent, "latent")
        if z.shape[1] != self.latent_dim:
            raise ValueError(f"NearHoleRegressor: latent has {z.shape[1]} columns, it was fitted on {self.latent_dim}")
        return _predict(self._reg, z).reshape(-1, 3)

    def state(self) -> dict:
        """The fitted map as plain float64 arrays (`ProbeMLP`'s): standardize the input by x_mean, x_scale, then
        affine layers weights[i] (in, out), biases[i] with ReLU between them, then y * y_scale + y_mean."""
        if self.model == "mlp":
            pipe, ty = self._reg.regressor_, self._reg.transformer_
            sx, mlp = pipe.steps[0][1], pipe.steps[1][1]
            if mlp.activation != "relu" or mlp.out_activation_ != "identity":
                raise ValueError(f"NearHoleRegressor: an MLP of {mlp.activation} / {mlp.out_activation_} units")
            weights, biases = list(mlp.coefs_), list(mlp.intercepts_)
            y_mean, y_scale = ty.mean_, ty.scale_
        else:
            sx, ridge = self._reg.steps[0][1], self._reg.steps[1][1]
            weights, biases = [ridge.coef_.T], [np.asarray(ridge.intercept_)]
            y_mean, y_scale = np.zeros(3), np.ones(3)
        f64 = lambda a: np.asarray(a, np.float64).copy()  # noqa: E731
        return {"model": self.model, "num_fit": self.num_fit, "x_mean": f64(sx.mean_), "x_scale": f64(sx.scale_),
                "weights": [f64(w) for w in weights], "biases": [f64(b).reshape(-1) for b in biases],
                "y_mean": f64(y_mean), "y_scale": f64(y_scale)}


class ProbeMLP(torch.nn.Module):
    """`NearHoleRegressor.state()` in torch, to run beside the encoder on the env's device (no host round trip):
    latent (E, d_z) -> the fixed tip minus the held part's origin in the image's frame (E, 3), m, in the latent's
    dtype. The policy's input with --vision-probe-obs (envs.camera_latent) and the ceiling's camera estimate."""

    def __init__(self, state: dict) -> None:
        super().__init__()
        t = lambda a: torch.as_tensor(np.asarray(a, np.float64))  # noqa: E731
        for name in ("x_mean", "x_scale", "y_mean", "y_scale"):
            self.register_buffer(name, t(state[name]))
        if len(state["weights"]) != len(state["biases"]) or not state["weights"]:
            raise ValueError("ProbeMLP: weights and biases must be lists of the same, non-zero length")
        self.layers = torch.nn.ModuleList()
        for w, b in zip(state["weights"], state["biases"]):
            lin = torch.nn.Linear(*np.shape(w), dtype=torch.float64)
            with torch.no_grad():
                lin.weight.copy_(t(w).T)
                lin.bias.copy_(t(b))
            self.layers.append(lin)
        self.requires_grad_(False)
        self.latent_dim = int(np.shape(state["weights"][0])[0])

    @torch.no_grad()
    def forward(self, z: torch.Tensor) -> torch.Tensor:
        x = (z.to(self.x_mean.dtype) - self.x_mean) / self.x_scale
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i + 1 < len(self.layers):
                x = torch.relu(x)
        return (x * self.y_scale + self.y_mean).to(z.dtype)


def lateral_from_image(d_image: torch.Tensor, optical_quat_w: torch.Tensor) -> torch.Tensor:
    """(E, 2) world x, y of the held part's origin minus the fixed tip, from the probe's image-frame vector (fixed tip
    minus held, (E, 3)) and the optical frame's orientation in the world ((E, 4) xyzw): -(R d)_xy."""
    from ..rotations import quat_rotate

    return -quat_rotate(optical_quat_w.to(d_image.dtype), d_image)[:, :2]


def episode_bootstrap_se(errors: np.ndarray, episodes: np.ndarray, draws: int = 1000, seed: int = 0) -> np.ndarray:
    """(k,) standard error of the RMSE per column over a resampling of whole episodes (frames of
    one episode are correlated: resampling frames would understate it): the std of the RMSE of
    `draws` sets of as many episodes drawn with replacement."""
    ids, inverse = np.unique(np.asarray(episodes), return_inverse=True)
    sq = np.zeros((len(ids), errors.shape[1]))
    np.add.at(sq, inverse, errors ** 2)
    count = np.bincount(inverse, minlength=len(ids)).astype(np.float64)
    pick = np.random.default_rng(seed).integers(0, len(ids), size=(draws, len(ids)))
    rmse = np.sqrt(sq[pick].sum(axis=1) / count[pick].sum(axis=1)[:, None])
    return rmse.std(axis=0, ddof=1)


def near_hole_probe(latent_train, geometry_train, latent_val, geometry_val, pixels_train=None, pixels_val=None,
                    seed: int = 0, min_images: int = 20, episodes_val=None) -> dict:
    """The near-hole probe: fit on the near-hole training frames, RMSE (mm per image axis) on the
    near-hole validation frames, of the fixed tip relative to the held part in the image's frame.

    Returns {"latent_linear_rmse_mm": {x, y, z}, "latent_mlp_rmse_mm": {...}, "pixel_baseline_rmse_mm":
    {...} (the MLP on the pixel measurements; None without them), "pixel_baseline_linear_rmse_mm",
    "mean_predictor_rmse_mm" (predicting the training mean: what no information gives),
    "observation_noise_mm" 1.0 (Factory's per-axis noise on the fixed part's position), "num_images"
    (validation frames scored), "num_fit", "pixel_baseline_num_images" (validation frames with both
    parts in view, where the baseline is scored), and the selection's definition}. Given the
    validation frames' episode ids, also "num_episodes" and, per RMSE, "<name>_se" (mm per axis):
    its standard error over a bootstrap of whole held-out episodes (`episode_bootstrap_se`). With
    fewer than `min_images` near-hole frames in either split the RMSEs are None and "skipped"
    says why."""
    from ..tasks import TARGET_OBS_NOISE

    zt, zv = _as_2d(latent_train, "latent_train"), _as_2d(latent_val, "latent_val")
    gt, gv = np.asarray(geometry_train, np.float64), np.asarray(geometry_val, np.float64)
    mt, mv = near_hole_mask(gt), near_hole_mask(gv)
    out: dict = {"selection": f"held part within {NEAR_HOLE_XY * 1e3:g} mm (xy) of the fixed tip and less than "
                              f"{NEAR_HOLE_HEIGHT * 1e3:g} mm above it",
                 "target": "fixed tip minus held part, image frame (x right, y down, z optical axis)",
                 "observation_noise_mm": TARGET_OBS_NOISE * 1e3, "num_images": int(mv.sum()), "num_fit": int(mt.sum()),
                 "latent_linear_rmse_mm": None, "latent_mlp_rmse_mm": None, "pixel_baseline_rmse_mm": None,
                 "pixel_baseline_linear_rmse_mm": None, "mean_predictor_rmse_mm": None,
                 "pixel_baseline_num_images": 0}
    if mt.sum() < min_images or mv.sum() < min_images:
        out["skipped"] = (f"{int(mt.sum())} training and {int(mv.sum())} validation near-hole frames; "
                          f"the probe needs at least {min_images} of each")
        return out
    yt, yv = relative_in_image(gt[mt]), relative_in_image(gv[mv])

    ep = None if episodes_val is None else np.asarray(episodes_val)[mv]
    if ep is not None:
        out["num_episodes"] = int(len(np.unique(ep)))

    def mm(rmse: np.ndarray) -> dict:
        return {a: float(v * 1e3) for a, v in zip(PROBE_AXES, rmse)}

    def put(name: str, errors: np.ndarray, rows=slice(None)) -> None:
        out[name] = mm(np.sqrt((errors ** 2).mean(axis=0)))
        if ep is not None:
            out[name + "_se"] = mm(episode_bootstrap_se(errors, ep[rows], seed=seed))

    put("mean_predictor_rmse_mm", yt.mean(axis=0) - yv)
    put("latent_linear_rmse_mm", regression_errors(zt[mt], yt, zv[mv], yv, "linear"))
    put("latent_mlp_rmse_mm", regression_errors(zt[mt], yt, zv[mv], yv, "mlp", seed))
    if pixels_train is not None and pixels_val is not None:
        pt, pv = np.asarray(pixels_train, np.float64)[mt], np.asarray(pixels_val, np.float64)[mv]
        ft, fv = np.isfinite(pt).all(axis=1), np.isfinite(pv).all(axis=1)
        out["pixel_baseline_num_images"] = int(fv.sum())
        if ft.sum() >= min_images and fv.sum() >= min_images:
            put("pixel_baseline_rmse_mm", regression_errors(pt[ft], yt[ft], pv[fv], yv[fv], "mlp", seed), fv)
            put("pixel_baseline_linear_rmse_mm", regression_errors(pt[ft], yt[ft], pv[fv], yv[fv], "linear"), fv)
    return out
