"""Results of training runs: each run's learning curves (curves.jsonl) and the thesis's own
numbers (Tables 6.1-6.4, thesis_tables.csv), read by train/report.py and train/plot_runs.py."""

from vkgrl_newton.results.curves import CURVE_KEYS, CURVES_FILE, CurveWriter, read_curves
from vkgrl_newton.results.thesis import METRICS, THESIS_METHOD_NAMES, load_thesis_tables

__all__ = ["CURVES_FILE", "CURVE_KEYS", "CurveWriter", "read_curves", "METRICS", "THESIS_METHOD_NAMES",
           "load_thesis_tables"]
