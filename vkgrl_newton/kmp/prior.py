"""The KGRL trajectory prior of a task: demonstrations -> GMM -> GMR -> per-step KMP tables.

Defaults for the KMP parameters (thesis Table 5.4 gives dt, h and the weights, not these):

    KMP_LAMBDA = 1.0, KMP_BETA = 4.0, KMP_L = 20.0   (kernel exp(-l (s_i - s_j)^2))

They were chosen with `python -m vkgrl_newton.tools.kmp_param_study` on 10 synthetic
demonstrations per task (Table 5.2 start spread, 1 mm target noise), 6D, lam in {0.1, 1, 6},
beta in {1, 2, 3, 4, 6, 10, 30}, l in {2, 20, 200, 1000}. Per task at (1, 4, 20):

    task       cond(K+gamma*Sigma)  fit (mm / deg)  reach at |a|=1 (mm / deg)  reach/sigma
    PegInsert        9.0e6          0.19 / 0.89          6.7 / 7.2                0.98
    GearMesh         5.0e6          0.09 / 0.60          7.4 / 4.8                1.56
    NutThread        5.7e7          0.36 / 4.99          1.4 / 6.1                0.67

  - cond: worst over the control grid; 1e6-1e8, hence float64 Cholesky (float32 would keep
    no digits). lam = 0.1 barely improves the fit but raises cond to 4e7 on PegInsert; lam = 6
    costs fidelity (PegInsert 0.27 mm / 1.25 deg).
  - fit: largest gap between the prior m[n] and the GMR mean. l = 2 (the KGRL code's value)
    makes the 16-26 point window act as a moving average that leads the motion: 17 deg of
    yaw on NutThread, whose demonstrations turn the nut 120 deg; l = 20 cuts that to 5.0
    deg and is the best of the grid on all three tasks (l = 200: 6.6 deg, 1000: 11.8 deg).
  - reach: median over steps of the command move produced by one saturated action axis,
    with the Table 5.4 weights (zeta = w * a). The null-space gain is about beta * Sigma, so
    beta sets how far RL can push the prior; beta = 4 puts a full action at about one
    demonstrated standard deviation (reach/sigma 0.7-1.6): RL can explore across the band
    the demonstrations span, not far outside it. beta = 6 gives 1.4 (PegInsert) to 2.3
    (GearMesh), beta = 3 gives 0.5 (NutThread).
Demonstrations from the simulator will have a different spread; rerun the study on them.
"""

from __future__ import annotations

from pathlib import Path

from ..tasks import get_task
from .demos import DemoSet
from .gmr import DEFAULT_N_COMPONENTS, fit_gmm
from ..cache import file_sha256
from .tables import REFERENCES, EmpiricalReference, KMPTables, build_kmp_tables, tables_path_for

__all__ = ["KMP_LAMBDA", "KMP_BETA", "KMP_L", "fit_prior", "load_or_fit_prior", "prior_fit", "format_prior_fit"]

KMP_LAMBDA = 1.0
KMP_BETA = 4.0
KMP_L = 20.0


def fit_prior(
    demos: DemoSet,
    action_dim: int | None = None,
    lam: float = KMP_LAMBDA,
    beta: float = KMP_BETA,
    l: float = KMP_L,
    n_components: int = DEFAULT_N_COMPONENTS,
    seed: int = 0,
    source_sha256: str = "",
    reference: str = "gmr",
) -> KMPTables:
    """Fit the GMM to a demonstration set and precompute the KGRL tables on its task's grid.

    action_dim: 4 or 6; None means the demonstrations' own. 6D tables need 6D demonstrations.
    reference: "gmr" (the thesis) or "empirical" (the demonstrations' per-step mean and
    covariance, kmp.tables.EmpiricalReference; the GMM is still fitted and kept for plots).
    """
    if reference not in REFERENCES:
        raise ValueError(f"reference={reference!r}; allowed: {list(REFERENCES)}")
    spec = get_task(demos.task)
    if abs(demos.psi_ref - spec.psi_ref) > 1e-9:
        raise ValueError(
            f"demonstrations: psi_ref {demos.psi_ref:.6g} rad differs from {spec.name}'s {spec.psi_ref:.6g} rad; "
            "eta must be relative to the task's q_ref"
        )
    action_dim = demos.action_dim if action_dim is None else action_dim
    if action_dim == 6 and demos.action_dim == 4:
        raise ValueError("action_dim: 6D tables need 6D demonstrations; these hold roll and pitch at the reference")
    gmm = fit_gmm(demos.s, demos.eta, n_components=n_components, seed=seed)
    ref = EmpiricalReference(demos, spec.kmp_dt) if reference == "empirical" else None
    return build_kmp_tables(gmm, spec.kmp_dt, spec.kmp_horizon, lam, beta, l, action_dim, source_sha256, seed,
                            reference=ref)


def load_or_fit_prior(
    demo_path,
    action_dim: int | None = None,
    lam: float = KMP_LAMBDA,
    beta: float = KMP_BETA,
    l: float = KMP_L,
    n_components: int = DEFAULT_N_COMPONENTS,
    seed: int = 0,
    reference: str = "gmr",
) -> tuple[KMPTables, Path, bool]:
    """Tables for a demonstration file, cached beside it (`<stem>.kmp<D>d.npz`).

    The cache is reused only if it was built from the same file contents (sha256) with the
    same parameters and GMM seed; otherwise it is rebuilt (the tables are derived data). A
    file at that path that is not a tables file is never overwritten (ValueError).
    action_dim None means the demonstrations' own. Returns (tables, tables_path, rebuilt).
    """
    demo_path = Path(demo_path)
    demos = DemoSet.load(demo_path)
    spec = get_task(demos.task)
    action_dim = demos.action_dim if action_dim is None else action_dim
    digest = file_sha256(demo_path)
    path = tables_path_for(demo_path, action_dim, reference)
    if path.exists():
        try:
            cached = KMPTables.load(path)
        except ValueError as e:
            if "not a KMP tables file" in str(e) and "missing keys" in str(e):
                raise ValueError(f"{path} exists and is not a KMP tables file; move it away, it is not overwritten") from None
            cached = None  # damaged or stale tables: derived data, rebuilt below
        if cached is not None and (
            cached.source_sha256 == digest
            and cached.action_dim == action_dim
            and (cached.lam, cached.beta, cached.l) == (float(lam), float(beta), float(l))
            and (cached.dt, cached.horizon) == (spec.kmp_dt, spec.kmp_horizon)
            and cached.gmm.n_components == n_components
            and cached.fit_seed == int(seed)
            and cached.reference == reference
        ):
            return cached, path, False
    tables = fit_prior(demos, action_dim, lam, beta, l, n_components, seed, source_sha256=digest, reference=reference)
    tables.save(path)
    return tables, path, True


def prior_fit(tables: KMPTables, demos: DemoSet) -> dict:
    """How the prior follows its demonstrations, per control step n and position axis (x, y, z):

        mean_error  m[n] - the demonstrations' mean at s_n (m), (S, 3)
        ref_sd      the reference's sd at s_n (GMR's, or the demonstrations' for "empirical"), (S, 3)
        demo_sd     the demonstrations' sd at s_n (ddof 1), (S, 3)
        reach       how far a saturated action moves the command, sum_j |B[n]_ij| w_j (m), (S, 3)

    and summaries over the episode: max_abs_error_mm, sd_ratio_max / sd_ratio_min (ref_sd /
    demo_sd), reach_median_mm. The demonstrations are put on the control grid as the empirical
    reference does (kmp.tables.demonstrations_on_grid). A fit reported against the GMR mean
    alone cannot show a GMR that misses the demonstrations; this compares with them.
    """
    import numpy as np

    from .gmr import gmr
    from .tables import control_grid, demonstrations_on_grid, null_space_reach

    spec = get_task(demos.task)
    on_grid = demonstrations_on_grid(demos, tables.dt)
    mean, sd = on_grid.mean(0)[:, :3], on_grid.std(0, ddof=1)[:, :3]
    if tables.reference == "empirical":
        ref_sd = sd
    else:
        _, sigma = gmr(tables.gmm, control_grid(tables.dt))
        ref_sd = np.sqrt(np.diagonal(sigma.numpy(), axis1=1, axis2=2))[:, :3]
    err = tables.mean.numpy()[:, :3] - mean
    w = np.array([spec.w_pos] * 3 + [spec.w_rot] * 3)
    reach = null_space_reach(tables.gain, w).numpy()[:, :3]
    ratio = ref_sd / np.maximum(sd, 1e-9)
    return {"mean_error": err, "ref_sd": ref_sd, "demo_sd": sd, "reach": reach,
            "max_abs_error_mm": (1e3 * np.abs(err).max(0)).tolist(), "sd_ratio_max": ratio.max(0).tolist(),
            "sd_ratio_min": ratio.min(0).tolist(), "reach_median_mm": (1e3 * np.median(reach, 0)).tolist(),
            "reference": tables.reference}


def format_prior_fit(fit: dict) -> str:
    """The summaries of `prior_fit` as lines (x, y, z)."""
    f = lambda v, d=2: "/".join(f"{x:.{d}f}" for x in v)  # noqa: E731
    return (f"prior vs its demonstrations ({fit['reference']} reference), x/y/z over the episode:\n"
            f"  max |m[n] - their mean|  {f(fit['max_abs_error_mm'])} mm\n"
            f"  reference sd / theirs    {f(fit['sd_ratio_min'])} (min) .. {f(fit['sd_ratio_max'])} (max)\n"
            f"  reach at |a| = 1         {f(fit['reach_median_mm'])} mm (median over steps)")
