"""Run a grid of train/run.py trials on Ray: a local Ray by default, a cluster with --address.

    python train/sweep.py --out runs/sweeps/quick --grid quick        # 57 min on 2 cores with kgrl base; longer now
    python train/sweep.py --out runs/sweeps/peg --tasks PegInsert --envs factory --action-dims 4 6 \\
        --methods sac kgrl --seeds 0 1 2 -- --total-steps 30000 --num-envs 16
    python train/sweep.py --out runs/sweeps/thesis --grid thesis --address auto --gpus-per-trial 0.25
    python train/sweep.py --out runs/sweeps/quick --status       # one line per trial
    python train/report.py runs/sweeps/quick --out runs/reports/quick

A JSON grid holds the five axes and optionally "variants" ({name: [run.py arguments]}: one more
axis, compared seed by seed) and "method_args" ({method: [run.py arguments]}: for that method's
trials alone, e.g. kgrl's --kgrl-recipe in a grid with sac).

A sweep directory holds sweep.json (its grid and the arguments every trial gets) and one run
directory of train/run.py per trial, named from the configuration alone:
DIR/<task>_<env>_<D>d_<method>/seed<S>/ with run.py's files, the trial's log train.log (every
attempt appended, with the host and Ray node that ran it) and trial.json (state, attempts, host,
Ray node, times, the log's tail on failure).

Trials are Ray core tasks, each running one train/run.py process. Core tasks rather than Ray
Tune: a trial is a whole training process with its own run directory, checkpointing and resume,
and nothing here searches hyperparameters; Tune would move each trial's working directory and
storage into its own layout. Restartable:
- a trial with metrics.json is done and never started again; re-running a finished sweep starts
  nothing;
- a trial with a checkpoint continues with `--resume` (run.py checkpoints as soon as it starts);
- a trial whose process dies (a signal such as SIGKILL, or the machine's OOM killer) is retried
  by Ray up to --max-retries times (`retry_exceptions` names only that case: an ordinary error
  exit of run.py, e.g. a bad argument, fails the trial at once), then reported as failed with the
  tail of its log;
- a trial whose Ray worker or node is lost (a node killed or cut off) is retried by Ray under the
  same --max-retries, on any node with room, and resumes from its checkpoint on the shared --out;
  trials already finished are not run again. A retry on the host where the previous attempt's
  run.py still runs (it got SIGTERM from its dead worker and finishes its step) waits for it to
  stop first;
- killing the driver leaves the trials' checkpoints; starting it again continues the rest;
- sweep.json records the commit the sweep started at: started again from another commit, whose code the trials
  still to run would train on, it is refused unless --code-moved (recorded in sweep.json). Run a study from a
  checkout that does not move under it (a worktree at its commit). Uncommitted changes are not seen.
Shared prerequisites (KGRL's demonstrations and KMP tables, the vision methods' image sets and
VAEs) are made by the first trial that needs them, under vkgrl_newton/cache.py's file locks:
never by two trials at once, the others wait and reuse them. On a cluster --cache-dir (passed to
run.py) and --out must be on storage every node sees.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import re
import os
import sys
import time
from pathlib import Path

from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from vkgrl_newton._io import atomic_write_text, one_line, output_path_error, read_json_object  # noqa: E402
from vkgrl_newton.cli_types import SEED_BITS, stderr_without  # noqa: E402
from vkgrl_newton.signals import describe, exit_code, stop_signals_as_interrupts  # noqa: E402
from vkgrl_newton.run.methods import RUN_METHODS, THESIS_METHODS as METHODS  # noqa: E402
from vkgrl_newton.tasks import ACTION_DIMS  # noqa: E402
from vkgrl_newton.tasks import FAMILIES as ENVS  # noqa: E402
from vkgrl_newton.tasks import TASKS as TASK_SPECS  # noqa: E402
from vkgrl_newton.sweep import (TrialProcessDied, checkout_commit, log_tail, read_trial_state, run_trial,  # noqa: E402
                                trial_status, write_trial_state)

RUN_PY = ROOT / "train" / "run.py"
TASKS = tuple(TASK_SPECS)
AXES = ("tasks", "envs", "action_dims", "methods", "seeds")
GRIDS = {
    # the thesis's comparison: 48 configurations x 10 seeds (chapter 6)
    "thesis": {"tasks": list(TASKS), "envs": list(ENVS), "action_dims": list(ACTION_DIMS), "methods": list(METHODS),
               "seeds": list(range(10))},
    # what a 2-core CPU finishes in hours on the quick preset (57 min with kgrl's base recipe, docs/log/benchmarks.md;
    # kgrl's trials take 2-4x as long: ~25-28 min each, two at a time; 4D runs the residual recipe, the quick
    # default there, and 6D reach_keep_prior)
    "quick": {"tasks": ["PegInsert"], "envs": ["factory"], "action_dims": [4, 6], "methods": ["sac", "kgrl"],
              "seeds": [0, 1, 2]},
}
FORBIDDEN_RUN_ARGS = ("--run-dir", "--task", "--env", "--action-dim", "--method", "--seed", "--resume")
ALLOWED = {"tasks": TASKS, "envs": ENVS, "action_dims": ACTION_DIMS, "methods": RUN_METHODS}  # (+ the ppo baselines)
# ----------------------------------------------------------------------------- the grid
def load_grid(path) -> dict:
    """A grid JSON file, read and checked: FileNotFoundError if missing, else ValueError in one line
    naming the file when it is not a grid (another kind of file, damaged, a bad axis or value)."""
    grid = read_json_object(path, "grid file")
    try:
        return validate_grid(grid)
    except ValueError as e:
        raise ValueError(one_line(f"{path}: {e}", 400)) from None


def validate_grid(grid: dict) -> dict:
    """The grid with its axes checked; ValueError names a bad axis or value and the allowed ones."""
    if not isinstance(grid, dict):
        raise ValueError(f"grid: a JSON object of axes, not a {type(grid).__name__}")
    unknown = set(grid) - set(AXES) - {"variants", "method_args"}
    if unknown:
        raise ValueError(f"grid: unknown axes {sorted(unknown)}; allowed: {list(AXES)}, 'variants' and 'method_args'")
    out = {}
    for axis in AXES:
        values = grid.get(axis)
        if not values:
            raise ValueError(f"grid: axis {axis!r} is missing or empty")
        if not isinstance(values, list) or not all(isinstance(v, (str, int)) for v in values):  # (JSON: no tuples)
            raise ValueError(f"grid: axis {axis!r} must be a list of names or numbers, got {one_line(repr(values), 100)}")
        if axis == "seeds":
            if not all(isinstance(s, int) and not isinstance(s, bool) and 0 <= s < 2**SEED_BITS for s in values):
                raise ValueError(f"grid: seeds must be integers in [0, 2**{SEED_BITS}) (run.py's --seed), got {values!r}")
        else:
            bad = [v for v in values if isinstance(v, bool) or v not in ALLOWED[axis]]
            if bad:
                raise ValueError(f"grid: {axis} {bad!r} not allowed; allowed: {list(ALLOWED[axis])}")
        if len(set(values)) != len(values):
            raise ValueError(f"grid: axis {axis!r} repeats a value: {values!r}")
        out[axis] = list(values)
    # "variants" {name: [run.py arguments]}: one more axis, of option sets; "method_args" {method: [run.py
    # arguments]}: options for one method's trials only (a mixed grid can pin kgrl's --kgrl-recipe, which sac refuses)
    for key, what in (("variants", "name"), ("method_args", "method")):
        if key not in grid:
            continue
        sets = grid[key]
        if not isinstance(sets, dict) or not sets:
            raise ValueError(f"grid: {key!r} must be a non-empty object {{{what}: [run.py arguments]}}")
        for name, extra in sets.items():
            if key == "variants" and not re.fullmatch(r"[A-Za-z0-9_.-]{1,40}", name):
                raise ValueError(f"grid: variant name {name!r}: 1-40 letters, digits, '_', '.', '-'")
            if key == "method_args" and name not in ALLOWED["methods"]:
                raise ValueError(f"grid: method_args names {name!r}, not a method; allowed: {list(ALLOWED['methods'])}")
            where = "variant" if key == "variants" else key
            if not isinstance(extra, list) or not all(isinstance(a, str) for a in extra):
                raise ValueError(f"grid: {where} {name!r}: a list of run.py arguments (strings), got {extra!r}")
            bad = [a for a in extra if a.split("=")[0] in FORBIDDEN_RUN_ARGS + ("--label",)]
            if bad:
                raise ValueError(f"grid: {where} {name!r} sets {bad[0]}, which the sweep sets per trial")
        # (a method the axis flags took out of the grid, e.g. --methods sac on a grid of sac and kgrl: its
        # arguments go with it)
        out[key] = {k: list(v) for k, v in sets.items() if key == "variants" or k in out["methods"]}
    return out


def configuration_name(task: str, env: str, action_dim: int, method: str) -> str:
    return f"{task}_{env}_{action_dim}d_{method}"


def trials_of(grid: dict, out: Path) -> list[dict]:
    """One dict per trial, in grid order (task, env, action dim, method, seed, variant). A variant's
    trials live in <configuration>+<variant>/ and run with `--label <variant>` and its arguments; a
    method's trials get its method_args after them."""
    trials = []
    variants = grid.get("variants") or {None: []}
    for task, env, dim, method in itertools.product(*(grid[a] for a in AXES[:-1])):
        per_method = grid.get("method_args", {}).get(method, [])
        for seed in grid["seeds"]:  # seeds outermost: a sweep stopped midway has as many seeds of each variant
            for variant, extra in variants.items():
                name = configuration_name(task, env, dim, method) + (f"+{variant}" if variant else "")
                trial = {"name": f"{name}/seed{seed}", "task": task, "env": env, "action_dim": dim,
                         "method": method, "seed": seed, "run_dir": str(out / name / f"seed{seed}")}
                if variant:
                    trial.update(variant=variant, extra_args=["--label", variant, *extra])
                if per_method:
                    trial["extra_args"] = [*trial.get("extra_args", []), *per_method]
                trials.append(trial)
    return trials


# ----------------------------------------------------------------------------- the driver
def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--out", type=Path, required=True, help="the sweep's directory")
    ap.add_argument("--grid", default=None,
                    help=f"a named grid ({', '.join(GRIDS)}) or a JSON file with the axes {list(AXES)}; "
                         "the axis flags below replace its axes")
    ap.add_argument("--tasks", nargs="+", default=None)
    ap.add_argument("--envs", nargs="+", default=None)
    ap.add_argument("--action-dims", nargs="+", type=int, default=None)
    ap.add_argument("--methods", nargs="+", default=None)
    ap.add_argument("--seeds", nargs="+", type=int, default=None)
    ap.add_argument("--address", default=None,
                    help="a Ray cluster to join (e.g. auto, or ray://host:10001; default: $RAY_ADDRESS, else a local "
                         "Ray started for this sweep)")
    ap.add_argument("--cpus-per-trial", type=float, default=1.0,
                    help="Ray CPUs per trial (default 1; with 1 CPU a trial runs run.py --no-overlap unless the "
                         "run arguments say --overlap)")
    ap.add_argument("--gpus-per-trial", type=float, default=0.0, help="GPU fraction per trial (CUDA; default 0)")
    ap.add_argument("--max-concurrent", type=int, default=None,
                    help="trials in flight at once (default: as many as the cluster's resources allow)")
    ap.add_argument("--max-retries", type=int, default=2,
                    help="restarts of a trial whose process, Ray worker or node died (default 2)")
    ap.add_argument("--status", action="store_true", help="print one line per trial and exit")
    ap.add_argument("--code-moved", action="store_true",
                    help="continue a sweep although this checkout is at another commit than the one it started at "
                         "(its sweep.json's): the trials still to run then train on this code, and sweep.json records "
                         "the move. Without it such a restart is refused: a study runs from a commit that does not "
                         "move under it (e.g. a worktree at that commit)")
    ap.add_argument("--no-progress", action="store_true")
    return ap


def resolve_grid(args, ap) -> dict:
    grid: dict = {}
    if args.grid in GRIDS:
        grid = dict(GRIDS[args.grid])
    elif args.grid is not None:
        path = Path(args.grid)
        if not path.exists():
            ap.error(f"--grid {args.grid!r}: neither a named grid ({', '.join(GRIDS)}) nor a file")
        try:
            grid = read_json_object(path, "grid file")  # checked whole below, with the axis flags applied
        except ValueError as e:
            ap.error(f"--grid {e}")
    for axis in AXES:
        if getattr(args, axis) is not None:
            grid[axis] = getattr(args, axis)
    try:
        return validate_grid(grid)
    except ValueError as e:
        ap.error(f"--grid {args.grid}: {e}" if args.grid not in (None, *GRIDS) else str(e))


def split_argv(argv: list[str]) -> tuple[list[str], list[str]]:
    """(the sweep's own arguments, the ones after `--` that every run.py gets)."""
    if "--" in argv:
        i = argv.index("--")
        return argv[:i], argv[i + 1:]
    return argv, []




def main(argv: list[str] | None = None) -> int:
    own, run_args = split_argv(list(sys.argv[1:] if argv is None else argv))
    ap = build_parser()
    args = ap.parse_args(own)
    for flag, value, low in (("--cpus-per-trial", args.cpus_per_trial, 0.0), ("--gpus-per-trial", args.gpus_per_trial, 0.0),
                             ("--max-retries", args.max_retries, 0), ("--max-concurrent", args.max_concurrent, 1)):
        if value is not None and not (value >= low and math.isfinite(value)):
            ap.error(f"{flag} {value}: must be {'>' if flag == '--cpus-per-trial' else '>='} {low}")
    if args.cpus_per_trial == 0:
        ap.error("--cpus-per-trial 0: must be > 0 (a trial runs one training process)")
    for flag in FORBIDDEN_RUN_ARGS:
        if any(a == flag or a.startswith(flag + "=") for a in run_args):
            ap.error(f"{flag} after `--`: the sweep sets it per trial (grid axes: {list(AXES)})")
    if not args.status and (why := output_path_error(args.out, "--out", may_exist=True)):  # (before Ray starts)
        ap.error(why)
    record_path = args.out / "sweep.json"
    given_grid = args.grid is not None or any(getattr(args, a) is not None for a in AXES)
    moved = None
    if record_path.exists():
        try:
            record = read_json_object(record_path, "sweep record")
            if not all(k in record for k in ("grid", "run_args")):
                raise ValueError(f"missing {[k for k in ('grid', 'run_args') if k not in record]}")
            validate_grid(record["grid"])  # what trials_of indexes below
            if not isinstance(record["run_args"], list) or not all(isinstance(a, str) for a in record["run_args"]):
                raise ValueError("run_args is not a list of strings")
            if not isinstance(record.get("commit", ""), (str, type(None))):
                raise ValueError("commit is not a string")
            moves = record.get("code_moved", [])
            if not isinstance(moves, list) or not all(isinstance(m, dict) and isinstance(m.get("to"), str)
                                                      for m in moves):
                raise ValueError("code_moved is not a list of {from, to, at}")
        except ValueError as e:
            ap.error(one_line(f"--out {args.out}: its sweep.json is damaged ({e}); restore it or choose another "
                              "directory", 500))
        if given_grid or run_args:
            grid = resolve_grid(args, ap) if given_grid else record["grid"]
            if grid != record["grid"] or (run_args and run_args != record["run_args"]):
                ap.error(f"--out {args.out} holds another sweep (grid {record['grid']}, run arguments "
                         f"{record['run_args']}); run it again with just --out, or choose another directory")
        grid, run_args = record["grid"], record["run_args"]
        moved = _code_moved(record, args, ap, record_path)
    elif args.status:
        ap.error(f"--out {args.out} holds no sweep (no sweep.json)")
    elif not given_grid:
        ap.error("give a grid: --grid NAME|FILE or the axis flags (--tasks --envs --action-dims --methods --seeds)")
    else:
        grid = resolve_grid(args, ap)
    trials = trials_of(grid, args.out)
    try:  # a damaged trial.json, metrics.json or curves.jsonl: one line naming it, before Ray starts
        for t in trials:
            trial_status(t)
            read_trial_state(Path(t["run_dir"]))
    except ValueError as e:
        ap.error(str(e))

    if args.status:
        return print_status(trials)

    if not record_path.exists():
        args.out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(record_path, json.dumps({"grid": grid, "run_args": run_args, "trials": len(trials),
                                                   "created": time.strftime("%Y-%m-%d %H:%M:%S"),
                                                   "commit": checkout_commit(ROOT)}, indent=2))
    elif moved is not None:  # --code-moved: the record says from when on the trials ran other code
        record.setdefault("code_moved", []).append({"from": moved[0], "to": moved[1],
                                                    "at": time.strftime("%Y-%m-%d %H:%M:%S")})
        atomic_write_text(record_path, json.dumps(record, indent=2), overwrite=True)  # (a rename: whole or not)
    trial_args = list(run_args)
    if args.cpus_per_trial <= 1 and "--overlap" not in run_args and "--no-overlap" not in run_args:
        trial_args.append("--no-overlap")  # one core: a second thread only contends
    todo = [t for t in trials if not (Path(t["run_dir"]) / "metrics.json").exists()]
    print(f"train/sweep.py: {len(trials)} trials in {args.out}, {len(trials) - len(todo)} done, {len(todo)} to run")
    if not todo:
        return print_status(trials)
    return run_sweep(args, todo, trials, trial_args)


def _code_moved(record: dict, args, ap, record_path: Path) -> tuple[str, str] | None:
    """A restart from another commit than the sweep's last (its sweep.json's "commit", or its last --code-moved):
    refused unless --code-moved, which returns (from, to). None when the code is the same or unknown (a sweep from
    before the record had a commit, or a checkout outside git); --status reads files only and is never refused."""
    if args.status:
        return None
    last = record["code_moved"][-1]["to"] if record.get("code_moved") else record.get("commit")
    now = checkout_commit(ROOT)
    if not last or not now or last == now:
        return None
    if not args.code_moved:
        ap.error(f"--out {args.out} was started at commit {last[:12]} ({record_path}) and this checkout is at "
                 f"{now[:12]}: its trials still to run would train on other code than those done. Continue it from "
                 f"a checkout at {last[:12]} (git worktree add DIR {last[:12]}), or pass --code-moved to run the rest "
                 "on this code")
    print(f"train/sweep.py: --code-moved: the trials still to run train on {now[:12]}, not {last[:12]} "
          "(recorded in sweep.json)", flush=True)
    return last, now


def run_sweep(args, todo: list[dict], trials: list[dict], trial_args: list[str]) -> int:
    import ray

    address = args.address or os.environ.get("RAY_ADDRESS")
    # a local Ray by default: no dashboard, the trials' output in their own logs, not the driver's
    # Ray 2.5x announces its (kept) token authentication on every start: nothing to act on here
    with stderr_without("Token authentication is enabled for this Ray cluster"):
        ray.init(address=address, include_dashboard=False, log_to_driver=False, configure_logging=False)
    # after ray.init, which installs a SIGTERM handler of its own (sys.exit): ours replaces it while
    # the sweep drives its trials, so SIGTERM / SIGHUP stop it like Ctrl-C (trials marked interrupted)
    with stop_signals_as_interrupts():
        return _drive(ray, args, todo, trials, trial_args)


def _drive(ray, args, todo: list[dict], trials: list[dict], trial_args: list[str]) -> int:
    remote = ray.remote(run_trial).options(
        num_cpus=args.cpus_per_trial, num_gpus=args.gpus_per_trial, max_retries=args.max_retries,
        retry_exceptions=[TrialProcessDied])
    limit = args.max_concurrent or len(todo)
    queue, running, failed = list(todo), {}, []
    bar = tqdm(total=len(todo), unit="trial", disable=args.no_progress, desc="sweep")
    try:
        while queue or running:
            while queue and len(running) < limit:
                trial = queue.pop(0)
                running[remote.remote(trial, str(RUN_PY), trial_args, time.time())] = trial
            ready, _ = ray.wait(list(running), num_returns=1, timeout=10.0)
            for ref in ready:
                trial = running.pop(ref)
                try:
                    ray.get(ref)
                except ray.exceptions.RayError as e:  # the trial failed, or died more often than retried
                    cause = getattr(e, "cause", None) or e
                    write_trial_state(Path(trial["run_dir"]), state="failed", error=str(cause)[-4000:],
                                      log_tail=log_tail(Path(trial["run_dir"])))
                    failed.append(trial["name"])
                    tqdm.write(f"FAILED {trial['name']}:\n{cause}")
                bar.update(1)
            done_tr = sum(trial_status(t)[1] for t in running.values())
            bar.set_postfix(running=len(running), failed=len(failed), transitions=done_tr, refresh=True)
    except KeyboardInterrupt as e:  # Ctrl-C, SIGTERM or SIGHUP (vkgrl_newton/signals.py)
        bar.close()
        tqdm.write(f"{describe(e)}: the running trials checkpoint at their next step and stop; "
                   "run the same command again to continue them")
        for ref, trial in running.items():
            write_trial_state(Path(trial["run_dir"]), state="interrupted")
            ray.cancel(ref)  # the trial's task sends its run.py SIGINT and waits for it (vkgrl_newton/sweep.py)
        ray.shutdown()
        return exit_code(e)
    bar.close()
    summary = sweep_summary(trials)
    atomic_write_text(args.out / "sweep_summary.json", json.dumps(summary, indent=2), overwrite=True)
    ray.shutdown()
    print_status(trials)
    return 1 if failed else 0


def sweep_summary(trials: list[dict]) -> dict:
    """Per trial: state, attempts and the sweep's overhead (submitted -> first env transition)."""
    out = {}
    for t in trials:
        run_dir = Path(t["run_dir"])
        state, transitions = trial_status(t)
        ts = read_trial_state(run_dir)
        record = {"state": state, "transitions": transitions,
                  **{k: v for k, v in ts.items() if k in ("attempts", "resumed")}}
        if state == "done" and "submitted_unix" in ts:
            training = read_json_object(run_dir / "metrics.json", "run's metrics").get("training")
            if isinstance(training, dict) and "first_transition_unix" in training:
                # queueing and a worker's start; a retried trial's submission is its first attempt's, so its
                # span would hold the lost attempts too: left out (its train.log has each attempt's times)
                if ts.get("attempts", 1) == 1:
                    record["ray_s"] = ts["started_unix"] - ts["submitted_unix"]
                record["startup_s"] = training["first_transition_unix"] - ts["started_unix"]  # process, env, caches
        out[t["name"]] = record
    return out


def print_status(trials: list[dict]) -> int:
    counts: dict[str, int] = {}
    lines = []
    for t in trials:
        state, transitions = trial_status(t)
        counts[state] = counts.get(state, 0) + 1
        attempts = read_trial_state(Path(t["run_dir"])).get("attempts", 0)
        lines.append(f"{state:8s} {t['name']:40s} {transitions:9d} transitions  attempts {attempts}")
    lines.append("  ".join(f"{k}: {v}" for k, v in sorted(counts.items())))
    try:
        print("\n".join(lines), flush=True)
    except BrokenPipeError:  # `--status | head`: the reader has left; end quietly (Python's documented recipe)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 1 if counts.get("failed") else 0


if __name__ == "__main__":
    sys.exit(main())
