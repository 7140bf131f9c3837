"""`cpu_matmul="auto"`: the SAC networks' CPU matmul library chosen per machine, by timing.

Why: which library is faster depends on the CPU. MKL's sgemm dispatches its AVX-512 kernels on
Intel only (AVX2 on AMD), oneDNN runs AVX-512 on both; on a 2-core AMD EPYC oneDNN is ~1.5x MKL
on the thesis network's update, on a 2-core Intel Xeon MKL is ~1.4x oneDNN (docs/benchmarks.md).
No rule of thumb on the CPU's name holds for every model and thread count, so, as FFTW keeps its
"wisdom", the choice is measured once per machine on the run's own layer shapes (about a second)
and kept in a JSON file; every later run on that machine reads the same choice and so stays
bitwise reproducible.

The key of a kept choice: the CPU model, the core count, torch's thread count and version, and
the networks' shapes (observation and action widths, hidden layers, critics, LayerNorm, batch).
What is timed: the SAC gradient step itself, on the run's networks, batch and policy delay.
Where oneDNN is missing (or disagrees with `F.linear`), "auto" is "torch", without timing. On
CUDA both backends are cuBLAS; "auto" is "torch" there.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from pathlib import Path

import torch

from .._io import atomic_write_text, strict_json
from ..cache import entry_lock
from ..runtime import cpu_model
from .dense import onednn_available
from .sac_config import MATMUL_BACKENDS, SACConfig

__all__ = ["choose_cpu_matmul", "choice_key", "time_backends", "default_choice_file", "CHOICE_FILE"]

CHOICE_FILE = "cpu_matmul.json"  # in a run's cache directory (runs/cache/)
_FORMAT = 1


def default_choice_file() -> Path:
    """Where a SAC built outside a run (gym ids, skrl, a script) keeps its choice: the user's cache
    ($VKGRL_NEWTON_CACHE_DIR, else $XDG_CACHE_HOME/vkgrl_newton, else ~/.cache/vkgrl_newton), as Warp
    keeps its kernel cache. run.py keeps it in its --cache-dir instead."""
    if d := os.environ.get("VKGRL_NEWTON_CACHE_DIR"):
        return Path(d) / CHOICE_FILE
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "vkgrl_newton" / CHOICE_FILE


def choice_key(cfg: SACConfig, obs_dim: int, action_dim: int) -> str:
    """What a kept choice holds for: this machine, this torch, these shapes."""
    shapes = (f"obs{obs_dim}-act{action_dim}-h{'x'.join(map(str, cfg.hidden_dims))}-q{cfg.n_critics}"
              f"-ln{int(cfg.critic_layer_norm)}-b{cfg.batch_size}-{cfg.activation}")
    return (f"{cpu_model()} | cores {os.cpu_count()} | threads {torch.get_num_threads()} | "
            f"torch {torch.__version__} | {shapes}")


def time_backends(cfg: SACConfig, obs_dim: int, action_dim: int, rounds: int = 7,
                  min_call_s: float = 0.05) -> dict[str, float]:
    """Seconds of one SAC gradient step (`SAC.update(1)`, this config's networks, batch and policy
    delay, on random transitions) per backend, on the CPU: the fastest of `rounds` timed calls.

    On one torch thread (run.py's) the clock is the process's CPU time (time.process_time), not the
    wall's: on a shared machine (a sweep's other trials, a test suite) the wall time of a step is
    mostly the time the process waits for a core, alike for both libraries, and it made the choice a
    coin toss; the CPU time the step takes is what the library decides. On several threads it is the
    wall's (CPU time would count the threads' spin-waits at every barrier), which a loaded machine
    disturbs: the kept entry records the load average it was measured under. The fastest of the calls, as another process on the cores only
    ever adds to it (caches, memory bandwidth). Timed interleaved (drift hits both alike), after a
    warm-up; each call repeats enough steps to last >= min_call_s of CPU time (and a whole
    policy-delay cycle), so the clock's resolution does not decide."""
    from .sac import SAC  # (sac.py imports this module)

    n = max(4 * cfg.batch_size, 1024)
    gen = torch.Generator().manual_seed(0)
    data = (torch.randn(n, obs_dim, generator=gen), torch.rand(n, action_dim, generator=gen) * 2 - 1,
            torch.rand(n, generator=gen) + 0.1, torch.randn(n, obs_dim, generator=gen), torch.zeros(n))
    # the same work as the run's steps; the prior buffer and cloning only add backend-independent rows
    bare = dict(buffer_size=n, learning_starts=0, prior_rollouts=0, prior_ratio=0.0, bc_weight=0.0,
                prior_rollouts_policy="prior")
    agents = {}
    for backend in MATMUL_BACKENDS:
        agent = SAC(obs_dim, action_dim, dataclasses.replace(cfg, cpu_matmul=backend, **bare), "cpu", seed=0)
        agent.add(*data)
        agent.update(max(2, cfg.policy_delay))  # warm-up: allocator, optimizer state, oneDNN's primitive cache
        agents[backend] = agent
    clock = time.process_time if torch.get_num_threads() == 1 else time.perf_counter
    t = clock()
    agents["torch"].update(cfg.policy_delay)
    per_step = max(clock() - t, 1e-6) / cfg.policy_delay
    steps = cfg.policy_delay * max(1, math.ceil(min_call_s / per_step / cfg.policy_delay))
    times: dict[str, list[float]] = {b: [] for b in MATMUL_BACKENDS}
    for _ in range(rounds):
        for backend, agent in agents.items():
            t = clock()
            agent.update(steps)
            times[backend].append((clock() - t) / steps)
    return {b: min(ts) for b, ts in times.items()}


def _read(path: Path) -> dict:
    """The kept choices; a missing or damaged file holds none (it is measured and written again)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(data, dict) or data.get("format") != _FORMAT or not isinstance(data.get("choices"), dict):
        return {}
    return {k: v for k, v in data["choices"].items()
            if isinstance(v, dict) and v.get("backend") in MATMUL_BACKENDS}


def choose_cpu_matmul(cfg: SACConfig, obs_dim: int, action_dim: int, device: torch.device | str = "cpu",
                      choice_file: Path | str | None = None, log=None, threads: int | None = None) -> str:
    """The backend "auto" means here: the kept choice for this machine and these shapes, else the
    faster of the two, timed now and kept (under the file's lock: runs starting together time once).

    A concrete cfg.cpu_matmul is returned as it is. `threads`: the torch intra-op threads the run
    will use, when it sets them later (run.py: 1); the choice is made, and kept, for that count.
    `log(str)` hears a new measurement."""
    if cfg.cpu_matmul != "auto":
        return cfg.cpu_matmul
    if torch.device(device).type != "cpu" or not onednn_available():
        return "torch"  # cuBLAS on CUDA; torch's (MKL's) matmul where this torch has no oneDNN linear
    before = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    try:
        return _choose(cfg, obs_dim, action_dim, choice_file, log)
    finally:
        torch.set_num_threads(before)


def _choose(cfg: SACConfig, obs_dim: int, action_dim: int, choice_file, log) -> str:
    path = Path(choice_file) if choice_file is not None else default_choice_file()
    key = choice_key(cfg, obs_dim, action_dim)
    if (kept := _read(path).get(key)) is not None:
        return kept["backend"]
    with entry_lock(path, log=log or (lambda _msg: None), what="the CPU matmul choice"):
        choices = _read(path)  # another run may have measured it while this one waited
        if key in choices:
            return choices[key]["backend"]
        seconds = time_backends(dataclasses.replace(cfg, cpu_matmul="torch"), obs_dim, action_dim)
        backend = min(seconds, key=seconds.get)
        choices[key] = {"backend": backend, "seconds_per_step": seconds,
                        "clock": "cpu" if torch.get_num_threads() == 1 else "wall",
                        "load_average": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
                        "measured": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        atomic_write_text(path, strict_json({"format": _FORMAT, "choices": choices}, indent=2), overwrite=True)
    if log is not None:
        log(f"CPU matmul: {backend} ({', '.join(f'{b} {s * 1e3:.2f} ms' for b, s in seconds.items())} per "
            f"gradient step on this machine; kept in {path})")
    return backend
