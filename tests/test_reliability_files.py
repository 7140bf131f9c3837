"""Issue 41's cases, as a new user meets them: any file handed over that is not what it should be ends in
one line and the right exit code, never a traceback, and leaves nothing half-written (a stop at each
phase of a run: tests/test_signals_phases.py)."""

import json
import subprocess
import sys

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
    _one_line_refusal(_cli("train/run.py", "--method", "vision_kgrl", "--vae", str(notes), "--device", "cpu",
                           "--kgrl-recipe", "reach_keep_prior"),
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
