"""train/sweep.py on a Ray cluster that loses a node: two nodes on loopback (Ray's own
ray.cluster_utils.Cluster, one CPU each), a sweep of three trials across both, the worker node
killed (no graceful shutdown) while its trial runs. The killed trial is retried on the surviving
node and resumes from its checkpoint; the finished trials are not run again; the files the report
reads (config.json, metrics.json, curves.jsonl) are those of an uninterrupted sweep of the grid.

The trials run a stand-in for train/run.py (written below, swapped in for sweep.py's RUN_PY) that
keeps run.py's contract: the same arguments, a checkpoint that --resume continues from, curves.jsonl
through the project's CurveWriter (rows past the checkpoint dropped on resume), metrics.json at the
end, and on SIGTERM it finishes its step, checkpoints and exits 143. What is under test is the
project's own path: sweep.py's driver, vkgrl_newton/sweep.py's Ray task and Ray's retries. A
real run.py trial costs ~25 s of one core; this one costs ~2 s, so the test fits a busy 2-core CI.
Every wait is on files or Ray's node table and bounded."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from scripts import ROOT

from vkgrl_newton.sweep import _alive, _runs_in

GRID = ["--tasks", "PegInsert", "--envs", "factory", "--action-dims", "4", "--methods", "sac", "--seeds", "0", "1", "2"]
STEPS = 6  # the stand-in's steps of 100 transitions; the held trial waits after its step HOLD_AT
HOLD_AT = 2
MB = 1024 * 1024

STAND_IN = r'''
"""A stand-in for train/run.py (tests/test_sweep_cluster.py): run.py's arguments, checkpoint,
resume, curves, metrics and stop signals; 100 deterministic transitions a step."""
import argparse, json, os, signal, sys, time
from pathlib import Path
from vkgrl_newton._io import atomic_write_text
from vkgrl_newton.results.curves import CurveWriter

STEPS, HOLD_AT = {steps}, {hold_at}
ap = argparse.ArgumentParser()
for flag in ("--run-dir", "--task", "--env", "--action-dim", "--method", "--seed"):
    ap.add_argument(flag, required=True)
ap.add_argument("--resume", action="store_true")
args, _ = ap.parse_known_args()
run, ctl = Path(args.run_dir), Path(__file__).resolve().parents[1] / "control"
stop = []
for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
    signal.signal(s, lambda n, f: stop.append(n))
node = json.loads((run / "trial.json").read_text()).get("node")
ckpt = run / "checkpoints" / "last.pt"
start, total = 0, 0.0
if args.resume:
    saved = json.loads(ckpt.read_text())
    start, total = saved["step"], saved["total"]
    print(f"resumed from {{ckpt}} at {{start * 100}} transitions", flush=True)
else:
    atomic_write_text(run / "config.json", json.dumps({{k: getattr(args, k) for k in
                      ("task", "env", "action_dim", "method", "seed")}}), overwrite=True)
with open(ctl / "attempts.jsonl", "a") as f:  # one line per process: what the test counts
    f.write(json.dumps({{"run": run.name, "resumed_at": start, "node": node, "pid": os.getpid()}}) + "\n")
curves = CurveWriter(run, resume_at=start * 100 if args.resume else None)
held = not args.resume and (ctl / "hold_node").exists() and (ctl / "hold_node").read_text() == node
step = start
while step < STEPS:
    step += 1
    time.sleep(0.2)  # the work of a step
    reward = int(args.seed) * 10 + step * 0.5
    total += reward
    curves.append(transitions=step * 100, episode_reward=reward, success_rate=0.0, success_rate_any=0.0,
                  mean_contact_force=1.0, peak_contact_force=2.0, time_to_first_success_s=None, wall_s=step)
    ckpt.parent.mkdir(exist_ok=True)
    atomic_write_text(ckpt, json.dumps({{"step": step, "total": total}}), overwrite=True)
    if stop:  # run.py's stop: the step finished and checkpointed
        sys.exit(128 + stop[0])
    if held and step == HOLD_AT:  # on the node the test kills: wait for it (or for SIGTERM)
        (ctl / f"held_{{args.seed}}").write_text(str(os.getpid()))
        deadline = time.time() + 600
        while not stop and time.time() < deadline and not (ctl / "release").exists():
            time.sleep(0.1)
        if stop:  # SIGTERM from its dead Ray worker (_die_with_parent): finish the step run.py is in, then
            # stop. (A worker that exits on its node's death SIGKILLs it first: Ray's
            # kill_child_processes_on_worker_exit; the test accepts either.)
            time.sleep(1.0)
            step += 1
            total += int(args.seed) * 10 + step * 0.5
            curves.append(transitions=step * 100, episode_reward=int(args.seed) * 10 + step * 0.5,
                          success_rate=0.0, success_rate_any=0.0, mean_contact_force=1.0, peak_contact_force=2.0,
                          time_to_first_success_s=None, wall_s=step)
            atomic_write_text(ckpt, json.dumps({{"step": step, "total": total}}), overwrite=True)
            sys.exit(128 + stop[0])
atomic_write_text(run / "metrics.json", json.dumps({{"training": {{"transitions": STEPS * 100}},
                  "episode_reward": total, "success_rate": 0.0}}), overwrite=True)
'''.format(steps=STEPS, hold_at=HOLD_AT)

# the driver: train/sweep.py's main with RUN_PY swapped for the stand-in (argv: stand-in, sweep arguments)
DRIVER = """import importlib.util, sys
from pathlib import Path
spec = importlib.util.spec_from_file_location("sweep_driver", {sweep!r})
sweep = importlib.util.module_from_spec(spec)
spec.loader.exec_module(sweep)
sweep.RUN_PY = Path(sys.argv[1])
sys.exit(sweep.main(sys.argv[2:]))
""".format(sweep=str(ROOT / "train" / "sweep.py"))


def wait_for(predicate, timeout: float, what: str, proc: subprocess.Popen | None = None) -> None:
    t = time.time()
    while not predicate():
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"the driver exited ({proc.returncode}) while waiting for {what}:\n"
                                 f"{proc.communicate()[0]}")
        if time.time() - t > timeout:
            raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.2)


def trial_state(run_dir: Path) -> dict:
    try:
        return json.loads((run_dir / "trial.json").read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return {}


def attempts(ctl: Path) -> list[dict]:
    path = ctl / "attempts.jsonl"
    return [json.loads(ln) for ln in path.read_text().splitlines()] if path.exists() else []


def report_files(out: Path) -> dict:
    """What train/report.py reads of each run: config.json, metrics.json, curves.jsonl."""
    return {f"{d.relative_to(out).as_posix()}/{name}": (d / name).read_text()
            for d in sorted(out.glob("*/seed*")) for name in ("config.json", "metrics.json", "curves.jsonl")}


@pytest.fixture
def cluster(monkeypatch):
    """A head and a worker node on 127.0.0.1, one CPU each, in a Ray temp directory of the test's
    own (Ray writes the address of the last cluster started there: no other test's ray.init finds it)."""
    from ray.cluster_utils import Cluster

    ray_tmp = tempfile.mkdtemp(prefix="vkrc", dir="/tmp")  # short: Ray's socket paths must fit 107 bytes
    monkeypatch.setenv("RAY_TMPDIR", ray_tmp)
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    # Ray on Linux turns an address of 127.0.0.1 into the host's outward IP, where nodes bound to
    # loopback do not listen; this switch (Ray's own) keeps every address on loopback
    monkeypatch.setenv("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    node_args = dict(num_cpus=1, object_store_memory=80 * MB, node_ip_address="127.0.0.1")
    c = Cluster(initialize_head=True, connect=False, head_node_args={**node_args, "include_dashboard": False})
    try:
        worker = c.add_node(**node_args)
        c.wait_for_nodes(timeout=120)
        yield c, worker
    finally:
        c.shutdown()
        shutil.rmtree(ray_tmp, ignore_errors=True)


def start_driver(stand_in: Path, out: Path, address: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", DRIVER, str(stand_in), "--out", str(out), "--address", address,
                             "--no-progress", *GRID], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True)


def finish(driver: subprocess.Popen, timeout: float) -> str:
    try:
        return driver.communicate(timeout=timeout)[0]
    finally:
        stop(driver)


def stop(driver: subprocess.Popen) -> None:
    if driver.poll() is None:
        os.killpg(driver.pid, signal.SIGKILL)
        driver.wait(30)


@pytest.fixture
def stand_in(tmp_path) -> tuple[Path, Path]:
    """(the stand-in run.py, its control directory: attempts.jsonl, hold_node, held_<seed>, release)."""
    path = tmp_path / "stand_in" / "train" / "run.py"
    path.parent.mkdir(parents=True)
    path.write_text(STAND_IN)
    (tmp_path / "stand_in" / "control").mkdir()
    return path, tmp_path / "stand_in" / "control"


def test_a_retry_waits_for_its_previous_attempts_process(stand_in, tmp_path):
    """A retry on the host where the previous attempt's run.py still runs (its Ray worker died; run.py
    finishes its step and checkpoints first) waits for it to stop: never two processes in one run
    directory."""
    from vkgrl_newton.sweep import run_trial

    run_py, ctl = stand_in
    run_dir = tmp_path / "sweep" / "PegInsert_factory_4d_sac" / "seed0"
    run_dir.mkdir(parents=True)
    stopped = tmp_path / "stopped"
    previous = subprocess.Popen([sys.executable, "-c", "import sys, time; time.sleep(2); "
                                 "open(sys.argv[3], 'w').write(repr(time.time()))", "--run-dir", str(run_dir),
                                 str(stopped)])
    try:
        wait_for(lambda: _runs_in(previous.pid, run_dir), 60, "the previous attempt's process to start")
        (run_dir / "trial.json").write_text(json.dumps({"state": "running", "attempts": 1, "pid": previous.pid,
                                                        "host": socket.gethostname()}))
        trial = {"name": "PegInsert_factory_4d_sac/seed0", "task": "PegInsert", "env": "factory", "action_dim": 4,
                 "method": "sac", "seed": 0, "run_dir": str(run_dir)}
        assert run_trial(trial, str(run_py), [], time.time()) == {"name": trial["name"], "skipped": False,
                                                                  "attempts": 2}
    finally:
        previous.kill()
        previous.wait()
    assert trial_state(run_dir)["started_unix"] >= float(stopped.read_text())
    assert "=== waiting for attempt 1's run.py" in (run_dir / "train.log").read_text()
    assert [a["run"] for a in attempts(ctl)] == ["seed0"]


@pytest.mark.slow
def test_a_sweep_that_loses_a_node_resumes_its_trial_on_the_other(cluster, stand_in, tmp_path):
    c, worker = cluster
    stand_in, ctl = stand_in
    (ctl / "hold_node").write_text(worker.node_id)  # the trial that lands on the worker node waits there
    out = tmp_path / "sweep"
    runs = {s: out / "PegInsert_factory_4d_sac" / f"seed{s}" for s in (0, 1, 2)}

    driver = start_driver(stand_in, out, c.address)
    try:
        # one trial held on the worker node after its checkpoint at step HOLD_AT; the head runs the
        # other two to the end meanwhile (one CPU: one after the other)
        wait_for(lambda: len(list(ctl.glob("held_*"))) == 1, 240, "a trial to hold on the worker node", driver)
        victim = int(next(ctl.glob("held_*")).name.split("_")[1])
        others = [s for s in runs if s != victim]
        wait_for(lambda: all((runs[s] / "metrics.json").exists() for s in others), 240,
                 "the head node to finish the other trials", driver)
        finished_at = {s: (runs[s] / "metrics.json").stat().st_mtime_ns for s in others}
        orphan = int((ctl / f"held_{victim}").read_text())
        c.remove_node(worker, allow_graceful=False)  # raylet, object store and all: no goodbye
        log = finish(driver, 240)
    finally:
        (ctl / "release").write_text("")  # a held stand-in left behind by a failure ends
        stop(driver)
    assert driver.returncode == 0, log
    assert "done: 3" in log, log
    wait_for(lambda: not _alive(orphan), 60, "the killed node's trial process to stop")

    # the victim: attempt 1 on the worker node, attempt 2 on the head, resumed where attempt 1's
    # process last checkpointed (its step HOLD_AT, or the one it finished on its SIGTERM)
    head_id = c.head_node.node_id
    tried = attempts(ctl)
    victim_runs = [a for a in tried if a["run"] == f"seed{victim}"]
    assert [a["node"] for a in victim_runs] == [worker.node_id, head_id], tried
    assert victim_runs[0]["resumed_at"] == 0 and victim_runs[1]["resumed_at"] in (HOLD_AT, HOLD_AT + 1), tried
    state = trial_state(runs[victim])
    assert state["attempts"] == 2 and state["resumed"] is True and state["state"] == "done", state
    assert state["node"] == head_id, state
    # the finished trials ran once, on the head, and were not touched again
    for s in others:
        assert [a["node"] for a in tried if a["run"] == f"seed{s}"] == [head_id], tried
        assert trial_state(runs[s])["attempts"] == 1
        assert (runs[s] / "metrics.json").stat().st_mtime_ns == finished_at[s]

    # an uninterrupted sweep of the same grid (on the head alone) leaves the same files for the report
    (ctl / "hold_node").unlink()
    plain = tmp_path / "plain"
    again = start_driver(stand_in, plain, c.address)
    log = finish(again, 240)
    assert again.returncode == 0 and "done: 3" in log, log
    expected = report_files(plain)
    assert len(expected) == 9 and report_files(out) == expected
