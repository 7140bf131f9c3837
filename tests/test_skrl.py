"""skrl (https://skrl.readthedocs.io, torch) trains on the gymnasium ids (issue 42 item 3).

The env takes no adapter: skrl's own `wrap_env(envs, wrapper="gymnasium")` takes the AssemblyVectorEnv
as it is. The agent does: `vkgrl_newton.envs.skrl.with_final_obs` records an ended episode's
`info["final_obs"]` as the next observation (skrl would record the new episode's first, autoreset
SAME_STEP) and a blown-up world's row as terminal; the tests below hold it to that.
"""

from __future__ import annotations

import math
import re

import gymnasium as gym
import numpy as np
import pytest
import torch
from scripts import ROOT

import vkgrl_newton  # noqa: F401  (registers the ids)

skrl = pytest.importorskip("skrl")

from skrl.agents.torch.ppo import PPO  # noqa: E402
from skrl.agents.torch.sac import SAC  # noqa: E402
from skrl.envs.wrappers.torch import wrap_env  # noqa: E402
from skrl.memories.torch import RandomMemory  # noqa: E402
from skrl.models.torch import DeterministicMixin, GaussianMixin, Model  # noqa: E402
from skrl.resources.preprocessors.torch import RunningStandardScaler  # noqa: E402
from skrl.trainers.torch import SequentialTrainer  # noqa: E402

from vkgrl_newton.envs.skrl import FinalObs, with_final_obs  # noqa: E402

pytestmark = pytest.mark.usefixtures("torch_one_thread")

ID = "VKGRL/PegInsert-Factory-4D-KGRL-v0"
STEPS = 160  # batched steps of 2 worlds: 320 transitions, one time-out of every world (150 steps per episode)
TRAINER = {"timesteps": STEPS, "headless": True, "disable_progressbar": True, "close_environment_at_exit": False}


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    from vkgrl_newton.kmp.demos import synthetic_demos

    return synthetic_demos("PegInsert", 8, action_dim=6, seed=1).save(tmp_path_factory.mktemp("demos") / "d.npz")


@pytest.fixture(scope="module")
def envs(demos, tmp_path_factory, wp_cpu):
    """The KGRL id's 2 worlds on the CPU (the SAC and PPO tests share them: skrl resets them once per wrapper)."""
    envs = gym.make_vec(ID, num_envs=2, device="cpu", cache_dir=tmp_path_factory.mktemp("skrl") / "cache", demos=demos)
    yield envs
    envs.close()


def mlp(n_in: int, n_out: int) -> torch.nn.Sequential:
    return torch.nn.Sequential(torch.nn.Linear(n_in, 64), torch.nn.ELU(), torch.nn.Linear(64, 64), torch.nn.ELU(),
                               torch.nn.Linear(64, n_out))


class Policy(GaussianMixin, Model):
    def __init__(self, observation_space, action_space, device):
        Model.__init__(self, observation_space=observation_space, action_space=action_space, device=device)
        GaussianMixin.__init__(self, clip_actions=True)
        self.net = mlp(self.num_observations, 2 * self.num_actions)

    def compute(self, inputs, role=""):
        mean, log_std = self.net(inputs["observations"]).chunk(2, dim=-1)
        return torch.tanh(mean), {"log_std": log_std}


class Critic(DeterministicMixin, Model):
    def __init__(self, observation_space, action_space, device, with_action=True):
        Model.__init__(self, observation_space=observation_space, action_space=action_space, device=device)
        DeterministicMixin.__init__(self)
        self.with_action = with_action
        self.net = mlp(self.num_observations + (self.num_actions if with_action else 0), 1)

    def compute(self, inputs, role=""):
        x = inputs["observations"]
        return self.net(torch.cat([x, inputs["taken_actions"]], dim=-1) if self.with_action else x), {}


def sac_models(spaces: dict, seed: int) -> dict:
    torch.manual_seed(seed)
    return {"policy": Policy(**spaces)} | {name: Critic(**spaces) for name in
                                           ("critic_1", "critic_2", "target_critic_1", "target_critic_2")}


def ppo_models(spaces: dict, seed: int) -> dict:
    torch.manual_seed(seed)
    return {"policy": Policy(**spaces), "value": Critic(**spaces, with_action=False)}


def mean_actions(agent, obs: torch.Tensor) -> torch.Tensor:
    """The agent's deterministic action (its policy's mean) through its own act (and preprocessor)."""
    with torch.no_grad():
        return agent.act(obs, None, timestep=10**6, timesteps=10**6)[1]["mean_actions"]


def params(model) -> list[torch.Tensor]:
    return [p.detach().clone() for p in model.parameters()]


def check_saved_agent_acts_the_same(agent, fresh, path, obs) -> None:
    """agent.save -> a fresh agent (other initial weights) -> load: the same deterministic actions, bit for bit."""
    agent.save(str(path))
    assert not torch.equal(mean_actions(fresh, obs), mean_actions(agent, obs))  # else the load proves nothing
    fresh.load(str(path))
    torch.testing.assert_close(mean_actions(fresh, obs), mean_actions(agent, obs), rtol=0, atol=0)


def test_skrl_sac_trains_on_the_kgrl_id_and_bootstraps_time_outs_from_the_final_observation(envs, tmp_path):
    # no adapter for the env: skrl's own gymnasium wrapper takes the AssemblyVectorEnv as it is
    env = wrap_env(envs, wrapper="gymnasium")
    assert type(env).__name__ == "GymnasiumWrapper" and env.num_envs == 2 and str(env.device) == "cpu"
    assert env.observation_space.shape == (8,) and env.action_space.shape == (4,)
    spaces = {"observation_space": env.observation_space, "action_space": env.action_space, "device": env.device}
    memory = RandomMemory(memory_size=STEPS, num_envs=env.num_envs, device=env.device)
    cfg = {"batch_size": 32, "learning_starts": 32, "random_timesteps": 16,
           # write_interval beyond the run: skrl keeps every tracked loss (it clears them when it writes)
           "experiment": {"directory": str(tmp_path), "write_interval": 10**6, "checkpoint_interval": 0}}
    agent = with_final_obs(SAC)(models=sac_models(spaces, seed=0), memory=memory, cfg=cfg, **spaces)
    before = params(agent.policy)
    SequentialTrainer(env=env, agents=agent, cfg=TRAINER).train()

    # learning ran: one gradient step per batched step from learning_starts on, finite losses, new weights
    for name in ("Loss / Critic loss", "Loss / Policy loss", "Loss / Entropy loss"):
        losses = agent.tracking_data[name]
        assert len(losses) == STEPS - 32 and all(math.isfinite(v) for v in losses), name
    assert any(not torch.equal(a, b) for a, b in zip(before, params(agent.policy)))
    assert len(memory) == 2 * STEPS

    # the replay's transitions: the observation's first entry is the episode's normalized time (thesis eq. 5.5)
    obs, nxt = memory.get_tensor_by_name("observations"), memory.get_tensor_by_name("next_observations")
    assert torch.isfinite(obs).all() and torch.isfinite(nxt).all()
    assert (obs[1:, :, 0] < obs[:-1, :, 0]).any(axis=0).all()  # every world timed out and began a new episode
    # ... and every transition moves forward in time, the time-outs' too: their next observation is the
    # episode's last (info["final_obs"]), not the new episode's first that skrl's trainer passes
    assert (nxt[:, :, 0] > obs[:, :, 0]).all()

    fresh = with_final_obs(SAC)(models=sac_models(spaces, seed=1), memory=None, cfg=cfg, **spaces)
    check_saved_agent_acts_the_same(agent, fresh, tmp_path / "sac.pt", obs.reshape(-1, 8)[::10])


def test_skrl_ppo_trains_on_the_kgrl_id_and_loads_its_checkpoint(envs, tmp_path):
    env = wrap_env(envs, wrapper="gymnasium")  # no adapter for the env (see the SAC test)
    spaces = {"observation_space": env.observation_space, "action_space": env.action_space, "device": env.device}
    rollouts = 32
    memory = RandomMemory(memory_size=rollouts, num_envs=env.num_envs, device=env.device)
    cfg = {"rollouts": rollouts, "learning_epochs": 2, "mini_batches": 2, "learning_rate": 3e-4,
           "time_limit_bootstrap": True,  # with_final_obs requires it (skrl's GAE otherwise runs across episode ends)
           "observation_preprocessor": RunningStandardScaler,
           "observation_preprocessor_kwargs": {"size": env.observation_space, "device": env.device},
           "experiment": {"directory": str(tmp_path), "write_interval": 10**6, "checkpoint_interval": 0}}
    agent = with_final_obs(PPO)(models=ppo_models(spaces, seed=0), memory=memory, cfg=cfg, **spaces)
    before = params(agent.policy)
    SequentialTrainer(env=env, agents=agent, cfg=TRAINER).train()

    updates = STEPS // rollouts
    for name in ("Loss / Policy loss", "Loss / Value loss"):
        losses = agent.tracking_data[name]
        assert len(losses) == updates and all(math.isfinite(v) for v in losses), name
    assert any(not torch.equal(a, b) for a, b in zip(before, params(agent.policy)))
    assert memory.get_tensor_by_name("truncated").any()  # the last rollout held the time-out (steps 128-160)

    obs = memory.get_tensor_by_name("observations").reshape(-1, 8)[::4]
    fresh = with_final_obs(PPO)(models=ppo_models(spaces, seed=1), memory=None, cfg=cfg, **spaces)
    check_saved_agent_acts_the_same(agent, fresh, tmp_path / "ppo.pt", obs)  # the scaler's statistics included


class _Recorder:
    """A stand-in for a skrl agent's record_transition: keeps what it was given."""

    def __init__(self, cfg=None):
        self.cfg = cfg

    def record_transition(self, **kwargs):
        self.got = kwargs


def test_with_final_obs_takes_the_final_observation_and_ends_blown_up_worlds():
    agent = type("Agent", (FinalObs, _Recorder), {})()
    nxt = torch.zeros(3, 2)  # the step's observations: the reset worlds' new first ones
    info = {"final_obs": np.array([[0, 0], [1, 1], [np.nan, np.nan]], np.float32),
            "_final_obs": np.array([0, 1, 1], bool),
            "final_info": {"success": np.zeros(3, bool), "physics_reset": np.array([0, 0, 1], bool)}}
    done = torch.tensor([[False], [True], [True]])
    agent.record_transition(next_observations=nxt, terminated=torch.zeros(3, 1, dtype=torch.bool), truncated=done,
                            infos=info, rewards=torch.zeros(3, 1))
    got = agent.got
    torch.testing.assert_close(got["next_observations"], torch.tensor([[0.0, 0], [1, 1], [0, 0]]))  # no NaN kept
    assert got["terminated"].view(-1).tolist() == [False, False, True]  # the blown-up world: terminal
    assert got["truncated"].view(-1).tolist() == [False, True, False]  # the time-out: bootstrapped
    # steps without an ended world pass through untouched
    agent.record_transition(next_observations=nxt, terminated=done, truncated=done, infos={}, rewards=None)
    assert agent.got["next_observations"] is nxt and agent.got["terminated"] is done
    with pytest.raises(ValueError, match="one agent on all worlds"):  # simultaneous agents: infos are not sliced
        agent.record_transition(next_observations=nxt[:2], terminated=done[:2], truncated=done[:2], infos=info)


def test_with_final_obs_refuses_ppo_without_time_limit_bootstrap():
    box = gym.spaces.Box(-1.0, 1.0, (4,), np.float32)
    spaces = {"observation_space": gym.spaces.Box(-np.inf, np.inf, (8,), np.float32), "action_space": box,
              "device": "cpu"}
    with pytest.raises(ValueError, match="time_limit_bootstrap=True is needed"):
        with_final_obs(PPO)(models=ppo_models(spaces, seed=0), memory=None, cfg={}, **spaces)
    agent = with_final_obs(PPO)(models=ppo_models(spaces, seed=0), memory=None, cfg={"time_limit_bootstrap": True},
                                **spaces)
    assert isinstance(agent, PPO) and type(agent).__name__ == "PPO"


README_SMALL = {  # the README's skrl example at test size (each replacement must apply: a changed README fails here)
    'num_envs=16)': 'num_envs=2, device="cpu", cache_dir=CACHE, demos=DEMOS)',
    'memory_size=62_500': 'memory_size=160',
    '"batch_size": 256': '"batch_size": 32',
    '"learning_starts": 320, "random_timesteps": 320': '"learning_starts": 32, "random_timesteps": 16',
    '"directory": "runs/skrl_sac"': '"directory": LOGDIR',
    '"timesteps": 30_000, "headless": True': '"timesteps": 160, "headless": True, "disable_progressbar": True, '
                                            '"close_environment_at_exit": False',
}


def test_the_readmes_skrl_example_runs(demos, tmp_path, wp_cpu):
    """The README's skrl SAC example, run as written but at test size (no adapter for the env there either)."""
    readme = (ROOT / "README.md").read_text()
    section = readme.split("\n## skrl\n")[1].split("\n## ")[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert len(blocks) == 1 and "wrap_env(" in blocks[0] and "with_final_obs(SAC)" in blocks[0]
    block = blocks[0]
    for old, new in README_SMALL.items():
        assert block.count(old) == 1, f"the README's skrl example no longer has {old!r}"
        block = block.replace(old, new)
    scope = {"CACHE": tmp_path / "cache", "DEMOS": demos, "LOGDIR": str(tmp_path / "skrl")}
    exec(compile(block, "README.md", "exec"), scope)
    agent, memory = scope["agent"], scope["memory"]
    assert len(memory) == 2 * 160 and torch.isfinite(memory.get_tensor_by_name("next_observations")).all()
    # skrl's automatic checkpoints (every 16 steps here): the first is from before learning_starts, the
    # last from after 128 gradient steps
    ckpt = sorted((tmp_path / "skrl").glob("*/checkpoints/agent_*.pt"), key=lambda p: int(p.stem.split("_")[1]))
    assert [int(p.stem.split("_")[1]) for p in ckpt] == list(range(16, 161, 16))
    first = torch.load(ckpt[0], weights_only=False)["policy"]
    now = agent.policy.state_dict()
    assert any(not torch.equal(first[k], now[k]) for k in now)
    scope["env"].close()
