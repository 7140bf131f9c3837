"""train/run.py's overlapped loop (--overlap: the env steps in a worker thread while the previous
step's SAC update runs) against the serial loop (--no-overlap): the same transitions when nothing
is learned, a deterministic run with learning, a policy exactly one update old at every action,
and a worker's exception surfacing with its traceback."""

import pytest
import torch
from scripts import load_script

TINY = ["--num-envs", "2", "--device", "cpu", "--no-progress", "--eval-episodes", "0", "--sac", "batch_size=8",
        "--sac", "gradient_steps=2", "--sac", "hidden_dims=16,16", "--sac", "buffer_size=1000"]


@pytest.fixture(scope="module")
def run_py():
    return load_script("run")


def _run(run_py, tmp_path, name, *extra, total=40, learning_starts=8):
    from vkgrl_newton.agents.checkpoint import load_checkpoint

    run_dir = tmp_path / name
    assert run_py.main(["--method", "sac", "--run-dir", str(run_dir), "--total-steps", str(total),
                        "--sac", f"learning_starts={learning_starts}", *TINY, *extra]) == 0
    return load_checkpoint(run_dir / "checkpoints" / "last.pt")


def test_without_updates_both_loops_store_the_same_transitions(run_py, wp_cpu, tmp_path):
    serial = _run(run_py, tmp_path, "serial", "--no-overlap", total=24, learning_starts=10_000)
    overlap = _run(run_py, tmp_path, "overlap", "--overlap", total=24, learning_starts=10_000)
    a, b = serial["agent"]["buffer"], overlap["agent"]["buffer"]
    assert a["size"] == b["size"] == 24
    # bitwise: two runs of the same computation on this machine, one after the other (same-machine determinism)
    for key in ("obs", "action", "reward", "next_obs"):
        assert torch.equal(a[key], b[key]), key
    assert serial["agent"]["counters"][2] == overlap["agent"]["counters"][2] == 0  # nothing learned


@pytest.mark.slow
def test_overlap_is_deterministic_and_acts_one_update_late(run_py, wp_cpu, tmp_path, monkeypatch):
    from vkgrl_newton.agents.sac import SAC

    versions: list[int] = []
    explore = SAC.explore

    def recording_explore(self, obs):
        versions.append(self.num_updates)  # the policy version that draws this action
        return explore(self, obs)

    monkeypatch.setattr(SAC, "explore", recording_explore)
    serial = _run(run_py, tmp_path, "serial", "--no-overlap")
    serial_versions, versions[:] = list(versions), []
    first = _run(run_py, tmp_path, "overlap1", "--overlap")
    overlap_versions, versions[:] = list(versions), []
    second = _run(run_py, tmp_path, "overlap2", "--overlap")
    assert versions == overlap_versions
    # serial: the action of step k comes after the update of step k-1; overlapped: after that of
    # step k-2 (the update of step k-1 runs while step k does)
    assert len(serial_versions) == len(overlap_versions) == 20
    assert overlap_versions[0] == 0 and overlap_versions[1:] == serial_versions[:-1]
    assert serial_versions[-1] > serial_versions[4] > 0  # learning happened in the window
    # the same gradient steps in all (the last step's update runs after the loop)
    assert first["agent"]["counters"] == second["agent"]["counters"] == serial["agent"]["counters"]
    # bitwise: two overlapped runs on this machine (same-machine determinism; never compared across CPUs)
    for name in ("actor", "critic", "critic_target"):
        for k, v in first["agent"][name].items():
            assert torch.equal(v, second["agent"][name][k]), (name, k)
    assert any(not torch.equal(v, serial["agent"]["actor"][k]) for k, v in first["agent"]["actor"].items())
    for key in ("obs", "action", "reward"):
        assert torch.equal(first["agent"]["buffer"][key], second["agent"]["buffer"][key]), key


def test_a_worker_exception_stops_the_run_with_its_traceback(run_py, wp_cpu, tmp_path, monkeypatch):
    from vkgrl_newton.envs.assembly_env import AssemblyEnv

    calls = {"n": 0}
    real_step = AssemblyEnv.step

    def failing_step(self, actions):
        calls["n"] += 1
        if calls["n"] == 5:
            raise RuntimeError("physics exploded in the worker")
        return real_step(self, actions)

    monkeypatch.setattr(AssemblyEnv, "step", failing_step)
    with pytest.raises(RuntimeError, match="exploded in the worker") as exc:
        _run(run_py, tmp_path, "failing", "--overlap")
    assert any(entry.name == "failing_step" for entry in exc.traceback)  # the worker's frame is in it
    assert calls["n"] == 5  # stopped there: no further step was submitted
