"""The thesis's own results, Tables 6.1-6.4 (final values, mean and std over 10 seeds), as
transcribed in thesis_tables.csv beside this file."""

from __future__ import annotations

import csv
import math
from pathlib import Path

# metrics.json key -> the thesis table that reports it
METRICS = {"mean_episode_reward": "6.1", "success_rate": "6.2", "mean_contact_force": "6.3",
           "time_to_first_success_s": "6.4"}
THESIS_METHOD_NAMES = {"kgrl": "KGRL", "sac": "SAC", "vision_kgrl": "VisionKGRL", "vision_sac": "VisionSAC"}
THESIS_TABLES = Path(__file__).with_name("thesis_tables.csv")


def load_thesis_tables(path: Path = THESIS_TABLES) -> dict[tuple[str, str, str, str, int], tuple[float, float]]:
    """{(metric, task, method, env, action_dim): (mean, std)}; NaN, NaN for the thesis's dash."""
    lines = [ln for ln in Path(path).read_text().splitlines() if ln and not ln.startswith("#")]
    out = {}
    for row in csv.DictReader(lines):
        if METRICS.get(row["metric"]) != row["table"]:
            raise ValueError(f"{path}: metric {row['metric']!r} is not Table {row['table']}'s")
        key = (row["metric"], row["task"], row["method"], row["env"], int(row["action_dim"]))
        mean, std = (math.nan if row[k] == "" else float(row[k]) for k in ("mean", "std"))
        out[key] = (mean, std)
    return out
