"""--keep-at: a run keeps its policy at the transition counts asked (checkpoints/at_<N>.pt), the points of a
learning curve that evaluate.py scores on the run's own evaluation episodes, without changing the training.

References: the same seed run without the option (training unchanged, bit for bit), the run's own periodic
checkpoint written at the same count (the kept policy is the run's at that moment), and for PPO a run trained to N
alone (the kept policy is what a run of N transitions ends with).
"""

from __future__ import annotations

import json

import pytest
import torch
from scripts import TINY_RUN, load_script

from test_ppo_run import PER_ITERATION, TINY_PPO


@pytest.fixture(scope="module")
def run_py():
    return load_script("run")


def _tensors_equal(a, b, path="") -> None:
    """Every tensor in two nested state dicts equal (the same keys)."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for k in a:
            _tensors_equal(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, torch.Tensor):
        assert torch.equal(a, b), path
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _tensors_equal(x, y, f"{path}[{i}]")


def test_sac_keeps_its_policy_at_each_count_without_changing_the_training(run_py, wp_cpu, tmp_path, monkeypatch):
    from vkgrl_newton.agents import checkpoint as checkpoint_module
    from vkgrl_newton.agents.checkpoint import load_checkpoint

    written = []  # (path name, transitions, actor weights) of every checkpoint the kept run writes, in order
    real_save = checkpoint_module.save_checkpoint

    def recording_save(path, payload):
        written.append((path.name, payload["counters"]["transitions"],
                        {k: v.clone() for k, v in payload["agent"]["actor"].items()}))
        return real_save(path, payload)

    base = ["--method", "sac", "--eval-episodes", "0", "--total-steps", "40", "--checkpoint-every", "16",
            "--overlap", *TINY_RUN]
    assert run_py.main([*base, "--run-dir", str(tmp_path / "plain")]) == 0
    monkeypatch.setattr(checkpoint_module, "save_checkpoint", recording_save)
    kept_dir = tmp_path / "kept"
    # 2 worlds: 2 transitions a step; 17 is reached at 18 (the first step at or past it); given out of order
    assert run_py.main([*base, "--run-dir", str(kept_dir), "--keep-at", "32", "16", "17"]) == 0

    # the training is the same run's, bit for bit (agent, replay buffer, optimizers, counters)
    plain = load_checkpoint(tmp_path / "plain" / "checkpoints" / "last.pt")
    last = load_checkpoint(kept_dir / "checkpoints" / "last.pt")
    _tensors_equal(plain["agent"], last["agent"])
    assert plain["counters"] == {**last["counters"], "wall_s": plain["counters"]["wall_s"]}

    for n, at in ((16, 16), (17, 18), (32, 32)):
        kept = load_checkpoint(kept_dir / "checkpoints" / f"at_{n}.pt")
        assert kept["counters"]["transitions"] == at and kept["agent"]["counters"][0] == at
        assert "buffer" not in kept["agent"] and kept["meta"] == last["meta"]
        assert kept["plan"]["keep_at"] == [16, 17, 32]
    # the kept policy is the run's at that count: the periodic checkpoint written at the same step holds the same
    # actor, and the kept file comes first (a stop between them resumes before the count and keeps it again)
    names = [name for name, _, _ in written]
    for n in (16, 32):
        i = names.index(f"at_{n}.pt")
        name, transitions, actor = written[i + 1]
        assert (name, transitions) == ("last.pt", n)
        _tensors_equal(written[i][2], actor)
    config = json.loads((kept_dir / "config.json").read_text())
    assert config["keep_at"] == [16, 17, 32]
    assert "keep_at" not in json.loads((tmp_path / "plain" / "config.json").read_text())  # absent unless asked

    # evaluate.py scores a kept policy like a run's last checkpoint
    evaluate_py = load_script("evaluate")
    out = tmp_path / "at_16.json"
    assert evaluate_py.main(["--checkpoint", str(kept_dir / "checkpoints" / "at_16.pt"), "--num-envs", "2",
                             "--episodes", "1", "--json", str(out), "--cache-dir", str(tmp_path / "cache")]) == 0
    result = json.loads(out.read_text())
    assert result["policy"] == "sac" and result["episodes"] == 2


def test_a_resumed_run_keeps_the_counts_still_ahead(run_py, wp_cpu, tmp_path, monkeypatch, capsys):
    from vkgrl_newton.agents.checkpoint import load_checkpoint
    from vkgrl_newton.envs.assembly_env import AssemblyEnv

    run_dir = tmp_path / "run"
    calls = {"n": 0}
    real_step = AssemblyEnv.step

    def stopping_step(self, actions):  # Ctrl-C on the 13th env step: checkpointed at 24 transitions
        calls["n"] += 1
        if calls["n"] == 13:
            raise KeyboardInterrupt
        return real_step(self, actions)

    monkeypatch.setattr(AssemblyEnv, "step", stopping_step)
    argv = ["--method", "sac", "--run-dir", str(run_dir), "--eval-episodes", "0", "--total-steps", "40",
            "--checkpoint-every", "100", "--no-overlap", "--keep-at", "8", "10", "24", "32", *TINY_RUN]
    assert run_py.main(argv) == 130
    monkeypatch.setattr(AssemblyEnv, "step", real_step)
    kept = run_dir / "checkpoints"
    at_8 = (kept / "at_8.pt").read_bytes()
    assert not (kept / "at_32.pt").exists()
    stopped = load_checkpoint(kept / "last.pt")
    assert stopped["counters"]["transitions"] == 24
    # as if the stop had come between the step that reached 24 (and 10) and their kept files
    (kept / "at_24.pt").unlink()
    (kept / "at_10.pt").unlink()
    capsys.readouterr()
    # resumed without naming it again: the plan in the checkpoint asks for them still
    assert run_py.main(["--run-dir", str(run_dir), "--resume", "--no-progress"]) == 0
    assert load_checkpoint(kept / "at_32.pt")["counters"]["transitions"] == 32
    assert (kept / "at_8.pt").read_bytes() == at_8  # a count behind the checkpoint: untouched
    # 24 is the checkpoint's own step: kept from it; 10 is older: said, and not kept under a wrong name
    again = load_checkpoint(kept / "at_24.pt")
    assert again["counters"]["transitions"] == 24
    _tensors_equal(again["agent"]["actor"], stopped["agent"]["actor"])
    assert not (kept / "at_10.pt").exists()
    assert "--keep-at 10 is behind this run's checkpoint (24 transitions)" in capsys.readouterr().out


def test_ppo_keeps_what_a_run_of_that_many_transitions_ends_with(run_py, wp_cpu, tmp_path):
    from vkgrl_newton.agents.checkpoint import load_checkpoint

    def run(name, *extra):
        return run_py.main(["--method", "ppo", "--run-dir", str(tmp_path / name), "--eval-episodes", "0",
                            "--checkpoint-every", "1000", *TINY_PPO, *extra])

    assert run("short", "--total-steps", str(PER_ITERATION)) == 0
    assert run("long", "--total-steps", str(2 * PER_ITERATION), "--keep-at", str(PER_ITERATION)) == 0
    short = load_checkpoint(tmp_path / "short" / "checkpoints" / "last.pt")
    kept = load_checkpoint(tmp_path / "long" / "checkpoints" / f"at_{PER_ITERATION}.pt")
    assert kept["counters"]["transitions"] == PER_ITERATION
    _tensors_equal(short["agent"], kept["agent"])


@pytest.mark.parametrize("argv, message", [
    (["--keep-at", "50", "--total-steps", "40"], "--keep-at 50: past the run's --total-steps 40"),
    (["--keep-at", "40000"], "--keep-at 40000: past the run's --total-steps 30000"),  # the quick preset's
    (["--keep-at", "0"], "--keep-at"),
])
def test_keep_at_refuses_counts_it_cannot_keep(run_py, tmp_path, capsys, argv, message):
    with pytest.raises(SystemExit) as exc:
        run_py.main(["--method", "sac", "--run-dir", str(tmp_path / "r"), *TINY_RUN, *argv])
    assert exc.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "r").exists()  # refused before anything was made


def test_evaluate_py_scores_a_checkpoint_on_the_runs_own_evaluation_episodes(run_py, wp_cpu, tmp_path):
    """What the kept policies' learning curve rests on: train/evaluate.py --checkpoint with the run's worlds, episodes
    per world and eval seed plays the episodes of the run's final evaluation, whatever the run's seed (the
    construction seed of evaluate.py differs here), so that its points pair with metrics.json and the prior's."""
    import numpy as np

    run_dir = tmp_path / "run"
    assert run_py.main(["--method", "sac", "--run-dir", str(run_dir), "--eval-episodes", "2", "--total-steps", "16",
                        "--seed", "3", "--eval-seed", "77", *TINY_RUN]) == 0
    metrics = json.loads((run_dir / "metrics.json").read_text())
    evaluate_py = load_script("evaluate")
    out = tmp_path / "again.json"
    assert evaluate_py.main(["--checkpoint", str(run_dir / "checkpoints" / "last.pt"), "--num-envs", "2",
                             "--episodes", "2", "--eval-seed", "77", "--json", str(out),
                             "--cache-dir", str(tmp_path / "cache")]) == 0
    again = json.loads(out.read_text())
    assert len(again["per_episode"]) == len(metrics["per_episode"]) == 2
    # each names the processor that played its episodes (outcomes pair only on the same kind of CPU)
    from vkgrl_newton.runtime import cpu_model

    assert metrics["processor"] == again["processor"] and metrics["processor"].startswith(cpu_model())
    for a, b in zip(again["per_episode"], metrics["per_episode"]):
        assert a["world_success"] == b["world_success"]
        # the same float32 physics and policy on the same machine: equal up to float32 summation order over an
        # episode's steps (~1e-7 relative a step, a few hundred steps)
        np.testing.assert_allclose(a["world_contact_force"], b["world_contact_force"], rtol=1e-4, atol=1e-6)
