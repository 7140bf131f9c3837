"""Why Forge's prior seats 0.031 of PegInsert's paired episodes where Factory's seats 0.141 (issue 40, noticed in
time_40): the same controllers as tools.ceiling, on Forge 4D, with Forge's dynamics randomization (the OSC gains
scaled per episode, the force dead zone of up to 5 N redrawn every 2 s, the held mass +-5 g) on and off.

    python docs/results/forge_prior_40/probe.py --json OUT.json [--episodes-per-world 4] [--controllers prior ...]

Not a library tool: an ad hoc probe built from tools.ceiling's parts (its recorder, classifier and controllers),
kept beside its results so they can be reproduced. The categories' `held` threshold assumes Factory's Kp (100 N/m);
on Forge (565 N/m, dead zone) read `held` / `jam-in` together.
"""

import argparse
import sys
from pathlib import Path

from vkgrl_newton.runtime import configure_warp, cpu_model


def build(dynamics: bool, num_envs: int, cache_dir: str):
    from vkgrl_newton.envs.assembly_env import AssemblyEnv, EnvConfig
    from vkgrl_newton.run.build import prior_tables
    from vkgrl_newton.run.evaluate import evaluation_config
    from vkgrl_newton.sim.scene import SimConfig

    args = argparse.Namespace(task="PegInsert", env="forge", action_dim=4, seed=0, num_envs=num_envs,
                              no_time_obs=False, geometry=None, demos=None, kmp_reference="gmr", device="cpu",
                              cache_dir=cache_dir, eager_physics=False, policy="kmp_prior")
    cfg = evaluation_config(args, None)
    env = AssemblyEnv(EnvConfig(task="PegInsert", family="forge", action_dim=4, num_envs=num_envs, device="cpu",
                                seed=0, sim=SimConfig(geometry=cfg.geometry), graph=True,
                                randomize_dynamics=dynamics))
    tables, demos = prior_tables(cfg)  # the prior every forge kgrl run of time_40 used (same cache key)
    return env, tables, demos


def wider_oracle(env, tables, floor_mm, gain):
    """tools.ceiling's oracle with other x, y reach floors and lateral gain (None: the ceiling's)."""
    from dataclasses import replace

    from vkgrl_newton.envs.evaluation import ORACLE_GAIN, ORACLE_PUSH_MM, KMPOraclePolicy
    from vkgrl_newton.tools.ceiling import CEILING_GEOMETRY, oracle_params

    g = CEILING_GEOMETRY["PegInsert"]
    p = replace(oracle_params("PegInsert"), settle_mm=0.3)
    if floor_mm is not None:
        p = replace(p, reach_floor_mm=floor_mm)
    return KMPOraclePolicy.with_floors(tables, env, p, gain=ORACLE_GAIN if gain is None else gain,
                                       push_mm=ORACLE_PUSH_MM, inside_mm=1e3 * (g.rest_height - g.entry_depth))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--episodes-per-world", type=int, default=4)
    ap.add_argument("--num-envs", type=int, default=16)
    ap.add_argument("--controllers", nargs="+", default=["prior"])
    ap.add_argument("--dynamics", nargs="+", default=["on", "off"], choices=["on", "off"])
    ap.add_argument("--cache-dir", default="runs/cache")
    ap.add_argument("--oracle-floor-mm", type=float, default=None, help="the oracle's x, y reach floors (default 4)")
    ap.add_argument("--oracle-gain", type=float, default=None, help="the oracle's lateral gain (default 1.5)")
    args = ap.parse_args()
    if args.json.exists():
        ap.error(f"--json {args.json}: exists (a new file only)")
    configure_warp()
    import torch

    from vkgrl_newton._io import atomic_write_text, strict_json
    from vkgrl_newton.tools.ceiling import make_controller, run_controller, summary

    torch.set_num_threads(1)
    out = {"task": "PegInsert", "env": "forge", "action_dim": 4, "num_envs": args.num_envs,
           "episodes_per_world": args.episodes_per_world, "eval_seed": 10_000, "cpu": cpu_model(),
           "command": "python docs/results/forge_prior_40/probe.py " + " ".join(sys.argv[1:]), "runs": {}}
    for dyn in args.dynamics:
        env, tables, demos = build(dyn == "on", args.num_envs, args.cache_dir)
        out["demos"] = str(demos)
        for name in args.controllers:
            key = f"{name}_dynamics_{dyn}"
            print(key, flush=True)
            policy = make_controller(name, env, tables, "PegInsert")
            if name == "oracle" and (args.oracle_floor_mm is not None or args.oracle_gain is not None):
                policy = wider_oracle(env, tables, args.oracle_floor_mm, args.oracle_gain)
                key = f"oracle_floor{args.oracle_floor_mm}_gain{args.oracle_gain}_dynamics_{dyn}"
            records, wall = run_controller(env, policy, args.episodes_per_world, 10_000, "PegInsert")
            out["runs"][key] = {**summary(records), "wall_s": round(wall, 1), "records": records}
            s = out["runs"][key]
            print(f"{key}: {s['n_success']}/{s['episodes']} (any {s['n_success_any']}) {s['categories']} {wall:.0f} s",
                  flush=True)
            atomic_write_text(args.json, strict_json(out, indent=1) + "\n", overwrite=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
