"""The gymnasium ids, the VectorEnv contract and the stable-baselines3 adapter (issue 29)."""

from __future__ import annotations

import re

import gymnasium as gym
import numpy as np
import pytest
import torch
from scripts import ROOT

import vkgrl_newton  # noqa: F401  (registers the ids)
from vkgrl_newton.registration import VARIANTS, env_id, env_ids
from vkgrl_newton.tasks import ACTION_DIMS, FAMILIES, TASKS, observation_dim

pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def peg4(wp_cpu):
    """One 2-world PegInsert Factory 4D env, shared by the vector-env tests of this module."""
    from vkgrl_newton.envs.assembly_env import AssemblyEnv, EnvConfig

    return AssemblyEnv(EnvConfig(task="PegInsert", family="factory", action_dim=4, num_envs=2, device="cpu", seed=0))


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    from vkgrl_newton.kmp.demos import synthetic_demos

    return synthetic_demos("PegInsert", 6, action_dim=6, seed=0).save(tmp_path_factory.mktemp("demos") / "d.npz")


def test_every_configuration_has_one_id_registered_and_in_the_readme():
    ids = env_ids()
    assert len(ids) == len(TASKS) * len(FAMILIES) * len(ACTION_DIMS) * len(VARIANTS) == 48
    readme = (ROOT / "README.md").read_text()
    for name, kw in ids.items():
        spec = gym.spec(name)
        assert spec.vector_entry_point == "vkgrl_newton.run.gym:make_vec_env" and spec.kwargs == kw
        assert env_id(**kw) == name and re.fullmatch(r"VKGRL/[A-Za-z]+-(Factory|Forge)-[46]D(-Vision)?(-KGRL)?-v0",
                                                    name)
        assert f"`{name}`" in readme, f"README's table of ids lacks {name}"
    vkgrl_newton.registration.register_envs()  # again: idempotent
    assert sum(k.startswith("VKGRL/") for k in gym.registry) == 48


@pytest.mark.parametrize("kwargs, message", [
    ({"num_envs": 0}, "num_envs=0 is not allowed; allowed: an integer >= 1"),
    ({"tensors": "jax"}, "tensors='jax' is not allowed; allowed: ['numpy', 'torch']"),
    ({"device": "gpu"}, "device 'gpu' is not a device"),
    ({"device": "cuda:7"}, "device cuda:7: Warp sees"),
    ({"geometry": "mesh"}, "geometry 'mesh' exists for ['GearMesh', 'NutThread'], not PegInsert"),
    ({"vae": "x.pt"}, "vae is for the Vision ids"),
])
def test_bad_kwargs_are_one_line_errors_before_anything_is_built(kwargs, message, wp_cpu):
    with pytest.raises(ValueError) as e:
        gym.make_vec("VKGRL/PegInsert-Factory-4D-v0", **{"num_envs": 2, **kwargs})
    assert message in str(e.value) and "\n" not in str(e.value)


def test_a_bad_id_is_gymnasiums_error_naming_it():
    with pytest.raises(gym.error.Error, match="PegInsert-Factory-5D"):
        gym.make_vec("VKGRL/PegInsert-Factory-5D-v0", num_envs=2)


def test_vector_contract_spaces_reset_seed_and_steps(peg4, demos, tmp_path):
    from vkgrl_newton.run.gym import make_vec_env

    envs = make_vec_env("PegInsert", "factory", 4, method="kgrl", num_envs=2, device="cpu", cache_dir=tmp_path,
                             demos=demos, env=peg4)
    assert envs.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP
    assert envs.single_observation_space.shape == (observation_dim("factory", 0),)
    assert envs.action_space.shape == (2, 4) and envs.action_space.dtype == np.float32
    first, info = envs.reset(seed=7)
    again, _ = envs.reset(seed=7)
    other, _ = envs.reset(seed=8)
    assert info == {} and first.dtype == np.float32 and envs.observation_space.contains(first)
    np.testing.assert_array_equal(first, again)  # a seed gives the same initial states, world by world
    assert not np.array_equal(first, other)
    obs, reward, terminated, truncated, info = envs.step(envs.action_space.sample())
    assert obs.shape == (2, 8) and reward.shape == (2,) and reward.dtype == np.float32
    assert terminated.dtype == truncated.dtype == np.bool_ and not terminated.any() and not truncated.any()
    with pytest.raises(ValueError, match=r"actions must have shape \(2, 4\)"):
        envs.step(np.zeros((2, 6), np.float32))
    with pytest.raises(ValueError, match="a list of seeds is not supported"):
        envs.reset(seed=[1, 2])


def test_time_out_gives_the_pre_reset_observation_as_final_obs(peg4, demos, tmp_path):
    """The ended episode's last observation, captured independently just before the env resets the
    worlds, is info['final_obs']; the returned observation is the new episode's first (time 0)."""
    from vkgrl_newton.run.gym import make_vec_env

    envs = make_vec_env("PegInsert", "factory", 4, method="kgrl", num_envs=2, device="cpu", cache_dir=tmp_path,
                             demos=demos, env=peg4, tensors="torch")
    captured = []
    original = peg4._reset_worlds

    def capture(mask):
        captured.append(peg4.get_observations()["policy"].clone())
        return original(mask)

    envs.reset(seed=1)
    peg4._reset_worlds = capture
    try:
        for step in range(peg4.max_episode_length):
            obs, reward, terminated, truncated, info = envs.step(torch.zeros(2, 4))
            if truncated.any():
                break
    finally:
        del peg4._reset_worlds
    assert step == peg4.max_episode_length - 1 and truncated.all() and isinstance(obs, torch.Tensor)
    assert info["_final_obs"].all() and info["_final_info"].all()
    torch.testing.assert_close(info["final_obs"], captured[-1], rtol=0, atol=0)
    assert torch.equal(info["final_obs"][:, 0], torch.ones(2)) and torch.equal(obs[:, 0], torch.zeros(2))
    assert info["final_info"]["physics_reset"].dtype == torch.bool and not info["final_info"]["physics_reset"].any()
    # the prior (a = 0) either seated the peg or not; success is the env's own per-world record
    assert torch.equal(info["final_info"]["success"], peg4.last_episode_success_any)


def test_stable_baselines3_sac_trains_through_the_adapter_and_reloads(peg4, demos, tmp_path):
    sb3 = pytest.importorskip("stable_baselines3")
    from vkgrl_newton.envs.sb3 import SB3VecEnv
    from vkgrl_newton.run.gym import make_vec_env

    venv = make_vec_env("PegInsert", "factory", 4, method="kgrl", num_envs=2, device="cpu", cache_dir=tmp_path,
                             demos=demos, env=peg4)
    env = SB3VecEnv(venv)
    env.seed(3)
    model = sb3.SAC("MlpPolicy", env, learning_starts=64, batch_size=32, buffer_size=1000, train_freq=1,
                    gradient_steps=1, policy_kwargs={"net_arch": [32, 32]}, seed=0, device="cpu")
    model.learn(total_timesteps=320)  # 160 env steps x 2 worlds: crosses one time-out
    assert model.num_timesteps >= 320 and model.replay_buffer.size() >= 150
    ended = model.replay_buffer.timeouts[: model.replay_buffer.size()].any(axis=1)
    assert ended.sum() == 1  # the time-out step: stored as truncated (SB3 bootstraps it)
    model.save(tmp_path / "sac.zip")
    loaded = sb3.SAC.load(tmp_path / "sac.zip", device="cpu")
    obs = env.reset()
    action, _ = loaded.predict(obs, deterministic=True)
    assert action.shape == (2, 4) and np.all(np.abs(action) <= 1)
    np.testing.assert_array_equal(action, model.predict(obs, deterministic=True)[0])


def test_rsl_rl_ppo_runs_in_the_prior_null_space_and_its_checkpoint_reloads(peg4, demos, tmp_path):
    """rsl-rl's OnPolicyRunner with Factory's PPO settings (agents/ppo.py) on the KGRL env: two
    iterations of 16 steps x 2 worlds, saved, loaded into a fresh runner: the same actions."""
    from rsl_rl.runners import OnPolicyRunner

    from vkgrl_newton.envs.kgrl_action import KGRLActionPath

    from vkgrl_newton.prepare.prior import load_or_make_prior
    from vkgrl_newton.agents.ppo import FACTORY_PPO, ppo_train_cfg
    from vkgrl_newton.envs.rsl_rl import KGRLVecEnv

    cfg = ppo_train_cfg("PegInsert", "factory", 2, num_steps_per_env=16)
    assert cfg["algorithm"]["num_mini_batches"] == 1 and cfg["algorithm"]["gamma"] == 0.995
    assert ppo_train_cfg("NutThread", "forge", 128)["num_steps_per_env"] == 256
    assert ppo_train_cfg("PegInsert", "factory", 128)["algorithm"]["num_mini_batches"] == 32  # 512 each
    assert FACTORY_PPO["num_steps_per_env"] == 128  # the template is not changed by a call
    with pytest.raises(ValueError, match="PPO setting 'algorithm.gama' unknown|PPO setting 'gama' unknown"):
        ppo_train_cfg("PegInsert", "factory", 2, **{"algorithm.gama": 0.9})
    tables, _ = load_or_make_prior("PegInsert", 4, tmp_path, demos=demos, device="cpu", log=lambda m: None)
    env = KGRLVecEnv(peg4, KGRLActionPath(tables, peg4))
    env.reset()
    runner = OnPolicyRunner(env, cfg, log_dir=str(tmp_path / "ppo"), device="cpu")
    runner.learn(num_learning_iterations=2)
    # the runner steps under torch.inference_mode: the env's state must stay writable outside it
    env.reset()
    env.step(torch.zeros(2, 4))
    saved = sorted((tmp_path / "ppo").glob("model_*.pt"))
    assert saved and (tmp_path / "ppo").glob("events.out.tfevents.*")
    obs = env.get_observations()
    act = runner.get_inference_policy(device="cpu")(obs)
    assert act.shape == (2, 4) and torch.isfinite(act).all()
    fresh = OnPolicyRunner(env, ppo_train_cfg("PegInsert", "factory", 2, num_steps_per_env=16), log_dir=None,
                           device="cpu")
    fresh.load(str(saved[-1]))
    torch.testing.assert_close(fresh.get_inference_policy(device="cpu")(obs), act, rtol=0, atol=0)


README_SMALL = {  # the README's examples at test size (each replacement must apply: a changed README fails here)
    'num_envs=16)': 'num_envs=2, device="cpu", cache_dir=CACHE, demos=DEMOS)',
    'learning_starts=1024).learn(30_000)': 'learning_starts=16, batch_size=16).learn(64)',
    'ppo_train_cfg("PegInsert", "factory", 16,': 'ppo_train_cfg("PegInsert", "factory", 2, num_steps_per_env=8,',
    'log_dir="runs/my_ppo"': 'log_dir=LOGDIR',
    'num_learning_iterations=15': 'num_learning_iterations=1',
}


def test_the_readmes_learner_examples_run(demos, tmp_path, wp_cpu):
    """The README's stable-baselines3 and rsl-rl examples, run as written but at test size."""
    pytest.importorskip("stable_baselines3")
    readme = (ROOT / "README.md").read_text()
    section = readme.split("## Your own learner")[1].split("\n## ")[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert len(blocks) == 2 and "stable_baselines3" in blocks[0] and "OnPolicyRunner" in blocks[1]
    for block in blocks:
        for old, new in README_SMALL.items():
            if old in block:
                block = block.replace(old, new)
        assert not any(old in block for old in README_SMALL)
        scope = {"CACHE": tmp_path / "cache", "DEMOS": demos, "LOGDIR": str(tmp_path / "ppo")}
        exec(compile(block, "README.md", "exec"), scope)
    assert scope["runner"].current_learning_iteration == 0 and sorted((tmp_path / "ppo").glob("model_*.pt"))
    assert scope["runner"].alg.get_policy().output_std.detach().max() < 0.2  # kgrl_ppo's init_std 0.1, not 1
    used = "".join(blocks)
    assert all(old in used for old in README_SMALL)  # every replacement applied to some block


@pytest.mark.slow
@pytest.mark.parametrize("task", sorted(TASKS))
def test_every_registered_id_makes_resets_and_steps(task, tmp_path_factory, wp_cpu):
    """Each of the task's 16 ids through gymnasium.make_vec with 1 world on the CPU: the KGRL ids with
    synthetic demonstrations of the task, the Vision ids with an untrained 32-px VAE of the task (their
    prior and encoder as the ids prepare them, without the minutes of recording and training)."""
    from vkgrl_newton.kmp.demos import synthetic_demos
    from vkgrl_newton.vision import DenoisingVAE, VAEConfig, save_vae

    root = tmp_path_factory.mktemp(f"ids_{task}")
    demos = synthetic_demos(task, 6, action_dim=6, seed=0).save(root / "demos.npz")
    cfg = VAEConfig(resolution=32, channels=(8, 16, 16, 32, 32), groups=8)
    vae = save_vae(root / "vae.pt", DenoisingVAE(cfg, torch.Generator().manual_seed(0)), cfg, {"task": task})
    ids = {name: kw for name, kw in env_ids().items() if kw["task"] == task}
    assert len(ids) == 16
    for name, kw in ids.items():
        extra = {"demos": demos} if "kgrl" in kw["method"] else {}
        extra |= {"vae": vae} if "vision" in kw["method"] else {}
        if kw["method"] == "vision_kgrl":  # (a given vae: not with the residual recipe, the quick default on
            extra |= {"kgrl_recipe": "reach_keep_prior"}  # PegInsert Factory 4D, whose probe is the cache's VAE's)
        envs = gym.make_vec(name, num_envs=1, device="cpu", cache_dir=root, **extra)
        obs, _ = envs.reset(seed=0)
        dim = observation_dim(kw["family"], 16 if "vision" in kw["method"] else 0)
        assert obs.shape == (1, dim) and obs.dtype == np.float32, name
        obs, reward, terminated, truncated, _ = envs.step(envs.action_space.sample())
        assert obs.shape == (1, dim) and np.isfinite(obs).all() and np.isfinite(reward).all(), name
        assert envs.action_space.shape == (1, kw["action_dim"]) and not terminated.any(), name
        envs.close()
