"""A run's learning curves as a plain table: curves.jsonl in its run directory, one JSON object
per finished batch of episodes (all worlds end together), appended as the run trains.

Keys (thesis 6.1): transitions (env transitions summed over worlds, the x axis), episode_reward,
success_rate, success_rate_any, mean_contact_force, peak_contact_force, time_to_first_success_s
(null when no world succeeded) and wall_s. On `--resume` the rows past the checkpoint's
transitions are dropped first (they belong to the part of the run that is replayed), so a
resumed run's table is the one an uninterrupted run writes (as tensorboard's purge_step does).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from vkgrl_newton._io import atomic_write_text

CURVES_FILE = "curves.jsonl"
CURVE_KEYS = ("transitions", "episode_reward", "success_rate", "success_rate_any", "mean_contact_force",
              "peak_contact_force", "time_to_first_success_s", "wall_s")


def read_curves(run_dir: Path) -> list[dict]:
    """The rows of a run's curves.jsonl in order ([] when it has none yet); NaN for null."""
    path = Path(run_dir) / CURVES_FILE
    if not path.exists():
        return []
    rows, lines = [], path.read_text().splitlines()
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            if n == len(lines):  # the last line cut by a kill mid-write: that row was not written
                break
            raise ValueError(f"{path}: line {n} is not JSON") from None
        rows.append({k: (math.nan if row.get(k) is None else row[k]) for k in CURVE_KEYS})
    return rows


class CurveWriter:
    """Appends rows to run_dir/curves.jsonl; resume_at drops the rows after that many transitions."""

    def __init__(self, run_dir: Path, resume_at: int | None = None) -> None:
        self.path = Path(run_dir) / CURVES_FILE
        if resume_at is not None and self.path.exists():
            kept = [r for r in read_curves(run_dir) if r["transitions"] <= resume_at]
            atomic_write_text(self.path, "".join(_line(r) for r in kept), overwrite=True)

    def append(self, **row: float) -> None:
        missing = set(CURVE_KEYS) - set(row)
        if missing:
            raise ValueError(f"curve row lacks {sorted(missing)}")
        with open(self.path, "a") as f:
            f.write(_line(row))


def _line(row: dict) -> str:
    clean = {k: (None if isinstance(row[k], float) and math.isnan(row[k]) else row[k]) for k in CURVE_KEYS}
    return json.dumps(clean) + "\n"
