"""Tests of the learning pipeline: the KGRL action path against a float64 reference, and
`train/run.py` end to end (both methods, checkpoints, kill-and-resume, bad input).

The run tests use 2 worlds and a tiny SAC (--sac overrides) so that they take seconds; the
KGRL run uses synthetic demonstrations (--demos), so nothing is recorded in the simulator.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scripts import TINY_RUN, load_script
import torch

from quat_ref import q_to_matrix
from vkgrl_newton.kmp.demos import synthetic_demos
from vkgrl_newton.rotations import quat_from_euler_xyz
from vkgrl_newton.kmp.prior import fit_prior
from vkgrl_newton.tasks import get_task

TINY = TINY_RUN


def load_run_module():
    return load_script("run")


@pytest.fixture(scope="module")
def run_py():
    return load_run_module()


@pytest.fixture(scope="module")
def peg_demos_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("demos") / "peg_synthetic.npz"
    synthetic_demos("PegInsert", 8, action_dim=6, seed=1).save(path)
    return path


# ---------------------------------------------------------------------------------------------
# KGRL action path (no simulator: a stand-in env with the attributes the path reads)


def fake_env(num_envs: int, action_dim: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    spec = get_task("PegInsert")
    yaw = torch.rand(num_envs, generator=g) * 2 * math.pi
    return SimpleNamespace(
        task=spec, num_envs=num_envs, num_actions=action_dim, max_episode_length=spec.episode_steps,
        tdev=torch.device("cpu"), device="cpu",
        step_index=torch.randint(0, spec.episode_steps + 5, (num_envs,), generator=g, dtype=torch.int32),
        target_frame_pos_w=(torch.rand(num_envs, 3, generator=g) - 0.5),
        # q(pi, 0, yaw): gripper pointing down, any yaw (the path passes it through)
        ref_quat_w=quat_from_euler_xyz(torch.full_like(yaw, math.pi), torch.zeros_like(yaw), yaw).float().contiguous(),
    )


def rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    """Rodrigues, float64."""
    theta = np.linalg.norm(r)
    if theta < 1e-12:
        return np.eye(3)
    k = r / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * kx + (1 - math.cos(theta)) * kx @ kx


@pytest.mark.parametrize("action_dim", [4, 6])
def test_kgrl_action_path_matches_float64_reference(wp_cpu, action_dim):
    from vkgrl_newton.envs.kgrl_action import KGRLActionPath

    tables = fit_prior(synthetic_demos("PegInsert", 6, action_dim=6, seed=0), action_dim=action_dim)
    env = fake_env(7, action_dim)
    path = KGRLActionPath(tables, env)
    g = torch.Generator().manual_seed(3)
    actions = torch.rand(7, action_dim, generator=g) * 2.4 - 1.2  # some outside [-1, 1]: clamped
    pos, quat = path.pose(actions)
    spec = env.task
    mean, gain = tables.mean.numpy(), tables.gain.numpy()
    for e in range(7):
        a = np.clip(actions[e].double().numpy(), -1, 1)
        zeta = np.zeros(6)
        zeta[:3] = spec.w_pos * a[:3]
        if action_dim == 4:
            zeta[5] = spec.w_rot * a[3]
        else:
            zeta[3:] = spec.w_rot * a[3:]
        n = min(int(env.step_index[e]), tables.n_steps)
        eta = mean[n] + gain[n] @ zeta
        want_pos = env.target_frame_pos_w[e].double().numpy() + eta[:3]
        want_rot = q_to_matrix(env.ref_quat_w[e].double().numpy()) @ rotvec_to_matrix(eta[3:])
        # float32 path (target + m + B zeta, positions < 1 m: ulp 6e-8, ~5e-7 observed worst) against float64: 2e-6
        # bounds a few ulp of each of the ~6 float32 additions and the quaternion's rounding with margin
        np.testing.assert_allclose(pos[e].numpy(), want_pos, atol=2e-6)
        np.testing.assert_allclose(q_to_matrix(quat[e].double().numpy()), want_rot, atol=2e-6)
        if action_dim == 4:  # roll and pitch stay at the reference: the gripper axis points down
            np.testing.assert_allclose(q_to_matrix(quat[e].double().numpy())[:, 2], [0, 0, -1], atol=1e-6)
    # the path reads the env's step counter in place (views, not copies)
    env.step_index.zero_()
    pos0, _ = path.pose(torch.zeros(7, action_dim))
    np.testing.assert_allclose(pos0.numpy(), (env.target_frame_pos_w + tables.mean[0, :3].float()).numpy(), atol=1e-6)


def test_kgrl_action_path_rejects_mismatched_tables(wp_cpu):
    from vkgrl_newton.envs.kgrl_action import KGRLActionPath

    tables6 = fit_prior(synthetic_demos("PegInsert", 6, action_dim=6, seed=0), action_dim=6)
    with pytest.raises(ValueError, match="6D"):
        KGRLActionPath(tables6, fake_env(3, 4))
    env = fake_env(3, 6)
    env.max_episode_length = 225
    with pytest.raises(ValueError, match="steps"):
        KGRLActionPath(tables6, env)
    with pytest.raises(ValueError, match="shape"):
        KGRLActionPath(tables6, fake_env(3, 6)).pose(torch.zeros(2, 6))


def test_kgrl_action_path_applies_both_reach_floors(wp_cpu):
    """reach_floor (x, y) and reach_floor_z (z) lift those axes' reach to the floors (brute force over the
    action corners is test_prior_learning's); a = 0 still commands the prior's mean."""
    from vkgrl_newton.envs.kgrl_action import KGRLActionPath
    from vkgrl_newton.kmp.tables import null_space_reach

    tables = fit_prior(synthetic_demos("PegInsert", 6, action_dim=6, seed=0), action_dim=4)
    env = fake_env(5, 4)
    w6 = [env.task.w_pos] * 3 + [env.task.w_rot] * 3
    path = KGRLActionPath(tables, env, reach_floor=2e-3, reach_floor_z=10e-3)
    before, after = null_space_reach(tables.gain, w6).numpy(), null_space_reach(path.tables.gain, w6).numpy()
    # float64 tables: as test_prior_learning's brute-force floor test, a few ulp (~1e-15 relative) per reach
    assert (before[:, 2] < 10e-3).any() and (before[:, :2] < 2e-3).any()  # both floors bind somewhere
    np.testing.assert_allclose(after[:, :2], np.maximum(before[:, :2], 2e-3), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(after[:, 2], np.maximum(before[:, 2], 10e-3), rtol=1e-9, atol=1e-15)
    pos0, _ = path.pose(torch.zeros(5, 4))
    n = env.step_index.long().clamp(max=tables.n_steps)
    # float32 kernel: positions < 1 m (ulp 6e-8) through a few additions; atol 1e-6 as the float64 reference test above
    np.testing.assert_allclose(pos0.numpy(), (env.target_frame_pos_w + tables.mean[n, :3].float()).numpy(), atol=1e-6)
    # the seat press (--kgrl-seat-press) on top: a = 0 commands the pressed mean (with_seat_press's own test checks
    # the ramp); the floors' gains are kept
    pressed = KGRLActionPath(tables, env, reach_floor=2e-3, reach_floor_z=10e-3, seat_press=5e-3)
    assert torch.equal(pressed.tables.gain, path.tables.gain) and not torch.equal(pressed.tables.mean, path.tables.mean)
    pos1, _ = pressed.pose(torch.zeros(5, 4))
    np.testing.assert_allclose(pos1.numpy(), (env.target_frame_pos_w + pressed.tables.mean[n, :3].float()).numpy(),
                               atol=1e-6)


def test_spiral_offset_is_archimedean_at_the_given_speed():
    """r = b theta (b = pitch / 2 pi), the angle is theta, a turn adds one pitch, and the exact arc length
    s(theta) = b / 2 (theta sqrt(1 + theta^2) + asinh theta) advances by ~speed per step."""
    from vkgrl_newton.envs.evaluation import spiral_offset

    pitch, speed = 1.2e-3, 0.3e-3
    b = pitch / (2 * math.pi)
    k = torch.arange(0, 200, dtype=torch.float64)
    off = spiral_offset(k, pitch, speed)
    th = np.sqrt(2 * speed * k.numpy() / b)
    np.testing.assert_allclose(off.norm(dim=-1).numpy(), b * th, rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(np.cos(th) * b * th, off[:, 0].numpy(), rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(np.sin(th) * b * th, off[:, 1].numpy(), rtol=1e-12, atol=1e-18)
    k_turn = torch.tensor([50.0, 0.0], dtype=torch.float64)  # k one turn later: theta + 2 pi
    k_turn[1] = b * (math.sqrt(2 * speed * 50 / b) + 2 * math.pi) ** 2 / (2 * speed)
    r = spiral_offset(k_turn, pitch, speed).norm(dim=-1)
    assert abs(float(r[1] - r[0]) - pitch) < 1e-15
    s = b / 2 * (th * np.sqrt(1 + th ** 2) + np.arcsinh(th))
    per_step = np.diff(s)[50:]  # theta > 5: the approximation's error ~ 1 / (2 theta^2) < 2 %
    assert np.all(np.abs(per_step / speed - 1) < 0.02)


def test_kmp_search_policy_keeps_the_prior_until_blocked_then_searches_and_settles(wp_cpu):
    """Three worlds of observations: one descending to the prior's seat (a = 0 throughout), one blocked
    20 mm high from step 30 (a = 0 until n_min, then a light press and the spiral, checked against a
    float64 computation of eta = m[n] + G[n] zeta), one that drops 0.5 mm while searching (x, y frozen,
    z the prior's from then on). A world whose episode restarts (step 0) starts over alone."""
    from vkgrl_newton.envs.evaluation import KMPSearchPolicy, SearchParams, spiral_offset

    tables = fit_prior(synthetic_demos("PegInsert", 6, action_dim=6, seed=0), action_dim=4)
    env = fake_env(3, 4)
    env.episode_length_buf = torch.zeros(3, dtype=torch.long)
    p = SearchParams()
    policy = KMPSearchPolicy.with_floors(tables, env, p)
    mean = policy.path.tables.mean.numpy()  # the floored tables: m unchanged, G lifted
    gain = policy.path.tables.gain.numpy()
    w = np.array([env.task.w_pos] * 3)
    seat = mean[-1, 2]
    high = seat + 20e-3
    drop_at = 75
    N = env.max_episode_length
    blocked_at = None
    held = None
    unclipped = settled = 0
    for n in range(N):
        env.episode_length_buf.fill_(n)
        rel = np.zeros((3, 3))
        rel[0] = mean[n, :3]  # follows the prior down
        rel[1] = mean[n, :3] if n < 30 else [mean[100, 0], mean[100, 1], high]  # held over the face from 30
        rel[2] = rel[1]
        if n >= drop_at:
            rel[2, 2] = high - 0.5e-3
        obs = torch.zeros(3, 8)
        obs[:, 0] = n / N
        obs[:, 1:4] = torch.from_numpy(rel).float()
        a = policy.actions(env, {"policy": obs}).double().numpy()
        assert a.shape == (3, 4) and np.all(a[:, 3] == 0)  # yaw action 0
        assert np.all(a[0] == 0)
        if n < p.n_min:
            assert np.all(a == 0), n
            continue
        if n == p.n_min:  # stalled and high since step 30: found blocked at the first step allowed
            assert policy.since.tolist() == [-1, p.n_min, p.n_min] and not bool(policy.found.any())
        if n == drop_at:
            assert policy.found.tolist() == [False, False, True]
        blocked_at = p.n_min
        eta = mean[n, :3] + np.einsum("eij,ej->ei", gain[n][None, :3, :3], a[:, :3] * w)
        rel32 = obs[:, 1:4].double().numpy()  # what the policy saw
        centre = mean[100, :2]
        sp = centre + spiral_offset(torch.tensor(float(n - blocked_at), dtype=torch.float64), 1.2e-3, 0.3e-3).numpy()
        want1 = np.r_[sp + 1.0 * (sp - rel32[1, :2]), rel32[1, 2] - 1e-3]
        if np.all(np.abs(a[1, :3]) < 1):
            # the policy rounds obs (|rel| < 0.05 m) and actions (|G w a| < 0.03 m) to float32: ~6e-8 relative,
            # ~5e-9 m; atol 1e-6 m leaves two orders of margin on either CPU
            np.testing.assert_allclose(eta[1], want1, atol=1e-6)
            unclipped += 1
        else:
            assert np.all(np.sign(a[1, :3]) == np.sign(np.linalg.solve(gain[n][:3, :3], want1 - mean[n, :3])))
        if n < drop_at:
            np.testing.assert_array_equal(a[2], a[1])
            continue
        if held is None:  # the x, y wanted when it dropped, kept; z the prior's
            held = sp + 1.0 * (sp - rel32[2, :2])
        want2 = np.r_[held, mean[n, 2]]
        if np.all(np.abs(a[2, :3]) < 1):
            np.testing.assert_allclose(eta[2], want2, atol=1e-6)  # the same float32 roundings as above
            settled += 1
        else:
            assert np.all(np.sign(a[2, :3]) == np.sign(np.linalg.solve(gain[n][:3, :3], want2 - mean[n, :3])))
    assert unclipped >= 5 and settled >= 5, (unclipped, settled)  # both cases exercised, clipped and not
    # world 2 alone starts a new episode (a blown-up world resets alone; no reset() call in training): only its
    # search starts over, and the others keep theirs
    env.episode_length_buf = torch.tensor([N - 1, N - 1, 0])
    a = policy.actions(env, {"policy": obs})
    assert policy.since.tolist() == [-1, p.n_min, -1] and policy.found.tolist() == [False, False, False]
    assert torch.equal(a[2], torch.zeros(4)) and bool((a[1] != 0).any())


# ---------------------------------------------------------------------------------------------
# train/run.py


def read_scalars(tb_dir: Path) -> dict:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(tb_dir))
    acc.Reload()
    return {tag: [e.value for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


@pytest.mark.slow
def test_run_sac_checkpoint_kill_and_resume(run_py, wp_cpu, tmp_path, monkeypatch):
    from vkgrl_newton.agents.checkpoint import load_checkpoint
    from vkgrl_newton.envs.assembly_env import AssemblyEnv

    run_dir = tmp_path / "sac"
    # the overlapped loop (the CPU default, named here): the interrupt is raised in its worker thread
    base = ["--method", "sac", "--run-dir", str(run_dir), "--eval-episodes", "0", "--checkpoint-every", "100",
            "--overlap", *TINY]
    # "kill" the run on its 9th env step: it checkpoints what it has (16 transitions) and exits 130
    calls = {"n": 0}
    real_step = AssemblyEnv.step

    def killing_step(self, actions):
        calls["n"] += 1
        if calls["n"] == 9:
            raise KeyboardInterrupt
        return real_step(self, actions)

    monkeypatch.setattr(AssemblyEnv, "step", killing_step)
    assert run_py.main([*base, "--total-steps", "40"]) == 130
    monkeypatch.setattr(AssemblyEnv, "step", real_step)
    ckpt_path = run_dir / "checkpoints" / "last.pt"
    killed = load_checkpoint(ckpt_path)
    assert killed["counters"]["transitions"] == 16 and killed["counters"]["env_steps"] == 8
    assert killed["agent"]["counters"][2] > 0  # learning started (learning_starts 8)
    config = json.loads((run_dir / "config.json").read_text())
    assert config["method"] == "sac" and config["sac"]["batch_size"] == 8
    assert config["sac"]["warmup"] == "uniform" and config["sac"]["actor_init_std"] is None
    # the CPU matmul library that ran ("auto" resolved before the run), in config.json and the checkpoint
    backend = config["sac"]["cpu_matmul"]
    assert backend in ("onednn", "torch") and killed["meta"]["sac"]["cpu_matmul"] == backend

    # a directory that holds a run is never reused without --resume
    with pytest.raises(SystemExit):
        run_py.main([*base, "--total-steps", "40"])

    # resume with nothing left to do: same counters and weights as the checkpoint
    assert run_py.main(["--run-dir", str(run_dir), "--resume", "--total-steps", "16", "--eval-episodes", "0",
                        "--no-progress"]) == 0
    same = load_checkpoint(ckpt_path)
    assert same["counters"]["transitions"] == 16
    for name in ("actor", "critic", "critic_target"):
        for k, v in killed["agent"][name].items():
            assert torch.equal(v, same["agent"][name][k]), (name, k)

    # resume to 40 transitions: counters continue, weights move
    assert run_py.main(["--run-dir", str(run_dir), "--resume", "--total-steps", "40", "--eval-episodes", "0",
                        "--no-progress"]) == 0
    done = load_checkpoint(ckpt_path)
    assert done["counters"]["transitions"] == 40 and done["counters"]["env_steps"] == 20
    assert done["agent"]["counters"][2] > same["agent"]["counters"][2]
    assert any(not torch.equal(v, done["agent"]["actor"][k]) for k, v in same["agent"]["actor"].items())
    scalars = read_scalars(run_dir / "tb")
    assert "train/critic_loss" in scalars and all(math.isfinite(v) for v in scalars["train/critic_loss"])
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["training"]["transitions"] == 40
    assert metrics["cpu_matmul"] == backend == load_checkpoint(ckpt_path)["meta"]["sac"]["cpu_matmul"]  # kept on resume
    other = "torch" if backend == "onednn" else "onednn"
    with pytest.raises(SystemExit) as exc:  # never changed silently
        run_py.main(["--run-dir", str(run_dir), "--resume", "--total-steps", "48", "--no-progress", "--cpu-matmul", other])
    assert exc.value.code == 2
    assert json.loads((run_dir / "metrics_at_16.json").read_text())["training"]["transitions"] == 16  # kept aside
    assert json.loads((run_dir / "config_at_16.json").read_text())["total_steps"] == 16  # the earlier plan
    assert json.loads((run_dir / "config.json").read_text())["total_steps"] == 40

    # a finished run resumed without a larger --total-steps says so and changes nothing
    before = {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()} | {"ckpt": ckpt_path.read_bytes()}
    assert run_py.main(["--run-dir", str(run_dir), "--resume", "--no-progress", "--eval-episodes", "3"]) == 0
    assert {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()} | {"ckpt": ckpt_path.read_bytes()} == before

    # a damaged checkpoint is a clear error, never a silent restart
    data = ckpt_path.read_bytes()
    ckpt_path.write_bytes(data[: len(data) // 2])
    with pytest.raises(SystemExit) as exc:
        run_py.main(["--run-dir", str(run_dir), "--resume", "--no-progress"])
    assert exc.value.code == 2


@pytest.mark.slow
def test_run_kgrl_end_to_end_with_evaluation(run_py, wp_cpu, tmp_path, peg_demos_file):
    run_dir = tmp_path / "kgrl"
    code = run_py.main(["--method", "kgrl", "--run-dir", str(run_dir), "--demos", str(peg_demos_file),
                        "--total-steps", "16", "--eval-episodes", "1", *TINY,
                        "--sac", "prior_rollouts=8"])  # (the recipe's 4 800: the learner acts in half of this run)
    assert code == 0
    metrics = json.loads((run_dir / "metrics.json").read_text())
    for key in ("success_rate", "success_rate_any", "mean_contact_force", "peak_contact_force",
                "time_to_first_success_s", "mean_episode_reward", "env_steps_per_s", "physics_resets", "ik_failures"):
        assert key in metrics
    assert metrics["training"]["ik_failures"] == 0 and metrics["ik_failures"] == 0
    # the run records exactly the prior it learned with
    from vkgrl_newton.cache import file_sha256
    from vkgrl_newton.kmp.prior import KMP_BETA, KMP_L, KMP_LAMBDA

    # (the quick preset's recipe on PegInsert Factory 4D, residual: its reach floors and seat press in the prior's
    # record)
    assert metrics["prior"] == {"demos": str(peg_demos_file), "demos_sha256": file_sha256(peg_demos_file),
                                "lam": KMP_LAMBDA, "beta": KMP_BETA, "l": KMP_L, "num_demos": 8,
                                "reach_floor_mm": 4.0, "reach_floor_z_mm": 25.0, "seat_press_mm": 5.0}
    assert metrics["episodes"] == 2 and metrics["method"] == "kgrl"
    config = json.loads((run_dir / "config.json").read_text())
    sac = config["sac"]  # the recipe's SAC fields over the preset, TINY's over both
    assert (config["kgrl_recipe"], config["kgrl_base"], config["kgrl_residual_scale"]) == ("residual", "centre_search",
                                                                                            0.2)
    from vkgrl_newton.run.presets import KGRL_RECIPES

    assert {k: sac[k] for k in KGRL_RECIPES["residual"]["sac"]} == \
        {**KGRL_RECIPES["residual"]["sac"], "prior_rollouts": 8} and sac["batch_size"] == 8
    assert (sac["log_std_bound"], sac["prior_anchor"], sac["critic_layer_norm"], sac["prior_ratio"]) == \
        ("tanh", True, True, 0.5)  # the recipe, spelled out
    assert (sac["warmup"], sac["actor_init_std"], sac["log_std_max"]) == ("policy", 0.1, -1.2)
    assert 0.0 <= metrics["success_rate"] <= 1.0 and metrics["mean_contact_force"] >= 0.0
    # the KMP tables were fitted beside the demonstrations and are reused
    assert peg_demos_file.with_name(peg_demos_file.stem + ".kmp4d.npz").exists()


def recorded_adds(monkeypatch) -> list:
    """(transitions so far, action, prior-buffer rows) of every SAC.add, which still runs."""
    from vkgrl_newton.agents.sac import SAC

    stored = []

    def add(self, obs, action, reward, next_obs, terminated, _add=SAC.add):
        # the run's agent only: where no CPU-matmul choice is kept yet for these shapes (a subset of the
        # suite, a fresh machine), run.py first times a bare agent without a prior buffer
        if self.prior_buffer is not None:
            stored.append((self.num_transitions, action.clone(), len(self.prior_buffer)))
        _add(self, obs, action, reward, next_obs, terminated)

    monkeypatch.setattr(SAC, "add", add)
    return stored


def test_the_search_acts_in_the_first_prior_rollouts_and_fills_their_buffer(run_py, wp_cpu, tmp_path, peg_demos_file,
                                                                             monkeypatch):
    """--sac prior_rollouts_policy=search through run.py's loop: the search's actions (here a marker
    value in place of KMPSearchPolicy's, which tests/test_prior_learning.py checks on its own) are the
    ones stepped and stored for exactly the first prior_rollouts transitions, the learner's after."""
    from vkgrl_newton.envs import evaluation

    marker, calls = 0.25, []

    def search_actions(self, env, obs):
        calls.append(int(env.episode_length_buf[0]))
        return torch.full((env.num_envs, 4), marker, device=env.tdev)

    monkeypatch.setattr(evaluation.KMPSearchPolicy, "actions", search_actions)
    stored = recorded_adds(monkeypatch)
    run_dir = tmp_path / "search"
    assert run_py.main(["--method", "kgrl", "--run-dir", str(run_dir), "--demos", str(peg_demos_file),
                        "--total-steps", "16", "--eval-episodes", "0", *TINY, "--sac", "prior_rollouts=8",
                        "--sac", "prior_rollouts_policy=search", "--sac", "prior_ratio=0.5",
                        "--kgrl-recipe", "reach_keep_prior"]) == 0  # (the search is for a = 0 the prior)
    assert calls == [0, 1, 2, 3] and len(stored) == 8  # 2 worlds: the first 4 env steps searched, 4 the learner
    for n, action, prior_rows in stored:
        searched = n < 8
        assert bool((action == marker).all()) == searched, (n, action)
        assert prior_rows == min(n, 8)  # the prior buffer holds the search's transitions, and only those


def test_sac_learns_from_the_scripted_demonstrators_rollouts_in_its_first_transitions(run_py, wp_cpu, tmp_path,
                                                                                      monkeypatch):
    """--sac prior_rollouts_policy=scripted (the SAC methods' RLPD demonstrations): the demonstrator's
    actions through the SAC action space are stepped and kept in the second buffer for exactly the first
    prior_rollouts transitions. The real policy acts here (not a marker): its actions are the ones stored,
    in [-1, 1] and not all 0 (the inverse mapping itself: tests/test_delta_command_kernel.py)."""
    from vkgrl_newton.envs import evaluation

    made = []

    def actions(self, env, obs, _actions=evaluation.ScriptedDeltaPolicy.actions):
        a = _actions(self, env, obs)
        made.append((int(env.episode_length_buf[0]), a.clone()))
        return a

    monkeypatch.setattr(evaluation.ScriptedDeltaPolicy, "actions", actions)
    stored = recorded_adds(monkeypatch)
    run_dir = tmp_path / "sac_demos"
    assert run_py.main(["--method", "sac", "--action-dim", "4", "--run-dir", str(run_dir), "--total-steps", "16",
                        "--eval-episodes", "0", *TINY, "--sac", "prior_rollouts=8",
                        "--sac", "prior_rollouts_policy=scripted", "--sac", "prior_ratio=0.5"]) == 0
    assert [n for n, _ in made] == [0, 1, 2, 3] and len(stored) == 8  # 2 worlds: 4 env steps scripted, 4 learned
    for (n, action, prior_rows), (_, scripted) in zip(stored, made + [(None, None)] * 4):
        if n < 8:
            assert torch.equal(action, scripted) and float(action.abs().max()) <= 1.0
        assert prior_rows == min(n, 8)  # the second buffer holds the demonstrator's transitions, and only those
    assert any(float(a.abs().max()) > 0 for _, a in made)  # it moved the arm (a = 0 would be SAC's zero default)
    assert json.loads((run_dir / "config.json").read_text())["sac"]["prior_rollouts_policy"] == "scripted"


def test_scripted_delta_policy_restarts_only_the_worlds_that_start(peg_env):
    """A world reset alone (a blow-up's) mid-episode: at the next `actions` the demonstrator restarts
    there (new draws, approach phase, not started) and every per-world state of the others is what their
    episode had made of it."""
    from vkgrl_newton.envs.evaluation import ScriptedDeltaPolicy

    env = peg_env
    if int(env.episode_length_buf.max()) > 0:
        env.reset()
    policy = ScriptedDeltaPolicy(seed=5)
    for _ in range(6):  # past the start delays (0-4 steps): the worlds have started, their state has evolved
        a = policy.actions(env, env.get_observations())
        assert a.shape == (env.num_envs, 6) and float(a.abs().max()) <= 1.0
        env.step(a)
    mask = torch.tensor([False, True, False, False])
    env._reset_worlds(mask)  # what the env does to a blown-up world
    before = {k: v.clone() for k, v in vars(policy.inserter).items() if isinstance(v, torch.Tensor)}
    assert bool(before["started"].all())
    seen = {}
    act = policy.inserter.act

    def recording_act(env_):  # the state the demonstrator acts from, once restarted
        seen.update({k: v.clone() for k, v in vars(policy.inserter).items() if isinstance(v, torch.Tensor)})
        return act(env_)

    policy.inserter.act = recording_act
    policy.actions(env, env.get_observations())
    per_world = [k for k, v in before.items() if v.ndim >= 1 and v.shape[0] == env.num_envs]
    assert {"phase", "started", "seg_start", "seg_goal", "bias", "height", "offset_tcp"} <= set(per_world)
    for name in per_world:
        assert torch.equal(seen[name][~mask], before[name][~mask]), name
    assert not bool(seen["started"][1]) and int(seen["phase"][1]) == 0  # world 1 starts over
    for name in ("height", "t_approach", "v_insert", "push"):  # with draws of its own
        assert not torch.equal(seen[name][mask], before[name][mask]), name
    env.reset()  # (the shared env back at an episode start)


def test_a_kgrl_run_refuses_a_changed_prior_on_resume_and_evaluate(run_py, wp_cpu, tmp_path, capsys, monkeypatch):
    """The run's meta records the demonstrations by sha256; a file changed under that name stops
    --resume and evaluate.py --checkpoint with both hashes named; evaluate's --demos overrides."""
    from vkgrl_newton.agents.checkpoint import load_checkpoint
    from vkgrl_newton.cache import file_sha256

    demos = tmp_path / "demos.npz"
    synthetic_demos("PegInsert", 6, action_dim=6, seed=3).save(demos)
    recorded = file_sha256(demos)
    run_dir = tmp_path / "kgrl"
    assert run_py.main(["--method", "kgrl", "--run-dir", str(run_dir), "--demos", str(demos), "--total-steps", "8",
                        "--eval-episodes", "0", "--kgrl-recipe", "base", *TINY]) == 0
    ckpt = run_dir / "checkpoints" / "last.pt"
    meta = load_checkpoint(ckpt)["meta"]
    prior = meta["prior"]
    assert prior["demos"] == str(demos) and prior["demos_sha256"] == recorded and prior["num_demos"] == 6
    # the base recipe: the thesis's null space (no floors recorded) and its SAC fields; no recipe recorded,
    # as in the runs made before recipes existed, which therefore resume as base
    assert "reach_floor_mm" not in prior and "reach_floor_z_mm" not in prior and "kgrl_recipe" not in meta
    assert (meta["sac"]["log_std_bound"], meta["sac"]["prior_anchor"], meta["sac"]["prior_rollouts"]) == \
        ("clamp", False, 0)
    # a resume under another recipe is refused, naming it
    with pytest.raises(SystemExit) as exc:
        run_py.main(["--run-dir", str(run_dir), "--resume", "--total-steps", "16", "--no-progress",
                     "--kgrl-recipe", "reach_keep_prior"])
    assert exc.value.code == 2 and "kgrl_recipe" in capsys.readouterr().err
    # so is another reach floor, in one line, before the env is built (train() is never entered)
    with monkeypatch.context() as m:
        m.setattr("vkgrl_newton.run.train.train", lambda *a, **k: pytest.fail("train() entered before the refusal"))
        for flag in ("--kgrl-reach-floor", "--kgrl-reach-floor-z", "--kgrl-seat-press"):
            with pytest.raises(SystemExit) as exc:
                run_py.main(["--run-dir", str(run_dir), "--resume", "--total-steps", "16", "--no-progress", flag, "3"])
            err = capsys.readouterr().err
            assert exc.value.code == 2 and f"the run's {flag} was 0 mm, not 3" in err.strip().splitlines()[-1]
    # resumed without the flag, it continues as base
    assert run_py.main(["--run-dir", str(run_dir), "--resume", "--total-steps", "16", "--no-progress"]) == 0
    assert "kgrl_recipe" not in load_checkpoint(ckpt)["meta"]
    assert load_checkpoint(ckpt)["meta"]["sac"] == meta["sac"] and load_checkpoint(ckpt)["counters"]["transitions"] == 16

    demos.unlink()
    synthetic_demos("PegInsert", 6, action_dim=6, seed=4).save(demos)  # other demonstrations, same name
    now = file_sha256(demos)
    evaluate_py = load_script("evaluate")
    for call in (lambda: run_py.main(["--run-dir", str(run_dir), "--resume", "--total-steps", "24", "--no-progress"]),
                 lambda: evaluate_py.main(["--checkpoint", str(ckpt), "--device", "cpu", "--num-envs", "2"])):
        with pytest.raises(SystemExit) as exc:
            call()
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert recorded in err and now in err, err


@pytest.mark.parametrize("argv, message", [
    (["--method", "qlearning"], "invalid choice"),
    (["--action-dim", "5"], "invalid choice"),
    (["--num-envs", "0"], "must be an integer >= 1"),
    (["--sac", "bogus=1"], "FIELD one of"),
    (["--sac", "batch_size=zero"], "not a valid int"),
    (["--sac", "batch_size=0"], "batch_size"),
    (["--resume"], "--resume needs --run-dir"),
    (["--geometry", "mesh"], "--geometry 'mesh' exists for ['GearMesh', 'NutThread'], not PegInsert"),
    (["--geometry", "sdf"], "invalid choice"),
    (["--task", "GearMesh", "--method", "vision_kgrl", "--geometry", "mesh"], "--geometry mesh is for the sac and kgrl"),
    (["--method", "sac", "--vae", "x.pt"], "--vae is for the vision methods"),
    (["--method", "vision_sac", "--vae", "no_such_vae.pt"], "does not exist"),
])
def test_run_bad_flags_are_argparse_errors(run_py, argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        run_py.main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


@pytest.mark.slow
def test_run_vision_kgrl_with_a_given_vae_and_evaluate_its_checkpoint(run_py, wp_cpu, tmp_path, peg_demos_file,
                                                                       capsys):
    from vkgrl_newton.vision import DenoisingVAE, VAEConfig, save_vae

    cfg = VAEConfig(resolution=32, channels=(8, 8, 8, 8, 8))
    vae_file = save_vae(tmp_path / "vae.pt", DenoisingVAE(cfg), cfg, meta={"task": "PegInsert"})
    run_dir = tmp_path / "vkgrl"
    code = run_py.main(["--method", "vision_kgrl", "--vae", str(vae_file), "--run-dir", str(run_dir),
                        "--demos", str(peg_demos_file), "--total-steps", "16", "--eval-episodes", "1", *TINY,
                        "--kgrl-recipe", "reach_keep_prior"])  # (a given VAE: the residual recipe reads the cache's)
    assert code == 0
    config = json.loads((run_dir / "config.json").read_text())
    from vkgrl_newton.cache import file_sha256

    assert config["obs_dim"] == 8 + 16 and config["vision"] == {"vae": str(vae_file), "latent_dim": 16,  # eq. 5.6
                                                                "vae_sha256": file_sha256(vae_file)}
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["episodes"] == 2 and metrics["method"] == "vision_kgrl"
    evaluate_py = load_script("evaluate")
    out = tmp_path / "eval.json"
    assert evaluate_py.main(["--checkpoint", str(run_dir / "checkpoints" / "last.pt"), "--num-envs", "2",
                             "--episodes", "1", "--device", "cpu", "--demos", str(peg_demos_file),
                             "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["policy"] == "vision_kgrl" and result["geometry"] == "primitives"  # the run's (not stored)

    # another VAE under the same name: evaluating or resuming the run is refused, naming both hashes
    recorded = file_sha256(vae_file)
    other = VAEConfig(resolution=32, channels=(8, 8, 8, 8, 16))
    vae_file.unlink()
    save_vae(vae_file, DenoisingVAE(other), other, meta={"task": "PegInsert"})
    for call in (lambda: evaluate_py.main(["--checkpoint", str(run_dir / "checkpoints" / "last.pt"), "--device", "cpu",
                                           "--demos", str(peg_demos_file)]),
                 lambda: run_py.main(["--run-dir", str(run_dir), "--resume", "--total-steps", "32", "--no-progress"])):
        with pytest.raises(SystemExit) as exc:
            call()
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert recorded in err and file_sha256(vae_file) in err, err


def test_run_vae_of_another_task_is_an_argparse_error(run_py, tmp_path, capsys):
    from vkgrl_newton.vision import DenoisingVAE, VAEConfig, save_vae

    cfg = VAEConfig(resolution=32, channels=(8, 8, 8, 8, 8))
    vae_file = save_vae(tmp_path / "vae.pt", DenoisingVAE(cfg), cfg, meta={"task": "GearMesh"})
    with pytest.raises(SystemExit) as exc:
        run_py.main(["--method", "vision_sac", "--vae", str(vae_file), "--device", "cpu"])
    assert exc.value.code == 2
    assert "task mismatch, expected 'PegInsert'" in capsys.readouterr().err


def test_env_vision_slot_follows_the_state(wp_cpu):
    """attach_vision: the latent is recomputed whenever the state changed, so it always shows the
    state the rest of the observation shows (here a stand-in source: the TCP position)."""
    from vkgrl_newton.envs.assembly_env import AssemblyEnv, EnvConfig

    env = AssemblyEnv(EnvConfig(num_envs=2, action_dim=4, device="cpu", seed=3, vision_latent_dim=3))
    calls = []

    def source(e):
        calls.append(int(e.episode_length_buf[0]))
        return e.tcp_pose()[0].clone()

    env.attach_vision(source)
    obs = env.get_observations()["policy"]
    torch.testing.assert_close(obs[:, -3:], env.tcp_pose()[0])
    env.get_observations()
    assert len(calls) == 1  # unchanged state: not rendered again
    for _ in range(3):
        obs = env.step(torch.full((2, 4), 0.5))[0]["policy"]
        torch.testing.assert_close(obs[:, -3:], env.tcp_pose()[0])
        torch.testing.assert_close(obs[:, 1:4], env.tcp_pose()[0] - env.target_frame_pos_w)
    assert calls == [0, 1, 2, 3]
    # across a time-out: the final observation shows the last state, the returned one the reset state
    outputs = []

    def recording_source(e):
        outputs.append((int(e.episode_length_buf[0]), e.tcp_pose()[0].clone()))
        return outputs[-1][1]

    env.attach_vision(recording_source)
    while True:
        obs, _, dones, extras = env.step(torch.zeros(2, 4))
        if bool(dones.all()):
            break
    (k_final, z_final), (k_reset, z_reset) = outputs[-2:]
    assert (k_final, k_reset) == (env.max_episode_length, 0)
    torch.testing.assert_close(extras["final_observations"]["policy"][:, -3:], z_final)
    torch.testing.assert_close(obs["policy"][:, -3:], z_reset)
    assert (z_final - z_reset).abs().max() > 1e-3  # the reset moved the hand
    with pytest.raises(ValueError, match="vision_latent_dim"):
        AssemblyEnv.attach_vision(type("E", (), {"cfg": EnvConfig(num_envs=1)})(), source)


def test_run_unavailable_task_says_what_is_missing(run_py):
    """Every task of the table is simulated; a task name from elsewhere (an old or foreign
    checkpoint's meta) is refused with the list of simulated ones."""
    import argparse

    from vkgrl_newton.envs.assembly_env import TASK_GEOMETRY
    from vkgrl_newton.tasks import TASKS

    assert sorted(TASK_GEOMETRY) == sorted(TASKS)
    from vkgrl_newton.run.config import unavailable

    for task in TASKS:
        assert unavailable(argparse.Namespace(task=task)) is None
    message = unavailable(argparse.Namespace(task="BoltScrew"))
    assert "not simulated" in message and "GearMesh" in message and "NutThread" in message


def test_plot_runs_mean_and_std_over_seeds(tmp_path):
    from torch.utils.tensorboard import SummaryWriter

    plot_runs = load_script("plot_runs")
    finals = {"sac": [], "kgrl": []}
    dirs = []
    for method, offset in (("sac", 0.0), ("kgrl", 0.5)):
        for seed in range(3):
            d = tmp_path / f"{method}_{seed}"
            d.mkdir()
            (d / "config.json").write_text(json.dumps({"task": "PegInsert", "method": method, "env": "factory",
                                                       "action_dim": 4, "time_obs": True}))
            w = SummaryWriter(str(d / "tb"))
            steps = np.arange(0, 2400 * (6 + seed), 2400)  # runs of different lengths
            for i, s in enumerate(steps):
                w.add_scalar("episode/success_rate", offset + 0.1 * seed + 0.01 * i, int(s))
                w.add_scalar("episode/reward", 10.0 * i, int(s))
                w.add_scalar("episode/mean_contact_force", 1.0, int(s))
            w.close()
            finals[method].append(offset + 0.1 * seed + 0.01 * 5)  # value at the shortest run's end
            dirs.append(d)
    out = tmp_path / "curves.png"
    summary = plot_runs.plot(dirs, out)
    assert out.stat().st_size > 10_000
    for method, vals in finals.items():
        got = summary[method]["episode/success_rate"]
        assert got["final_mean"] == pytest.approx(np.mean(vals), abs=1e-6)
        assert got["final_std"] == pytest.approx(np.std(vals), abs=1e-6)
    # the success panel's levels: the thesis's Table 6.2 for each method; no prior (no metrics.json) and no
    # ceiling (these configs name no evaluation episodes)
    assert summary["reference_levels"] == {"thesis:kgrl": 0.797, "thesis:sac": 0.535}
    with pytest.raises(FileExistsError):
        plot_runs.plot(dirs, out)
    # runs evaluated on the ceiling's episodes, with their prior: the prior's level and the task's ceiling join
    for d in dirs:
        config = json.loads((d / "config.json").read_text())
        (d / "config.json").write_text(json.dumps({**config, "eval_seed": 10000, "num_envs": 16}))
        (d / "metrics.json").write_text(json.dumps({"success_rate": 0.3, "prior_eval": {"success_rate": 0.140625}}))
    levels = plot_runs.plot(dirs, tmp_path / "curves2.png")["reference_levels"]
    assert levels == {"thesis:kgrl": 0.797, "thesis:sac": 0.535, "prior": 0.140625, "ceiling:scripted": 1.0,
                      "ceiling:oracle": 1.0, "ceiling:search": 38 / 128}
    # a prior evaluated differently in one run (another episode set): no single prior level is drawn
    (dirs[0] / "metrics.json").write_text(json.dumps({"success_rate": 0.3, "prior_eval": {"success_rate": 0.5}}))
    assert "prior" not in plot_runs.plot(dirs, tmp_path / "curves3.png")["reference_levels"]


def test_run_geometry_is_part_of_a_mesh_runs_identity(run_py, tmp_path):
    """--geometry mesh is recorded in the checkpoint's meta (a resume must match it) and keeps its
    scripted demonstrations apart; the default leaves both as before, so older runs still resume."""
    import argparse

    from vkgrl_newton.prepare.prior import demos_path_for
    from vkgrl_newton.agents.sac import SAC_PRESETS

    from vkgrl_newton.run.config import RunConfig

    base = dict(task="GearMesh", method="kgrl", env="factory", action_dim=4, seed=0, num_envs=2, preset="quick",
                time_obs=True, kgrl_recipe="base")
    prim = RunConfig(**base, geometry="primitives", sac=SAC_PRESETS["quick"]).meta()
    mesh = RunConfig(**base, geometry="mesh", sac=SAC_PRESETS["quick"]).meta()
    assert "geometry" not in prim and mesh["geometry"] == "mesh"
    assert {k: v for k, v in mesh.items() if k != "geometry"} == prim
    p = demos_path_for(tmp_path, "GearMesh", 16, 0)
    bvh = demos_path_for(tmp_path, "GearMesh", 16, 0, "mesh", device="cpu")
    sdf = demos_path_for(tmp_path, "GearMesh", 16, 0, "mesh", device="cuda:0")
    assert p.name == "demos_scripted_v1_factory_n16_seed0.npz"  # v: the demonstrator's version
    assert (bvh.name, sdf.name) == ("demos_scripted_v1_factory_n16_seed0_mesh_bvh.npz",
                                    "demos_scripted_v1_factory_n16_seed0_mesh_sdf.npz")


def test_run_resume_with_another_geometry_is_refused(run_py, tmp_path, capsys):
    """A mesh run's checkpoint resumed with --geometry primitives stops before anything is built,
    naming the field."""
    import argparse

    from vkgrl_newton.agents.checkpoint import CHECKPOINT_FORMAT, save_checkpoint
    from vkgrl_newton.agents.sac import SAC_PRESETS

    from vkgrl_newton.run.config import RunConfig

    meta = RunConfig(task="GearMesh", method="kgrl", env="factory", action_dim=4, seed=0, num_envs=2, preset="quick",
                     time_obs=True, geometry="mesh", kgrl_recipe="base", sac=SAC_PRESETS["quick"]).meta()
    run_dir = tmp_path / "mesh_run"
    save_checkpoint(run_dir / "checkpoints" / "last.pt",
                    {"format": CHECKPOINT_FORMAT, "meta": meta, "counters": {}, "agent": {}, "rng": {}})
    with pytest.raises(SystemExit) as exc:
        run_py.main(["--run-dir", str(run_dir), "--resume", "--geometry", "primitives", "--device", "cpu"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "belongs to a different run; geometry: checkpoint 'mesh', now 'primitives'" in err
    assert err.count("checkpoint '") == 1  # nothing else differs
    assert "kgrl_recipe" not in err  # a checkpoint from before recipes resumes as base, the recipe it ran


def test_the_search_is_refused_without_z_reach_under_the_final_presets_recipe(run_py):
    """The check runs again once the preset is known (thesis on a CUDA device: the base recipe, no z floor)."""
    import argparse

    from vkgrl_newton.agents.sac_config import make_sac_config

    cfg = make_sac_config("quick", prior_rollouts=480, prior_rollouts_policy="search")
    from vkgrl_newton.run.config import search_without_z_reach

    args = argparse.Namespace(method="kgrl", kgrl_recipe=None, kgrl_reach_floor_z=None, resume=False, task="PegInsert",
                              env="factory", action_dim=4)
    assert search_without_z_reach(args, cfg, "quick") is None  # residual (the quick default here): 25 mm
    assert "needs z reach" in search_without_z_reach(args, cfg, "thesis")
    args.kgrl_reach_floor_z = 10.0
    assert search_without_z_reach(args, cfg, "thesis") is None
