"""One trial of a sweep (train/sweep.py): a Ray task that runs train/run.py in its run directory,
resumes it when it has a checkpoint, and records its state on disk (trial.json, train.log).

A module of the package, not of train/, so that Ray's workers import it by name (the exception
class they raise must be the one the driver's retry_exceptions names).
"""

from __future__ import annotations

import ctypes
import json
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from vkgrl_newton._io import atomic_write_text, one_line, read_json_object
from vkgrl_newton.results.curves import read_curves
from vkgrl_newton.signals import STOP_EXIT_CODES

LOG_TAIL_LINES = 30


class TrialProcessDied(RuntimeError):
    """run.py was killed (a signal or an interrupt): Ray retries the trial, which resumes."""


class TrialFailed(RuntimeError):
    """run.py exited with an error: retrying would fail the same way."""


def trial_command(trial: dict, run_py: str, run_args: list[str], resume: bool) -> list[str]:
    cmd = [sys.executable, run_py, "--run-dir", trial["run_dir"], "--task", trial["task"],
           "--env", trial["env"], "--action-dim", str(trial["action_dim"]), "--method", trial["method"],
           "--seed", str(trial["seed"]), "--no-progress", *run_args, *trial.get("extra_args", [])]
    return cmd + ["--resume"] if resume else cmd


def _die_with_parent() -> None:
    """In the child: SIGTERM when the Ray worker that started it dies (Linux), so a retried trial
    never runs beside an orphan of its previous attempt. And SIGINT back to its default: a sweep started
    in the background (`nohup python train/sweep.py ... &`) passes SIGINT ignored down to its workers, and
    run.py would then ignore the SIGINT with which a cancelled trial is stopped (Python installs its
    KeyboardInterrupt handler only where SIGINT is not ignored), leaving the worker waiting on it."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux (no libc.so.6 / prctl): the child outlives a
        return  # killed worker there, so a retry can run beside it; Linux is what this project runs on


def checkout_commit(root: Path) -> str | None:
    """The git commit checked out at `root` (the code a sweep's trials run), or None outside a git checkout or
    without git. Uncommitted changes are not part of it."""
    try:
        done = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=60)
    except (OSError, subprocess.SubprocessError):
        return None
    commit = done.stdout.strip()
    return commit if done.returncode == 0 and len(commit) == 40 and all(c in "0123456789abcdef" for c in commit) \
        else None


# ----------------------------------------------------------------------------- trial state on disk
def read_trial_state(run_dir: Path) -> dict:
    """The trial's trial.json ({} when it has none); ValueError in one line naming it when damaged."""
    path = run_dir / "trial.json"
    if not path.exists():
        return {}
    state = read_json_object(path, "trial state")
    for key, kind in (("attempts", int), ("pid", int), ("state", str), ("host", str)):
        if key in state and (not isinstance(state[key], kind) or isinstance(state[key], bool)):
            raise ValueError(f"{path} is damaged: {key} is {one_line(repr(state[key]), 60)}, not a {kind.__name__}; "
                             "delete it and the trial is run again from its checkpoint")
    return state


def run_transitions(metrics_path: Path) -> int:
    """training.transitions of a finished run's metrics.json; ValueError in one line naming it when damaged."""
    training = read_json_object(metrics_path, "run's metrics").get("training")
    transitions = training.get("transitions") if isinstance(training, dict) else None
    if type(transitions) is not int or transitions < 0:
        raise ValueError(f"{metrics_path} is damaged: no whole number training.transitions")
    return transitions


def write_trial_state(run_dir: Path, **fields) -> None:
    state = {**read_trial_state(run_dir), **fields}
    atomic_write_text(run_dir / "trial.json", json.dumps(state, indent=2), overwrite=True)


def log_tail(run_dir: Path, lines: int = LOG_TAIL_LINES) -> str:
    log = run_dir / "train.log"
    return "\n".join(log.read_text(errors="replace").splitlines()[-lines:]) if log.exists() else ""


def trial_status(trial: dict, stale_s: float = 300.0) -> tuple[str, int]:
    """(done | running | failed | interrupted | pending, transitions so far) from the trial's files.

    Running: its run.py process is alive (on this host), or, for a trial on another node, one of
    its files changed within stale_s."""
    run_dir = Path(trial["run_dir"])
    metrics_path = run_dir / "metrics.json"
    if metrics_path.exists():
        return "done", run_transitions(metrics_path)
    try:
        rows = read_curves(run_dir) if run_dir.exists() else []
        transitions = int(rows[-1]["transitions"]) if rows else 0
    except (ValueError, TypeError, AttributeError, OverflowError) as e:  # (a row that is no object, a bad count)
        raise ValueError(one_line(f"{run_dir / 'curves.jsonl'} is damaged ({type(e).__name__}: {e})")) from None
    state = read_trial_state(run_dir)
    if state.get("state") == "failed":
        return "failed", transitions
    if state.get("state") in ("running", "interrupted"):
        if state.get("host") == socket.gethostname() and state.get("pid"):
            alive = _alive(int(state["pid"]))
        else:
            files = [run_dir / n for n in ("train.log", "curves.jsonl", "checkpoints/last.pt")]
            alive = any(f.exists() and time.time() - f.stat().st_mtime < stale_s for f in files)
        if alive:
            return "running", transitions
        if state.get("state") == "interrupted":  # the sweep was stopped; running it again continues it
            return "interrupted", transitions
    return "pending", transitions


def _alive(pid: int) -> bool:
    """The process exists and is not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, IndexError):
        return False


# ----------------------------------------------------------------------------- one trial (a Ray task)
def _ray_node_id() -> str | None:
    """The Ray node running this task (None outside one): which node ran an attempt, where several
    nodes share a host name."""
    try:
        import ray

        return ray.get_runtime_context().get_node_id() if ray.is_initialized() else None
    except Exception:  # (no Ray here, or no task context: the record is only informative)
        return None


def _runs_in(pid: int, run_dir: Path) -> bool:
    """Process pid is alive and is a run.py of run_dir (not a later process given the same pid)."""
    try:
        args = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return False
    return _alive(pid) and any(a == b"--run-dir" and b == str(run_dir).encode() for a, b in zip(args, args[1:]))


def _wait_for_previous_attempt(run_dir: Path, poll_s: float = 0.5) -> None:
    """Wait while the trial's previous attempt's run.py still runs on this host. Ray retries a trial
    as soon as its worker dies (a worker killed, a node lost), and that worker's run.py, told by
    SIGTERM (_die_with_parent), first finishes its step and checkpoints; a retry started beside it
    would resume from the checkpoint before and both would write the run directory. The same for a
    sweep started again while its interrupted trials still stop. (Another host's process is out of
    reach: there the node's death ends it.)"""
    state = read_trial_state(run_dir)
    pid = state.get("pid")
    if state.get("state") not in ("running", "interrupted") or state.get("host") != socket.gethostname() or not pid:
        return
    if _runs_in(pid, run_dir):
        with open(run_dir / "train.log", "a") as log:
            log.write(f"=== waiting for attempt {state.get('attempts')}'s run.py (pid {pid}) to stop\n")
        while _runs_in(pid, run_dir):
            time.sleep(poll_s)


def run_trial(trial: dict, run_py: str, run_args: list[str], submitted_unix: float) -> dict:
    """Run (or resume) one trial's train/run.py to the end; the body of the Ray task."""
    run_dir = Path(trial["run_dir"])
    run_dir.mkdir(parents=True, exist_ok=True)
    _wait_for_previous_attempt(run_dir)
    if (run_dir / "metrics.json").exists():
        return {"name": trial["name"], "skipped": True}
    resume = (run_dir / "checkpoints" / "last.pt").exists()
    if not resume and (run_dir / "config.json").exists():  # killed before its first checkpoint
        aside = run_dir / f"aborted_{time.strftime('%Y%m%d-%H%M%S')}"
        aside.mkdir()
        for name in ("config.json", "tb", "curves.jsonl"):
            if (run_dir / name).exists():
                (run_dir / name).rename(aside / name)
    cmd = trial_command(trial, run_py, run_args, resume)
    attempts = int(read_trial_state(run_dir).get("attempts", 0)) + 1
    started = time.time()
    node = _ray_node_id()
    write_trial_state(run_dir, state="running", attempts=attempts, host=socket.gethostname(), node=node,
                      submitted_unix=submitted_unix, started_unix=started, resumed=resume, command=cmd)
    with open(run_dir / "train.log", "a") as log:
        where = socket.gethostname() + (f" (Ray node {node})" if node else "")
        log.write(f"=== attempt {attempts} on {where} at {time.strftime('%Y-%m-%d %H:%M:%S')}: {' '.join(cmd)}\n")
        log.flush()
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=Path(run_py).parents[1],
                                start_new_session=True, preexec_fn=_die_with_parent)
        write_trial_state(run_dir, pid=proc.pid)
        try:
            code = proc.wait()
        except BaseException:  # the Ray task cancelled or the worker stopping: stop the run too
            proc.send_signal(signal.SIGINT)
            proc.wait()
            raise
    write_trial_state(run_dir, returncode=code, ended_unix=time.time())
    if code == 0 and (run_dir / "metrics.json").exists():
        write_trial_state(run_dir, state="done")
        return {"name": trial["name"], "skipped": False, "attempts": attempts}
    if code < 0 or code in STOP_EXIT_CODES:  # killed or stopped by a signal: resumable from its checkpoint
        raise TrialProcessDied(f"{trial['name']}: run.py died (exit {code}); log tail:\n{log_tail(run_dir)}")
    write_trial_state(run_dir, state="failed", log_tail=log_tail(run_dir))
    raise TrialFailed(f"{trial['name']}: run.py exited {code}; log tail:\n{log_tail(run_dir)}")
