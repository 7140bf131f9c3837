"""Issue 41's cases, as a new user meets them: any file handed over that is not what it should be, and a
stop while the prior's demonstrations are recorded, end in one line and the right exit code, never a
traceback, and leave nothing half-written."""

import json
import shutil
import signal
import subprocess
import sys
import time

import pytest
from scripts import ROOT

NOT_A_FILE_OF_OURS = "hello, these are my notes\n"


def _cli(*argv, timeout=300):
    return subprocess.run([sys.executable, *argv], cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def _one_line_refusal(out, *needles):
    assert out.returncode == 2, (out.returncode, out.stderr[-2000:])
    assert "Traceback" not in out.stderr, out.stderr[-2000:]
    last = out.stderr.strip().splitlines()[-1]
    for n in needles:
        assert n in last, last


@pytest.fixture()
def notes(tmp_path):
    path = tmp_path / "notes.txt"
    path.write_text(NOT_A_FILE_OF_OURS)
    return path


def test_a_checkpoint_that_is_another_kind_of_file_is_refused_in_one_line(notes):
    """torch's unpickler fails on a text file with a KeyError or IndexError (not an UnpicklingError)."""
    _one_line_refusal(_cli("train/evaluate.py", "--checkpoint", str(notes), "--device", "cpu"),
                      "--checkpoint", str(notes), "is damaged or not a checkpoint")


def test_evaluate_refuses_a_bad_demos_file_in_one_line_as_run_py_does(notes):
    _one_line_refusal(_cli("train/evaluate.py", "--policy", "kmp_prior", "--action-dim", "4", "--demos", str(notes),
                           "--device", "cpu"), "--demos", "not a readable demonstration file")


def test_run_refuses_a_vae_that_is_another_kind_of_file_in_one_line(notes):
    _one_line_refusal(_cli("train/run.py", "--method", "vision_kgrl", "--vae", str(notes), "--device", "cpu"),
                      "--vae", str(notes), "is damaged or not a checkpoint")


def test_report_refuses_a_damaged_metrics_json_naming_it(tmp_path):
    run = tmp_path / "sweep" / "r0"
    run.mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"task": "PegInsert", "env": "factory", "action_dim": 4,
                                                 "method": "kgrl", "seed": 0}))
    (run / "metrics.json").write_text('{"success_rate": 0.5, ')  # cut short, as by a full disk
    out = _cli("train/report.py", str(tmp_path / "sweep"), "--out", str(tmp_path / "report"))
    _one_line_refusal(out, str(run / "metrics.json"), "is damaged")
    assert not (tmp_path / "report").exists()  # nothing written


@pytest.mark.slow
def test_sigterm_while_the_demonstrations_are_recorded_is_one_line_and_leaves_no_half_file(tmp_path):
    cache, run_dir = tmp_path / "cache", tmp_path / "run"
    p = subprocess.Popen([sys.executable, "train/run.py", "--method", "kgrl", "--num-envs", "2", "--device", "cpu",
                          "--no-progress", "--num-demos", "2", "--cache-dir", str(cache), "--run-dir", str(run_dir)],
                         cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        for line in p.stdout:  # the run says when it starts recording (then the simulation is under way)
            if "recording 2 scripted" in line or time.monotonic() > deadline:
                break
        time.sleep(2.0)
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 143, err[-2000:]
    assert "Traceback" not in err and "stopped by SIGTERM while preparing the KMP prior" in err.strip().splitlines()[-1]
    assert not run_dir.exists()  # nothing of the run was written before its prerequisites were made
    from vkgrl_newton.kmp.demos import DemoSet

    for f in cache.rglob("*.npz"):  # whole or absent: whatever is there loads
        DemoSet.load(f)
    leftovers = [f for f in cache.rglob("*") if f.is_file() and not f.name.endswith((".npz", ".lock"))]
    assert not leftovers, leftovers  # no temporary half-file
    shutil.rmtree(tmp_path)
