"""Tables 6.1-6.4, learning curves and aggregate statistics from train/run.py runs or sweeps.

    python train/report.py runs/sweeps/quick --out runs/reports/quick
    python train/report.py runs/train/PegInsert_* runs/sweeps/peg --out runs/reports/peg

Reads every run directory under the given paths that holds a finished run (config.json and
metrics.json) and groups the runs by configuration (task, env, action space, method, and the
run's --label: a labelled run's method is shown as `<method>+<label>`); inside
one configuration the runs must differ in their seed alone (budget, worlds, preset, SAC fields,
geometry, time observation), else the report stops and names them. Writes to --out (a new or
empty directory; nothing is overwritten):

  tables.md, tables.tex  Tables 6.1-6.4 in the thesis's layout: rows task x method, columns
                         Factory 4D / 6D, Forge 4D / 6D; mean +- std over seeds (numpy's std,
                         ddof 0; n seeds shown); the best method per task and column in bold
                         (higher reward and success, lower force and time); "—" where no run of
                         the cell succeeded (time to first success) or the cell has no runs.
                         Beside each cell, the thesis's value and ours minus the thesis's.
  results.csv            one row per metric and cell: ours (n, mean, std), the thesis's, difference
  stats.json, stats.png  rliable (Agarwal et al. 2021): the IQM of the final success rate over
                         the configurations each method ran, with 95 % stratified-bootstrap
                         intervals; the probabilities of improvement P(kgrl > sac) and
                         P(vision_kgrl > kgrl) over their shared configurations, with intervals
  prior_gain.md          KGRL runs against their prior on the same evaluation episodes: success,
                         the prior's, the paired gain with 95 % bootstrap intervals over seeds and
                         over pooled episodes, training success early (5k-10k) and late (last 5k)
  method_pairs.md        each two methods (variants included) of a task, env and D against each
                         other on the same evaluation episodes: B minus A per seed both ran with one
                         eval seed, its mean with a 95 % bootstrap interval over seeds, and pooled

Wherever a gain over seeds is reported (prior_gain.md, method_pairs.md and their rows in stats.json,
key seed_stats: vkgrl_newton/results/seeds.py), beside the percentile bootstrap: the 95 % Student-t
interval over seeds, the exact sign test and the Wilcoxon signed-rank test, and the verdict: "beats"
only where the t-interval lies above 0 ("loses" below), else "not established"; with the seeds the
rule asks of a headline claim (10 where a trial, training and evaluation as they ran, costs <= 30 min,
else 5: trial_minutes, seeds_needed).
  curves_<task>_<env>_<D>d.png  learning curves, methods overlaid, mean +- std over seeds
                         (vkgrl_newton/results/plots.py, as train/plot_runs.py)
  runs/                  a copy of each run read (config.json, metrics.json, curves.jsonl) in
                         runs/<parent>/<run>/: give the report's directory to report.py to read
                         them again, alone or merged with later runs, once the run directories are
                         gone (a run found both as itself and as a copy counts once)

--from-stats: the paths are earlier reports whose runs are gone (no runs/ to read again). Their
stats.json's per-seed values (prior_gain seed_gains, method_pairs seed_differences, and the
difference of two gain rows over the same prior) get the statistics above, in seed_stats.md and
seed_stats.json under --out:

    python train/report.py --from-stats docs/results/kgrl_reach_28c/report --out runs/reports/restat

The metrics are each run's metrics.json: the deterministic evaluation of its final policy
(train/evaluate.py's keys). The thesis's values are Tables 6.1-6.4 of the spec as transcribed
in vkgrl_newton/results/thesis_tables.csv. Time to first success averages the seeds that
succeeded at all.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import json
import math
import os
import shutil
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vkgrl_newton._io import (atomic_write, atomic_write_text, current_umask, one_line, output_path_error,  # noqa: E402
                              read_json_object, short_repr, strict_json)
from vkgrl_newton.agents.sac_config import SACConfig  # noqa: E402
from vkgrl_newton.results.curves import CURVES_FILE, read_curves  # noqa: E402
from vkgrl_newton.results.paired import paired_gain, world_outcomes  # noqa: E402
from vkgrl_newton.results.plots import plot, read_run_config  # noqa: E402
from vkgrl_newton.results.seeds import format_t, format_tests, over_seeds, seeds_needed  # noqa: E402
from vkgrl_newton.results.thesis import METRICS, THESIS_METHOD_NAMES, load_thesis_tables  # noqa: E402
from vkgrl_newton.signals import run_cli  # noqa: E402
from vkgrl_newton.run.methods import RUN_METHODS  # noqa: E402
from vkgrl_newton.tasks import ACTION_DIMS, FAMILIES, TASKS  # noqa: E402

TASK_ORDER = tuple(TASKS)  # PegInsert, GearMesh, NutThread: the thesis's row order
# the thesis's row order, then the other rows of the method table (run/methods.py) in its order
METHOD_ORDER = ("kgrl", "sac", "vision_kgrl", "vision_sac") + tuple(m for m in RUN_METHODS
                                                              if m not in ("kgrl", "sac", "vision_kgrl", "vision_sac"))
COLUMNS = tuple((env, dim) for env in FAMILIES for dim in ACTION_DIMS)  # Factory 4D, 6D, Forge 4D, 6D
TABLE_TITLES = {"mean_episode_reward": "Final mean reward", "success_rate": "Final success rate",
                "mean_contact_force": "Final mean contact force magnitude (N)",
                "time_to_first_success_s": "Time to first success (s)"}
HIGHER_IS_BETTER = {"mean_episode_reward": True, "success_rate": True, "mean_contact_force": False,
                    "time_to_first_success_s": False}
# what may differ between the runs of one configuration: the seed, and what does not change the
# experiment (where it ran, how often it checkpointed, where its files are)
NOT_IDENTITY = ("seed", "device", "checkpoint_every", "prior", "vision")
COMPARISONS = (("kgrl", "sac"), ("vision_kgrl", "kgrl"))
DASH = "—"


class MixedCellError(ValueError):
    """The runs of one configuration differ in more than the seed, or a run's file is damaged (named):
    the report refuses rather than leave a run out unseen."""


# ----------------------------------------------------------------------------- reading runs
def find_runs(paths: list[Path]) -> list[Path]:
    """Finished run directories (config.json and metrics.json) at or under the paths, sorted. A run
    found twice, as itself and as a report's copy of it (the same config.json and metrics.json),
    counts once, as itself."""
    found = set()
    for p in paths:
        p = Path(p)
        if not p.exists():
            raise FileNotFoundError(f"{p} does not exist")
        candidates = [p] if (p / "metrics.json").is_file() else [m.parent for m in p.rglob("metrics.json")]
        found.update(d for d in candidates if (d / "config.json").is_file() and (d / "metrics.json").is_file())
    kept: dict[bytes, Path] = {}
    for d in sorted(found, key=lambda d: (is_archived(d), d)):  # originals first
        kept.setdefault(_read_bytes(d / "config.json") + b"\0" + _read_bytes(d / "metrics.json"), d)
    return sorted(kept.values())


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as e:  # (no permission)
        raise _damaged(path, f"not readable ({type(e).__name__}: {e})") from None


# A report keeps a copy of the runs it read (their config.json, metrics.json and curves) in
# <report>/runs/<parent>/<run>/ (a sweep's trial: <configuration>/seed<k>), so that a committed report can be read again and merged
# with later runs after the run directories themselves are gone: report.py <report> runs/sweeps/more.
ARCHIVE_DIR = "runs"
ARCHIVE_NOTE = "ARCHIVE.md"
ARCHIVED_FILES = ("config.json", "metrics.json", CURVES_FILE)


def is_archived(run_dir: Path) -> bool:
    """Whether the run directory is a report's copy of a run (<report>/runs/<parent>/<run>)."""
    return (Path(run_dir).parent.parent / ARCHIVE_NOTE).exists()


def archive_runs(run_dirs: list[Path], archive: Path) -> None:
    """Copy each run's config.json, metrics.json and curves.jsonl (its tensorboard scalars where it
    predates curves.jsonl) to archive/<parent>/<run>; more of the path where two runs share both names."""
    archive.mkdir()
    atomic_write_text(archive / ARCHIVE_NOTE, (
        "# The runs this report read\n\nCopies of each run's config.json, metrics.json and curves.jsonl, "
        "from:\n\n" + "".join(f"- {d}\n" for d in run_dirs) +
        "\nGive this report's directory to train/report.py to read them again, with later runs beside them.\n"))
    taken = set()
    for d in run_dirs:
        parts = Path(d).resolve().parts
        k = 1  # the parents that name the copy: one, more where two runs share the names
        while (name := "__".join(parts[-1 - k:-1]) + "/" + parts[-1]) in taken:
            k += 1
        taken.add(name)
        copy = archive / name
        copy.mkdir(parents=True)
        for f in ARCHIVED_FILES:
            if (Path(d) / f).exists():
                shutil.copy2(Path(d) / f, copy / f)
        if not (Path(d) / CURVES_FILE).exists() and (Path(d) / "tb").is_dir():
            shutil.copytree(Path(d) / "tb", copy / "tb")


def cell_key(config: dict) -> tuple[str, str, int, str]:
    """(task, env, D, method); a labelled run's method is shown as `<method>+<label>` (run.py --label)."""
    method = config["method"] + (f"+{config['label']}" if config.get("label") else "")
    return config["task"], config["env"], int(config["action_dim"]), method


def identity(config: dict) -> dict:
    """What must agree between the runs of a cell. A SAC field a run's config.json predates counts at
    its default (as run.py's --resume reads such a checkpoint), so older runs and newer ones still
    share a cell when nothing but the field's existence differs."""
    ident = {k: v for k, v in config.items() if k not in NOT_IDENTITY}
    if isinstance(ident.get("sac"), dict):
        defaults = {f.name: f.default for f in dataclasses.fields(SACConfig)
                    if f.default is not dataclasses.MISSING}
        ident["sac"] = {**{k: _plain(v) for k, v in defaults.items() if k not in ident["sac"]}, **ident["sac"]}
    return ident


def _plain(value):
    return list(value) if isinstance(value, tuple) else value  # as JSON holds it


def _damaged(path: Path, reason: str) -> MixedCellError:
    return MixedCellError(one_line(f"{path} is damaged: {reason}; restore it or move its run directory out of "
                                   "the report's paths", 600))


def _read_json(path: Path, what: str = "run's JSON file") -> dict:
    """A run's config.json or metrics.json (or a report's stats.json) as a JSON object (vkgrl_newton._io's
    read_json_object); a damaged one (not UTF-8 JSON, not an object, bare NaN) is a MixedCellError naming
    the file."""
    try:
        return read_json_object(path, what)
    except ValueError as e:
        reason = str(e)
        reason = reason[len(f"{path}: "):] if reason.startswith(f"{path}: ") else reason
        raise _damaged(path, reason) from None


class _Damage(Exception):
    """What is wrong inside one file (the caller names the file)."""


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _number(v, where: str, optional: bool = True):
    """v as a finite float (None stays None where optional); _Damage otherwise."""
    if v is None and optional:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _Damage(f"{where} is {short_repr(v)}, not a number")
    try:
        x = float(v)
    except OverflowError:
        x = math.inf
    if not math.isfinite(x):
        raise _Damage(f"{where} is {short_repr(v)}, not a finite number")
    return x


def _check_config(config: dict) -> None:
    """What cell_key, identity and load_cells index in a run's config.json, with its type."""
    for key in ("task", "method"):
        if not isinstance(config.get(key), str) or not config[key]:
            raise _Damage(f"its {key} is {short_repr(config.get(key))}, not a name" if key in config
                          else f"it has no {key!r}")
    if config.get("env") not in FAMILIES:
        raise _Damage(f"its env is {short_repr(config.get('env'))}, not one of {', '.join(FAMILIES)}" if "env" in config
                      else "it has no 'env'")
    dim = config.get("action_dim")
    if not _is_int(dim) or dim not in ACTION_DIMS:
        raise _Damage(f"its action_dim is {short_repr(dim)}, not one of {', '.join(map(str, ACTION_DIMS))}"
                      if "action_dim" in config else "it has no 'action_dim'")
    if not _is_int(config.get("seed")):
        raise _Damage(f"its seed is {short_repr(config.get('seed'))}, not a whole number" if "seed" in config
                      else "it has no 'seed'")
    if not isinstance(config.get("label"), (str, type(None))):
        raise _Damage(f"its label is {short_repr(config['label'])}, not a name")
    if config.get("num_envs") is not None and not (_is_int(config["num_envs"]) and config["num_envs"] > 0):
        raise _Damage(f"its num_envs is {short_repr(config['num_envs'])}, not a whole number > 0")
    if "sac" in config and not isinstance(config["sac"], dict):
        raise _Damage(f"its sac is {short_repr(config['sac'])}, not an object")


def _outcomes(result: dict, where: str) -> np.ndarray:
    """world_outcomes(result), checked: per_episode a list of objects whose world_success are lists of
    numbers or null, one per world, as many in each."""
    episodes = result.get("per_episode")
    if not isinstance(episodes, list) or not all(isinstance(e, dict) for e in episodes):
        raise _Damage(f"{where}per_episode is {short_repr(episodes)}, not a list of objects")
    widths = set()
    for i, e in enumerate(episodes):
        w = e.get("world_success")
        if not isinstance(w, list):
            raise _Damage(f"{where}per_episode[{i}].world_success is {short_repr(w)}, not a list")
        for j, v in enumerate(w):
            _number(v, f"{where}per_episode[{i}].world_success[{j}]")
        widths.add(len(w))
    if len(widths) > 1:
        raise _Damage(f"{where}per_episode's world_success lists hold {sorted(widths)} worlds, not one count")
    return world_outcomes(result)


def _check_metrics(metrics: dict) -> None:
    """What load_cells reads of a run's metrics.json, with its type."""
    for m in METRICS:
        _number(metrics.get(m), m)
    training = metrics.get("training")
    if training is not None and not isinstance(training, dict):
        raise _Damage(f"its training is {short_repr(training)}, not an object")
    _number((training or {}).get("wall_s"), "training.wall_s")
    _number(metrics.get("wall_s"), "wall_s")
    episodes = metrics.get("per_episode")
    if episodes is not None and not (isinstance(episodes, list) and all(isinstance(e, dict) for e in episodes)):
        raise _Damage(f"its per_episode is {short_repr(episodes)}, not a list of objects")
    if "eval_seed" in metrics and all("world_success" in e for e in episodes or [{}]):
        if not _is_int(metrics["eval_seed"]):
            raise _Damage(f"its eval_seed is {short_repr(metrics['eval_seed'])}, not a whole number")
        _outcomes(metrics, "")
    if "paired_gain" in metrics:
        gain, prior = metrics["paired_gain"], metrics.get("prior_eval")
        if not isinstance(gain, dict) or not isinstance(gain.get("success_rate"), dict) or \
                "mean" not in gain["success_rate"]:
            raise _Damage(f"its paired_gain is {short_repr(gain)}, not an object with success_rate.mean")
        _number(gain["success_rate"]["mean"], "paired_gain.success_rate.mean")
        if not isinstance(prior, dict) or "success_rate" not in prior:
            raise _Damage(f"its prior_eval is {short_repr(prior)}, not an evaluation with success_rate "
                          "(paired_gain needs it)")
        _number(prior["success_rate"], "prior_eval.success_rate")
        policy = _outcomes(metrics, "")
        if _outcomes(prior, "prior_eval.").size != policy.size:
            raise _Damage("its prior_eval and its own evaluation ran different numbers of episodes (not paired)")


def load_run(run_dir: Path) -> tuple[dict, dict]:
    """A finished run's (config, metrics), the one loader of the files the report reads (a run directory or a
    report's copy of one): config.json and metrics.json must be JSON objects holding what the report indexes,
    with its type (a metric: a finite number or null), and curves.jsonl and config.json must be what
    results.plots reads; else a MixedCellError naming the file and what is wrong."""
    run_dir = Path(run_dir)
    files = {name: run_dir / name for name in ("config.json", "metrics.json")}
    config = _read_json(files["config.json"], "run's config.json")
    try:
        _check_config(config)
        read_run_config(run_dir)  # what the curves are grouped and titled by
    except (_Damage, ValueError) as e:
        reason = str(e).split(" is damaged: ", 1)[-1]
        raise _damaged(files["config.json"], reason) from None
    metrics = _read_json(files["metrics.json"], "run's metrics.json")
    try:
        _check_metrics(metrics)
    except _Damage as e:
        raise _damaged(files["metrics.json"], str(e)) from None
    try:
        read_curves(run_dir)  # read again for prior_gain.md and the curves: checked before anything is written
    except ValueError as e:
        raise MixedCellError(one_line(f"{e}; restore it or move its run directory out of the report's paths",
                                      600)) from None
    return config, metrics


def load_cells(run_dirs: list[Path]) -> dict[tuple, list[dict]]:
    """{(task, env, D, method): [{"run_dir", "seed", metric: value}]}; MixedCellError on a mixed cell."""
    cells: dict[tuple, list[dict]] = defaultdict(list)
    identities: dict[tuple, tuple[Path, dict]] = {}
    for d in run_dirs:
        config, metrics = load_run(d)
        key = cell_key(config)
        ident = identity(config)
        if key in identities:
            first_dir, first = identities[key]
            diff = sorted(k for k in set(first) | set(ident) if first.get(k) != ident.get(k))
            if diff:
                raise MixedCellError(
                    f"configuration {'/'.join(map(str, key))}: {first_dir} and {d} differ in "
                    f"{', '.join(f'{k} ({first.get(k)!r} vs {ident.get(k)!r})' for k in diff)}; "
                    "one cell holds runs that differ in their seed alone")
        else:
            identities[key] = (d, ident)
        twin = next((r["run_dir"] for r in cells[key] if r["seed"] == config["seed"]), None)
        if twin is not None:
            raise MixedCellError(f"configuration {'/'.join(map(str, key))}: two runs of seed {config['seed']} "
                                 f"({twin} and {d}); keep one, or give them different --label")
        row = {"run_dir": str(d), "seed": config["seed"], "total_steps": config.get("total_steps"),
               "trial_s": _trial_seconds(metrics)}
        for m in METRICS:
            v = metrics.get(m)
            row[m] = math.nan if v is None else float(v)
        if "eval_seed" in metrics and all("world_success" in e for e in metrics.get("per_episode") or [{}]):
            # its final evaluation's episodes, for pairing with other methods (runs from before per-world
            # outcomes and evaluation seeds were recorded have none to pair)
            row["outcomes"] = world_outcomes(metrics)
            # and the processor that played them: an Intel and an AMD CPU seat different episodes of one eval seed
            # (docs/results/intel_prior_40); a run from before the field pairs only with another such run
            row["episodes_key"] = (metrics["eval_seed"], config.get("num_envs"), len(metrics["per_episode"]),
                                   row["outcomes"].size, metrics.get("processor"))
        if "paired_gain" in metrics:  # a KGRL run's paired evaluation against its prior (run.py)
            row["paired"] = {"gain": metrics["paired_gain"]["success_rate"],
                             "prior_success": metrics["prior_eval"]["success_rate"],
                             "policy": world_outcomes(metrics), "prior": world_outcomes(metrics["prior_eval"])}
        cells[key].append(row)
    return dict(cells)


def _trial_seconds(metrics: dict) -> float:
    """A trial's wall time as it ran: training plus the final evaluation (NaN where not recorded)."""
    training = (metrics.get("training") or {}).get("wall_s")
    if training is None or metrics.get("wall_s") is None:
        return math.nan
    return float(training) + float(metrics["wall_s"])


# ----------------------------------------------------------------------------- statistics
def trial_minutes(*cells: list[dict]) -> float | None:
    """The median trial wall time, in minutes, of the costlier of the given cells' runs (None if unrecorded):
    what decides how many seeds a claim over them needs (results.seeds.seeds_needed)."""
    medians = [np.nanmedian(t) for t in ([r["trial_s"] for r in rows] for rows in cells)
               if t and not np.all(np.isnan(t))]
    return round(float(max(medians)) / 60.0, 1) if medians else None


def seed_rule(minutes: float | None) -> dict:
    return {"trial_minutes": minutes, "seeds_needed": seeds_needed(minutes)}


def cell_stats(rows: list[dict], metric: str) -> tuple[int, float, float]:
    """(n, mean, std) over the seeds; time to first success over the seeds that succeeded."""
    values = np.array([r[metric] for r in rows], dtype=np.float64)
    values = values[~np.isnan(values)]
    if len(values) == 0:
        return 0, math.nan, math.nan
    return len(values), float(values.mean()), float(values.std())


def best_methods(cells: dict, metric: str) -> set[tuple]:
    """The cells holding the best mean of their task and column (ties all bold)."""
    best = set()
    for task in {k[0] for k in cells}:
        for env, dim in COLUMNS:
            means = {k: cell_stats(cells[k], metric)[1] for k in cells if k[:3] == (task, env, dim)}
            means = {k: v for k, v in means.items() if not math.isnan(v)}
            if not means:
                continue
            target = (max if HIGHER_IS_BETTER[metric] else min)(means.values())
            best.update(k for k, v in means.items() if v == target)
    return best


def fmt(mean: float, std: float, digits: int) -> str:
    return DASH if math.isnan(mean) else f"{mean:.{digits}f} ± {std:.{digits}f}"


DIGITS = {"mean_episode_reward": 2, "success_rate": 3, "mean_contact_force": 3, "time_to_first_success_s": 3}


def result_rows(cells: dict, thesis: dict) -> list[dict]:
    rows = []
    for metric in METRICS:
        for key in sorted(cells, key=_order):
            n, mean, std = cell_stats(cells[key], metric)
            t_mean, t_std = thesis.get((metric, key[0], key[3], key[1], key[2]), (math.nan, math.nan))
            rows.append({"table": METRICS[metric], "metric": metric, "task": key[0], "method": key[3],
                         "env": key[1], "action_dim": key[2], "runs": len(cells[key]), "n": n, "mean": mean,
                         "std": std, "thesis_mean": t_mean, "thesis_std": t_std, "difference": mean - t_mean})
    return rows


def _order(key: tuple) -> tuple:
    task, env, dim, method = key
    t = TASK_ORDER.index(task) if task in TASK_ORDER else len(TASK_ORDER)
    m = METHOD_ORDER.index(method) if method in METHOD_ORDER else len(METHOD_ORDER)
    return t, task, m, method, COLUMNS.index((env, dim))


# ----------------------------------------------------------------------------- tables
def markdown_tables(cells: dict, thesis: dict) -> str:
    out = []
    for metric, table in METRICS.items():
        best = best_methods(cells, metric)
        d = DIGITS[metric]
        out += [f"## Table {table}: {TABLE_TITLES[metric]}", "",
                "Ours: mean ± std over n seeds (**bold**: the best method of the task in that column); "
                "in brackets the thesis's value (10 seeds) and ours minus the thesis's.", "",
                "| Task | Method | Factory 4D | Factory 6D | Forge 4D | Forge 6D |", "|---|---|---|---|---|---|"]
        for task, method in _rows(cells):
            line = [task, method]
            for env, dim in COLUMNS:
                key = (task, env, dim, method)
                if key not in cells:
                    line.append("")
                    continue
                n, mean, std = cell_stats(cells[key], metric)
                text = fmt(mean, std, d)
                text = f"**{text}**" if key in best else text
                text += f" (n={len(cells[key])})"
                t_mean, t_std = thesis.get((metric, task, method, env, dim), (math.nan, math.nan))
                diff = DASH if math.isnan(mean) or math.isnan(t_mean) else f"{mean - t_mean:+.{d}f}"
                line.append(f"{text} [{fmt(t_mean, t_std, d)}; {diff}]")
            out.append("| " + " | ".join(line) + " |")
        out.append("")
    return "\n".join(out)


def latex_tables(cells: dict, thesis: dict) -> str:
    out = ["% Tables 6.1-6.4 (train/report.py): ours, mean \\pm std over seeds; the thesis's value below each cell"]
    for metric, table in METRICS.items():
        best = best_methods(cells, metric)
        d = DIGITS[metric]
        out += ["\\begin{table}[t]", "\\centering", f"\\caption{{{TABLE_TITLES[metric]} (mean $\\pm$ std over "
                f"seeds; thesis Table {table} in parentheses). Best per task and column in bold.}}",
                "\\begin{tabular}{llcccc}", "\\toprule",
                "Task & Method & \\multicolumn{2}{c}{Factory} & \\multicolumn{2}{c}{Forge} \\\\",
                " & & 4D & 6D & 4D & 6D \\\\", "\\midrule"]
        for task, method in _rows(cells):
            ours, theirs = [], []
            for env, dim in COLUMNS:
                key = (task, env, dim, method)
                n, mean, std = cell_stats(cells[key], metric) if key in cells else (0, math.nan, math.nan)
                text = "---" if math.isnan(mean) else f"{mean:.{d}f} $\\pm$ {std:.{d}f}"
                ours.append(f"\\textbf{{{text}}}" if key in best else text)
                t_mean, t_std = thesis.get((metric, task, method, env, dim), (math.nan, math.nan))
                theirs.append("(---)" if math.isnan(t_mean) else f"({t_mean:.{d}f} $\\pm$ {t_std:.{d}f})")
            name = THESIS_METHOD_NAMES.get(method, method)
            out.append(f"{task} & {name} & " + " & ".join(ours) + " \\\\")
            out.append(" & & " + " & ".join(theirs) + " \\\\")
        out += ["\\bottomrule", "\\end{tabular}", "\\end{table}", ""]
    return "\n".join(out)


def _rows(cells: dict) -> list[tuple[str, str]]:
    pairs = {(k[0], k[3]) for k in cells}
    return sorted(pairs, key=lambda tm: _order((tm[0], "factory", 4, tm[1]))[:4])


# ----------------------------------------------------------------------------- the prior
def prior_gain_rows(cells: dict, reps: int) -> list[dict]:
    """Per KGRL configuration: the final policy against its prior on the same evaluation episodes.

    gain_over_seeds: the mean of the seeds' paired gains with a percentile-bootstrap interval over
    seeds (the seed is the unit of replication); gain_pooled: all seeds' paired episodes pooled.
    training_early / training_late: the mean over seeds of the training-episode success rate over
    transitions (5k, 10k] and over the run's last 5k (curves.jsonl): a falling curve has late < early.
    """
    rows = []
    for key in sorted(cells, key=_order):
        runs = [r for r in cells[key] if "paired" in r]
        if not runs:
            continue
        gains = np.array([math.nan if r["paired"]["gain"]["mean"] is None else r["paired"]["gain"]["mean"]
                          for r in runs], dtype=np.float64)
        early, late = [], []
        for r in runs:
            curve = read_curves(Path(r["run_dir"]))
            if not curve:
                continue
            end = curve[-1]["transitions"]
            early.append(np.nanmean([c["success_rate"] for c in curve if 5000 < c["transitions"] <= 10000] or [np.nan]))
            late.append(np.nanmean([c["success_rate"] for c in curve if c["transitions"] > end - 5000] or [np.nan]))
        rows.append({
            "task": key[0], "env": key[1], "action_dim": key[2], "method": key[3], "seeds": len(runs),
            "seed_ids": [r["seed"] for r in runs],
            "success": float(np.mean([r["success_rate"] for r in runs])),
            "prior_success": float(np.nanmean([math.nan if r["paired"]["prior_success"] is None
                                               else r["paired"]["prior_success"] for r in runs])),
            "seed_gains": gains.tolist(),
            # one seed has no spread to resample: its interval is left out (None), not a point
            "gain_over_seeds": {**paired_gain(gains, np.zeros_like(gains), reps=reps, seed=0),
                                **({"ci_low": None, "ci_high": None} if len(runs) < 2 else {})},
            "gain_pooled": paired_gain(np.concatenate([r["paired"]["policy"] for r in runs]),
                                       np.concatenate([r["paired"]["prior"] for r in runs]), reps=reps, seed=0),
            "training_early": float(np.nanmean(early)) if early else None,
            "training_late": float(np.nanmean(late)) if late else None,
            # the bootstrap above is too narrow over few seeds: a t-interval, sign and Wilcoxon tests beside it
            "seed_stats": over_seeds(gains, reps=reps, seed=0),
            **seed_rule(trial_minutes(runs)),
        })
    return rows


def ci(g: dict) -> str:
    """A paired difference as '+0.123 [+0.050, +0.190]' (its mean and interval)."""
    if g["mean"] is None:
        return DASH
    if g["ci_low"] is None:
        return f"{g['mean']:+.3f} [one seed: no interval]"
    return f"{g['mean']:+.3f} [{g['ci_low']:+.3f}, {g['ci_high']:+.3f}]"


def verdict(s: dict) -> str:
    """The over-seeds verdict of results.seeds.over_seeds (the t-interval's bounds against 0), bold when it
    claims something."""
    return f"**{s['verdict']}**" if s["verdict"] in ("beats", "loses") else s["verdict"]


def seeds_rule_cell(seeds: int, row: dict) -> str:
    """'10 (17 min): 7 short', from the rule of results.seeds.seeds_needed; '?' where trial times are unrecorded."""
    needed, minutes = row.get("seeds_needed"), row.get("trial_minutes")
    if needed is None:
        return "? (trial time not recorded)"
    return f"{needed} ({minutes:.0f} min): " + (f"{needed - seeds} short" if seeds < needed else "met")


SEED_STATS_NOTE = (
    "Over seeds, beside the percentile bootstrap (too narrow with few seeds: it never reaches past the seeds' "
    "own range): the 95 % Student-t interval of the mean, mean ± t(0.975, n-1) sd / sqrt(n); the exact two-sided "
    "sign test (positive against negative seeds, zeros dropped) and the Wilcoxon signed-rank test (exact "
    "enumeration). Verdict: **beats** only where the t-interval lies above 0, **loses** where below, else not "
    "established (one seed or seeds all equal: no t-interval). Seeds needed: 10 where a trial (training and "
    "final evaluation, wall time as it ran) costs <= 30 min, else 5 (issue 40's rule for a headline claim).")


def prior_gain_markdown(rows: list[dict]) -> str:
    def num(v):
        return DASH if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.3f}"

    out = ["# The final policy against its KMP prior (train/report.py)", "",
           "Each KGRL run evaluates its final policy and its prior (a = 0) on the same episodes (run.py "
           "--eval-seed). Gain: policy minus prior success, per seed; mean over seeds with a 95 % percentile "
           "bootstrap interval over seeds, and over all seeds' episodes pooled. Training success: the mean over "
           "seeds of the training episodes' success over transitions (5k, 10k] and over the last 5k.", "",
           SEED_STATS_NOTE, "",
           "| Task | Env | D | Method | Seeds | Success | Prior (same episodes) | Gain over seeds [95 % bootstrap] | "
           "t-interval [95 %] | Sign test, Wilcoxon | Verdict | "
           "Gain, episodes pooled [95 % CI] | Training success 5k-10k | last 5k | Seeds needed |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        s = r["seed_stats"]
        out.append(f"| {r['task']} | {r['env']} | {r['action_dim']} | {r['method']} | {r['seeds']} | "
                   f"{num(r['success'])} | {num(r['prior_success'])} | {ci(r['gain_over_seeds'])} | "
                   f"{format_t(s)} | {format_tests(s)} | {verdict(s)} | "
                   f"{ci(r['gain_pooled'])} ({r['gain_pooled']['n_pairs']}) | {num(r['training_early'])} | "
                   f"{num(r['training_late'])} | {seeds_rule_cell(r['seeds'], r)} |")
    return "\n".join(out) + "\n"


# ----------------------------------------------------------------------------- methods against each other
def method_pair_rows(cells: dict, reps: int) -> list[dict]:
    """Per task, env and D, each two methods (variants included) on the same evaluation episodes: B minus A
    in success, per seed run by both on the same episodes (one evaluation seed, world count and round
    count, played on one kind of processor; each seed's difference over the episodes both counted), their
    mean with a percentile-bootstrap interval over seeds, and all those seeds' episodes pooled. A before B
    in the report's method order.
    Runs that recorded no per-world outcomes or evaluation seed (older runs) are not paired."""
    rows = []
    groups: dict[tuple, list[tuple]] = defaultdict(list)
    for key in sorted(cells, key=_order):
        groups[key[:3]].append(key)
    for (task, env, dim), keys in groups.items():
        for i, key_a in enumerate(keys):
            for key_b in keys[i + 1:]:
                by_seed_a = {r["seed"]: r for r in cells[key_a] if "outcomes" in r}
                # the same episodes: one evaluation seed, worlds and rounds, played on one kind of processor
                pairs = [(by_seed_a[r["seed"]], r) for r in cells[key_b] if "outcomes" in r and r["seed"] in by_seed_a
                         and r["episodes_key"] == by_seed_a[r["seed"]]["episodes_key"]]
                # per seed over the episodes both counted (a blown-up world's is NaN), as the pooled figure;
                # paired_gain(b, a): its a_mean is B's success, its b_mean A's
                kept = [((a, b), paired_gain(b["outcomes"], a["outcomes"], reps=1))
                        for a, b in sorted(pairs, key=lambda ab: ab[0]["seed"])]
                kept = [(ab, g) for ab, g in kept if g["mean"] is not None]
                if not kept:
                    continue
                pairs, per_seed = [ab for ab, _ in kept], [g for _, g in kept]
                diffs = np.array([g["mean"] for g in per_seed], dtype=np.float64)
                rows.append({
                    "task": task, "env": env, "action_dim": dim, "a": key_a[3], "b": key_b[3],
                    "seeds": [a["seed"] for a, _ in pairs], "seed_differences": diffs.tolist(),
                    "a_success": float(np.mean([g["b_mean"] for g in per_seed], dtype=np.float64)),
                    "b_success": float(np.mean([g["a_mean"] for g in per_seed], dtype=np.float64)),
                    "over_seeds": {**_without_means(paired_gain(diffs, np.zeros_like(diffs), reps=reps, seed=0)),
                                   **({"ci_low": None, "ci_high": None} if len(pairs) < 2 else {})},
                    "pooled": _a_and_b(paired_gain(np.concatenate([b["outcomes"] for _, b in pairs]),
                                                   np.concatenate([a["outcomes"] for a, _ in pairs]),
                                                   reps=reps, seed=0)),
                    "seed_stats": over_seeds(diffs, reps=reps, seed=0),
                    **seed_rule(trial_minutes(cells[key_a], cells[key_b])),
                })
    return rows


def _without_means(gain: dict) -> dict:
    """An interval over per-seed differences: its a_mean and b_mean (the differences' mean and 0) say nothing."""
    return {k: v for k, v in gain.items() if k not in ("a_mean", "b_mean")}


def _a_and_b(gain: dict) -> dict:
    """paired_gain(B, A) with a_mean and b_mean named as the pair's A and B (A's success is its b_mean)."""
    return {**gain, "a_mean": gain["b_mean"], "b_mean": gain["a_mean"]}


def method_pairs_markdown(rows: list[dict]) -> str:
    out = ["# Methods against each other on the same episodes (train/report.py)", "",
           "B minus A in final success, over the seeds both ran with one evaluation seed (run.py --eval-seed): "
           "the mean of the seeds' differences with a 95 % percentile-bootstrap interval over seeds, and over all "
           "those seeds' episodes pooled. Verdict: whether B beats A.", "",
           SEED_STATS_NOTE, "",
           "| Task | Env | D | A | B | Seeds | A success | B success | B - A over seeds [95 % bootstrap] | "
           "t-interval [95 %] | Sign test, Wilcoxon | Verdict (B against A) | "
           "B - A, episodes pooled [95 % CI] | Per seed | Seeds needed |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        per_seed = ", ".join(f"{d:+.3f}" for d in r["seed_differences"])
        s = r["seed_stats"]
        out.append(f"| {r['task']} | {r['env']} | {r['action_dim']} | {r['a']} | {r['b']} | {len(r['seeds'])} | "
                   f"{r['a_success']:.3f} | {r['b_success']:.3f} | {ci(r['over_seeds'])} | "
                   f"{format_t(s)} | {format_tests(s)} | {verdict(s)} | "
                   f"{ci(r['pooled'])} ({r['pooled']['n_pairs']}) | {per_seed} | "
                   f"{seeds_rule_cell(len(r['seeds']), r)} |")
    return "\n".join(out) + "\n"


# ----------------------------------------------------------------------------- rliable
def aggregate_stats(cells: dict, reps: int = 2000, seed: int = 0) -> dict:
    """IQM of success per method over its configurations, and probabilities of improvement, with
    95 % stratified-bootstrap intervals (rliable). Each score matrix is (seeds, configurations);
    where configurations have different seed counts, the smallest count is used (lowest seeds)."""
    import warnings

    from rliable import library as rly
    from rliable import metrics as rly_metrics

    warnings.filterwarnings("ignore", message="random_state is deprecated", category=FutureWarning)  # arch, via rliable

    def matrix(method: str, configs: list[tuple]) -> np.ndarray:
        per = [sorted(cells[c + (method,)], key=lambda r: r["seed"]) for c in configs]
        n = min(len(p) for p in per)
        return np.array([[p[i]["success_rate"] for p in per] for i in range(n)], dtype=np.float64)

    methods = sorted({k[3] for k in cells}, key=lambda m: METHOD_ORDER.index(m) if m in METHOD_ORDER else 99)
    configs_of = {m: sorted(k[:3] for k in cells if k[3] == m) for m in methods}
    out: dict = {"metric": "success_rate", "reps": reps, "iqm": {}, "probability_of_improvement": {}}
    rng = np.random.RandomState(seed)
    scores = {m: matrix(m, configs_of[m]) for m in methods}
    point, interval = rly.get_interval_estimates(
        scores, lambda x: np.array([rly_metrics.aggregate_iqm(x)]), reps=reps, random_state=rng)
    for m in methods:
        out["iqm"][m] = {"value": float(point[m][0]), "ci95": [float(interval[m][0, 0]), float(interval[m][1, 0])],
                         "configurations": len(configs_of[m]), "seeds_per_configuration": scores[m].shape[0]}
    for a, b in COMPARISONS:
        shared = sorted(set(configs_of.get(a, [])) & set(configs_of.get(b, [])))
        if not shared:
            continue
        xa, xb = matrix(a, shared), matrix(b, shared)
        n = min(len(xa), len(xb))
        pairs = {f"{a}>{b}": (xa[:n], xb[:n])}
        p_point, p_interval = rly.get_interval_estimates(
            pairs, rly_metrics.probability_of_improvement, reps=reps, random_state=rng)
        name = f"{a}>{b}"
        out["probability_of_improvement"][name] = {
            "value": float(np.squeeze(p_point[name])), "ci95": [float(v) for v in np.ravel(p_interval[name])],
            "configurations": len(shared), "seeds_per_configuration": n}
    return out


def stats_figure(stats: dict) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.2))
    for ax, (name, block, xlabel) in zip(axes, (("IQM of final success", stats["iqm"], "IQM success rate"), (
            "P(X > Y)", stats["probability_of_improvement"], "probability of improvement"))):
        labels = list(block)
        for i, label in enumerate(labels):
            v, (lo, hi) = block[label]["value"], block[label]["ci95"]
            ax.errorbar([v], [i], xerr=[[v - lo], [hi - v]], fmt="o", capsize=4)
        ax.set_yticks(range(len(labels)), labels)
        ax.set_xlim(0, 1)
        ax.set_xlabel(xlabel + " (95 % stratified bootstrap)")
        ax.set_title(name)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120)
    plt.close(fig)
    return buf.getvalue()


# ----------------------------------------------------------------------------- older reports (--from-stats)
def _base_order(method: str) -> tuple:
    base = method.split("+")[0]
    return (METHOD_ORDER.index(base) if base in METHOD_ORDER else len(METHOD_ORDER)), method


STATS_ROW_KINDS = {"prior_gain": {"task": str, "env": str, "action_dim": int, "method": str},
                   "method_pairs": {"task": str, "env": str, "action_dim": int, "a": str, "b": str}}
STATS_ROW_VALUES = {"prior_gain": ("seed_gains", "seed_ids"), "method_pairs": ("seed_differences", "seeds")}


def read_stats(path: Path) -> dict:
    """An earlier report's stats.json, as --from-stats reads it: its prior_gain and method_pairs rows (where
    present) lists of objects with their names, D, per-seed values (numbers, null read as NaN) and seed ids
    (whole numbers, as many as the values, or absent); else a MixedCellError naming the file."""
    try:
        stats = read_json_object(path, "report's stats.json")
    except ValueError as e:
        raise MixedCellError(one_line(f"{e}; give the directory of a report written by train/report.py", 600)) from None
    try:
        for block, kinds in STATS_ROW_KINDS.items():
            rows = stats.get(block, [])
            if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
                raise _Damage(f"its {block} is {short_repr(rows)}, not a list of objects")
            values_key, seeds_key = STATS_ROW_VALUES[block]
            for i, r in enumerate(rows):
                where = f"{block}[{i}]"
                for key, kind in kinds.items():
                    if not isinstance(r.get(key), kind) or isinstance(r.get(key), bool):
                        raise _Damage(f"{where}.{key} is {short_repr(r.get(key))}" if key in r
                                      else f"{where} has no {key!r}")
                values = r.get(values_key)
                if not isinstance(values, list):
                    raise _Damage(f"{where}.{values_key} is {short_repr(values)}, not a list")
                r[values_key] = [math.nan if v is None else _number(v, f"{where}.{values_key}[{j}]")
                                 for j, v in enumerate(values)]
                seeds = r.get(seeds_key)
                if seeds is not None and not (isinstance(seeds, list) and len(seeds) == len(values)
                                              and all(_is_int(k) for k in seeds)):
                    raise _Damage(f"{where}.{seeds_key} is {short_repr(seeds)}, not {len(values)} whole numbers")
                if block == "prior_gain":
                    _number(r.get("prior_success"), f"{where}.prior_success")
    except _Damage as e:
        raise MixedCellError(one_line(f"{path} is damaged: {e}; give the directory of a report written by "
                                      "train/report.py", 600)) from None
    return stats


def restat_rows(reports: list[Path], reps: int) -> list[dict]:
    """The over-seeds statistics of the per-seed values that earlier reports' stats.json hold, for reports
    whose runs are gone (no runs/ copies to read again): each prior_gain row's seed_gains, each
    method_pairs row's seed_differences, and B minus A for each two prior_gain rows of one task, env and D
    with the same prior success (one eval seed, a deterministic prior: the prior's outcome is the same
    episode by episode, so gain_B - gain_A per seed is B's success minus A's). Rows are paired by seed id,
    or where a report predates seed ids, in run order when both have as many seeds ("run order" in the row).
    A row found in several reports (same values) counts once, with all its reports named."""
    entries: list[dict] = []

    def add(entry: dict) -> None:
        same = next((e for e in entries if all(e[k] == entry[k] for k in
                                               ("kind", "task", "env", "action_dim", "name", "values", "prior"))), None)
        if same is None:
            entries.append(entry)
        elif entry["reports"][0] not in same["reports"]:
            same["reports"].append(entry["reports"][0])

    for report in reports:
        path = Path(report) / "stats.json" if Path(report).is_dir() else Path(report)
        if not path.exists():
            raise FileNotFoundError(f"{path} does not exist (--from-stats reads reports' stats.json)")
        stats = read_stats(path)
        name = str(path.parent)
        for r in stats.get("prior_gain", []):
            add({"kind": "gain over the prior", "task": r["task"], "env": r["env"], "action_dim": r["action_dim"],
                 "name": r["method"], "method": r["method"], "values": r["seed_gains"], "seeds": r.get("seed_ids"),
                 "prior": r.get("prior_success"), "reports": [name]})
        for r in stats.get("method_pairs", []):
            add({"kind": "B - A", "task": r["task"], "env": r["env"], "action_dim": r["action_dim"],
                 "name": f"{r['b']} - {r['a']}", "values": r["seed_differences"], "seeds": r.get("seeds"),
                 "prior": None, "reports": [name]})
    gains = sorted((e for e in entries if e["kind"] == "gain over the prior"),
                   key=lambda e: (e["task"], e["env"], e["action_dim"], _base_order(e["method"])))
    for i, a in enumerate(gains):
        for b in gains[i + 1:]:
            if (a["task"], a["env"], a["action_dim"]) != (b["task"], b["env"], b["action_dim"]) or \
                    a["prior"] is None or a["prior"] != b["prior"] or a["method"] == b["method"]:
                continue
            if a["seeds"] is not None and b["seeds"] is not None:
                shared = sorted(set(a["seeds"]) & set(b["seeds"]))
                va, vb = dict(zip(a["seeds"], a["values"])), dict(zip(b["seeds"], b["values"]))
                values, seeds, how = [vb[k] - va[k] for k in shared], shared, "seed id"
            elif len(a["values"]) == len(b["values"]):
                values, seeds, how = [y - x for x, y in zip(a["values"], b["values"])], None, "run order"
            else:
                continue
            name = f"{b['method']} - {a['method']}"
            if any(e["kind"] == "B - A" and e["name"] == name and (e["task"], e["env"], e["action_dim"]) ==
                   (a["task"], a["env"], a["action_dim"]) for e in entries):
                continue  # a report paired them itself, episode by episode
            if values:
                entries.append({"kind": "B - A (gains' difference)", "task": a["task"], "env": a["env"],
                                "action_dim": a["action_dim"], "name": name,
                                "values": values, "seeds": seeds, "prior": a["prior"], "paired_by": how,
                                "reports": sorted(set(a["reports"]) | set(b["reports"]))})
    for e in entries:
        e["seed_stats"] = over_seeds(e["values"], reps=reps, seed=0)
    return entries


def restat_markdown(rows: list[dict], reports: list[Path]) -> str:
    out = ["# Over-seeds statistics of earlier reports (train/report.py --from-stats)", "",
           "Read from the per-seed values in the stats.json of: " + ", ".join(str(r) for r in reports) +
           " (their runs are gone; nothing was rerun). Gain over the prior: policy minus prior success per seed "
           "on the same episodes. B - A: a report's method pair, or two gain rows' difference per seed "
           "(the prior's outcome is the same in both; paired by seed id, or in run order where the report predates "
           "seed ids). Trial times are not in stats.json: the seeds a claim needs are not judged here.", "",
           SEED_STATS_NOTE.split(" Seeds needed:")[0], "",
           "| Task | Env | D | Comparison | Seeds | Per seed | Mean | Bootstrap over seeds [95 %] | t-interval [95 %] | "
           "Sign test, Wilcoxon | Verdict | Reports |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        s = r["seed_stats"]
        per_seed = ", ".join(f"{v:+.3f}" for v in r["values"])
        boot = DASH if s["ci_low"] is None else f"[{s['ci_low']:+.3f}, {s['ci_high']:+.3f}]"
        mean = DASH if s["mean"] is None else f"{s['mean']:+.3f}"
        what = {"gain over the prior": f"{r['name']} over its prior ({r['prior']:.3f})" if r["prior"] is not None
                else f"{r['name']} over its prior"}.get(r["kind"], f"{r['name']}" + (
                    f" (gains' difference, by {r['paired_by']})" if "paired_by" in r else ""))
        out.append(f"| {r['task']} | {r['env']} | {r['action_dim']} | {what} | {s['n_seeds']} | {per_seed} | {mean} | "
                   f"{boot} | {format_t(s)} | {format_tests(s)} | {verdict(s)} | {', '.join(r['reports'])} |")
    return "\n".join(out) + "\n"


def write_restat(reports: list[Path], out: Path, reps: int = 2000) -> dict:
    """seed_stats.md and seed_stats.json in `out` (new or empty, all or nothing) from earlier reports' stats.json."""
    rows = restat_rows(reports, reps)
    if not rows:
        raise FileNotFoundError(f"no prior_gain or method_pairs rows in {', '.join(map(str, reports))}")

    def write(staging: Path) -> dict:
        atomic_write_text(staging / "seed_stats.md", restat_markdown(rows, reports))
        atomic_write_text(staging / "seed_stats.json", strict_json({"reps": reps, "rows": rows}, indent=2))
        return {"rows": len(rows)}

    return _staged(out, write)


# ----------------------------------------------------------------------------- main
def write_report(paths: list[Path], out: Path, reps: int = 2000) -> dict:
    """The report of the runs under `paths` in the directory `out` (new or empty), all or nothing:
    it is written into a hidden staging directory beside `out`, renamed into place only when every
    file is done, and removed if anything fails (`out` is then as it was)."""
    run_dirs = find_runs(paths)
    if not run_dirs:
        raise FileNotFoundError(f"no finished runs (config.json and metrics.json) under {', '.join(map(str, paths))}")
    cells = load_cells(run_dirs)
    thesis = load_thesis_tables()
    return _staged(out, lambda staging: _write_report_files(run_dirs, cells, thesis, staging, reps))


def _staged(out: Path, write) -> dict:
    """write(staging) into a hidden directory beside `out`, renamed to `out` when done, removed on failure."""
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    try:
        summary = write(staging)
        if out.exists():
            out.rmdir()  # empty (checked by main): only an empty directory is replaced
        os.chmod(staging, 0o777 & ~current_umask())  # mkdtemp's 0700 -> what mkdir would have made
        staging.rename(out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return summary


def _write_report_files(run_dirs, cells, thesis, out: Path, reps: int) -> dict:
    atomic_write_text(out / "tables.md", "# Results (train/report.py)\n\n" + markdown_tables(cells, thesis))
    atomic_write_text(out / "tables.tex", latex_tables(cells, thesis))
    rows = result_rows(cells, thesis)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]))
    w.writeheader()
    w.writerows(rows)
    atomic_write_text(out / "results.csv", buf.getvalue())
    stats = aggregate_stats(cells, reps=reps)
    gains = prior_gain_rows(cells, reps=reps)
    if gains:
        stats["prior_gain"] = gains
        atomic_write_text(out / "prior_gain.md", prior_gain_markdown(gains))
    pairs = method_pair_rows(cells, reps=reps)
    if pairs:
        stats["method_pairs"] = pairs
        atomic_write_text(out / "method_pairs.md", method_pairs_markdown(pairs))
    atomic_write_text(out / "stats.json", strict_json(stats, indent=2))
    figure = stats_figure(stats)
    atomic_write(out / "stats.png", overwrite=False, write=lambda f: f.write(figure), suffix=".png")
    by_panel: dict[tuple, list[Path]] = defaultdict(list)
    for key, members in cells.items():
        by_panel[key[:3]].extend(Path(r["run_dir"]) for r in members)
    curves = {}
    for (task, env, dim), dirs in sorted(by_panel.items()):
        name = f"curves_{task}_{env}_{dim}d.png"
        curves[name] = plot(dirs, out / name, title=f"{task} {env} {dim}D")
    archive_runs(run_dirs, out / ARCHIVE_DIR)
    return {"runs": len(run_dirs), "configurations": len(cells), "stats": stats, "curves": sorted(curves)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("paths", type=Path, nargs="+", help="run directories or sweep directories")
    ap.add_argument("--out", type=Path, required=True, help="the report's directory (new or empty)")
    ap.add_argument("--reps", type=int, default=2000, help="bootstrap resamples (rliable)")
    ap.add_argument("--from-stats", action="store_true",
                    help="the paths are earlier reports whose runs are gone: read the per-seed values in their "
                         "stats.json and write seed_stats.md and seed_stats.json (t-interval, sign and Wilcoxon "
                         "tests, verdict) to --out")
    args = ap.parse_args(argv)
    if args.reps < 1:
        ap.error(f"--reps {args.reps}: must be >= 1 (bootstrap resamples)")
    if args.out.exists() and not args.out.is_dir():
        ap.error(f"--out {args.out} is a file; give a new or empty directory")
    if args.out.exists() and any(args.out.iterdir()):
        ap.error(f"--out {args.out} is not empty; choose another directory (reports are never overwritten)")
    if why := output_path_error(args.out, "--out", may_exist=True):  # (checked before the runs are read)
        ap.error(why)
    if args.from_stats:
        try:
            summary = write_restat(args.paths, args.out, reps=args.reps)
        except (FileNotFoundError, MixedCellError, KeyError) as e:
            ap.error(f"--from-stats: {e}")
        print(f"train/report.py --from-stats: {summary['rows']} rows -> {args.out}")
        return 0
    try:
        summary = write_report(args.paths, args.out, reps=args.reps)
    except (FileNotFoundError, MixedCellError) as e:
        ap.error(str(e))
    print(strict_json({k: v for k, v in summary["stats"].items() if k != "prior_gain"}, indent=2))
    print(f"train/report.py: {summary['runs']} runs, {summary['configurations']} configurations -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main, "train/report.py", "nothing was written (--out is as it was)"))
