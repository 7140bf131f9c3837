"""--obs-history K (envs.history): the stacked input carries the last K (input, action) pairs of its own world,
newest first, aligned with the steps they came from; a world's history starts empty at its episode's first
step; the loop's bootstrap input of a time-out carries the history the episode ended with."""

from __future__ import annotations

import pytest
import torch

from vkgrl_newton.envs.history import ObservationHistory, stacked_width
from scripts import on_the_prior

E, W, A, K = 3, 4, 2, 3


def test_the_stack_is_the_last_k_pairs_newest_first_and_restarts_with_each_episode():
    h = ObservationHistory(E, W, A, K, "cpu")
    step_index = torch.zeros(E, dtype=torch.int32)
    inputs, actions = [], []
    for t in range(6):
        if t == 4:
            step_index[1] = 0  # world 1 starts a new episode at step 4
        x = torch.full((E, W), float(t)) + torch.arange(E)[:, None] * 100  # value: 100 world + step
        stacked = h.stack(x, step_index)
        assert stacked.shape == (E, stacked_width(W, A, K))
        assert torch.equal(stacked[:, :W], x)
        for e in range(E):
            start = 4 if (e == 1 and t >= 4) else 0  # the step its episode began
            for j in range(K):  # pair j: the step t - 1 - j, if it belongs to this episode
                pair = stacked[e, W + j * (W + A): W + (j + 1) * (W + A)]
                s = t - 1 - j
                if s >= start:
                    assert torch.equal(pair[:W], inputs[s][e]) and torch.equal(pair[W:], actions[s][e]), (t, e, j)
                else:
                    assert torch.equal(pair, torch.zeros(W + A)), (t, e, j)
        a = torch.full((E, A), -float(t)) - torch.arange(E)[:, None] * 10
        h.push(x, a)
        inputs.append(x)
        actions.append(a)
        step_index += 1


def test_without_step_index_the_history_is_kept_for_a_time_outs_bootstrap():
    h = ObservationHistory(E, W, A, 1, "cpu")
    h.push(torch.ones(E, W), torch.ones(E, A))
    ended = h.stack(torch.zeros(E, W))  # the final state: the episode's history, not cleared
    assert torch.equal(ended[:, W:], torch.ones(E, W + A))
    fresh = h.stack(torch.zeros(E, W), torch.zeros(E, dtype=torch.int32))  # the new episode's first input
    assert torch.equal(fresh[:, W:], torch.zeros(E, W + A))
    with pytest.raises(ValueError, match="k=0"):
        ObservationHistory(E, W, A, 0, "cpu")


def test_the_runs_width_is_the_stacks_and_the_option_is_refused_where_it_cannot_hold(tmp_path):
    from vkgrl_newton.run.config import ConfigError, build_parser
    from vkgrl_newton.run.resolve import resolve

    def run(*argv):
        return resolve(build_parser(), [*on_the_prior(list(argv)), "--device", "cpu", "--run-dir", str(tmp_path / "r")]).config

    cfg = run("--method", "sac", "--obs-history", "2", "--cpu-matmul", "torch")
    assert cfg.obs_dim == stacked_width(8, 4, 2) == 8 + 2 * 12 and cfg.meta()["obs_history"] == 2
    timed = run("--method", "kgrl", "--obs-history", "2", "--kgrl-time-action", "2", "--cpu-matmul", "torch")
    assert timed.obs_dim == stacked_width(9, 5, 2)
    with pytest.raises(ConfigError, match="--obs-history is for the SAC methods"):
        run("--method", "ppo", "--obs-history", "2")
    with pytest.raises(ConfigError, match=r"in \[0, 16\]"):
        run("--method", "sac", "--obs-history", "17")


@pytest.mark.slow
def test_a_history_run_trains_and_its_checkpoint_evaluates(wp_cpu, tmp_path):
    import json

    from scripts import TINY_RUN, load_script

    run_dir = tmp_path / "hist"
    tiny = [*TINY_RUN, "--cpu-matmul", "torch"]
    assert load_script("run").main(["--method", "sac", "--obs-history", "2", "--run-dir", str(run_dir),
                                    "--total-steps", "16", "--eval-episodes", "1", *tiny]) == 0
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["obs_history"] == 2 and metrics["obs_dim"] == 32 and metrics["episodes"] == 2
    from vkgrl_newton.agents.checkpoint import load_checkpoint

    buf = load_checkpoint(run_dir / "checkpoints" / "last.pt")["agent"]["buffer"]
    obs, act, nxt = buf["obs"], buf["action"], buf["next_obs"]  # rows: 2 worlds per env step, in order
    assert obs.shape == (16, 32) and torch.equal(obs[:2, 8:], torch.zeros(2, 24))  # the episode's first input
    for t in range(1, 8):  # the loop stored each input with its own world's previous (input, action)
        for e in range(2):
            row, prev = 2 * t + e, 2 * (t - 1) + e
            assert torch.equal(obs[row, 8:20], torch.cat([obs[prev, :8], act[prev]])), (t, e)
            assert torch.equal(obs[row, 20:32], obs[prev, 8:20]), (t, e)  # and the one before
            assert torch.equal(nxt[prev], obs[row]), (t, e)  # the bootstrap input is the next input
    out = tmp_path / "eval.json"
    assert load_script("evaluate").main(["--checkpoint", str(run_dir / "checkpoints" / "last.pt"), "--num-envs", "2",
                                         "--episodes", "1", "--device", "cpu", "--json", str(out)]) == 0
