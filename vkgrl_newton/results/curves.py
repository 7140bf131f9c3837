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

from vkgrl_newton._io import atomic_write_text, one_line, short_repr

CURVES_FILE = "curves.jsonl"
CURVE_KEYS = ("transitions", "episode_reward", "success_rate", "success_rate_any", "mean_contact_force",
              "peak_contact_force", "time_to_first_success_s", "wall_s")


def read_curves(run_dir: Path) -> list[dict]:
    """The rows of a run's curves.jsonl in order ([] when it has none yet); NaN for null or a missing key.

    A damaged file is a ValueError in one line naming the file and the line: not UTF-8, a line that is
    not JSON or not a JSON object, a row without transitions, a value that is not a number (or null),
    bare NaN / Infinity (not JSON: the writer writes null) or a number too large for a float. The last
    line alone may be cut short (a kill mid-write): that row was not written, and is left out."""
    path = Path(run_dir) / CURVES_FILE
    if not path.exists():
        return []
    try:
        data = path.read_bytes()
    except OSError as e:  # (a directory of that name, no permission)
        raise ValueError(one_line(f"{path}: not a readable curves file ({type(e).__name__}: {e})")) from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        line = data.count(b"\n", 0, e.start) + 1
        raise ValueError(f"{path}: line {line} is not UTF-8 text") from None
    rows, lines = [], text.split("\n")
    while lines and not lines[-1].strip():
        lines.pop()
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line, parse_constant=_refuse_constant)
        except json.JSONDecodeError:
            if n == len(lines):  # the last line cut by a kill mid-write: that row was not written
                break
            raise ValueError(f"{path}: line {n} is not JSON") from None
        except (ValueError, RecursionError) as e:  # bare NaN / Infinity; nesting too deep for the parser
            raise ValueError(one_line(f"{path}: line {n} is not a curve row ({type(e).__name__}: {e})")) from None
        problem = _row_problem(row)
        if problem:
            raise ValueError(one_line(f"{path}: line {n} is not a curve row: {problem}"))
        rows.append({k: (math.nan if row.get(k) is None else row[k]) for k in CURVE_KEYS})
    return rows


def _refuse_constant(name: str):
    raise ValueError(f"bare {name} (not JSON; a curve's missing value is null)")


def _row_problem(row) -> str:
    """What is wrong with a parsed row ("" if nothing): a JSON object of numbers (or null) with its transitions."""
    if not isinstance(row, dict):
        return f"a JSON {type(row).__name__}, not an object"
    if row.get("transitions") is None:
        return "it has no transitions"
    for k in CURVE_KEYS:
        v = row.get(k)
        if v is None:
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            return f"{k} is {short_repr(v)}, not a number"
        try:
            finite = math.isfinite(float(v))
        except OverflowError:
            finite = False
        if not finite:
            return f"{k} is {short_repr(v)}, not a finite number"
    return ""


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
    """A row as strict JSON: NaN and +-inf (a blown-up episode's force) are written as null, which reads back as NaN."""
    clean = {k: (None if isinstance(row[k], float) and not math.isfinite(row[k]) else row[k]) for k in CURVE_KEYS}
    return json.dumps(clean, allow_nan=False) + "\n"
