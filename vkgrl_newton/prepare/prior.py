"""The task's KMP prior, prepared once: scripted demonstrations recorded in the simulator, then the
KMP tables fitted to them, both cached per task under `cache_dir` and reused.

The demonstrations are recorded by `envs.demonstrations.record_demonstrations` (the scripted
demonstrator in the Factory env, 6D); 4D and 6D tables come from the same demonstrations
(`kmp.prior.load_or_fit_prior`). `prior_record` is what a run records of the prior it learned in.
"""

from __future__ import annotations

from pathlib import Path

from ..cache import file_sha256
from ..kmp.demos import DemoSet
from ..kmp.prior import KMP_BETA, KMP_L, KMP_LAMBDA, load_or_fit_prior
from ..kmp.tables import KMPTables
from ..signals import phase

__all__ = ["load_or_make_prior", "demos_path_for", "prior_record"]


def demos_path_for(cache_dir, task: str, num_demos: int, seed: int, geometry: str = "primitives",
                   device: str | None = None) -> Path:
    """Where the scripted demonstrations are cached, keyed by the demonstrator's version (a changed
    demonstrator records anew). The mesh variant's apart, per contact path (SDF on CUDA, the
    triangle BVH and a coarser thread grid on a CPU: not the same physics)."""
    from ..envs.scripted import DEMONSTRATOR_VERSION

    suffix = ""
    if geometry != "primitives":
        from ..runtime import default_device

        suffix = f"_{geometry}_{'sdf' if str(device or default_device()).startswith('cuda') else 'bvh'}"
    return (Path(cache_dir) / task
            / f"demos_scripted_v{DEMONSTRATOR_VERSION}_factory_n{num_demos}_seed{seed}{suffix}.npz")


def load_or_make_prior(task: str, action_dim: int, cache_dir, demos: str | Path | None = None, num_demos: int = 16,
                       num_envs: int = 16, device: str | None = None, seed: int = 0,
                       geometry: str = "primitives", lam: float = KMP_LAMBDA, beta: float = KMP_BETA,
                       l: float = KMP_L, reference: str = "gmr", log=print,
                       progress: bool = True) -> tuple[KMPTables, Path]:
    """The task's KMP tables, with the demonstrations they come from recorded first if missing.

    demos: a demonstration npz of your own; None records `num_demos` scripted ones in the
    Factory env (6D, `num_envs` worlds, the parts' collision `geometry`: sim.scene.GEOMETRIES)
    into `cache_dir/<task>/` once and reuses them. The tables (KMP parameters lam, beta, l) are
    cached beside the demonstrations (kmp.prior.load_or_fit_prior: keyed by content). Both are
    made under the demonstration file's cache lock (`vkgrl_newton.cache`): runs started together
    record and fit once. reference: the KMP's reference distribution, "gmr" (the thesis) or
    "empirical" (kmp.tables.EmpiricalReference); progress: the recording's progress bar. Returns
    (tables, demonstration path).
    """
    from ..cache import entry_lock

    if demos is None:
        path = demos_path_for(cache_dir, task, num_demos, seed, geometry, device)
    else:
        path = Path(demos)
        if not path.exists():
            raise FileNotFoundError(f"demonstrations {path} not found")
        demo_task = DemoSet.load(path).task
        if demo_task != task:
            raise ValueError(f"demonstrations {path} are of task {demo_task!r}, not {task!r}")
    with entry_lock(path, log=log, what=f"the {task} demonstrations"):
        if demos is None and not path.exists():
            with phase(f"preparing the KMP prior: recording its {num_demos} {task} demonstrations",
                       "none is kept: the file is written whole, at the end"):
                _record_scripted(task, path, num_demos, num_envs, device, seed, geometry, log, progress)
        with phase("preparing the KMP prior: fitting its tables",
                   f"the demonstrations {path.name} are kept; the tables file is written whole or not at all"):
            tables, tables_path, rebuilt = load_or_fit_prior(path, action_dim=action_dim, lam=lam, beta=beta, l=l,
                                                             seed=seed, reference=reference)
    log(f"KMP prior {'fitted' if rebuilt else 'loaded'}: {tables_path}")
    return tables, path


def prior_record(tables: KMPTables, demos_path, reach_floor_mm: float = 0.0, reach_floor_z_mm: float = 0.0,
                 seat_press_mm: float = 0.0) -> dict:
    """What a KGRL run records of its prior (checkpoint meta "prior"): the demonstration file and its
    sha256, the KMP parameters and the number of demonstrations (`cache.check_unchanged` checks the file),
    and the action path's reach floors (mm, x-y and z) and seat press (mm) where there are."""
    record = {"demos": str(demos_path), "demos_sha256": file_sha256(demos_path), "lam": float(tables.lam),
              "beta": float(tables.beta), "l": float(tables.l),
              "num_demos": int(len(DemoSet.load(demos_path).demo_lengths))}
    if tables.reference != "gmr":  # absent for the thesis's GMR, so older runs' records still match
        record["reference"] = tables.reference
    if reach_floor_mm > 0:  # likewise absent for the thesis's null space
        record["reach_floor_mm"] = float(reach_floor_mm)
    if reach_floor_z_mm > 0:
        record["reach_floor_z_mm"] = float(reach_floor_z_mm)
    if seat_press_mm > 0:  # likewise
        record["seat_press_mm"] = float(seat_press_mm)
    return record


def _record_scripted(task, path, num_demos, num_envs, device, seed, geometry, log, progress=True,
                     prepare_env=None) -> None:
    """The scripted demonstrations recorded into `path`; prepare_env(env), where given, is called on the
    recording env first (tools.ceiling's sensitivity runs perturb its gains there)."""
    from ..envs.assembly_env import AssemblyEnv, EnvConfig
    from ..envs.demonstrations import record_demonstrations
    from ..sim.scene import SimConfig

    log(f"recording {num_demos} scripted {task} demonstrations into {path} (once; cached)")
    env = AssemblyEnv(EnvConfig(task=task, family="factory", action_dim=6, num_envs=num_envs, device=device,
                                seed=seed, sim=SimConfig(geometry=geometry)))
    if prepare_env is not None:
        prepare_env(env)
    demo_set, episodes = record_demonstrations(env, num_demos, seed=seed,
                                               max_episodes=max(4, 3 * num_demos // num_envs + 2), progress=progress)
    if demo_set is None or len(demo_set.demo_lengths) < num_demos:
        got = 0 if demo_set is None else len(demo_set.demo_lengths)
        raise RuntimeError(f"the scripted demonstrator seated the part in only {got} of {episodes * num_envs} "
                           f"episodes, {num_demos} needed; see docs/log/benchmarks.md for its success rate")
    path.parent.mkdir(parents=True, exist_ok=True)
    demo_set.save(path)
