"""train/sweep.py: a grid of tiny train/run.py trials through a local Ray. All finish; a trial
whose process is SIGKILLed mid-run is retried and resumes from its checkpoint; a killed driver,
started again, finishes the rest without redoing finished trials; a finished sweep starts
nothing; bad grids and arguments are clear errors.

Tiny trials: 2 worlds, 900 transitions (450 per world: 3 episodes), a 16-unit SAC; each takes
~15 s of process start-up and ~10 s of stepping on one core."""

from __future__ import annotations

import json
import re
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from scripts import ROOT, load_script

from vkgrl_newton.results.curves import read_curves

RUN_ARGS = ["--num-envs", "2", "--total-steps", "900", "--checkpoint-every", "150", "--device", "cpu",
            "--eval-episodes", "1", "--sac", "learning_starts=8", "--sac", "batch_size=8", "--sac", "gradient_steps=2",
            "--sac", "hidden_dims=16,16", "--sac", "buffer_size=1000"]
GRID = ["--tasks", "PegInsert", "--envs", "factory", "--methods", "sac"]


@pytest.fixture(scope="module")
def sweep_py():
    return load_script("sweep")


def start_driver(out: Path, *grid: str) -> subprocess.Popen:
    env = {**os.environ, "RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"}
    return subprocess.Popen([sys.executable, str(ROOT / "train" / "sweep.py"), "--out", str(out), "--no-progress",
                             *grid, "--", *RUN_ARGS], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)


def wait_for(predicate, timeout: float, what: str) -> None:
    t = time.time()
    while not predicate():
        if time.time() - t > timeout:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.5)


def state(run_dir: Path) -> dict:
    path = run_dir / "trial.json"
    try:
        return json.loads(path.read_text()) if path.exists() else {}
    except json.JSONDecodeError:
        return {}


def checkpointed_transitions(run_dir: Path) -> int:
    """The transitions the trial's checkpoint holds: what a resume starts from. (Not curves.jsonl:
    a row is appended before the checkpoint that covers it is written, so a kill between the two
    resumes from the checkpoint before and drops that row.) The checkpoint is renamed into place
    atomically, so a read sees the old file or the new one, never a torn one."""
    from vkgrl_newton.agents.checkpoint import load_checkpoint

    try:
        return int(load_checkpoint(run_dir / "checkpoints" / "last.pt", required=("counters",))
                   ["counters"]["transitions"])
    except (FileNotFoundError, ValueError):
        return 0


def resumed_at(run_dir: Path) -> int:
    """The transitions of the checkpoint the trial's last attempt resumed from (run.py's log line)."""
    lines = [ln for ln in (run_dir / "train.log").read_text().splitlines() if ln.startswith("resumed ")]
    assert lines, (run_dir / "train.log").read_text()
    return int(lines[-1].split(" at ")[-1].split()[0])


def assert_finished(run_dir: Path, resumed: bool = False, killed_at_least: int = 300) -> dict:
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["training"]["transitions"] == 900
    steps = [r["transitions"] for r in read_curves(run_dir)]  # a row per episode of the 2 worlds
    if resumed:  # the rows up to the checkpoint resumed from stay; episodes restart there (300 each)
        at = resumed_at(run_dir)
        assert at >= killed_at_least, at  # the kill came after a checkpoint of that many transitions
        expected = [s for s in (300, 600, 900) if s <= at] + list(range(at + 300, 901, 300))
        assert steps == expected, (at, steps)
    else:
        assert steps == [300, 600, 900]
    return metrics


def test_grid_errors_name_the_axis_and_the_allowed_values(sweep_py, tmp_path, capsys):
    cases = [
        (["--grid", "quick", "--tasks", "Peg"], "tasks \\['Peg'\\] not allowed.*PegInsert"),
        (["--grid", "quick", "--methods", "td3"], "methods \\['td3'\\] not allowed.*vision_kgrl', 'ppo', 'kgrl_ppo'"),
        (["--grid", "quick", "--seeds", "0", "0"], "repeats a value"),
        (GRID, "axis 'action_dims' is missing"),
        (["--grid", "nope"], "neither a named grid \\(thesis, quick\\)"),
        ([], "give a grid"),
    ]
    for argv, message in cases:
        with pytest.raises(SystemExit):
            sweep_py.main(["--out", str(tmp_path / "s"), *argv])
        assert __import__("re").search(message, capsys.readouterr().err), argv
    bad_file = tmp_path / "grid.json"
    bad_file.write_text(json.dumps({"tasks": ["PegInsert"], "envs": ["factory"], "action_dims": [5],
                                    "methods": ["sac"], "seeds": [0]}))
    with pytest.raises(SystemExit):
        sweep_py.main(["--out", str(tmp_path / "s"), "--grid", str(bad_file)])
    assert "action_dims [5] not allowed; allowed: [4, 6]" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # the sweep names each trial's run directory and identity itself
        sweep_py.main(["--out", str(tmp_path / "s"), "--grid", "quick", "--", "--seed", "3"])
    assert "--seed after `--`" in capsys.readouterr().err
    thesis = sweep_py.trials_of(sweep_py.validate_grid(sweep_py.GRIDS["thesis"]), tmp_path)
    assert len(thesis) == 48 * 10 and len({t["run_dir"] for t in thesis}) == 480
    assert thesis[0]["run_dir"] == str(tmp_path / "PegInsert_factory_4d_sac" / "seed0")


def test_variants_and_method_args_reach_their_trials_and_only_theirs(sweep_py, tmp_path):
    """A variant is one more axis (its own run directory, --label and arguments, after the seed); a
    method's method_args go to that method's trials alone, so a grid mixing sac and kgrl can pin kgrl's
    --kgrl-recipe (which sac refuses)."""
    grid = sweep_py.validate_grid({"tasks": ["PegInsert"], "envs": ["factory"], "action_dims": [4],
                                   "methods": ["sac", "kgrl"], "seeds": [0, 1],
                                   "variants": {"a": ["--sac", "tau=0.01"], "b": []},
                                   "method_args": {"kgrl": ["--kgrl-recipe", "base"]}})
    trials = sweep_py.trials_of(grid, tmp_path)
    expected = [(m, seed, v) for m in ("sac", "kgrl") for seed in (0, 1) for v in ("a", "b")]
    assert [(t["method"], t["seed"], t["variant"]) for t in trials] == expected
    for t in trials:
        variant_args = {"a": ["--sac", "tau=0.01"], "b": []}[t["variant"]]
        recipe = ["--kgrl-recipe", "base"] if t["method"] == "kgrl" else []
        assert t["extra_args"] == ["--label", t["variant"], *variant_args, *recipe], t
        assert t["run_dir"] == str(tmp_path / f"PegInsert_factory_4d_{t['method']}+{t['variant']}" / f"seed{t['seed']}")
    # without variants, method_args alone; a method without any gets no extra arguments
    plain = sweep_py.trials_of(sweep_py.validate_grid({k: v for k, v in grid.items() if k != "variants"}), tmp_path)
    assert [t.get("extra_args") for t in plain] == [None, None, ["--kgrl-recipe", "base"], ["--kgrl-recipe", "base"]]
    base = {k: v for k, v in grid.items() if k not in ("variants", "method_args")}
    # a method the grid lacks (say, taken out by --methods): its arguments go with it
    assert sweep_py.validate_grid({**base, "method_args": {"kgrl": ["--kgrl-recipe", "base"], "ppo": ["--ppo", "x=1"]}}
                                  )["method_args"] == {"kgrl": ["--kgrl-recipe", "base"]}
    for method_args, message in (({"td3": ["--sac", "tau=0.01"]}, "names 'td3', not a method; allowed: ['sac'"),
                                 ({"kgrl": "--kgrl-recipe base"}, "a list of run.py arguments"),
                                 ({"kgrl": ["--seed=3"]}, "sets --seed=3, which the sweep sets per trial"),
                                 ({}, "non-empty object")):
        with pytest.raises(ValueError, match=re.escape(message)):
            sweep_py.validate_grid({**base, "method_args": method_args})
    with pytest.raises(ValueError, match="unknown axes \\['method_arg'\\]"):
        sweep_py.validate_grid({**base, "method_arg": {}})


@pytest.mark.slow
def test_sweep_finishes_retries_a_killed_trial_and_restarts_nothing(sweep_py, wp_cpu, tmp_path, capsys):
    out = tmp_path / "sweep"
    grid = [*GRID, "--action-dims", "4", "6", "--seeds", "0", "1"]  # 2 x 2 trials, 2 at a time on 2 cores
    victim = out / "PegInsert_factory_6d_sac" / "seed0"
    driver = start_driver(out, *grid)
    try:  # SIGKILL the victim's run.py once it has checkpointed part of its run
        wait_for(lambda: state(victim).get("pid") and checkpointed_transitions(victim) >= 300, 240,
                 "the victim trial to train")
        os.kill(state(victim)["pid"], signal.SIGKILL)
        log, _ = driver.communicate(timeout=420)
    finally:
        if driver.poll() is None:
            os.killpg(driver.pid, signal.SIGKILL)
    assert driver.returncode == 0, log
    assert "done: 4" in log, log
    trial = state(victim)
    assert trial["attempts"] == 2 and trial["resumed"] is True and trial["state"] == "done"
    assert (victim / "train.log").read_text().count("=== attempt") == 2
    assert_finished(victim, resumed=True)
    for d in (out / "PegInsert_factory_4d_sac" / "seed0", out / "PegInsert_factory_4d_sac" / "seed1",
              out / "PegInsert_factory_6d_sac" / "seed1"):
        assert state(d)["attempts"] == 1
        assert "success_rate" in assert_finished(d)
    summary = json.loads((out / "sweep_summary.json").read_text())
    assert summary[victim.relative_to(out).as_posix()]["attempts"] == 2
    # a retried trial's queueing time would hold its lost attempt: not reported; a first attempt's is
    assert "ray_s" not in summary[victim.relative_to(out).as_posix()]
    assert summary["PegInsert_factory_4d_sac/seed0"]["ray_s"] >= 0

    # a finished sweep starts nothing; --status says done for every trial
    assert sweep_py.main(["--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "4 trials" in printed and "0 to run" in printed
    assert sweep_py.main(["--out", str(out), "--status"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "seed" in ln]
    assert len(lines) == 4 and all(ln.startswith("done") and " 900 transitions" in ln for ln in lines)
    with pytest.raises(SystemExit):  # another grid in the same directory is refused
        sweep_py.main(["--out", str(out), *GRID, "--action-dims", "4", "--seeds", "0"])
    assert "holds another sweep" in capsys.readouterr().err


@pytest.mark.slow
def test_a_killed_driver_started_again_finishes_the_rest(sweep_py, wp_cpu, tmp_path, capsys):
    out = tmp_path / "sweep"
    grid = [*GRID, "--action-dims", "4", "--seeds", "0", "1", "--max-concurrent", "1"]
    first, second = out / "PegInsert_factory_4d_sac" / "seed0", out / "PegInsert_factory_4d_sac" / "seed1"
    driver = start_driver(out, *grid)
    try:  # kill the driver once the first trial is done and the second has checkpointed some
        wait_for(lambda: (first / "metrics.json").exists() and checkpointed_transitions(second) >= 300, 300,
                 "one finished and one running trial")
        sweep_py.main(["--out", str(out), "--status"])  # read from the trials' files while they run
        lines = {ln.split()[1]: ln.split()[0] for ln in capsys.readouterr().out.splitlines() if "seed" in ln}
        assert lines == {"PegInsert_factory_4d_sac/seed0": "done", "PegInsert_factory_4d_sac/seed1": "running"}
        os.killpg(driver.pid, signal.SIGKILL)
        driver.wait(timeout=30)
    finally:
        if driver.poll() is None:
            os.killpg(driver.pid, signal.SIGKILL)
    done_at = (first / "metrics.json").stat().st_mtime
    orphan = state(second)["pid"]  # its run.py dies with the driver's Ray worker
    from vkgrl_newton.sweep import _alive

    wait_for(lambda: not _alive(orphan), 60, "the killed sweep's trial process to exit")
    again = start_driver(out, *grid)
    log, _ = again.communicate(timeout=300)
    assert again.returncode == 0, log
    assert "1 done, 1 to run" in log, log
    assert (first / "metrics.json").stat().st_mtime == done_at and state(first)["attempts"] == 1
    assert state(second)["attempts"] == 2 and state(second)["resumed"] is True
    assert_finished(second, resumed=True)



@pytest.mark.slow
def test_sigterm_to_the_driver_marks_trials_interrupted_and_a_restart_resumes_them(sweep_py, wp_cpu, tmp_path):
    """SIGTERM (a scheduler's pre-emption) stops the driver like Ctrl-C, after Ray installed its own
    handler: exit 143, the running trial is marked interrupted, and the same command resumes it."""
    out = tmp_path / "sweep"
    grid = [*GRID, "--action-dims", "4", "--seeds", "0", "--max-concurrent", "1"]
    trial = out / "PegInsert_factory_4d_sac" / "seed0"
    driver = start_driver(out, *grid)
    try:
        wait_for(lambda: state(trial).get("pid") and checkpointed_transitions(trial) >= 150, 300,
                 "the trial to checkpoint")
        driver.send_signal(signal.SIGTERM)
        log, _ = driver.communicate(timeout=120)
    finally:
        if driver.poll() is None:
            os.killpg(driver.pid, signal.SIGKILL)
    assert driver.returncode == 128 + signal.SIGTERM, log
    assert "stopped by SIGTERM" in log and state(trial)["state"] in ("interrupted", "running"), log
    from vkgrl_newton.sweep import _alive

    wait_for(lambda: not _alive(state(trial)["pid"]), 60, "the trial's run.py to stop")
    assert state(trial)["state"] == "interrupted"
    again = start_driver(out, *grid)
    log, _ = again.communicate(timeout=300)
    assert again.returncode == 0, log
    assert state(trial)["attempts"] == 2 and state(trial)["resumed"] is True
    assert_finished(trial, resumed=True, killed_at_least=150)


def test_status_into_a_closed_pipe_ends_quietly(tmp_path):
    """`sweep.py --status | head -1`: the reader leaves before the lines are written; the status
    ends without a BrokenPipeError traceback (it printed one before)."""
    out = tmp_path / "sweep"
    out.mkdir()
    grid = {"tasks": ["PegInsert", "GearMesh"], "envs": ["factory"], "action_dims": [4], "methods": ["sac"],
            "seeds": list(range(50))}  # 100 trials: more lines than the reader takes
    (out / "sweep.json").write_text(json.dumps({"grid": grid, "run_args": []}))
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader is gone before the first line
    try:
        proc = subprocess.run([sys.executable, str(ROOT / "train" / "sweep.py"), "--out", str(out), "--status"],
                              cwd=ROOT, stdout=write_end, stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        os.close(write_end)
    assert "Traceback" not in proc.stderr and "BrokenPipe" not in proc.stderr, proc.stderr
    assert proc.returncode == 0


def test_a_restart_from_another_commit_is_refused_unless_code_moved_says_so(sweep_py, tmp_path):
    """A sweep records the commit it starts at; started again from another commit (its trials still to run would
    train on other code) it is refused in one line naming both, before anything runs, unless --code-moved, which
    sweep.json records; --status and a sweep from before the record had a commit are not refused."""
    from vkgrl_newton.sweep import checkout_commit

    git = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True)
    if git.returncode != 0:
        pytest.skip("not a git checkout: a sweep records no commit here")
    head = git.stdout.strip()
    assert checkout_commit(ROOT) == head
    out = tmp_path / "sweep"
    grid = {"tasks": ["PegInsert"], "envs": ["factory"], "action_dims": [4], "methods": ["sac"], "seeds": [0]}
    run_dir = Path(sweep_py.trials_of(grid, out)[0]["run_dir"])
    run_dir.mkdir(parents=True)
    (run_dir / "metrics.json").write_text(json.dumps({"training": {"transitions": 900}}))  # the trial is done
    other = "0123456789ab" + "0" * 28
    record = {"grid": grid, "run_args": [], "trials": 1, "created": "2026-12-07 13:00:00", "commit": other}
    (out / "sweep.json").write_text(json.dumps(record))

    def sweep(*flags):
        return subprocess.run([sys.executable, str(ROOT / "train" / "sweep.py"), "--out", str(out), *flags],
                              cwd=ROOT, capture_output=True, text=True, timeout=300)

    refused = sweep()
    assert refused.returncode == 2, refused.stderr
    last = refused.stderr.strip().splitlines()[-1]
    assert f"started at commit {other[:12]}" in last and f"this checkout is at {head[:12]}" in last and \
        "--code-moved" in last, refused.stderr
    assert json.loads((out / "sweep.json").read_text()) == record  # nothing written
    assert sweep("--status").returncode == 0
    moved = sweep("--code-moved")
    assert moved.returncode == 0, moved.stderr
    after = json.loads((out / "sweep.json").read_text())
    assert [(m["from"], m["to"]) for m in after["code_moved"]] == [(other, head)]
    assert {k: v for k, v in after.items() if k != "code_moved"} == record
    assert sweep().returncode == 0  # the last move's commit is this one
    (out / "sweep.json").write_text(json.dumps({k: v for k, v in record.items() if k != "commit"}))
    assert sweep().returncode == 0  # a sweep from before the commit was recorded
    (out / "sweep.json").write_text(json.dumps({**record, "commit": 7}))
    damaged = sweep()
    assert damaged.returncode == 2 and "sweep.json is damaged (commit is not a string)" in damaged.stderr
