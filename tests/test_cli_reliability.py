"""The command lines as a user meets them (issue 27, first part): argument errors before anything
heavy is imported, SIGTERM handled like Ctrl-C by a real training process, files never overwritten
and written with the umask, strict JSON."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from scripts import ROOT

TINY = ["--num-envs", "2", "--device", "cpu", "--no-progress", "--sac", "learning_starts=8", "--sac", "batch_size=8",
        "--sac", "gradient_steps=2", "--sac", "hidden_dims=16,16", "--sac", "buffer_size=1000"]
HEAVY = ("torch", "warp", "newton", "rsl_rl")

PROBE = """
import sys, runpy
sys.argv = ["train/run.py", *{argv!r}]
try:
    runpy.run_path("train/run.py", run_name="__main__")
except SystemExit as e:
    code = e.code
print("EXIT", code, "HEAVY", sorted(m for m in {heavy!r} if m in sys.modules))
"""


RUN_PY_CASES = [
    (["--help"], None),
    (["--num-envs", "0"], "--num-envs: must be an integer >= 1"),
    (["--method", "ppo2"], "invalid choice: 'ppo2'"),
    (["--sac", "lr=inf"], "lr=inf must be finite"),
    (["--sac", "weight_decay=-1"], "weight_decay=-1.0 must be >= 0"),
    (["--sac", "buffer_size=8", "--sac", "batch_size=16"], "buffer_size=8 must be >= batch_size=16"),
    (["--sac", "prior_anchor=true", "--method", "sac"], "--sac prior_anchor: acts with or learns from the KMP prior"),
    (["--kmp-reference", "empirical", "--method", "sac"], "--kmp-reference is for the kgrl methods"),
    (["--kgrl-reach-floor", "3", "--method", "sac"], "--kgrl-reach-floor is for the kgrl methods"),
    (["--kgrl-reach-floor", "nan", "--method", "kgrl"], "--kgrl-reach-floor must be a number of mm in [0, 50]"),
    (["--kgrl-reach-floor-z", "25", "--method", "sac"], "--kgrl-reach-floor-z is for the kgrl methods"),
    (["--kgrl-reach-floor-z", "-1", "--method", "kgrl"], "--kgrl-reach-floor-z must be a number of mm in [0, 50]"),
    (["--kgrl-seat-press", "5", "--method", "sac"], "--kgrl-seat-press is for the kgrl methods"),
    (["--kgrl-seat-press", "30", "--method", "kgrl"], "--kgrl-seat-press must be a number of mm in [0, 20]"),
    (["--sac", "prior_rollouts_policy=spiral"],
     "prior_rollouts_policy='spiral'; allowed: ['prior', 'search', 'scripted']"),
    (["--sac", "prior_rollouts=480", "--method", "sac"],  # a = 0 is KGRL's prior; SAC's rollouts are the demonstrator's
     "learns from the KMP prior (a = 0), for the kgrl methods (kgrl, vision_kgrl), not 'sac'; the SAC methods learn "
     "from the demonstrator's rollouts with --sac prior_rollouts_policy=scripted"),
    (["--sac", "prior_rollouts=480", "--sac", "prior_rollouts_policy=scripted", "--method", "kgrl"],
     "--sac prior_rollouts_policy=scripted is for the SAC methods (sac, vision_sac), not 'kgrl'"),
    (["--sac", "prior_rollouts=480", "--sac", "prior_rollouts_policy=scripted", "--sac", "prior_anchor=true",
      "--method", "vision_sac"], "--sac prior_anchor: acts with or learns from the KMP prior"),
    (["--kgrl-recipe", "base", "--sac", "prior_rollouts_policy=search"],
     "prior_rollouts_policy='search' acts in the first prior_rollouts"),
    (["--sac", "prior_rollouts=480", "--sac", "prior_rollouts_policy=search", "--method", "sac"],
     "--sac prior_rollouts: acts with or learns from the KMP prior"),
    (["--sac", "prior_rollouts=480", "--sac", "prior_rollouts_policy=search", "--method", "kgrl", "--kgrl-recipe",
      "base"], "--sac prior_rollouts_policy=search lightens the prior's ~20 mm press on a blocked part: it needs z reach"),
    (["--sac", "prior_rollouts_policy=search", "--kgrl-reach-floor-z", "0", "--kgrl-recipe", "reach_keep_prior"],
     # (the recipe's z floor taken away
     "--sac prior_rollouts_policy=search lightens the prior's ~20 mm press on a blocked part: it needs z reach"),
    (["--kgrl-recipe", "fast"], "argument --kgrl-recipe: invalid choice: 'fast' (choose from 'base', 'reach_keep_prior', 'residual')"),
    (["--kgrl-recipe", "base", "--method", "sac"], "--kgrl-recipe is for the kgrl methods on SAC (kgrl, vision_kgrl)"),
    (["--kgrl-recipe", "base", "--method", "kgrl_ppo"], "--kgrl-recipe is for the kgrl methods on SAC"),
    (["--seed", "-1"], "--seed -1: must be in [0, 2**32)"),
    (["--eval-episodes", "-1"], "--eval-episodes -1: must be >= 0"),
    (["--label", "a b"], "--label 'a b': 1-40 characters"),
]


@pytest.mark.parametrize("argv, message", RUN_PY_CASES)
def test_run_py_argument_errors_come_before_any_heavy_import(argv, message, tmp_path):
    out = subprocess.run([sys.executable, "-c", PROBE.format(argv=argv, heavy=HEAVY)], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    last = out.stdout.strip().splitlines()[-1]
    assert last.endswith("HEAVY []"), (last, out.stderr[-2000:])  # nothing heavy imported to say it
    if message is None:
        assert last.startswith("EXIT 0") and "--eval-seed" in out.stdout
    else:
        assert last.startswith("EXIT 2"), last
        err = out.stderr.strip().splitlines()
        assert message in err[-1] and "Traceback" not in out.stderr, out.stderr  # one line, no traceback
    assert not any(tmp_path.iterdir()) and not (ROOT / "runs" / "train" / "nothing").exists()


@pytest.mark.parametrize("resume", [False, True])
def test_a_run_without_a_checkpoint_is_one_clear_message_with_or_without_resume(resume, tmp_path):
    """config.json but no checkpoint (stopped before its first): not 'pass --resume' then 'no checkpoint'."""
    (tmp_path / "config.json").write_text("{}")
    argv = ["--run-dir", str(tmp_path)] + (["--resume"] if resume else [])
    out = subprocess.run([sys.executable, "-c", PROBE.format(argv=argv, heavy=HEAVY)], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert out.stdout.strip().splitlines()[-1] == "EXIT 2 HEAVY []", out.stdout + out.stderr[-2000:]
    assert "stopped before its first checkpoint (no checkpoints/last.pt): nothing to resume" in \
        out.stderr.strip().splitlines()[-1]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["config.json"]


@pytest.mark.slow
def test_sigterm_checkpoints_a_real_run_and_resume_continues(tmp_path):
    from vkgrl_newton.agents.checkpoint import load_checkpoint

    run_dir = tmp_path / "sac"
    cmd = [sys.executable, str(ROOT / "train" / "run.py"), "--method", "sac", "--run-dir", str(run_dir),
           "--total-steps", "100000", "--checkpoint-every", "100000", "--eval-episodes", "0", *TINY]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:  # the run checkpoints once at its start; signal it once it is past that, in its loop
        deadline = time.time() + 1200  # a cold Warp cache compiles every kernel first (minutes under load)
        while not (run_dir / "curves.jsonl").exists():
            assert proc.poll() is None and time.time() < deadline, proc.stdout.read() if proc.poll() else "timeout"
            time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, out
    assert "stopped by SIGTERM; checkpoint at" in out and "Traceback" not in out, out
    ckpt = load_checkpoint(run_dir / "checkpoints" / "last.pt")
    stopped_at = ckpt["counters"]["transitions"]
    assert stopped_at >= 300  # one 150-step episode of 2 worlds had finished: what it learned is kept
    assert int(out.split("checkpoint at ")[1].split()[0]) == stopped_at
    resumed = subprocess.run([sys.executable, str(ROOT / "train" / "run.py"), "--run-dir", str(run_dir), "--resume",
                              "--total-steps", str(stopped_at + 20), "--no-progress"], cwd=ROOT, capture_output=True,
                             text=True, timeout=900)
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    assert f"resumed {run_dir} at {stopped_at} transitions" in resumed.stdout
    assert load_checkpoint(run_dir / "checkpoints" / "last.pt")["counters"]["transitions"] == stopped_at + 20


def test_bench_refuses_an_existing_json_before_running(tmp_path):
    existing = tmp_path / "mine.json"
    existing.write_text("user data")
    out = subprocess.run([sys.executable, "-m", "vkgrl_newton.tools.bench_kernels", "--json", str(existing)], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 2 and "exists; choose another path" in out.stderr.strip().splitlines()[-1]
    assert existing.read_text() == "user data" and "kernel" not in out.stdout  # nothing was benchmarked


def test_written_files_follow_the_umask_and_json_is_strict(tmp_path):
    from vkgrl_newton._io import atomic_write_text, strict_json

    old = os.umask(0o027)
    try:
        path = atomic_write_text(tmp_path / "a.json", strict_json({"x": math.nan, "y": [math.inf, 1.5], "z": 2}))
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o640  # as open() would have made it, not mkstemp's 0600
    assert json.loads(path.read_text(), parse_constant=lambda c: pytest.fail(f"bare {c}")) == {
        "x": None, "y": [None, 1.5], "z": 2}


def test_a_stopped_sweep_marks_its_trials_interrupted_and_reads_them(tmp_path):
    from vkgrl_newton.sweep import trial_status, write_trial_state

    run_dir = tmp_path / "t"
    run_dir.mkdir()
    write_trial_state(run_dir, state="interrupted", host="elsewhere", pid=1)
    old = time.time() - 3600
    assert trial_status({"run_dir": str(run_dir)})[0] == "interrupted"
    (run_dir / "train.log").write_text("x")  # fresh activity from another host: it runs again
    assert trial_status({"run_dir": str(run_dir)})[0] == "running"
    os.utime(run_dir / "train.log", (old, old))
    assert trial_status({"run_dir": str(run_dir)})[0] == "interrupted"
    assert Path(run_dir / "trial.json").exists()


@pytest.mark.slow
@pytest.mark.parametrize("content, message", [
    (None, "does not exist"),
    (b"just text\n", "not a readable demonstration file (an .npz archive)"),
    ("other_npz", "missing keys"),
])
def test_run_py_refuses_a_bad_demos_file_before_building_anything(content, message, tmp_path):
    import numpy as np

    demos = tmp_path / "demos.npz"
    if content == "other_npz":
        np.savez(demos, weights=np.zeros(3))
    elif content is not None:
        demos.write_bytes(content)
    out = subprocess.run([sys.executable, str(ROOT / "train" / "run.py"), "--method", "kgrl", "--demos", str(demos),
                          "--run-dir", str(tmp_path / "run"), "--device", "cpu"], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    err = out.stderr.strip().splitlines()
    assert out.returncode == 2 and "--demos" in err[-1] and message in err[-1], out.stderr
    assert "pickle" not in out.stderr and "Traceback" not in out.stderr and not (tmp_path / "run").exists()


def test_sweep_refuses_bad_numbers_and_a_damaged_record(tmp_path, capsys):
    from scripts import load_script

    sweep_py = load_script("sweep")
    grid = ["--tasks", "PegInsert", "--envs", "factory", "--action-dims", "4", "--methods", "sac", "--seeds", "0"]
    for flag, value in (("--max-concurrent", "-1"), ("--cpus-per-trial", "-1"), ("--cpus-per-trial", "0"),
                        ("--max-retries", "-2"), ("--gpus-per-trial", "nan")):
        with pytest.raises(SystemExit) as exc:
            sweep_py.main(["--out", str(tmp_path / "s"), *grid, flag, value])
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert exc.value.code == 2 and f"{flag} " in err, err
        assert not (tmp_path / "s").exists()  # refused before sweep.json is written or Ray started
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "sweep.json").write_text('{"grid": ')
    with pytest.raises(SystemExit):
        sweep_py.main(["--out", str(tmp_path / "d"), "--status"])
    assert "sweep.json is damaged" in capsys.readouterr().err


def test_evaluate_refuses_a_task_other_than_the_checkpoints(tmp_path):
    from vkgrl_newton.agents.checkpoint import save_checkpoint

    ckpt = save_checkpoint(tmp_path / "last.pt", {"meta": {"task": "PegInsert", "env": "factory", "action_dim": 4,
                                                           "method": "sac", "time_obs": True},
                                                  "counters": {}, "agent": {}, "rng": {}})
    out = subprocess.run([sys.executable, str(ROOT / "train" / "evaluate.py"), "--checkpoint", str(ckpt), "--task",
                          "GearMesh", "--env", "forge", "--action-dim", "6", "--device", "cpu"], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    err = out.stderr.strip().splitlines()
    assert out.returncode == 2 and "the checkpoint is a PegInsert factory 4D policy" in err[-1], out.stderr


DEVICE_CASES = [  # (command, its device flag): every CLI that takes a device
    (["train/run.py", "--run-dir", "{tmp}/run"], "--device"),
    (["train/evaluate.py", "--policy", "kmp_prior", "--json", "{tmp}/e.json"], "--device"),
    (["train/collect_demos.py", "--out", "{tmp}/d.npz"], "--device"),
    (["train/collect_images.py", "--out", "{tmp}/images"], "--device"),
    (["-m", "vkgrl_newton.tools.throughput"], "--device"),
    (["-m", "vkgrl_newton.tools.bench_sac"], "--device"),
    (["-m", "vkgrl_newton.tools.bench_kernels", "--json", "{tmp}/b.json"], "--devices"),
]


@pytest.mark.slow
@pytest.mark.parametrize("argv, flag", DEVICE_CASES, ids=lambda v: v[1] if isinstance(v, list) else v)
@pytest.mark.parametrize("device", ["gpu", "cuda:7"])
def test_every_cli_refuses_a_device_it_cannot_use_in_one_line(argv, flag, device, tmp_path):
    """A misspelt device is refused by argparse; a CUDA device this machine lacks names the ones it has.
    (CI machines have no CUDA device with 8 or more GPUs: cuda:7 is absent everywhere we test.)"""
    cmd = [sys.executable, *[a.format(tmp=tmp_path) for a in argv], flag, device]
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    err = out.stderr.strip().splitlines()
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr[-2000:]
    expected = "is not a device; allowed: cpu, cuda, cuda:N" if device == "gpu" else f"{flag} cuda:7: Warp sees"
    assert expected in err[-1] and "allowed" in err[-1], err[-1]
    assert not any(tmp_path.iterdir())  # nothing written


def _wait_for(predicate, proc, limit_s: float, what: str) -> None:
    """Poll until predicate() holds; the limit only bounds a failure (a cold kernel cache under load)."""
    deadline = time.monotonic() + limit_s
    while not predicate():
        assert proc.poll() is None, f"exited {proc.returncode} before {what}: {proc.stderr.read()[-2000:]}"
        assert time.monotonic() < deadline, f"no {what} within {limit_s} s"
        time.sleep(0.2)


@pytest.mark.slow
@pytest.mark.parametrize("command", ["collect_demos", "collect_images"])
def test_sigterm_stops_a_collection_in_one_line_and_leaves_nothing(command, tmp_path):
    """SIGTERM once the command works on its output: exit 143, one line naming the signal, no
    traceback, and no output (an unfinished image set is removed, it would only block a retry)."""
    out = tmp_path / ("demos.npz" if command == "collect_demos" else "images")
    argv = [sys.executable, f"train/{command}.py", "--device", "cpu", "--num-envs", "2", "--out", str(out)]
    if command == "collect_images":
        argv += ["--num-images", "100000", "--resolution", "32", "--no-progress"]
    err_path = tmp_path / "stderr.txt"
    with open(err_path, "w") as err_file:
        proc = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=err_file, text=True)
        try:
            with open(err_path) as reader:
                proc.stderr = reader  # for _wait_for's message
                if command == "collect_images":  # the writer has made the directory: a partial set exists
                    _wait_for(lambda: out.exists() and any(out.iterdir()), proc, 1200, "image files")
                else:  # parse_cli has said the device: the handlers are in place
                    _wait_for(lambda: "device cpu" in err_path.read_text(), proc, 600, "start")
                proc.send_signal(signal.SIGTERM)
                proc.wait(timeout=600)
        finally:
            if proc.poll() is None:
                proc.kill()
    err = err_path.read_text()
    assert proc.returncode == 143 and "Traceback" not in err, err[-3000:]
    assert err.strip().splitlines()[-1].startswith(f"train/{command}.py: stopped by SIGTERM; ")
    assert not out.exists()


def test_report_is_all_or_nothing(tmp_path, monkeypatch):
    """A failure after some files are written leaves --out as it was (and no staging directory)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("report_cli", ROOT / "train" / "report.py")
    report = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(report)
    run = tmp_path / "runs" / "r0"
    run.mkdir(parents=True)
    monkeypatch.setattr(report, "find_runs", lambda paths: [run])
    monkeypatch.setattr(report, "load_cells", lambda dirs: {("PegInsert", "factory", 4, "kgrl"): []})
    monkeypatch.setattr(report, "load_thesis_tables", lambda: {})
    written = []

    def fake_files(run_dirs, cells, thesis, out, reps):
        (out / "tables.md").write_text("half a report")
        written.append(out)
        raise RuntimeError("the figure failed")

    monkeypatch.setattr(report, "_write_report_files", fake_files)
    out = tmp_path / "report"
    out.mkdir()
    with pytest.raises(RuntimeError, match="the figure failed"):
        report.write_report([tmp_path / "runs"], out)
    assert written and not written[0].exists()  # the staging directory is gone
    assert out.is_dir() and not any(out.iterdir()) and sorted(p.name for p in tmp_path.iterdir()) == ["report", "runs"]

    def good_files(run_dirs, cells, thesis, out, reps):
        (out / "tables.md").write_text("a report")
        return {"runs": 1}

    monkeypatch.setattr(report, "_write_report_files", good_files)
    assert report.write_report([tmp_path / "runs"], out) == {"runs": 1}
    assert (out / "tables.md").read_text() == "a report" and sorted(p.name for p in tmp_path.iterdir()) == ["report", "runs"]


def test_stderr_without_drops_native_lines_and_passes_the_rest(capfd):
    from vkgrl_newton.cli_types import stderr_without

    with stderr_without("Token authentication is enabled"):
        os.write(2, b"Token authentication is enabled for this Ray cluster. Set RAY_AUTH_MODE=disabled\n")
        os.write(2, b"a real warning\n")
        print("from python", file=sys.stderr)
    err = capfd.readouterr().err
    assert "Token authentication" not in err and "a real warning" in err and "from python" in err


def test_docs_cli_table_names_every_tested_refusal():
    """docs/cli.md is checked against the tests: every flag refused in RUN_PY_CASES, every CLI of
    DEVICE_CASES and the stop behaviour tested above appear in it."""
    doc = (ROOT / "docs" / "cli.md").read_text()
    for argv, message in RUN_PY_CASES[1:]:
        flag = argv[0] if argv[0] != "--sac" else f"--sac {argv[1]}"
        assert flag.split("=")[0] in doc, f"docs/cli.md does not name the refusal of {argv}"
    for argv, _ in DEVICE_CASES:
        name = argv[0].removeprefix("train/") if argv[0] != "-m" else argv[1].rsplit(".", 1)[-1]
        assert name in doc, f"docs/cli.md does not name {name}'s device refusal"
    for phrase in ("is not a device; allowed: cpu, cuda, cuda:N", "Warp sees no CUDA device on this machine",
                   "nothing to resume", "stopped by SIGTERM; nothing was written", "the unfinished image set is removed",
                   "all or nothing", "not a readable demonstration file (an .npz archive)"):
        assert phrase in doc, phrase


@pytest.mark.slow
def test_collect_images_refuses_a_resolution_no_vae_accepts(tmp_path):
    """Checked at collection time, not after hours of rendering when train_vae.py refuses it."""
    out = subprocess.run([sys.executable, "train/collect_images.py", "--resolution", "100", "--out", str(tmp_path / "i")],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "--resolution: invalid choice: 100 (choose from 32, 64, 128, 256, 512)" in out.stderr.strip().splitlines()[-1]
    assert not any(tmp_path.iterdir())


LIGHT_PROBE = """
import sys, runpy
sys.argv = [{script!r}, *{argv!r}]
try:
    runpy.run_path({script!r}, run_name="__main__")
except SystemExit as e:
    code = e.code
print("EXIT", code, "HEAVY", sorted(m for m in {heavy!r} if m in sys.modules))
"""


@pytest.mark.parametrize("script, argv, message", [
    ("train/evaluate.py", ["--help"], None),
    ("train/evaluate.py", ["--episodes", "0"], "--episodes: must be an integer >= 1"),
    ("train/evaluate.py", ["--device", "gpu"], "'gpu' is not a device"),
    ("train/collect_demos.py", ["--help"], None),
    ("train/collect_demos.py", ["--num-envs", "0", "--out", "x.npz"], "--num-envs: must be an integer >= 1"),
    ("train/train_vae.py", ["--help"], None),
    ("train/train_vae.py", ["--images", "x", "--epochs", "0"], "--epochs: must be an integer >= 1"),
    ("train/train_vae.py", ["--images", "x", "--channels", "8,8"], "--channels: must be 5 comma-separated"),
])
def test_other_clis_answer_help_and_argument_errors_before_any_heavy_import(script, argv, message):
    out = subprocess.run([sys.executable, "-c", LIGHT_PROBE.format(script=script, argv=argv, heavy=HEAVY)], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    last = out.stdout.strip().splitlines()[-1]
    assert last.endswith("HEAVY []"), (last, out.stderr[-2000:])
    if message is None:
        assert last.startswith("EXIT 0") and "usage:" in out.stdout
    else:
        assert last.startswith("EXIT 2") and message in out.stderr.strip().splitlines()[-1], out.stderr[-2000:]


def test_train_vae_cli_names_the_vae_defaults_it_shows_without_importing_them():
    import importlib.util

    from vkgrl_newton.vision.vae import VAEConfig

    spec = importlib.util.spec_from_file_location("train_vae_cli", ROOT / "train" / "train_vae.py")
    cli = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cli)
    assert cli.DEFAULT_CHANNELS == VAEConfig().channels
