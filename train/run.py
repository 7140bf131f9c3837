"""Train a policy for an assembly task and report the thesis metrics.

    python train/run.py --task PegInsert --method kgrl --env factory --action-dim 4 --seed 0

Methods (thesis ch. 4-5): `sac` acts through Factory's delta-pose mapping; `kgrl` is the same
SAC acting in the null space of the task's KMP prior (vkgrl_newton/agents/kgrl.py), the action
path of eq. 4.36. `vision_sac` and `vision_kgrl` add the 16-d mean of a frozen denoising-VAE
encoder of the hand camera's image to the policy observation (eq. 5.6; vkgrl_newton/vision/).
Baselines beyond the thesis: `ppo` and `kgrl_ppo`, rsl-rl's PPO with Isaac Lab Factory's settings
on the same two action paths (vkgrl_newton/agents/ppo_config.py; `--ppo KEY=VALUE` overrides).

Everything a method needs is produced on first use and cached under `--cache-dir` (KGRL: scripted
demonstrations recorded in the simulator, and the KMP tables fitted to them; vision: the task
camera image set and the VAE trained on it, vkgrl_newton/vision/pipeline.py, per task and preset:
64 px / 4,096 images / 10 epochs for `quick`, 256 px / 130,000 / 400 for `thesis`; `--vae`
uses your own). A run directory holds:

    config.json          the arguments and the SAC configuration
    curves.jsonl         the learning curves as a table, a row per episode (vkgrl_newton/results/curves.py)
    tb/                  tensorboard scalars (episode reward, success rate, mean contact force,
                         time to first success, losses, alpha, throughput)
    checkpoints/last.pt  written atomically when the run starts, every --checkpoint-every
                         transitions, on Ctrl-C and at the end; `--resume` continues from it
    metrics.json         deterministic evaluation of the final policy (train/evaluate.py's keys)
                         and a training summary

A run directory that already holds a run is never reused without `--resume`. Resuming restores
the agent, its optimizers, normalizer and replay buffer, the RNG states and the counters; the
simulator starts fresh episodes (physics state is not checkpointed).

Steps are env transitions summed over worlds: 16 worlds x 150 control steps = 2400 per episode.
Defaults: preset `thesis` (Table 5.3, 128 worlds) on CUDA, `quick` (16 worlds) on CPU. kgrl and
vision_kgrl take the defaults of a recipe (`--kgrl-recipe`): `reach_keep_prior` with the quick
preset (issue 28's deviations, which beat the prior on paired episodes), `base` with the thesis's.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import json
import math
import re
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# Light imports only above the parser (no torch, Warp, Newton or rsl-rl): --help and every argument
# error answer in well under a second; the heavy modules load once the arguments are checked.
from vkgrl_newton._io import atomic_write_text, strict_json  # noqa: E402
from vkgrl_newton.agents.ppo_config import METHOD_PPO_DEFAULTS, parse_ppo_overrides, ppo_train_cfg  # noqa: E402
from vkgrl_newton.agents.sac_config import SAC_PRESETS, SACConfig, make_sac_config  # noqa: E402
from vkgrl_newton.cache import check_run_files  # noqa: E402
from vkgrl_newton.cli_types import add_verbose_flag, positive_int, device_name  # noqa: E402
from vkgrl_newton.results.curves import CURVES_FILE, CurveWriter  # noqa: E402
from vkgrl_newton.results.paired import (EVAL_SEED, cached_evaluation, format_gain, paired_gain,  # noqa: E402
                                         seed_evaluation, world_outcomes)
from vkgrl_newton.signals import describe, exit_code, stop_signals_as_interrupts  # noqa: E402
from vkgrl_newton.tasks import (ACTION_DIMS, FAMILIES, GEOMETRIES, PPO_METHODS, RUN_METHODS, TASKS,  # noqa: E402
                                VISION_LATENT_DIM, geometry_error, observation_dim)

# what a run writes in its directory; one holding any of them holds a run (other files, such as a
# sweep's train.log, may sit beside them)
# a run stopped before its first checkpoint: nothing to resume, and its files are not overwritten
_NO_CHECKPOINT = ("--run-dir {run_dir} holds a run that stopped before its first checkpoint (no checkpoints/last.pt): "
                  "nothing to resume; choose another directory, or delete this one to start it again")
RUN_FILES = ("config.json", "checkpoints", "tb", "metrics.json", CURVES_FILE)
# per preset: worlds, total transitions, checkpoint interval (transitions)
RUN_DEFAULTS = {
    "thesis": {"num_envs": 128, "total_steps": 1_000_000, "checkpoint_every": 50_000},
    "quick": {"num_envs": 16, "total_steps": 30_000, "checkpoint_every": 4_800},
}
# SAC fields a method sets on top of the preset (a --sac override still wins). KGRL's a = 0 is the
# KMP prior: it starts there with a small-std actor, warms up with that actor instead of uniform
# actions, and its std is capped at 0.3 (log -1.2). Uniform or std ~1 actions put the part ~7 mm
# off the prior against a 0.06 mm clearance, and without the cap the entropy term (alpha = 1,
# flat early Q) grows a 0.1 std to ~1 within ~100 actor updates (docs/benchmarks.md).
EVAL_MIN_EPISODES = 128  # sd of a success rate <= 0.5 / sqrt(128) = 0.044 over the evaluation episodes
CURVE_EPISODE_KEYS = ("episode_reward", "success_rate", "success_rate_any", "mean_contact_force",
                      "peak_contact_force", "time_to_first_success_s")  # the env's episode log -> curves.jsonl
KGRL_EXPLORATION = {"warmup": "policy", "actor_init_std": 0.1, "log_std_max": -1.2}
# The kgrl and vision_kgrl defaults by recipe (--kgrl-recipe): SAC fields over the preset and the null
# space's reach floors (mm). base: the thesis's null space (eq. 4.36) with the exploration above, the
# quick default of sessions 4-15. reach_keep_prior (issue 28): reach floors x, y 3 mm and z 25 mm
# (kmp.tables.with_reach_floor), a soft log-std bound, the IBRL anchor to a = 0, actor updates once a
# success is in the buffer, LayerNorm critics, the prior's own 4 800 rollouts kept in a second buffer
# sampled at 50 % (RLPD) and a 1e-3 normalizer floor; each a deviation from the thesis, measured in
# docs/benchmarks.md ("Learning beyond the prior") and docs/results/kgrl_reach_28c.
KGRL_RECIPES: dict[str, dict] = {
    "base": {"sac": KGRL_EXPLORATION, "reach_floor_mm": 0.0, "reach_floor_z_mm": 0.0},
    "reach_keep_prior": {"sac": {**KGRL_EXPLORATION, "log_std_bound": "tanh", "prior_anchor": True,
                                 "actor_after_reward": True, "critic_layer_norm": True, "prior_rollouts": 4800,
                                 "prior_ratio": 0.5, "obs_norm_eps": 1e-3},
                         "reach_floor_mm": 3.0, "reach_floor_z_mm": 25.0},
}
DEFAULT_KGRL_RECIPE = {"quick": "reach_keep_prior", "thesis": "base"}  # the thesis preset stays Table 5.3
KGRL_RECIPE_METHODS = ("kgrl", "vision_kgrl")  # the SAC methods on the KMP's null space
# ppo_train_cfg settings that only rsl-rl's OnPolicyRunner reads: refused by --ppo, with what run.py does instead
PPO_RUNNER_ONLY = {"save_interval": "checkpoints: --checkpoint-every", "logger": "it writes tensorboard itself",
                   "multi_gpu": "one device per run"}


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--task", default="PegInsert", choices=sorted(TASKS))
    ap.add_argument("--method", default="kgrl", choices=RUN_METHODS)
    ap.add_argument("--env", default="factory", choices=FAMILIES)
    ap.add_argument("--action-dim", type=int, default=4, choices=ACTION_DIMS)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--num-envs", type=positive_int, default=None, help="worlds (default: the preset's)")
    ap.add_argument("--total-steps", type=positive_int, default=None,
                    help="env transitions summed over worlds (default: the preset's)")
    ap.add_argument("--preset", default=None, choices=sorted(SAC_PRESETS),
                    help="SAC hyperparameters (default: thesis on CUDA, quick on CPU)")
    ap.add_argument("--sac", metavar="FIELD=VALUE", action="append", default=[],
                    help="override a SAC preset field, e.g. --sac batch_size=512 --sac hidden_dims=256,256 "
                         "(over the kgrl methods' --kgrl-recipe)")
    ap.add_argument("--kgrl-recipe", default=None, choices=sorted(KGRL_RECIPES),
                    help="kgrl, vision_kgrl: the defaults under --sac and the reach floors: reach_keep_prior (the "
                         "quick preset's: beats the prior on paired episodes, docs/benchmarks.md) or base (the "
                         "thesis preset's: the thesis's null space; the quick default until issue 28). Default: "
                         "the preset's, or on --resume the run's")
    ap.add_argument("--ppo", metavar="KEY=VALUE", action="append", default=[],
                    help="ppo methods: override an rsl-rl PPO setting by its dotted path, e.g. --ppo "
                         "num_steps_per_env=32 --ppo algorithm.learning_rate=3e-4 (default: Isaac Lab Factory's, "
                         "agents/ppo_config.py; kgrl_ppo starts at actor.distribution_cfg.init_std=0.1)")
    ap.add_argument("--device", default=None, type=device_name, help="cpu or cuda:0 (default: cuda:0 when present)")
    ap.add_argument("--geometry", default="primitives", choices=GEOMETRIES,
                    help="GearMesh/NutThread collision geometry (mesh: tooth/thread meshes with SDFs on CUDA; "
                         "the scripted demonstrations are recorded on it too)")
    ap.add_argument("--run-dir", type=Path, default=None,
                    help="default runs/train/<task>_<method>_<env>_<D>d_seed<S>_<date-time>")
    ap.add_argument("--resume", action="store_true", help="continue the run in --run-dir from its last checkpoint")
    ap.add_argument("--no-time-obs", action="store_true",
                    help="drop normalized time from the policy input (thesis A.1; the KMP still uses it)")
    ap.add_argument("--checkpoint-every", type=positive_int, default=None, help="transitions between checkpoints")
    ap.add_argument("--eval-episodes", type=int, default=None,
                    help="final deterministic evaluation: episodes per world, all worlds at once (0: none; default: "
                         f"enough for >= {EVAL_MIN_EPISODES} episodes, a success rate's standard error <= 0.045); "
                         "KGRL methods evaluate their prior (a = 0) on the same episodes")
    ap.add_argument("--eval-seed", type=int, default=EVAL_SEED,
                    help="seeds the evaluation episodes (train/evaluate.py's --eval-seed means the same): two policies "
                         "evaluated with one eval seed see identical initial states (default %(default)s)")
    ap.add_argument("--demos", type=Path, default=None, help="KGRL: your own demonstrations (npz)")
    ap.add_argument("--num-demos", type=int, default=16, help="KGRL: scripted demonstrations to record")
    ap.add_argument("--kmp-reference", default=None, choices=("gmr", "empirical"),
                    help="KGRL: the KMP's reference distribution: gmr (the thesis, eqs. 4.2-4.3; default) or empirical "
                         "(the demonstrations' per-step mean and covariance: a deviation, see docs/benchmarks.md)")
    ap.add_argument("--kgrl-reach-floor", type=float, default=None, metavar="MM",
                    help="KGRL: a saturated action moves the x and y command at least MM mm at every step (default: "
                         "the recipe's, reach_keep_prior 3, base 0: the thesis's null space, ~1 mm late in PegInsert; "
                         "a deviation, see kmp.tables.with_reach_floor and docs/benchmarks.md)")
    ap.add_argument("--kgrl-reach-floor-z", type=float, default=None, metavar="MM",
                    help="KGRL: likewise for z (default: the recipe's, reach_keep_prior 25, base 0: the thesis's, ~2 mm "
                         "late in PegInsert, while the prior presses a blocked peg ~20 mm into the face; a "
                         "deviation, see docs/benchmarks.md)")
    ap.add_argument("--vae", type=Path, default=None,
                    help="vision methods: your own trained vae.pt (train/train_vae.py) instead of the cached one")
    ap.add_argument("--cache-dir", type=Path, default=Path("runs/cache"),
                    help="demonstrations, KMP tables, image sets, VAEs")
    ap.add_argument("--label", default=None,
                    help="a name for the run's variant (e.g. the options it tries), recorded in config.json and "
                         "metrics.json; train/report.py shows runs of another label as another row")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--overlap", action=argparse.BooleanOptionalAction, default=None,
                    help="step the env in a worker thread while the SAC update of the previous transitions runs "
                         "(a one-update policy lag; default: on for a CPU device, off on CUDA, not yet measured there)")
    ap.add_argument("--eager-physics", action="store_true",
                    help="launch the physics kernels one by one instead of replaying one captured graph per control "
                         "step (bitwise the same results, slower: the reference)")
    add_verbose_flag(ap)
    return ap


def parse_sac_overrides(items: list[str]) -> dict:
    """FIELD=VALUE strings -> typed SACConfig overrides; ValueError names a bad field or value."""
    fields = {f.name: f for f in dataclasses.fields(SAC_PRESETS["quick"])}
    out: dict = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or name not in fields:
            raise ValueError(f"--sac {item!r}: expected FIELD=VALUE with FIELD one of {sorted(fields)}")
        current = getattr(SAC_PRESETS["quick"], name)
        try:
            if isinstance(current, tuple):
                out[name] = tuple(int(v) for v in text.split(","))
            elif isinstance(current, bool):
                if text.lower() not in ("true", "false", "1", "0"):
                    raise ValueError(text)
                out[name] = text.lower() in ("true", "1")
            elif current is None or isinstance(current, float):
                out[name] = None if text.lower() == "none" else float(text)
            elif isinstance(current, int):
                out[name] = int(text)
            else:
                out[name] = text
        except ValueError:
            raise ValueError(f"--sac {item!r}: {text!r} is not a valid {type(current).__name__} for {name}") from None
    return out


def unavailable(args) -> str | None:
    """Why this combination cannot run yet, or None."""
    from vkgrl_newton.envs.assembly_env import TASK_GEOMETRY

    if args.task not in TASK_GEOMETRY:
        return f"task {args.task!r} is not simulated yet; available tasks: {sorted(TASK_GEOMETRY)}"
    return None


def run_meta(args, obs_dim: int) -> dict:
    """What identifies a run; a resumed run must match it field by field. The learner's configuration:
    "sac" (the SACConfig) or, for the ppo methods, "ppo" (the rsl-rl runner configuration)."""
    meta = {"task": args.task, "method": args.method, "env": args.env, "action_dim": args.action_dim,
            "seed": args.seed, "num_envs": args.num_envs, "preset": args.preset, "time_obs": not args.no_time_obs,
            "obs_dim": obs_dim}
    if uses_ppo(args.method):
        meta["ppo"] = args.ppo_cfg
    else:
        meta["sac"] = dataclasses.asdict(args.sac_config)
    if args.geometry != "primitives":  # absent in the default case, so older checkpoints still resume
        meta["geometry"] = args.geometry
    if getattr(args, "label", None):  # absent unless given, so older runs still resume
        meta["label"] = args.label
    if getattr(args, "kgrl_recipe", None) not in (None, "base"):  # absent for base, as in runs before recipes
        meta["kgrl_recipe"] = args.kgrl_recipe
    if uses_vision(args.method):
        meta["vision"] = {"vae": str(vae_path(args)), "latent_dim": VISION_LATENT_DIM}
    return meta


def kgrl_recipe(args, preset: str) -> dict:
    """The run's KGRL_RECIPES entry: --kgrl-recipe, else the preset's (the base recipe's zero floors and no
    SAC fields for the methods without one)."""
    if args.method not in KGRL_RECIPE_METHODS:
        return {"sac": {}, "reach_floor_mm": 0.0, "reach_floor_z_mm": 0.0}
    return KGRL_RECIPES[args.kgrl_recipe or DEFAULT_KGRL_RECIPE[preset]]


def sac_config_for(args, preset: str) -> SACConfig:
    """The preset's SACConfig under the recipe's fields and --sac's (ValueError names a bad one)."""
    return make_sac_config(preset, **{**kgrl_recipe(args, preset)["sac"], **args.sac_overrides})


def _search_without_z_reach(args, sac_config, preset: str) -> str | None:
    """The refusal of prior_rollouts_policy=search where the run's z reach floor (given, else the recipe's
    of `preset`) is 0; None otherwise. A resumed run keeps the floors its checkpoint records."""
    reach_z = args.kgrl_reach_floor_z if args.kgrl_reach_floor_z is not None else \
        kgrl_recipe(args, preset)["reach_floor_z_mm"]
    if getattr(sac_config, "prior_rollouts_policy", "prior") == "search" and uses_kmp(args.method) \
            and not args.resume and not reach_z:
        return ("--sac prior_rollouts_policy=search lightens the prior's ~20 mm press on a blocked part: it needs "
                "z reach, give --kgrl-reach-floor-z MM (e.g. 25; the thesis's null space reaches ~2 mm there)")
    return None


def reach_floor_flags(args) -> tuple:
    """(prior-record key, flag, value given or None) of the two reach floors."""
    return (("reach_floor_mm", "--kgrl-reach-floor", args.kgrl_reach_floor),
            ("reach_floor_z_mm", "--kgrl-reach-floor-z", args.kgrl_reach_floor_z))


def uses_vision(method: str) -> bool:
    return method.startswith("vision_")


def uses_kmp(method: str) -> bool:
    return method in ("kgrl", "vision_kgrl", "kgrl_ppo")


def uses_ppo(method: str) -> bool:
    return method in PPO_METHODS


def vae_path(args) -> Path:
    """The run's vae.pt: --vae, or the cached one of the task and preset (made when missing)."""
    from vkgrl_newton.vision.pipeline import VISION_PRESETS, default_vae_dir

    if args.vae is not None:
        return Path(args.vae)
    return default_vae_dir(args.cache_dir, args.task, VISION_PRESETS[args.preset]) / "vae.pt"


# what a resumed run takes from its checkpoint unless given again (then it must agree)
_RUN_IDENTITY = ("task", "method", "env", "action_dim", "seed", "num_envs", "preset", "label")


def _explicit_args(argv) -> set[str]:
    """The options given on the command line (not defaults)."""
    ap = build_parser()
    for action in ap._actions:
        action.default = None
    ns = ap.parse_args(argv)
    return {k for k, v in vars(ns).items() if v is not None and v is not False and v != []}  # (0 is given)


def main(argv=None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    args.sac_config, args.ppo_cfg, payload = None, None, None
    if args.run_dir is not None and args.run_dir.is_dir() and any((args.run_dir / n).exists() for n in RUN_FILES):
        if not (args.run_dir / "checkpoints" / "last.pt").exists():  # with or without --resume: one message
            ap.error(_NO_CHECKPOINT.format(run_dir=args.run_dir))
        if not args.resume:
            ap.error(f"--run-dir {args.run_dir} already holds a run; pass --resume to continue it or choose another "
                     "directory")
    if args.resume:  # the run's identity comes from its checkpoint (a damaged one stops here)
        if args.run_dir is None:
            ap.error("--resume needs --run-dir (the run to continue)")
        from vkgrl_newton.agents.checkpoint import load_checkpoint

        try:
            payload = load_checkpoint(args.run_dir / "checkpoints" / "last.pt", map_location="cpu")
        except (FileNotFoundError, ValueError) as e:
            ap.error(f"--resume: {e}")
        meta, given = payload["meta"], _explicit_args(argv)
        for name in _RUN_IDENTITY:
            if name not in given:
                setattr(args, name, meta.get(name))
        if "no_time_obs" not in given:
            args.no_time_obs = not meta["time_obs"]
        if "kgrl_recipe" not in given and args.method in KGRL_RECIPE_METHODS:  # absent: a run before recipes
            args.kgrl_recipe = meta.get("kgrl_recipe", "base")
        if "geometry" not in given:
            args.geometry = meta.get("geometry", "primitives")
        if "vae" not in given and "vision" in meta:
            args.vae = Path(meta["vision"]["vae"])
        if "demos" not in given and "prior" in meta:
            args.demos = Path(meta["prior"]["demos"])
        try:  # a run continues from exactly what it learned from
            check_run_files(meta, demos=args.demos, vae=args.vae)
        except (FileNotFoundError, ValueError) as e:
            ap.error(f"--resume: {e}")
        done_at = int(payload["counters"].get("transitions", 0))
        metrics_file = args.run_dir / "metrics.json"
        try:  # finished: its metrics.json is of the checkpoint's transitions (not of an earlier, shorter plan)
            finished = metrics_file.exists() and int(
                json.loads(metrics_file.read_text()).get("training", {}).get("transitions", -1)) == done_at
        except (json.JSONDecodeError, ValueError, TypeError, AttributeError):
            finished = False
        if finished and not ("total_steps" in given and args.total_steps > done_at):
            # finished: nothing to continue and nothing rewritten (its metrics.json is what report.py reads)
            print(f"train/run.py: {args.run_dir} is a finished run ({done_at} transitions, "
                  f"{args.run_dir / 'metrics.json'}); nothing to resume. Train it further with --total-steps N "
                  f"(> {done_at}); evaluate it again with train/evaluate.py --checkpoint "
                  f"{args.run_dir / 'checkpoints' / 'last.pt'} --json FILE", file=sys.stderr)
            return 0
        for name, value in payload.get("plan", {}).items():  # total_steps, checkpoint_every, eval_episodes, eval_seed
            if name not in given:
                setattr(args, name, value)
        if uses_ppo(args.method):
            if not args.ppo:
                args.ppo_cfg = meta.get("ppo")
        elif not args.sac and "sac" in meta:  # (a PPO run resumed as a SAC method: check_meta names it below)
            try:
                args.sac_config = SACConfig(**meta["sac"])
            except (TypeError, ValueError) as e:
                ap.error(f"--resume: the checkpoint's SAC configuration is not valid today ({e}); give the fields "
                         "again with --sac FIELD=VALUE")
    if geometry_error(args.task, args.geometry):
        ap.error(f"--{geometry_error(args.task, args.geometry)}")
    if args.geometry == "mesh" and uses_vision(args.method):
        ap.error(f"--geometry mesh is for the sac and kgrl methods: the image sets and VAEs of {args.method} "
                 "are made on the primitives")
    if args.eval_episodes is not None and args.eval_episodes < 0:
        ap.error(f"--eval-episodes {args.eval_episodes}: must be >= 0 (episodes per world; 0: no final evaluation)")
    if args.label is not None and not re.fullmatch(r"[A-Za-z0-9_.-]{1,40}", args.label):
        ap.error(f"--label {args.label!r}: 1-40 characters of letters, digits, '_', '.', '-'")
    if not 0 <= args.eval_seed < 2**63:
        ap.error(f"--eval-seed {args.eval_seed}: must be in [0, 2**63)")
    if args.num_demos < 2:
        ap.error(f"--num-demos {args.num_demos}: must be >= 2")
    if not 0 <= args.seed < 2**32:
        ap.error(f"--seed {args.seed}: must be in [0, 2**32)")
    if args.demos is not None and not uses_kmp(args.method) and not args.resume:
        ap.error(f"--demos is for the kgrl methods (kgrl, vision_kgrl, kgrl_ppo), not {args.method!r}")
    if uses_ppo(args.method):  # PPO's settings are --ppo's; the SAC-loop options do not apply
        # (--no-overlap is what PPO does anyway: sweep.py passes it to every one-core trial)
        for flag, given_here in (("--sac", args.sac), ("--overlap", args.overlap is True),
                                 ("--no-time-obs", args.no_time_obs)):
            if given_here:
                ap.error(f"{flag} is for the SAC methods (sac, kgrl, vision_sac, vision_kgrl), not {args.method!r}")
        try:
            args.ppo_overrides = {**METHOD_PPO_DEFAULTS.get(args.method, {}), **parse_ppo_overrides(args.ppo)}
            if runner_only := sorted(set(args.ppo_overrides) & set(PPO_RUNNER_ONLY)):
                key = runner_only[0]
                raise ValueError(f"{key} is for rsl-rl's OnPolicyRunner, not run.py's loop ({PPO_RUNNER_ONLY[key]})")
            ppo_train_cfg(args.task, args.env, 1, **args.ppo_overrides)  # checked now; sized below
        except ValueError as e:
            ap.error(f"--ppo: {e}")
    elif args.ppo:
        ap.error(f"--ppo is for the ppo methods ({', '.join(PPO_METHODS)}), not {args.method!r}")
    try:
        args.sac_overrides = parse_sac_overrides(args.sac)
    except ValueError as e:
        ap.error(str(e))
    if args.kgrl_recipe is not None and args.method not in KGRL_RECIPE_METHODS:
        ap.error(f"--kgrl-recipe is for the kgrl methods on SAC ({', '.join(KGRL_RECIPE_METHODS)}), not {args.method!r}")
    # the SAC config checked before torch and Warp are imported, with the preset the device implies
    # when it is given (a CUDA default is known only below; then it is checked again there)
    provisional = args.preset or ("thesis" if (args.device or "").startswith("cuda") else "quick")
    checked = args.sac_config
    if checked is None and not uses_ppo(args.method):
        try:
            checked = sac_config_for(args, provisional)
        except ValueError as e:
            ap.error(f"--sac: {e}")
    prior_only = [f for f in ("prior_anchor", "prior_ratio", "prior_rollouts") if getattr(checked, f, None)]
    rollouts = getattr(checked, "prior_rollouts_policy", "prior")
    if rollouts == "scripted":  # the SAC methods' demonstrations: the first rollouts and their buffer are theirs
        if uses_kmp(args.method):
            ap.error(f"--sac prior_rollouts_policy=scripted is for the SAC methods (sac, vision_sac), not "
                     f"{args.method!r}, whose first rollouts are the prior's (prior) or the search's (search)")
        prior_only = [f for f in prior_only if f == "prior_anchor"]
    elif rollouts != "prior":
        prior_only.append("prior_rollouts_policy")
    if prior_only and not uses_kmp(args.method):
        hint = "" if prior_only[0] == "prior_anchor" else \
            "; the SAC methods learn from the demonstrator's rollouts with --sac prior_rollouts_policy=scripted"
        ap.error(f"--sac {prior_only[0]}: acts with or learns from the KMP prior (a = 0), for the kgrl methods "
                 f"(kgrl, vision_kgrl), not {args.method!r}{hint}")
    if args.kmp_reference is not None and not uses_kmp(args.method):
        ap.error(f"--kmp-reference is for the kgrl methods (kgrl, vision_kgrl, kgrl_ppo), not {args.method!r}")
    if why := _search_without_z_reach(args, checked, provisional):
        ap.error(why)
    for flag, value in (("--kgrl-reach-floor", args.kgrl_reach_floor), ("--kgrl-reach-floor-z", args.kgrl_reach_floor_z)):
        if value is None:
            continue
        if not uses_kmp(args.method):
            ap.error(f"{flag} is for the kgrl methods (kgrl, vision_kgrl, kgrl_ppo), not {args.method!r}")
        if not (math.isfinite(value) and 0 <= value <= 50):
            ap.error(f"{flag} must be a number of mm in [0, 50], got {value}")
    if args.vae is not None and not uses_vision(args.method):
        ap.error(f"--vae is for the vision methods (vision_sac, vision_kgrl), not {args.method!r}")
    if args.run_dir is not None and args.run_dir.exists() and not args.run_dir.is_dir():
        ap.error(f"--run-dir {args.run_dir} is a file; give a directory (new, or a run's with --resume)")

    reason = unavailable(args)  # (imports the env's module: the heavy part starts here)
    if reason is not None:
        print(f"train/run.py: {reason}", file=sys.stderr)
        return 2
    from vkgrl_newton.runtime import configure_warp, default_device, device_error  # torch and Warp from here on

    if args.demos is not None and not args.resume:  # a missing, damaged or foreign file stops here
        from vkgrl_newton.kmp.demos import DemoSet

        try:
            demo_task = DemoSet.load(args.demos).task
        except (FileNotFoundError, ValueError) as e:
            ap.error(f"--demos: {e}")
        if demo_task != args.task:
            ap.error(f"--demos {args.demos}: demonstrations of {demo_task}, not --task {args.task}")
    configure_warp(args.verbose)
    args.device = args.device or default_device()
    if (why := device_error(args.device)) is not None:
        ap.error(why)
    args.preset = args.preset or ("thesis" if args.device.startswith("cuda") else "quick")
    if args.method in KGRL_RECIPE_METHODS:
        args.kgrl_recipe = args.kgrl_recipe or DEFAULT_KGRL_RECIPE[args.preset]
    if args.sac_config is None and not uses_ppo(args.method):
        try:
            args.sac_config = checked if args.preset == provisional else sac_config_for(args, args.preset)
        except ValueError as e:
            ap.error(f"--sac: {e}")
        if why := _search_without_z_reach(args, args.sac_config, args.preset):  # (the preset may have changed)
            ap.error(why)
    defaults = RUN_DEFAULTS[args.preset]
    args.num_envs = args.num_envs or defaults["num_envs"]
    args.total_steps = args.total_steps or defaults["total_steps"]
    args.checkpoint_every = args.checkpoint_every or defaults["checkpoint_every"]
    if args.eval_episodes is None:
        args.eval_episodes = -(-EVAL_MIN_EPISODES // args.num_envs)
    if uses_ppo(args.method) and args.ppo_cfg is None:  # minibatches of ~512 transitions for these worlds
        args.ppo_cfg = ppo_train_cfg(args.task, args.env, args.num_envs, **args.ppo_overrides)
    run_dir = args.run_dir or Path("runs/train") / (f"{args.task}_{args.method}_{args.env}_{args.action_dim}d_"
                                                     f"seed{args.seed}_{time.strftime('%Y%m%d-%H%M%S')}")
    ckpt_path = run_dir / "checkpoints" / "last.pt"
    if not args.resume and any((run_dir / name).exists() for name in RUN_FILES):  # a default name taken meanwhile
        ap.error(f"--run-dir {run_dir} already holds a run; pass --resume to continue it or choose another directory")
    args.latent_dim = VISION_LATENT_DIM if uses_vision(args.method) else 0
    if args.vae is not None:
        from vkgrl_newton.vision.vae import load_vae

        try:  # missing, the wrong task, damaged or not a VAE at all: stop before anything is built
            load_vae(args.vae, expect={"task": args.task, "latent_dim": VISION_LATENT_DIM})
        except (FileNotFoundError, ValueError) as e:
            ap.error(f"--vae: {e}")
    args.obs_dim = observation_dim(args.env, args.latent_dim) - (1 if args.no_time_obs else 0)
    if payload is not None:  # a foreign checkpoint stops here, before anything is built
        try:
            saved = _without_file_records(payload["meta"])  # checked above, by content
            # a checkpoint from before a SACConfig field existed holds that field's default
            if "sac" in saved:
                saved["sac"] = dataclasses.asdict(SACConfig(**saved["sac"]))
            now = run_meta(args, args.obs_dim)
            for m in (saved, now):  # the default geometry is not stored; name it in a mismatch
                m.setdefault("geometry", "primitives")
            from vkgrl_newton.agents.checkpoint import check_meta

            check_meta(saved, now, ckpt_path)
        except ValueError as e:
            ap.error(f"--resume: {e}")
        if uses_kmp(args.method) and "prior" in payload["meta"]:  # the null space it learned in, before any build
            for key, flag, given in reach_floor_flags(args):
                was = payload["meta"]["prior"].get(key, 0.0)
                if given is not None and given != was:
                    ap.error(f"--resume: the run's {flag} was {was:g} mm, not {given:g}; resume without it")
    with stop_signals_as_interrupts():  # SIGTERM / SIGHUP: checkpoint and exit like Ctrl-C
        return train(args, run_dir, ckpt_path, payload)



def _without_file_records(meta: dict) -> dict:
    """A run's meta less its file records (prior, VAE hash): compared by content, not as fields."""
    meta = dict(meta)
    meta.pop("prior", None)
    if "vision" in meta:
        meta["vision"] = {k: v for k, v in meta["vision"].items() if k != "vae_sha256"}
    return meta


def train(args, run_dir: Path, ckpt_path: Path, payload: dict | None) -> int:
    import torch
    from torch.utils.tensorboard import SummaryWriter
    from tqdm import tqdm

    from vkgrl_newton.agents.checkpoint import save_checkpoint
    from vkgrl_newton.envs.assembly_env import AssemblyEnv, EnvConfig
    from vkgrl_newton.sim.scene import SimConfig

    if _TORCH_THREADS:
        torch.set_num_threads(_TORCH_THREADS)
    torch.manual_seed(args.seed)
    log = tqdm.write
    log(f"train/run.py: {args.method} {args.task} {args.env} {args.action_dim}D on device {args.device} -> {run_dir}")

    encoder = None
    if uses_vision(args.method):
        from vkgrl_newton.vision.pipeline import VISION_PRESETS, load_or_make_encoder

        try:
            encoder, _ = load_or_make_encoder(args.task, VISION_PRESETS[args.preset], args.cache_dir, args.device,
                                              vae_path=args.vae, log=log, progress=not args.no_progress)
        except (FileExistsError, FileNotFoundError, ValueError) as e:
            print(f"train/run.py: the vision prerequisites: {e}", file=sys.stderr)
            return 2
        except KeyboardInterrupt as e:
            log("interrupted while preparing the image set or the VAE; run again to continue")
            return exit_code(e)
        if encoder.latent_dim != args.latent_dim:
            raise SystemExit(f"train/run.py: the VAE's latent has {encoder.latent_dim} dimensions, the vision "
                             f"methods use {args.latent_dim} (thesis 5.6)")
    env = AssemblyEnv(EnvConfig(task=args.task, family=args.env, action_dim=args.action_dim, num_envs=args.num_envs,
                                device=args.device, seed=args.seed, vision_latent_dim=args.latent_dim,
                                sim=SimConfig(geometry=args.geometry), graph=not args.eager_physics))
    if encoder is not None:
        from vkgrl_newton.vision.latent import CameraLatent

        env.attach_vision(CameraLatent(env, encoder))
    action_path = None
    if uses_kmp(args.method):
        from vkgrl_newton.agents.kgrl import KGRLActionPath, load_or_make_prior

        kw = {"reference": args.kmp_reference or "gmr"}
        recipe = kgrl_recipe(args, args.preset)
        floors = {key: float(given if given is not None else recipe[key]) for key, _, given in reach_floor_flags(args)}
        if payload is not None and "prior" in payload["meta"]:  # the KMP parameters it was fitted with
            kw = {k: payload["meta"]["prior"][k] for k in ("lam", "beta", "l")}
            kw["reference"] = payload["meta"]["prior"].get("reference", "gmr")
            for key, _, _ in reach_floor_flags(args):  # (a different one given was refused in main)
                floors[key] = payload["meta"]["prior"].get(key, 0.0)
        tables, demos_path = load_or_make_prior(args.task, args.action_dim, args.cache_dir, demos=args.demos,
                                                num_demos=args.num_demos, device=args.device, geometry=args.geometry,
                                                log=log, **kw)
        action_path = KGRLActionPath(tables, env, reach_floor=1e-3 * floors["reach_floor_mm"],
                                     reach_floor_z=1e-3 * floors["reach_floor_z_mm"])
    step_fn = action_path.step if action_path is not None else env.step
    time_obs = not args.no_time_obs
    obs_dim = args.obs_dim  # observation_dim(), the same function the env uses
    if uses_ppo(args.method):
        from vkgrl_newton.agents.ppo import PPOAgent

        agent = PPOAgent(env, args.ppo_cfg, device=str(env.tdev))
    else:
        from vkgrl_newton.agents.sac import SAC

        agent = SAC(obs_dim, args.action_dim, args.sac_config, device=env.tdev, seed=args.seed)
    meta = run_meta(args, obs_dim)
    if action_path is not None:  # exactly what the run learns from: the prior's file and parameters
        from vkgrl_newton.agents.kgrl import prior_record

        meta["prior"] = prior_record(action_path.tables, demos_path, **floors)
    if encoder is not None:
        from vkgrl_newton.cache import file_sha256

        meta["vision"]["vae_sha256"] = file_sha256(meta["vision"]["vae"])
    if payload is not None:
        for key in ("prior", "vision"):
            if key in payload["meta"] and payload["meta"][key] != meta.get(key):
                raise SystemExit(f"train/run.py: --resume: the run's {key} was {payload['meta'][key]}, "
                                 f"now {meta.get(key)}")
    counters = {"transitions": 0, "env_steps": 0, "episodes": 0, "wall_s": 0.0}
    if payload is not None:
        agent.load_state_dict(payload["agent"])
        counters.update(payload["counters"])
        _restore_rng(payload["rng"], env)
        log(f"resumed {run_dir} at {counters['transitions']} transitions")
    else:
        run_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(run_dir / "config.json", strict_json({**meta, **plan(args), "device": args.device},
                                                               indent=2))

    def checkpoint(pending_update: bool = False, snapshot: dict | None = None) -> None:
        """The run as it is now, or as `snapshot` (agent, counters, rng) holds it."""
        snapshot = snapshot or {"agent": agent.state_dict(), "counters": counters, "rng": _rng_state(env)}
        save_checkpoint(ckpt_path, {"meta": meta, "counters": dict(snapshot["counters"]), "agent": snapshot["agent"],
                                    "pending_update": pending_update,  # overlapped loop: due, not yet run
                                    "rng": snapshot["rng"], "plan": plan(args)})

    # a resumed run drops what was logged after its checkpoint (as curves.jsonl does): the events at
    # the checkpoint's own count were logged before it was written, so they stay (an update pending at
    # the checkpoint, or an interrupted final evaluation, logs a second point at that count on resume)
    writer = SummaryWriter(str(run_dir / "tb"), purge_step=counters["transitions"] + 1 if payload else None)
    curves = CurveWriter(run_dir, resume_at=counters["transitions"] if payload else None)
    bar = tqdm(total=args.total_steps, initial=counters["transitions"], unit="tr", disable=args.no_progress,
               desc=f"{args.method} {args.task} {args.env} {args.action_dim}D")
    if action_path is not None and args.method in KGRL_RECIPE_METHODS:
        log(f"KGRL recipe {args.kgrl_recipe}: reach floors x, y {floors['reach_floor_mm']:g} mm, "
            f"z {floors['reach_floor_z_mm']:g} mm (--kgrl-recipe, docs/cli.md)")
        if args.sac_config.prior_rollouts >= args.total_steps:
            log(f"note: the first {args.sac_config.prior_rollouts} transitions act with the prior "
                f"(--sac prior_rollouts), all of this run's {args.total_steps}: every training episode is the "
                "prior's; the learner acts only in the final evaluation")
    rollout_policy = None
    rollouts = getattr(args.sac_config, "prior_rollouts_policy", "prior")  # (PPO runs have no SACConfig)
    if rollouts == "search":
        from vkgrl_newton.agents.evaluation import KMPSearchPolicy

        rollout_policy = KMPSearchPolicy(action_path)  # within the run's own reach floors
    elif rollouts == "scripted":
        from vkgrl_newton.agents.evaluation import ScriptedDeltaPolicy

        rollout_policy = ScriptedDeltaPolicy(seed=args.seed)
        kept = (f"kept in a second buffer sampled at prior_ratio={args.sac_config.prior_ratio:g}"
                if args.sac_config.prior_ratio > 0 else "in the one replay buffer (prior_ratio=0)")
        log(f"the first {args.sac_config.prior_rollouts} transitions act with the scripted demonstrator through "
            f"the SAC action space (--sac prior_rollouts_policy=scripted), {kept}")
    loop = Loop(args=args, env=env, step_fn=step_fn, agent=agent, counters=counters, writer=writer, curves=curves,
                bar=bar, checkpoint=checkpoint, ckpt_path=ckpt_path, log=log, time_obs=time_obs, env_steps0=counters["env_steps"],
                grad0=agent.num_updates, rollout_policy=rollout_policy)
    rc = (ppo_loop if uses_ppo(args.method) else sac_loop)(loop, payload)
    if rc is not None:  # stopped by a signal: checkpointed, nothing evaluated
        return rc

    summary = {"transitions": counters["transitions"], "env_steps": counters["env_steps"],
               "episodes": counters["episodes"], "gradient_steps": agent.num_updates, "wall_s": counters["wall_s"],
               # whole loop (env, acting, buffer, updates) vs the env and action path alone
               "loop_transitions_per_s": (counters["env_steps"] - loop.env_steps0) * env.num_envs
               / max(time.perf_counter() - loop.t_session, 1e-9),
               "train_env_steps_per_s": (counters["env_steps"] - loop.env_steps0) * env.num_envs
               / max(loop.env_time, 1e-9),
               "grad_steps_per_s": ((agent.num_updates - loop.grad0) / loop.update_time if loop.update_time > 0
                                    else float("nan")),
               "physics_resets": env.physics_resets_total, "ik_failures": env.ik_failures_total,
               "contact_overflows": env.contact_overflows_total, "first_transition_unix": loop.first_transition_unix,
               "resumed": payload is not None}
    metrics: dict = {}
    try:
        if args.eval_episodes:
            metrics = final_evaluation(args, env, agent, action_path, time_obs)
            for k in ("success_rate", "mean_contact_force", "time_to_first_success_s", "mean_episode_reward"):
                writer.add_scalar(f"eval/{k}", metrics[k], counters["transitions"])
            if "prior_eval" in metrics:
                writer.add_scalar("eval/prior_success_rate", metrics["prior_eval"]["success_rate"],
                                  counters["transitions"])
    except KeyboardInterrupt as e:  # the checkpoint holds the whole run: --resume evaluates it again
        writer.close()
        log(f"{describe(e)} during the final evaluation; the trained checkpoint is {ckpt_path} "
            "(--resume evaluates)")
        return exit_code(e)
    writer.close()
    result = {**metrics, **meta, "device": env.device, "checkpoint": str(ckpt_path), "training": summary}
    result.pop("sac", None)
    result.pop("ppo", None)
    metrics_path = run_dir / "metrics.json"
    if metrics_path.exists():  # a finished run trained further: its earlier result stays beside the new one
        earlier = json.loads(metrics_path.read_text()).get("training", {}).get("transitions", "earlier")
        for name in ("metrics", "config"):  # config.json: the plan (total_steps) it was run to
            aside = run_dir / f"{name}_at_{earlier}.json"
            if not aside.exists():
                (run_dir / f"{name}.json").rename(aside)
                log(f"the earlier {name}.json -> {aside}")
    # the plan the run was finished to (a resume may have changed --total-steps or the evaluation)
    atomic_write_text(run_dir / "config.json", strict_json({**meta, **plan(args), "device": args.device}, indent=2),
                      overwrite=True)
    atomic_write_text(metrics_path, strict_json(result, indent=2), overwrite=True)  # the run's own file
    shown = {k: result[k] for k in ("success_rate", "mean_contact_force", "time_to_first_success_s",
                                    "mean_episode_reward") if k in result}
    log(f"done: {strict_json(shown)} -> {metrics_path}")
    if "paired_gain" in metrics:
        log(paired_line(metrics))
    return 0


class Loop:
    """What a training loop (sac_loop, ppo_loop) works with, and the timings it keeps for the summary.
    (A plain class: tests load this file as a module outside sys.modules, where a dataclass fails.)"""

    def __init__(self, *, args, env, step_fn, agent, counters: dict, writer, curves: CurveWriter, bar, checkpoint,
                 ckpt_path: Path, log, time_obs: bool, env_steps0: int, grad0: int, rollout_policy=None):
        self.args, self.env, self.agent, self.counters = args, env, agent, counters
        self.step_fn = step_fn  # env.step, or the KGRL action path's step
        self.writer, self.curves, self.bar, self.log = writer, curves, bar, log
        self.checkpoint = checkpoint  # checkpoint(pending_update=False, snapshot=None)
        self.ckpt_path, self.time_obs = ckpt_path, time_obs
        # acts instead of the agent in its first prior_rollouts transitions (SACConfig.prior_rollouts_policy)
        self.rollout_policy = rollout_policy
        self.env_steps0, self.grad0 = env_steps0, grad0  # where this session's throughput counts from
        self.env_time = self.update_time = 0.0
        self.t_session = time.perf_counter()
        self.first_transition_unix = time.time()  # a sweep's overhead: scheduled -> first env step (sweep.py)
        self.t_start = time.perf_counter()  # wall time not yet in counters["wall_s"]
        self.status: dict[str, float] = {}  # the progress bar's postfix

    def timed_step(self, actions):
        t = time.perf_counter()
        result = self.step_fn(actions)
        return result, time.perf_counter() - t

    def wall_s(self) -> float:
        return self.counters["wall_s"] + time.perf_counter() - self.t_start

    def bank_wall_time(self) -> None:
        """Move the wall time since the last call into counters (before a checkpoint)."""
        self.counters["wall_s"] += time.perf_counter() - self.t_start
        self.t_start = time.perf_counter()

    def after_step(self, extras: dict) -> None:
        """Count one batched env step; log an ended episode (tensorboard, curves.jsonl, the bar)."""
        counters, writer, env = self.counters, self.writer, self.env
        counters["transitions"] += env.num_envs
        counters["env_steps"] += 1
        if "episode" in extras:
            ep = extras["episode"]
            counters["episodes"] += 1
            step = counters["transitions"]
            writer.add_scalar("episode/reward", ep["episode_reward"], step)
            writer.add_scalar("episode/success_rate", ep["success_rate"], step)
            writer.add_scalar("episode/success_rate_any", ep["success_rate_any"], step)
            writer.add_scalar("episode/mean_contact_force", ep["mean_contact_force"], step)
            writer.add_scalar("episode/peak_contact_force", ep["peak_contact_force"], step)
            if not math.isnan(ep["time_to_first_success_s"]):
                writer.add_scalar("episode/time_to_first_success_s", ep["time_to_first_success_s"], step)
            writer.add_scalar("perf/env_steps_per_s", (counters["env_steps"] - self.env_steps0) * env.num_envs
                              / max(self.env_time, 1e-9), step)
            if self.update_time > 0:
                writer.add_scalar("perf/grad_steps_per_s", (self.agent.num_updates - self.grad0) / self.update_time,
                                  step)
            writer.add_scalar("perf/physics_resets", env.physics_resets_total, step)
            writer.add_scalar("perf/ik_failures", env.ik_failures_total, step)
            writer.add_scalar("perf/contact_overflows", env.contact_overflows_total, step)
            self.curves.append(transitions=step, **{k: float(ep[k]) for k in CURVE_EPISODE_KEYS}, wall_s=self.wall_s())
            self.status.update(success=ep["success_rate"], reward=ep["episode_reward"], force=ep["mean_contact_force"])
        self.bar.update(env.num_envs)
        if self.status:
            self.bar.set_postfix({k: f"{v:.3g}" for k, v in self.status.items()}, refresh=False)

    def stopped(self, e: BaseException, snapshot: dict | None = None, pending_update: bool = False) -> int:
        """Ctrl-C / SIGTERM: checkpoint (the run now, or `snapshot`), close the logs, say how to go on."""
        self.bank_wall_time()
        if snapshot is not None:  # the wall time spent since counts, though its partial work is redone
            snapshot["counters"]["wall_s"] = self.counters["wall_s"]
        self.checkpoint(pending_update, snapshot)
        self.bar.close()
        self.writer.close()
        at = (snapshot or {"counters": self.counters})["counters"]["transitions"]
        self.log(f"{describe(e)}; checkpoint at {at} transitions in {self.ckpt_path} (--resume continues)")
        return exit_code(e)


def sac_loop(loop: Loop, payload: dict | None) -> int | None:
    """SAC (sac, kgrl, vision_*): a transition per world per step into the replay buffer, updates as
    SACConfig says. None when done, an exit code when stopped by a signal (checkpointed)."""
    import torch

    from vkgrl_newton.agents.evaluation import policy_observation

    args, env, agent, counters = loop.args, loop.env, loop.agent, loop.counters
    # Overlapped loop (--overlap): env step k+1 runs in a worker thread while the main thread runs the
    # update due after step k; the action of step k+1 is drawn before that update, i.e. from the
    # policy after update k-1 (a one-update lag). The order of every draw from the agent's and the
    # env's generators is fixed, so a seed gives the same run whatever the threads' timing.
    overlap = (str(env.device) == "cpu") if args.overlap is None else args.overlap
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="env-step") if overlap else None
    pending_update = bool(payload.get("pending_update", False)) if payload is not None else False
    future = None

    def run_update() -> None:
        t = time.perf_counter()
        losses = agent.update()
        loop.update_time += time.perf_counter() - t
        if counters["env_steps"] % 10 == 0:
            for k, v in losses.items():
                loop.writer.add_scalar(f"train/{k}", v, counters["transitions"])
        loop.status["alpha"] = losses.get("alpha", float("nan"))

    obs = env.get_observations()
    last_ckpt = counters["transitions"] // args.checkpoint_every
    not_terminal = torch.zeros(env.num_envs, device=env.tdev)  # the `terminated` flags, all 0
    loop.t_start = time.perf_counter()
    if payload is None:  # resumable from its first moment (a sweep's retry of a killed trial)
        loop.checkpoint()
    try:
        while counters["transitions"] < args.total_steps:
            x = policy_observation(obs, loop.time_obs)
            a = agent.explore(x)
            if loop.rollout_policy is not None and agent.num_transitions < agent.cfg.prior_rollouts:
                a = loop.rollout_policy.actions(env, obs)
            if pool is not None:
                future = pool.submit(loop.timed_step, a)
                if pending_update:  # the update due after the previous step, while this one runs
                    run_update()
                    pending_update = False
                (next_obs, reward, dones, extras), dt = future.result()  # a worker's exception surfaces here
                future = None
            else:
                (next_obs, reward, dones, extras), dt = loop.timed_step(a)
            loop.env_time += dt
            x_next = policy_observation(next_obs, loop.time_obs)
            if "final_observations" in extras:  # time-outs bootstrap from the state they ended in
                final = policy_observation(extras["final_observations"], loop.time_obs)
                x_next = torch.where(dones.unsqueeze(-1), final, x_next)
            # episodes end by time-out only: nothing is terminal; blown-up worlds' rows are dropped
            # (the env has counted them on the host already: no extra sync on the common path)
            if extras["log"]["/physics_resets"] == 0:
                agent.add(x, a, reward, x_next, not_terminal)
            else:
                keep = ~extras["physics_resets"]
                agent.add(x[keep], a[keep], reward[keep], x_next[keep], not_terminal[keep])
            obs = next_obs
            loop.after_step(extras)
            if pool is not None:
                pending_update = agent.update_due()  # runs during the next env step
            elif agent.update_due():
                run_update()
            if counters["transitions"] // args.checkpoint_every > last_ckpt:
                last_ckpt = counters["transitions"] // args.checkpoint_every
                loop.bank_wall_time()
                loop.checkpoint(pending_update)
        if pending_update:  # the last step's update: as many gradient steps as the serial loop
            run_update()
            pending_update = False
    except KeyboardInterrupt as e:
        if future is not None:  # let the worker finish its env step (its transition is dropped)
            with contextlib.suppress(BaseException):
                future.result()
        return loop.stopped(e, pending_update=pending_update)
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
    loop.bank_wall_time()
    loop.checkpoint()
    loop.bar.close()
    return None


def ppo_loop(loop: Loop, payload: dict | None) -> int | None:
    """rsl-rl's PPO (ppo, kgrl_ppo): OnPolicyRunner.learn's loop (num_steps_per_env steps of every
    world, the returns, one PPO update) with this project's logging and checkpoints. A checkpoint
    holds the run at an update's end; a stop in mid-rollout saves the last update's end (the
    partial rollout is collected again on resume). None when done, an exit code when stopped."""
    import copy

    import torch

    args, env, agent, counters = loop.args, loop.env, loop.agent, loop.counters
    alg = agent.alg
    if agent.cfg.get("check_for_nan", True):  # as OnPolicyRunner: a ValueError naming what holds the NaN
        from rsl_rl.utils import check_nan
    else:
        check_nan = None

    def snapshot() -> dict:
        return {"agent": copy.deepcopy(agent.state_dict()), "counters": dict(counters), "rng": _rng_state(env)}

    obs = env.get_observations().to(agent.device)
    alg.train_mode()
    last_ckpt = counters["transitions"] // args.checkpoint_every
    loop.t_start = time.perf_counter()
    if payload is None:
        loop.checkpoint()
    at_update = snapshot()
    try:
        while counters["transitions"] < args.total_steps:
            with torch.inference_mode():
                for _ in range(agent.num_steps_per_env):
                    actions = alg.act(obs)
                    (obs, rewards, dones, extras), dt = loop.timed_step(actions.to(env.tdev))
                    loop.env_time += dt
                    obs, rewards, dones = obs.to(agent.device), rewards.to(agent.device), dones.to(agent.device)
                    # one host read for the NaN test (rsl-rl's check_nan reads each tensor), its message on a hit
                    if check_nan is not None and bool(torch.stack(
                            [torch.isnan(v).any() for v in (*obs.values(), rewards)]).any()):
                        check_nan(obs, rewards, dones)
                    # episodes end by time-out (extras["time_outs"]: PPO bootstraps them) or by a blow-up
                    # (the env reset and counted that world; PPO takes it as terminal)
                    alg.process_env_step(obs, rewards, dones, extras)
                    loop.after_step(extras)
                alg.compute_returns(obs)
            t = time.perf_counter()
            losses = alg.update()
            agent.iterations += 1
            loop.update_time += time.perf_counter() - t
            step = counters["transitions"]
            for k, v in losses.items():
                loop.writer.add_scalar(f"train/{k}", v, step)
            loop.writer.add_scalar("train/learning_rate", alg.learning_rate, step)
            loop.writer.add_scalar("train/action_std", float(alg.get_policy().output_std.detach().mean()), step)
            loop.status["std"] = float(alg.get_policy().output_std.detach().mean())
            loop.bank_wall_time()
            at_update = snapshot()
            if counters["transitions"] // args.checkpoint_every > last_ckpt:
                last_ckpt = counters["transitions"] // args.checkpoint_every
                loop.checkpoint(snapshot=at_update)
    except KeyboardInterrupt as e:
        return loop.stopped(e, snapshot=at_update)
    loop.checkpoint(snapshot=at_update)
    loop.bar.close()
    return None


def plan(args) -> dict:
    """What a run was asked to do beyond its identity; a resumed run keeps it unless given again."""
    return {"total_steps": args.total_steps, "checkpoint_every": args.checkpoint_every,
            "eval_episodes": args.eval_episodes, "eval_seed": args.eval_seed}


def final_evaluation(args, env, agent, action_path, time_obs: bool) -> dict:
    """The trained policy (deterministic) on the evaluation episodes of --eval-seed; a KGRL run's
    prior (a = 0) on the same episodes ("prior_eval"), and the paired gain of the policy over it."""
    from vkgrl_newton.agents.evaluation import AgentPolicy, KMPPriorPolicy, evaluate

    seed_evaluation(env, args.eval_seed)
    metrics = evaluate(env, AgentPolicy(agent, action_path, time_obs), args.eval_episodes,
                       progress=not args.no_progress, desc="final evaluation")
    metrics["eval_seed"] = args.eval_seed
    if action_path is not None:
        def evaluate_prior() -> dict:
            seed_evaluation(env, args.eval_seed)
            return evaluate(env, KMPPriorPolicy(action_path), args.eval_episodes, progress=not args.no_progress,
                            desc="the prior, same episodes")

        # a = 0 on these episodes is the same for every training seed and variant of the configuration
        key = {"what": "kgrl prior evaluation", "task": args.task, "env": args.env, "action_dim": args.action_dim,
               "num_envs": env.num_envs, "device": str(env.device), "geometry": args.geometry,
               "eager_physics": bool(args.eager_physics), "vision_latent_dim": env.cfg.vision_latent_dim,
               "eval_seed": args.eval_seed, "eval_episodes": args.eval_episodes,
               "prior_mean_sha256": hashlib.sha256(action_path.tables.mean.numpy().tobytes()).hexdigest()}
        prior, _ = cached_evaluation(args.cache_dir, key, evaluate_prior, log=print)
        metrics["prior_eval"] = {k: v for k, v in prior.items() if k != "per_episode"}
        metrics["prior_eval"]["per_episode"] = [{k: e[k] for k in ("world_success", "world_contact_force")}
                                           for e in prior["per_episode"]]
        metrics["paired_gain"] = {
            "success_rate": paired_gain(world_outcomes(metrics), world_outcomes(prior), seed=args.eval_seed),
            "mean_contact_force": paired_gain(world_outcomes(metrics, "world_contact_force"),
                                              world_outcomes(prior, "world_contact_force"), seed=args.eval_seed)}
    return metrics


def paired_line(metrics: dict) -> str:
    """One line: the policy's success, its prior's on the same episodes, and the paired gain."""
    g = metrics["paired_gain"]["success_rate"]
    return (f"success {metrics['success_rate']:.3f}, the prior {metrics['prior_eval']['success_rate']:.3f} on the same "
            f"{g['n_pairs']} episodes: " + format_gain("gain", g))


def _rng_state(env) -> dict:
    import torch

    state = {"torch": torch.get_rng_state(), "env_torch": env.generator.get_state()}
    if str(env.tdev).startswith("cuda"):  # rsl-rl's PPO samples actions and minibatches from the device's generator
        state["cuda"] = torch.cuda.get_rng_state(env.tdev)
    return state


def _restore_rng(state: dict, env) -> None:
    import torch

    torch.set_rng_state(state["torch"])
    env.generator.set_state(state["env_torch"])  # (older checkpoints also hold an unused "env_numpy")
    if "cuda" in state and str(env.tdev).startswith("cuda"):
        torch.cuda.set_rng_state(state["cuda"], env.tdev)


_TORCH_THREADS = None  # set when run as a program: one intra-op thread (the loop overlaps env and learner)

if __name__ == "__main__":
    _TORCH_THREADS = 1
    sys.exit(main())
