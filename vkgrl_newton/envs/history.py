"""A short history of the policy's inputs and actions, stacked onto its input (`--obs-history K`).

Why: an episode of the assembly tasks is decided by an error the proprioceptive policy cannot
observe (the in-hand offset, the target noise); where the part has been and what was commanded
there over the last few steps says where the hole is not. Isaac Lab's Factory gives its actor an
LSTM for this; a stack of the last K (input, action) pairs is the feed-forward form of it (a
deviation from eq. 5.5, off in the thesis).

The stacked input of world e at step t is [x_t, (x_{t-1}, a_{t-1}), ..., (x_{t-K}, a_{t-K})], oldest
last, with zeros for the steps before its episode began: a world at its episode's first step
(env.step_index == 0) starts with an empty history. `x` is the policy's own input (after
policy_observation and kgrl_observation), `a` the learner's action (the time action's a_t included).
The training loop and the evaluation policy stack alike, so both see the same inputs. Nothing of it
is checkpointed: a resumed run starts fresh episodes, whose histories start empty.
"""

from __future__ import annotations

import torch

__all__ = ["ObservationHistory", "stacked_width"]


def stacked_width(input_width: int, action_dim: int, k: int) -> int:
    """The stacked input's width: the current input plus k (input, action) pairs."""
    return input_width + k * (input_width + action_dim)


class ObservationHistory:
    """Per-world ring of the last k (input, action) pairs, on the env's device."""

    def __init__(self, num_envs: int, input_width: int, action_dim: int, k: int, device) -> None:
        if not (isinstance(k, int) and k >= 1):
            raise ValueError(f"k={k!r}: the steps of history, an int >= 1")
        self.k, self.input_width, self.action_dim = k, input_width, action_dim
        # pairs[:, 0] is the last step's (x, a), pairs[:, k - 1] the oldest
        self.pairs = torch.zeros(num_envs, k, input_width + action_dim, device=device)

    def stack(self, x: torch.Tensor, step_index: torch.Tensor | None = None) -> torch.Tensor:
        """x (E, input_width) with the history appended. With `step_index` (the env's), the worlds at an
        episode's first step start empty; without it (the state a finished episode ended in, for a
        time-out's bootstrap) the history is taken as it is."""
        if step_index is not None:  # in place, no host read
            self.pairs.masked_fill_((step_index == 0).view(-1, 1, 1), 0.0)
        return torch.cat([x, self.pairs.flatten(1)], -1)

    def push(self, x: torch.Tensor, a: torch.Tensor) -> None:
        """Record the step just acted on: its input x (E, input_width, unstacked) and action a (E, action_dim)."""
        self.pairs.copy_(torch.cat([torch.cat([x, a.to(x.dtype)], -1).unsqueeze(1), self.pairs[:, :-1]], 1))
