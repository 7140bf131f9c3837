"""Shared test setup: every test runs on the CPU device."""

import os
import tempfile

import pytest

os.environ.setdefault("CUDA_VISIBLE_DEVICES", "")
# A SAC built with cpu_matmul="auto" outside a run keeps its per-machine choice in the user's cache
# (agents/matmul_backend.py); the tests keep theirs apart, in a directory of the session's own.
os.environ.setdefault("VKGRL_NEWTON_CACHE_DIR", tempfile.mkdtemp(prefix="vkgrl_test_cache_"))


@pytest.fixture(scope="module")
def torch_one_thread():
    """One torch intra-op thread for a module of small-net tests, restored afterwards."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def wp_cpu():
    """Warp, initialized once per session, quiet, with the CPU device as default."""
    import warp as wp

    from vkgrl_newton.runtime import configure_warp

    configure_warp(verbose=False)
    wp.set_device("cpu")
    return wp


@pytest.fixture(scope="session")
def peg_env(wp_cpu):
    """One 4-world PegInsert env (Factory, 6-D actions, seed 0) on the CPU, shared by the env tests.

    Constructing it builds the scene and the MuJoCo-Warp solver and resets every world (IK + 30
    physics steps). Tests that need a freshly reset env call `env.reset()` themselves when
    `episode_length_buf` shows the env has stepped; tests that corrupt the state run last.
    """
    from vkgrl_newton.envs.assembly_env import AssemblyEnv, EnvConfig

    return AssemblyEnv(EnvConfig(task="PegInsert", family="factory", action_dim=6, num_envs=4, device="cpu", seed=0))
