"""KMP / NS-KMP core of KGRL: GMM/GMR, KMP mean and covariance, the KGRL prediction
(thesis eq. 4.36) and its precomputed per-step tables, and the 6D pose representation."""

from .demos import DemoSet, synthetic_demos
from .gmr import GMM, fit_gmm, gmr
from .kmp import kmp_covariance, kmp_mean, ns_kmp_predict, rbf_kernel
from .pose import eta_to_pose, pose_to_eta, reference_quat
from .prior import KMP_BETA, KMP_L, KMP_LAMBDA, fit_prior, load_or_fit_prior
from .tables import KMPTables, build_kmp_tables, tables_path_for

__all__ = [
    "DemoSet",
    "synthetic_demos",
    "GMM",
    "fit_gmm",
    "gmr",
    "kmp_mean",
    "kmp_covariance",
    "ns_kmp_predict",
    "rbf_kernel",
    "pose_to_eta",
    "eta_to_pose",
    "reference_quat",
    "KMP_LAMBDA",
    "KMP_BETA",
    "KMP_L",
    "fit_prior",
    "load_or_fit_prior",
    "KMPTables",
    "build_kmp_tables",
    "tables_path_for",
]
