"""KMP time as an action (KGRLActionPath(time_steps=k), --kgrl-time-action): a_t moves the prior's query by
1 + round(k a_t) control steps, clamped to the tables; a = 0 is still the prior, step by step and bitwise; a new
episode starts the query at 0; the query's phase is the policy's last input (the final one at a time-out)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from vkgrl_newton.kmp.demos import synthetic_demos
from vkgrl_newton.kmp.prior import fit_prior
from vkgrl_newton.rotations import quat_from_euler_xyz
from vkgrl_newton.tasks import get_task
from scripts import on_the_prior

E, D = 5, 4


@pytest.fixture(scope="module")
def tables():
    return fit_prior(synthetic_demos("PegInsert", 6, action_dim=6, seed=0), action_dim=D)


class StepEnv(SimpleNamespace):
    """A stand-in env with the attributes the action path reads; step_pose records the command and
    counts the control step (a world reaching the episode's end restarts at step 0, as the env's reset)."""

    def step_pose(self, pos, quat):
        self.commands.append(pos.clone())
        self.step_index.copy_(torch.where(self.step_index + 1 >= self.max_episode_length, 0, self.step_index + 1))
        return None


def make_env(seed: int = 0) -> StepEnv:
    g = torch.Generator().manual_seed(seed)
    spec = get_task("PegInsert")
    yaw = torch.rand(E, generator=g) * 6.28
    return StepEnv(task=spec, num_envs=E, num_actions=D, max_episode_length=spec.episode_steps,
                   tdev=torch.device("cpu"), device="cpu", commands=[],
                   step_index=torch.zeros(E, dtype=torch.int32),
                   target_frame_pos_w=torch.rand(E, 3, generator=g) - 0.5,
                   ref_quat_w=quat_from_euler_xyz(torch.full_like(yaw, 3.14159), torch.zeros_like(yaw), yaw)
                   .float().contiguous())


def test_a_zero_time_action_is_the_prior_step_by_step(wp_cpu, tables):
    from vkgrl_newton.envs.kgrl_action import KGRLActionPath

    plain_env, timed_env = make_env(), make_env()
    plain, timed = KGRLActionPath(tables, plain_env), KGRLActionPath(tables, timed_env, time_steps=3)
    assert (plain.action_dim, timed.action_dim) == (D, D + 1)
    g = torch.Generator().manual_seed(1)
    for n in range(tables.n_steps + 20):  # past an episode's end: the query restarts with the episode
        a = torch.rand(E, D, generator=g) * 2 - 1
        plain.step(a)
        timed.step(torch.cat([a, torch.zeros(E, 1)], -1))
        assert torch.equal(plain_env.commands[-1], timed_env.commands[-1]), n
        assert torch.equal(timed.query_index, timed_env.step_index)
        # one float32 division against float64's: relative error <= 2^-24 ~ 6e-8
        np.testing.assert_allclose(timed.query_phase().squeeze(-1).numpy(),
                                   timed_env.step_index.numpy() / tables.n_steps, rtol=1e-6)
    assert plain.query_phase() is None


def test_the_time_action_moves_the_query_by_the_commanded_amount(wp_cpu, tables):
    from vkgrl_newton.envs.kgrl_action import KGRLActionPath

    env, k = make_env(), 4
    path = KGRLActionPath(tables, env, time_steps=k)
    a_t = torch.tensor([-1.0, -0.5, 0.1, 0.5, 1.0])  # 1 + round(4 a_t): -3, -1, 1, 3, 5 (round half to even)
    want = np.zeros(E, dtype=np.int64)
    mean = tables.mean.numpy()
    for n in range(12):
        env.step_index.fill_(n + 1)  # mid-episode: no reset
        path.step(torch.cat([torch.zeros(E, D), a_t[:, None]], -1))
        step_cmd = env.commands[-1]
        # the command was the prior's mean (zeta = 0) at the query held before this step
        # the kernel's float32 target + eta (|.| < 1 m), less the target again: two roundings of 6e-8 m at most
        np.testing.assert_allclose(step_cmd.numpy() - env.target_frame_pos_w.numpy(), mean[want, :3], atol=1e-6)
        want = np.clip(want + 1 + np.round(k * a_t.numpy()).astype(np.int64), 0, tables.n_steps)
        assert path.query_index.tolist() == want.tolist()
        np.testing.assert_allclose(path.query_phase(final=True).squeeze(-1).numpy(), want / tables.n_steps,
                                   rtol=1e-6)  # one float32 division: <= u32 / 2 = 6e-8 relative, 1e-6 with margin
    assert want[0] == 0 and want[-1] == 12 * 5  # clamped at the start; running ahead


def test_a_new_episode_restarts_the_query_and_a_time_out_bootstraps_from_where_it_ended(wp_cpu, tables):
    from vkgrl_newton.envs.evaluation import kgrl_observation
    from vkgrl_newton.envs.kgrl_action import KGRLActionPath

    env = make_env()
    path = KGRLActionPath(tables, env, time_steps=2)
    env.step_index.fill_(env.max_episode_length - 1)  # every world at its last step
    path.query_index.fill_(7)
    path.step(torch.cat([torch.zeros(E, D), torch.ones(E, 1)], -1))  # +3 each, then the env resets them
    assert env.step_index.tolist() == [0] * E
    assert path.query_index.tolist() == [0] * E  # the new episode starts the prior again
    x = torch.zeros(E, 8)
    np.testing.assert_allclose(kgrl_observation(x, path)[:, -1].numpy(), 0.0)
    np.testing.assert_allclose(kgrl_observation(x, path, final=True)[:, -1].numpy(), 10 / tables.n_steps,
                               rtol=1e-6)  # one float32 division: <= u32 / 2 = 6e-8 relative, 1e-6 with margin
    assert torch.equal(kgrl_observation(x, None), x)


def test_bad_time_steps_and_the_runs_refusals(wp_cpu, tables, tmp_path):
    from vkgrl_newton.envs.kgrl_action import KGRLActionPath
    from vkgrl_newton.run.config import ConfigError, build_parser
    from vkgrl_newton.run.resolve import resolve

    with pytest.raises(ValueError, match="time_steps"):
        KGRLActionPath(tables, make_env(), time_steps=-1)
    with pytest.raises(ValueError, match="shape"):
        KGRLActionPath(tables, make_env(), time_steps=2).pose(torch.zeros(E, D))

    def run(*argv):
        return resolve(build_parser(), [*on_the_prior(list(argv)), "--device", "cpu", "--run-dir", str(tmp_path / "r")])

    for method in ("sac", "kgrl_ppo"):
        with pytest.raises(ConfigError, match="--kgrl-time-action is for the kgrl methods on SAC"):
            run("--method", method, "--kgrl-time-action", "2")
    with pytest.raises(ConfigError, match=r"in \[0, 10\]"):
        run("--method", "kgrl", "--kgrl-time-action", "11")
    cfg = run("--method", "kgrl", "--kgrl-time-action", "3", "--cpu-matmul", "torch").config
    assert cfg.kgrl_time_action == 3 and cfg.meta()["kgrl_time_action"] == 3
    assert (cfg.obs_dim, cfg.agent_action_dim) == (8 + 1, D + 1)


@pytest.mark.slow
def test_a_time_action_run_trains_evaluates_its_prior_and_its_checkpoint(wp_cpu, tmp_path):
    import json

    from scripts import TINY_RUN, load_script

    demos = tmp_path / "demos.npz"
    synthetic_demos("PegInsert", 8, action_dim=6, seed=1).save(demos)
    run_dir = tmp_path / "timed"
    tiny = [*TINY_RUN, "--sac", "prior_rollouts=8", "--cpu-matmul", "torch"]
    assert load_script("run").main(on_the_prior(["--method", "kgrl", "--kgrl-time-action", "2", "--demos", str(demos),
                                                 "--run-dir", str(run_dir), "--total-steps", "24", "--eval-episodes",
                                                 "1", "--cache-dir", str(tmp_path / "cache"), *tiny])) == 0
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["kgrl_time_action"] == 2 and metrics["obs_dim"] == 9 and "prior_eval" in metrics
    out = tmp_path / "eval.json"
    assert load_script("evaluate").main(["--checkpoint", str(run_dir / "checkpoints" / "last.pt"), "--num-envs", "2",
                                         "--episodes", "1", "--device", "cpu", "--json", str(out),
                                         "--cache-dir", str(tmp_path / "cache")]) == 0
    assert json.loads(out.read_text())["episodes"] == 2
