"""The policy's extra inputs of issue 40 (deviations from eq. 5.5): the TCP's velocity by finite differences
over the control step (against float64 frames from the env's own poses, scipy's rotations) and Factory's
force input; their widths through observation_dim, the run's options and refusals."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from vkgrl_newton.tasks import CONTROL_DT, observation_dim
from scripts import on_the_prior


def test_observation_widths():
    assert observation_dim("factory") == 8 and observation_dim("forge") == 11
    assert observation_dim("factory", 16, tcp_velocity=True, force=True) == 8 + 16 + 6 + 3
    assert observation_dim("forge", 0, tcp_velocity=True) == 11 + 6


@pytest.mark.slow
def test_tcp_velocity_and_force_inputs_on_a_stepped_env(wp_cpu):
    from vkgrl_newton.envs.assembly_env import FORCE_OBS_NOISE, AssemblyEnv, EnvConfig

    env = AssemblyEnv(EnvConfig(task="PegInsert", family="factory", action_dim=4, num_envs=2, device="cpu", seed=3,
                                tcp_velocity_obs=True, force_obs=True))
    obs = env.reset()["policy"]
    assert obs.shape == (2, 8 + 3 + 6) == (2, env.obs_dim)
    assert torch.equal(obs[:, 11:17], torch.zeros(2, 6))  # an episode starts at rest
    g = torch.Generator().manual_seed(0)
    for _ in range(4):
        p0, q0 = (t.double().numpy().copy() for t in env.tcp_pose())
        obs = env.step(torch.rand(2, 4, generator=g) * 2 - 1)[0]["policy"]
        p1, q1 = (t.double().numpy() for t in env.tcp_pose())
        lin, ang = obs[:, 11:14].double().numpy(), obs[:, 14:17].double().numpy()
        np.testing.assert_allclose(lin, (p1 - p0) / CONTROL_DT, atol=1e-4)  # float32 poses / (1/15 s)
        want = (Rotation.from_quat(q1) * Rotation.from_quat(q0).inv()).as_rotvec() / CONTROL_DT
        # the env's float32 quat_log of a rotation of ~1e-2 rad: an absolute error of a few 1e-7 rad (float32's
        # rounding of the quaternions' components, ~6e-8 each), / (1/15 s) ~ 1e-5 rad/s; 1e-3 bounds it with room
        np.testing.assert_allclose(ang, want, atol=1e-3)
        assert float(np.abs(lin).max()) > 1e-4  # the arm moved: a non-trivial comparison
        force = obs[:, 8:11] - env.force_smoothed_w
        assert bool((force.abs() < 6 * FORCE_OBS_NOISE).all())  # Forge's noise, 6 sigma
    with pytest.raises(ValueError, match="force_obs is Factory's"):
        EnvConfig(family="forge", force_obs=True)


def test_the_runs_options_and_refusals(tmp_path):
    from vkgrl_newton.run.config import ConfigError, build_parser
    from vkgrl_newton.run.resolve import resolve

    def run(*argv):
        return resolve(build_parser(), [*on_the_prior(list(argv)), "--device", "cpu", "--run-dir", str(tmp_path / "r"),
                                        "--cpu-matmul", "torch"]).config

    cfg = run("--method", "sac", "--tcp-velocity-obs", "--force-obs")
    assert cfg.obs_dim == 8 + 6 + 3 and cfg.meta()["tcp_velocity_obs"] and cfg.meta()["force_obs"]
    plain = run("--method", "sac")
    assert plain.obs_dim == 8 and "tcp_velocity_obs" not in plain.meta() and "force_obs" not in plain.meta()
    with pytest.raises(ConfigError, match="--force-obs is for --env factory"):
        run("--method", "sac", "--env", "forge", "--force-obs")
    # the camera's estimate over the hole: two more inputs beside the 16-d latent, recorded only when asked
    probe = run("--method", "vision_kgrl", "--vision-probe-obs")
    assert probe.obs_dim == 8 + 16 + 2 and probe.vision_width == 18 and probe.meta()["vision_probe_obs"]
    vision = run("--method", "vision_kgrl")
    assert vision.obs_dim == 8 + 16 and "vision_probe_obs" not in vision.meta()
    with pytest.raises(ConfigError, match="--vision-probe-obs is for the vision methods"):
        run("--method", "kgrl", "--vision-probe-obs")
    with pytest.raises(ConfigError, match="--vision-probe-obs takes the cached VAE"):
        run("--method", "vision_kgrl", "--vision-probe-obs", "--vae", str(tmp_path / "vae.pt"))
    # evaluate rebuilds the run's input from its checkpoint's record
    import argparse

    from vkgrl_newton.run.evaluate import evaluation_config

    args = argparse.Namespace(task="PegInsert", env="factory", action_dim=4, seed=0, num_envs=2, no_time_obs=False,
                              geometry=None, demos=None, kmp_reference="gmr", device="cpu", cache_dir=tmp_path,
                              eager_physics=False, policy=None)
    meta = probe.meta()
    assert evaluation_config(args, {"meta": meta}).vision_width == 18
    del meta["vision_probe_obs"]
    assert evaluation_config(args, {"meta": meta}).vision_width == 16


@pytest.mark.slow
def test_a_run_with_the_extra_inputs_trains_and_its_checkpoint_evaluates(wp_cpu, tmp_path):
    import json

    from scripts import TINY_RUN, load_script

    run_dir = tmp_path / "inputs"
    tiny = [*TINY_RUN, "--cpu-matmul", "torch"]
    assert load_script("run").main(["--method", "sac", "--tcp-velocity-obs", "--force-obs", "--run-dir", str(run_dir),
                                    "--total-steps", "16", "--eval-episodes", "0", *tiny]) == 0
    assert json.loads((run_dir / "config.json").read_text())["obs_dim"] == 17
    out = tmp_path / "eval.json"
    assert load_script("evaluate").main(["--checkpoint", str(run_dir / "checkpoints" / "last.pt"), "--num-envs", "2",
                                         "--episodes", "1", "--device", "cpu", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["episodes"] == 2
