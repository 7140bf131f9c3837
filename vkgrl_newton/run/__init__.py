"""The run layer: everything train/run.py and train/evaluate.py do, as a library.

- `methods`: the one table of methods (learner, action path, observation parts).
- `presets`: a run's defaults per preset and the KGRL recipes (named deviations from the thesis).
- `config`: `RunConfig` (frozen) and the command line's options; `resolve`: options or a checkpoint
  -> a RunConfig, every refusal a `ConfigError` of one line.
- `build`: the one builder, RunConfig -> (encoder, env, action path, agent), shared by run.py,
  evaluate.py and the gymnasium ids (`gym`).
- `loops`: the SAC and PPO training loops; `train`: a run from its configuration to metrics.json.

The names below load on first use (PEP 562): `methods`, `presets` and `config` are plain data, so a
command line imports them before it has parsed its arguments, without torch or Warp.
"""

import importlib

_LAZY = {"RunConfig": "config", "ConfigError": "config", "build_parser": "config",
         "METHODS": "methods", "Method": "methods", "RUN_METHODS": "methods",
         "resolve": "resolve", "Resolved": "resolve", "Done": "resolve",
         "build": "build", "Built": "build", "train": "train"}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(f"vkgrl_newton.run.{_LAZY[name]}"), name)
    raise AttributeError(f"module 'vkgrl_newton.run' has no attribute {name!r}")
