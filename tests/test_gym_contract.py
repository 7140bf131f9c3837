"""gymnasium's whole contract on the VKGRL ids: gymnasium.make's one-world env through gymnasium's and
stable-baselines3's env checkers, render_mode="rgb_array" recorded by gymnasium's own RecordVideo, the
vector wrappers users stack (against a hand computation), and bad kwargs / a closed env refused in one line."""

import glob

import gymnasium as gym
import numpy as np
import pytest
import torch

import vkgrl_newton  # noqa: F401  (registers the ids)

KGRL_ID = "VKGRL/PegInsert-Factory-4D-KGRL-v0"


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    from vkgrl_newton.kmp.demos import synthetic_demos
    from vkgrl_newton.vision import DenoisingVAE, VAEConfig, save_vae

    root = tmp_path_factory.mktemp("contract")
    demos = synthetic_demos("PegInsert", 8, action_dim=6, seed=1).save(root / "demos.npz")
    # (a 1-world batch through GroupNorm needs more than one value per group: 32 channels in 8 groups)
    cfg = VAEConfig(resolution=32, channels=(8, 16, 16, 32, 32), groups=8)
    vae = save_vae(root / "vae.pt", DenoisingVAE(cfg, torch.Generator().manual_seed(0)), cfg, {"task": "PegInsert"})
    return {"root": root, "demos": demos, "vae": vae}


def _kwargs(name: str, files) -> dict:
    kw = {"device": "cpu", "cache_dir": files["root"] / "cache"}
    kw |= {"demos": files["demos"]} if name.endswith("KGRL-v0") else {}
    kw |= {"vae": files["vae"]} if "-Vision" in name else {}
    return kw


@pytest.mark.parametrize("name", ["VKGRL/PegInsert-Factory-4D-v0", KGRL_ID, "VKGRL/PegInsert-Forge-6D-Vision-KGRL-v0"])
def test_make_gives_one_world_that_passes_both_env_checkers(name, files, wp_cpu):
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = gym.make(name, render_mode="rgb_array", **_kwargs(name, files))
    inner = env.unwrapped
    assert inner.vector_env.num_envs == 1 and inner.run_config.method == gym.spec(name).kwargs["method"]
    with pytest.warns(UserWarning, match="infinity"):  # the observation is unbounded (positions, forces)
        check_env(inner)  # raises on any breach of the contract (seeding, determinism, spaces, render)
    sb3_check_env(inner, warn=True)
    obs, info = env.reset(seed=3)
    assert env.observation_space.contains(obs) and info == {}
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.shape == (256, 256, 3) and frame.std() > 0  # the task camera sees
    env.close()


def test_a_one_world_episode_ends_truncated_with_its_last_observation_and_outcome(files, wp_cpu):
    env = gym.make(KGRL_ID, **_kwargs(KGRL_ID, files))
    env.reset(seed=0)
    steps = env.unwrapped.vector_env.env.max_episode_length
    for n in range(steps):
        obs, reward, terminated, truncated, info = env.step(np.zeros(4, np.float32))
        assert not terminated
        if truncated:
            break
    assert n == steps - 1 and truncated and set(info) == {"success", "physics_reset"}
    assert obs[0] == 1.0  # the ended episode's last observation: normalized time 1, not the reset's 0
    assert isinstance(reward, float) and isinstance(info["success"], bool)
    env.close()


def test_render_mode_rgb_array_is_recorded_by_gymnasiums_record_video(files, wp_cpu, tmp_path):
    imageio = pytest.importorskip("imageio.v3")
    from gymnasium.wrappers.vector import RecordVideo

    envs = gym.make_vec(KGRL_ID, num_envs=2, render_mode="rgb_array", **_kwargs(KGRL_ID, files))
    assert envs.metadata["render_fps"] == 15 and envs.render_mode == "rgb_array"
    frames = envs.render()
    assert len(frames) == 2 and all(f.shape == (256, 256, 3) and f.dtype == np.uint8 for f in frames)
    rec = RecordVideo(envs, str(tmp_path / "video"), step_trigger=lambda s: s == 0, video_length=6, fps=15)
    rec.reset(seed=0)
    for _ in range(8):
        rec.step(rec.action_space.sample())
    rec.close()
    (path,) = glob.glob(str(tmp_path / "video" / "*.mp4"))
    video = imageio.imread(path)
    assert video.shape == (6, 256, 512, 3)  # 6 frames of the 2 worlds side by side (gymnasium tiles them)


def test_the_vector_wrappers_users_stack_against_a_hand_computation(files, wp_cpu):
    from gymnasium.wrappers.vector import ClipAction, NormalizeObservation, RecordEpisodeStatistics

    kw = _kwargs(KGRL_ID, files)
    envs = gym.make_vec(KGRL_ID, num_envs=2, **kw)
    steps = envs.unwrapped.env.max_episode_length
    # RecordEpisodeStatistics: return and length of the episode that ends at the time limit
    stats = RecordEpisodeStatistics(envs)
    stats.reset(seed=1)
    returns = np.zeros(2)
    for n in range(steps):
        _, reward, _, truncated, info = stats.step(np.zeros((2, 4), np.float32))
        returns += reward
    assert truncated.all() and info["_episode"].all()
    # both sides add the same float32 rewards in float64 in the same order: equal but for rounding, and 150
    # float64 additions err by ~1e-14 relative, far inside 1e-6 (no CPU's float32 bits differ between them)
    np.testing.assert_allclose(info["episode"]["r"], returns, rtol=1e-6)
    np.testing.assert_array_equal(info["episode"]["l"], [steps, steps])
    # ClipAction: out-of-range actions act as their clipped values (the same episode, bitwise)
    clipped = ClipAction(envs)
    big = np.array([[3.0, -2.0, 0.5, 9.0], [-7.0, 0.25, 1.5, -1.0]], np.float32)
    clipped.reset(seed=2)
    a = [clipped.step(big)[0] for _ in range(3)]
    envs.reset(seed=2)
    b = [envs.step(np.clip(big, -1, 1))[0] for _ in range(3)]
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    # gymnasium 1.4's vector NormalizeObservation refuses same-step autoreset (it would normalize the ended
    # episode's final_obs with the statistics of after the reset): it is refused in one line, as gymnasium says
    with pytest.raises(ValueError, match="autoreset_mode"):
        NormalizeObservation(envs)
    # ... and the single-env NormalizeObservation on gymnasium.make's env: its running mean/var (count 1e-4
    # at mean 0, var 1), by hand in float64
    from gymnasium.wrappers import NormalizeObservation as NormalizeOne

    one = gym.make(KGRL_ID, **kw)
    norm = NormalizeOne(one, epsilon=1e-8)
    obs, _ = norm.reset(seed=4)
    inner = one.unwrapped.vector_env.env
    raw = [inner.get_observations()["policy"].numpy()[0].astype(np.float64)]
    for _ in range(5):
        obs, *_ = norm.step(np.zeros(4, np.float32))
        raw.append(inner.get_observations()["policy"].numpy()[0].astype(np.float64))
    mean, var, count = np.zeros(raw[0].shape[0]), np.ones(raw[0].shape[0]), 1e-4
    for x in raw:  # the parallel-variance update of gymnasium's RunningMeanStd, a batch of one at a time
        delta, total = x - mean, count + 1
        m2 = var * count + delta**2 * count / total
        mean, var, count = mean + delta / total, m2 / total, total
    # gymnasium returns the normalized observation as float32 (~6e-8 relative) of |x| up to ~1e2 over 6 samples
    # (sd near 0 for the constant components): 1e-4 covers that cast, not a CPU difference (same raw inputs)
    np.testing.assert_allclose(obs, (raw[-1] - mean) / np.sqrt(var + 1e-8), rtol=1e-4, atol=1e-4)
    one.close()
    envs.close()


@pytest.mark.parametrize("name", ["VKGRL/PegInsert-Factory-4D-v0", KGRL_ID, "VKGRL/GearMesh-Forge-6D-Vision-v0",
                                  "VKGRL/NutThread-Factory-4D-Vision-KGRL-v0"])
@pytest.mark.parametrize("kwargs, message", [
    ({"num_envs": 0}, "num_envs=0 is not allowed; allowed: an integer >= 1"),
    ({"num_envs": 2.5}, "num_envs=2.5 is not allowed"),
    ({"tensors": "jax"}, "tensors='jax' is not allowed; allowed: ['numpy', 'torch']"),
    ({"device": "gpu"}, "device 'gpu' is not a device"),
    ({"seed": -1}, "seed=-1 is not allowed; allowed: an integer in [0, 2**32)"),
    ({"seed": "0"}, "seed='0' is not allowed"),
    ({"geometry": "sdf"}, "geometry"),
    ({"cache_dir": 3}, "cache_dir=3 is not allowed; allowed: a path"),
    ({"preset": "fast"}, "preset='fast' is not allowed"),
    ({"render_mode": "human"}, "render_mode='human' is not allowed; allowed: None or one of ['rgb_array']"),
    ({"worlds": 4}, "worlds=4 is not a kwarg of the VKGRL ids; allowed:"),
    ({"kgrl_recipe": "fast"}, "kgrl_recipe='fast' is not allowed"),
])
def test_every_bad_kwarg_is_one_line_before_anything_is_built(name, kwargs, message, wp_cpu, monkeypatch):
    from vkgrl_newton.run import build

    monkeypatch.setattr(build, "build_env", lambda *a, **k: pytest.fail("an env was built before the refusal"))
    with pytest.raises(ValueError) as e:
        gym.make_vec(name, **{"num_envs": 2, "device": "cpu", **kwargs})
    assert message in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("kwargs, message", [
    ({"demos": "no_such.npz"}, "demos: "),
    ({"vae": "no_such.pt"}, "vae: "),
])
def test_a_bad_file_kwarg_is_one_line_before_anything_is_built(kwargs, message, wp_cpu, monkeypatch, tmp_path):
    from vkgrl_newton.run import build

    monkeypatch.setattr(build, "build_env", lambda *a, **k: pytest.fail("an env was built before the refusal"))
    with pytest.raises(ValueError) as e:  # (on the prior: the residual recipe, the default here, takes no vae)
        gym.make_vec("VKGRL/PegInsert-Factory-4D-Vision-KGRL-v0", num_envs=1, device="cpu", cache_dir=tmp_path,
                     kgrl_recipe="reach_keep_prior", **kwargs)
    assert message in str(e.value) and "does not exist" in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(ValueError, match="num_envs is not a kwarg of gymnasium.make"):
        gym.make("VKGRL/PegInsert-Factory-4D-v0", num_envs=2, device="cpu")


def test_a_closed_env_refuses_in_one_line_and_closes_twice_harmlessly(files, wp_cpu):
    envs = gym.make_vec(KGRL_ID, num_envs=1, **_kwargs(KGRL_ID, files))
    envs.reset(seed=0)
    envs.close()
    envs.close()  # harmless
    for call in (lambda: envs.step(np.zeros((1, 4), np.float32)), lambda: envs.reset(seed=0), envs.render):
        with pytest.raises(gym.error.ClosedEnvironmentError) as e:
            call()
        assert "closed" in str(e.value) and "\n" not in str(e.value)
