"""--vision-probe-fit closed_loop: the near-hole probe fitted on the image set and on the camera controller's own frames
(prepare.closed_loop, prepare.vision.load_or_make_probe), and the run option around it."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scripts import on_the_prior


def synthetic_frames(n: int, d: int, seed: int, rounds: int | None = None) -> dict:
    """Latents that carry the fixed tip minus the held part (image frame, the identity camera) in their first three
    columns (mm) plus noise; geometry rows near the hole (vision.probe.near_hole_mask) and some far from it."""
    rng = np.random.default_rng(seed)
    held = rng.uniform(-0.008, 0.008, size=(n, 3)) * [1, 1, 0.5] + [0, 0, 0.005]
    held[: n // 10, 0] += 0.05  # far from the hole: never fitted
    g = np.zeros((n, 13))
    g[:, 0:3] = held
    g[:, 12] = 1.0  # the optical frame = the world's (xyzw identity)
    rel = -held  # relative_in_image: the fixed tip (origin) minus the held part
    z = np.column_stack([1e3 * rel + 0.05 * rng.normal(size=(n, 3)), rng.normal(size=(n, d - 3))])
    out = {"z": z, "geometry": g}
    if rounds is not None:
        out["round"] = np.repeat(np.arange(rounds), int(np.ceil(n / rounds)))[:n]
        out["success"] = np.ones(rounds * 2, bool)
    return out


def test_a_closed_loop_probe_is_fitted_on_the_image_set_and_the_controllers_frames(tmp_path, monkeypatch):
    """The file is NearHoleRegressor's fit on the image set's frames followed by the controller's (predictions
    compared with a reference fitted here); its held-out score is the model fitted on the image set's training
    episodes and the first rounds, scored on the last two rounds' near-hole frames, with the image-set probe's score
    on those frames beside it; the controller steers by the image-set probe; a second call loads without collecting."""
    import vkgrl_newton.prepare.closed_loop as closed_loop
    import vkgrl_newton.prepare.vision as vision
    from vkgrl_newton.vision.probe import NearHoleRegressor, near_hole_mask, relative_in_image

    d = 6
    image = synthetic_frames(240, d, seed=1)
    split = np.arange(240) % 5 != 0  # the image set's training episodes
    frames = synthetic_frames(320, d, seed=2, rounds=8)
    # the controller's frames sit elsewhere in the latent (a noise column moved) and read the target shifted there:
    # the image-set probe is off on them, a fit on both is not
    frames["z"][:, 0] += 0.5
    frames["z"][:, 3] += 4.0
    calls = []

    def image_latents(task, preset, cache_dir, encoder, num_envs):
        return image["z"], image["geometry"], split

    def collect(task, encoder, probe, cache_dir, num_envs, rounds, eval_seed, log=print, progress=True):
        calls.append((probe, rounds, eval_seed))
        return frames

    monkeypatch.setattr(vision, "_image_set_latents", image_latents)
    monkeypatch.setattr(closed_loop, "collect_closed_loop_frames", collect)
    encoder = type("E", (), {"latent_dim": d})()
    preset = vision.VISION_PRESETS["quick"]
    monkeypatch.setattr(vision, "default_vae_dir", lambda cache_dir, task, preset, num_envs=16: tmp_path / "vae")
    (tmp_path / "vae").mkdir()
    quiet = lambda *a: None  # noqa: E731
    probe, path, record = vision.load_or_make_probe("PegInsert", preset, tmp_path, encoder, log=quiet,
                                                    fit="closed_loop", progress=False)
    assert path == tmp_path / "vae" / "near_hole_probe_mlp_closed_loop_seed0.npz"
    assert (tmp_path / "vae" / "near_hole_probe_mlp_seed0.npz").is_file()  # the image-set probe, made first
    image_probe = vision.load_or_make_probe("PegInsert", preset, tmp_path, encoder, log=quiet)[0]
    assert len(calls) == 1 and calls[0][1:] == (8, 20_000)
    steered = calls[0][0]  # the controller steered by the image-set probe
    x = torch.as_tensor(np.random.default_rng(5).normal(size=(50, d)))
    torch.testing.assert_close(steered(x), image_probe(x))
    # the saved probe: the reference fit on the same rows in the same order
    ref = NearHoleRegressor(np.concatenate([image["z"], frames["z"]]),
                            np.concatenate([image["geometry"], frames["geometry"]]), seed=preset.seed)
    # (the same float64 weights evaluated by torch and by scikit-learn: only the summation order differs, ~1e-15
    # relative over a 64-unit layer; 1e-9 leaves room for that and catches any other fit or row order)
    np.testing.assert_allclose(probe(x).numpy(), ref(x.numpy()), rtol=1e-9, atol=1e-12)
    assert record["num_fit"] == near_hole_mask(image["geometry"]).sum() + near_hole_mask(frames["geometry"]).sum()
    # held out: the last two rounds
    late = frames["round"] >= 6
    near = near_hole_mask(frames["geometry"][late])
    fit = NearHoleRegressor(np.concatenate([image["z"][split], frames["z"][~late]]),
                            np.concatenate([image["geometry"][split], frames["geometry"][~late]]), seed=preset.seed)
    truth = relative_in_image(frames["geometry"][late][near])
    err = fit(frames["z"][late][near]) - truth
    assert record["held_out_frames"] == near.sum()
    # (the reference refits the same rows with the same seed in this process, one BLAS thread: the same float64
    # computation, so the scores agree to summation rounding, ~1e-15; 1e-9 catches another split or another model)
    np.testing.assert_allclose(list(record["held_out_rmse_mm"].values()), 1e3 * np.sqrt((err ** 2).mean(0)), rtol=1e-9)
    image_err = image_probe(torch.as_tensor(frames["z"][late][near])).numpy() - truth
    np.testing.assert_allclose(list(record["image_probe_rmse_mm"].values()), 1e3 * np.sqrt((image_err ** 2).mean(0)),
                               rtol=1e-9)
    # the shifted latent: the image-set probe is off there, the closed-loop fit is not
    assert record["held_out_rmse_mm"]["x"] < 0.5 * record["image_probe_rmse_mm"]["x"]
    assert record["closed_loop_episodes"] == 16
    again = vision.load_or_make_probe("PegInsert", preset, tmp_path, encoder, log=quiet, fit="closed_loop")
    assert len(calls) == 1 and again[1] == path
    with pytest.raises(ValueError, match="probe fit 'dagger'; allowed: images, closed_loop"):
        vision.default_probe_path(tmp_path, "PegInsert", preset, fit="dagger")


def test_closed_loop_frames_are_the_states_the_camera_controller_steps_from(wp_cpu, monkeypatch):
    """Every row is one world's state before one control step of the camera controller: its held part and fixed tip
    (recorded here at each step_pose, before the physics moves), the latent of that state (a separate camera and the
    encoder, rendered here), the optical frame; rows go step by step, world by world, one round per episode."""
    from test_kgrl_base import prior_tables

    from vkgrl_newton.envs.assembly_env import AssemblyEnv, EnvConfig
    from vkgrl_newton.envs.camera_latent import LATERAL_DIM
    from vkgrl_newton.prepare.closed_loop import collect_closed_loop_frames
    from vkgrl_newton.sim.camera import TaskCamera
    from vkgrl_newton.vision.probe import ProbeMLP
    from vkgrl_newton.vision.vae import DenoisingVAE, FrozenEncoder, VAEConfig

    torch.manual_seed(0)
    cfg = VAEConfig(resolution=32, latent_dim=4, channels=(8, 8, 8, 8, 8), groups=8)
    encoder = FrozenEncoder(DenoisingVAE(cfg, torch.Generator().manual_seed(0)))
    rng = np.random.default_rng(0)
    probe = ProbeMLP({"x_mean": np.zeros(4), "x_scale": np.ones(4), "y_mean": np.zeros(3), "y_scale": np.ones(3),
                      "weights": [1e-3 * rng.normal(size=(4, 3))], "biases": [np.zeros(3)]})
    env = AssemblyEnv(EnvConfig(num_envs=2, action_dim=4, device="cpu", seed=0, vision_latent_dim=4 + LATERAL_DIM))
    seen = []
    step_pose = env.step_pose

    def recording_step_pose(pos, quat):
        camera = seen_camera[0]
        hand = env.hand_pose()
        images = camera.render_torch(env.state_0, *hand)
        seen.append((env.held_pose()[0].double().clone(), env.fixed_tip_w.double().clone(),
                     encoder(images).double(), camera.optical_poses_w(*hand).double()))
        return step_pose(pos, quat)

    monkeypatch.setattr(env, "step_pose", recording_step_pose)
    seen_camera = []
    attach = env.attach_vision

    def attach_and_copy(source):
        seen_camera.append(TaskCamera(env.model, source.spec, env.num_envs))
        attach(source)

    monkeypatch.setattr(env, "attach_vision", attach_and_copy)
    successes = []
    metrics = env.episode_metrics

    def recording_metrics(mask):  # the env's own per-world outcome at each time-out
        out = metrics(mask)
        successes.append(list(out["world_success"]))
        return out

    monkeypatch.setattr(env, "episode_metrics", recording_metrics)
    frames = collect_closed_loop_frames("PegInsert", encoder, probe, None, rounds=2, eval_seed=7, env=env,
                                        tables=prior_tables(), log=lambda *a: None, progress=False)
    T, E = env.max_episode_length, env.num_envs
    n = 2 * T * E
    assert frames["z"].shape == (n, 4) and frames["geometry"].shape == (n, 13) and len(seen) == 2 * T
    np.testing.assert_array_equal(frames["round"], np.repeat([0, 1], T * E))
    np.testing.assert_array_equal(frames["success"], np.asarray(successes, np.float64).reshape(-1) == 1.0)
    held = torch.stack([s[0] for s in seen]).reshape(n, 3).numpy()
    tip = torch.stack([s[1] for s in seen]).reshape(n, 3).numpy()
    np.testing.assert_array_equal(frames["geometry"][:, 0:3], held)
    np.testing.assert_array_equal(frames["geometry"][:, 3:6], tip)
    np.testing.assert_array_equal(frames["geometry"][:, 6:13], torch.stack([s[3] for s in seen]).reshape(n, 7))
    # the latent of the state (the same float32 encoder on the same image: equal but for the batch's summation order)
    z = torch.stack([s[2] for s in seen]).reshape(n, 4).numpy()
    np.testing.assert_allclose(frames["z"], z, rtol=0, atol=1e-5)
    assert np.ptp(frames["geometry"][:, 0], axis=0) > 1e-3  # the controller moved the part: not one state repeated


def test_the_option_is_recorded_refused_without_the_probe_and_rebuilt_by_evaluate(tmp_path):
    """--vision-probe-fit: in the run's meta only when closed_loop (older runs resume), the run's probe path is the
    closed-loop file beside the VAE, refused without --vision-probe-obs, rebuilt by evaluate.py --checkpoint, and the
    parser's choices are prepare.vision.PROBE_FITS."""
    import argparse

    from vkgrl_newton.prepare.vision import PROBE_FITS
    from vkgrl_newton.run.config import ConfigError, build_parser
    from vkgrl_newton.run.evaluate import evaluation_config
    from vkgrl_newton.run.resolve import resolve

    def run(*argv):
        return resolve(build_parser(), [*on_the_prior(list(argv)), "--device", "cpu", "--run-dir", str(tmp_path / "r"),
                                        "--cpu-matmul", "torch", "--cache-dir", str(tmp_path / "cache")]).config

    closed = run("--method", "vision_kgrl", "--vision-probe-obs", "--vision-probe-fit", "closed_loop")
    images = run("--method", "vision_kgrl", "--vision-probe-obs")
    assert closed.meta()["vision_probe_fit"] == "closed_loop" and "vision_probe_fit" not in images.meta()
    assert run("--method", "vision_kgrl", "--vision-probe-obs", "--vision-probe-fit", "images").meta() == images.meta()
    assert closed.probe_path().name == "near_hole_probe_mlp_closed_loop_seed0.npz"
    assert images.probe_path().name == "near_hole_probe_mlp_seed0.npz"
    assert closed.probe_path().parent == images.probe_path().parent  # beside the VAE
    with pytest.raises(ConfigError, match="add --vision-probe-obs"):
        run("--method", "vision_kgrl", "--vision-probe-fit", "closed_loop")
    with pytest.raises(ConfigError, match="add --vision-probe-obs"):
        run("--method", "kgrl", "--vision-probe-fit", "closed_loop")
    action = next(a for a in build_parser()._actions if a.dest == "vision_probe_fit")
    assert tuple(action.choices) == PROBE_FITS
    args = argparse.Namespace(task="PegInsert", env="factory", action_dim=4, seed=0, num_envs=2, no_time_obs=False,
                              geometry=None, demos=None, kmp_reference="gmr", device="cpu", cache_dir=tmp_path,
                              eager_physics=False, policy=None)
    assert evaluation_config(args, {"meta": closed.meta()}).vision_probe_fit == "closed_loop"
    assert evaluation_config(args, {"meta": images.meta()}).vision_probe_fit == "images"
