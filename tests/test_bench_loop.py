"""tools/bench_loop.py's FLOP count of a SAC gradient step against torch's own FlopCounterMode on
the real update (the figure the benchmark divides by the update's time)."""

import pytest
import torch
from torch.utils.flop_counter import FlopCounterMode

from vkgrl_newton.agents.sac import SAC
from vkgrl_newton.agents.sac_config import make_sac_config
from vkgrl_newton.tools.bench_loop import sac_step_flops


@pytest.mark.parametrize("delay, hidden, n_critics, obs_dim", [(1, (32, 16), 2, 8), (2, (64, 32, 16), 3, 11),
                                                               (4, (48, 24), 2, 27)])
def test_the_flop_count_is_torchs_count_of_the_update(delay, hidden, n_critics, obs_dim):
    batch, n = 64, 400
    cfg = make_sac_config("thesis", hidden_dims=hidden, n_critics=n_critics, batch_size=batch, policy_delay=delay,
                          buffer_size=1000, learning_starts=0, cpu_matmul="torch")  # (F.linear/baddbmm: counted)
    agent = SAC(obs_dim, 4, cfg, "cpu", seed=0)
    g = torch.Generator().manual_seed(0)
    agent.add(torch.randn(n, obs_dim, generator=g), torch.rand(n, 4, generator=g) * 2 - 1,
              torch.rand(n, generator=g) + 0.1, torch.randn(n, obs_dim, generator=g), torch.zeros(n))
    agent.update(delay)  # the actor starts with the first update too (no actor_after_reward here)
    counter = FlopCounterMode(display=False)
    with counter:
        agent.update(delay)  # one policy-delay cycle: the actor's update once
    assert counter.get_total_flops() / delay == sac_step_flops(obs_dim, 4, hidden, n_critics, batch, delay)
