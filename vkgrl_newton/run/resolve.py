"""From a command line (and, on --resume, the run's checkpoint) to a `RunConfig`, in the order that
keeps a refusal cheap: the run directory and the checkpoint, the options against the method's row
(before torch or Warp load), then the device and the preset's defaults, then the given files.

`resolve(parser, argv)` returns a `Resolved` (the config, and the checkpoint's payload on a resume)
or a `Done` (nothing to run: the message and the exit code); a refusal is a `ConfigError`.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

from .._io import output_path_error
from ..agents.ppo_config import METHOD_PPO_DEFAULTS, parse_ppo_overrides, ppo_train_cfg
from ..agents.sac_config import SACConfig
from ..cache import check_run_files
from ..tasks import geometry_error
from .config import (RUN_FILES, ConfigError, RunConfig, check_scalars, default_run_dir, explicit_args, kgrl_recipe,
                     parse_sac_overrides, prior_table_flags, sac_config_for, search_without_z_reach, unavailable)
from .methods import METHODS, names
from .presets import (EVAL_MIN_EPISODES, KGRL_RECIPES, PPO_RUNNER_ONLY, RUN_DEFAULTS, default_kgrl_recipe,
                      recipe_options)

__all__ = ["resolve", "Resolved", "Done", "without_file_records", "check_demos_file", "check_vae_file"]

_NO_CHECKPOINT = ("--run-dir {run_dir} holds a run that stopped before its first checkpoint (no checkpoints/last.pt): "
                  "nothing to resume; choose another directory, or delete this one to start it again")
# what a resumed run takes from its checkpoint unless given again (then it must agree)
_RUN_IDENTITY = ("task", "method", "env", "action_dim", "seed", "num_envs", "preset", "label", "privileged_critic",
                 "kgrl_time_action", "tcp_velocity_obs", "force_obs", "obs_history", "vision_probe_obs", "kgrl_base",
                 "kgrl_residual_scale", "vision_probe_fit", "kgrl_search_speed_mm", "kgrl_search_press_mm")


@dataclass(frozen=True)
class Resolved:
    config: RunConfig
    payload: dict | None  # the checkpoint a resumed run continues from


@dataclass(frozen=True)
class Done:
    message: str  # printed on stderr as it is
    code: int


def resolve(parser, argv, torch_threads: int | None = None) -> Resolved | Done:
    """torch_threads: the intra-op threads the run will train with (run.py: 1), for the CPU matmul choice."""
    ns = parser.parse_args(argv)
    ns.torch_threads = torch_threads
    ns.probe = None  # a resumed run's recorded near-hole probe (_from_checkpoint)
    if ns.vision_probe_obs and ns.vae is not None:  # (before a resume fills ns.vae from the run's own record)
        raise ConfigError("--vision-probe-obs takes the cached VAE of the task and preset: its probe is fitted on that "
                          "VAE's own image set, which a given --vae does not come with; leave out --vae")
    ns.sac_config, ns.ppo_cfg, payload = None, None, None
    _check_run_dir(ns)
    if ns.resume:
        payload = _from_checkpoint(ns, explicit_args(_fresh_parser(parser), argv))
        if isinstance(payload, Done):
            return payload
    provisional = ns.preset or ("thesis" if (ns.device or "").startswith("cuda") else "quick")
    ns.recipe_filled, ns.recipe_deferred = (), False
    try:
        ns.recipe_filled = _fill_recipe_options(ns, provisional)
        _check_options(ns)
        checked = _check_sac_options(ns, provisional)
    except ConfigError:
        # neither --preset nor --device: the preset is the quick one's guess until Warp says which device runs (a
        # CUDA default is the thesis preset, whose recipe fills nothing). A refusal that the guessed recipe's
        # options alone cause waits for the device (_apply_device_and_defaults); any other is refused here.
        if ns.preset is not None or ns.device is not None or ns.kgrl_recipe is not None or ns.resume:
            raise
        for option in ns.recipe_filled:
            setattr(ns, option, None)
        ns.recipe_filled, ns.recipe_deferred = (), True
        _check_options(ns)
        checked = _check_sac_options(ns, provisional)
    if (reason := unavailable(ns)) is not None:  # (imports the env's module: the heavy part starts here)
        return Done(f"train/run.py: {reason}", 2)
    _check_given_demos(ns)
    _apply_device_and_defaults(ns, provisional, checked)
    config = _with_cpu_matmul(ns, _to_config(ns, payload), payload)
    _check_given_vae(config)
    if payload is not None:
        _check_against_checkpoint(ns, config, payload)
    return Resolved(config, payload)


def _fresh_parser(parser):
    """A parser like `parser` whose defaults explicit_args may clear (build_parser is called again)."""
    from .config import build_parser

    return build_parser(parser.epilog)


def _check_run_dir(ns) -> None:
    d = ns.run_dir
    if d is not None and d.is_dir() and any((d / n).exists() for n in RUN_FILES):
        if not (d / "checkpoints" / "last.pt").exists():  # with or without --resume: one message
            raise ConfigError(_NO_CHECKPOINT.format(run_dir=d))
        if not ns.resume:
            raise ConfigError(f"--run-dir {d} already holds a run; pass --resume to continue it or choose another "
                              "directory")
    if ns.resume and d is None:
        raise ConfigError("--resume needs --run-dir (the run to continue)")


def _from_checkpoint(ns, given: set[str]) -> dict | Done:
    """The run's identity and plan from its checkpoint, into `ns` where not given again (a damaged
    checkpoint is refused here); Done when the run is finished and nothing more is asked."""
    from ..agents.checkpoint import load_checkpoint

    try:
        payload = load_checkpoint(ns.run_dir / "checkpoints" / "last.pt", map_location="cpu")
    except (FileNotFoundError, ValueError) as e:
        raise ConfigError(f"--resume: {e}") from None
    meta = payload["meta"]
    if isinstance(meta.get("sac"), dict):  # a run from before SACConfig.cpu_matmul ran on torch's matmul
        meta["sac"].setdefault("cpu_matmul", "torch")
    for name in _RUN_IDENTITY:
        if name not in given:
            setattr(ns, name, meta.get(name))
    if "no_time_obs" not in given:
        ns.no_time_obs = not meta["time_obs"]
    if "kgrl_recipe" not in given and ns.method in METHODS and METHODS[ns.method].takes_recipe:
        ns.kgrl_recipe = meta.get("kgrl_recipe", "base")  # absent: a run before recipes
    if "geometry" not in given:
        ns.geometry = meta.get("geometry", "primitives")
    if "vae" not in given and "vision" in meta:
        ns.vae = Path(meta["vision"]["vae"])
    if "probe" in meta.get("vision", {}):  # (no option names it: the run's own, always)
        ns.probe = Path(meta["vision"]["probe"])
    if "demos" not in given and "prior" in meta:
        ns.demos = Path(meta["prior"]["demos"])
    try:  # a run continues from exactly what it learned from
        check_run_files(meta, demos=ns.demos, vae=ns.vae, probe=ns.probe)
    except (FileNotFoundError, ValueError) as e:
        raise ConfigError(f"--resume: {e}") from None
    if (done := _finished(ns, payload, given)) is not None:
        return done
    for name, value in payload.get("plan", {}).items():  # total_steps, checkpoint_every, eval_episodes, eval_seed
        if name not in given:
            setattr(ns, name, value)
    ns.keep_at_planned = "keep_at" not in given and bool(ns.keep_at)
    if ns.method in METHODS and METHODS[ns.method].uses_ppo:
        if not ns.ppo:
            ns.ppo_cfg = meta.get("ppo")
    elif not ns.sac and "sac" in meta:  # (a PPO run resumed as a SAC method: the meta check names it)
        try:
            ns.sac_config = SACConfig(**meta["sac"])
        except (TypeError, ValueError) as e:
            raise ConfigError(f"--resume: the checkpoint's SAC configuration is not valid today ({e}); give the "
                              "fields again with --sac FIELD=VALUE") from None
    return payload


def _finished(ns, payload: dict, given: set[str]) -> Done | None:
    """A finished run (its metrics.json is of the checkpoint's transitions): nothing to continue and
    nothing rewritten (its metrics.json is what report.py reads), unless --total-steps asks for more."""
    done_at = int(payload["counters"].get("transitions", 0))
    metrics_file = ns.run_dir / "metrics.json"
    try:
        finished = metrics_file.exists() and int(
            json.loads(metrics_file.read_text()).get("training", {}).get("transitions", -1)) == done_at
    except (json.JSONDecodeError, ValueError, TypeError, AttributeError):
        finished = False
    if finished and not ("total_steps" in given and ns.total_steps > done_at):
        keep = (" (--keep-at keeps counts still to be trained: with --total-steps, counts above "
                f"{done_at})") if "keep_at" in given else ""
        return Done(f"train/run.py: {ns.run_dir} is a finished run ({done_at} transitions, {metrics_file}); nothing "
                    f"to resume{keep}. Train it further with --total-steps N (> {done_at}); evaluate it again with "
                    f"train/evaluate.py --checkpoint {ns.run_dir / 'checkpoints' / 'last.pt'} --json FILE", 0)
    return None


def _fill_recipe_options(ns, preset: str) -> tuple[str, ...]:
    """The run options the KGRL recipe sets for the method (presets.recipe_options: --kgrl-recipe's, else `preset`'s)
    put into `ns` where not given; the names filled. A resumed run keeps its own (from its checkpoint). An option
    whose prerequisite was given otherwise is left out (a residual scale without a base, a probe fit without the
    probe); what cannot go with the recipe is refused here, naming the recipe."""
    m = METHODS.get(ns.method)
    if ns.resume or m is None or not m.takes_recipe:
        return ()
    name = ns.kgrl_recipe or default_kgrl_recipe(preset, ns.task, ns.env, ns.action_dim)
    options = recipe_options(KGRL_RECIPES[name], ns.method)
    if not options:
        return ()
    source = f"--kgrl-recipe {name}" if ns.kgrl_recipe else \
        f"the {preset} preset's KGRL recipe for {ns.task} {ns.env} {ns.action_dim}D ({name})"
    if options.get("vision_probe_obs") and ns.vae is not None:
        raise ConfigError(f"--vae with {source}: its policy reads the near-hole probe fitted on the cached VAE's own "
                          "image set, which a given --vae does not come with; leave out --vae, or give --kgrl-recipe "
                          "reach_keep_prior")
    if options.get("kgrl_base") not in (None, "prior") and ns.kgrl_time_action and ns.kgrl_base is None:
        raise ConfigError(f"--kgrl-time-action with {source}: its a = 0 is a base controller (--kgrl-base "
                          f"{options['kgrl_base']}), which the time action does not move; give --kgrl-base prior or "
                          "--kgrl-recipe reach_keep_prior")
    filled = []
    for option, value in options.items():
        if getattr(ns, option) is not None:
            continue
        if option == "kgrl_residual_scale" and ns.kgrl_base in (None, "prior"):
            continue
        if option == "vision_probe_fit" and not ns.vision_probe_obs:
            continue
        if option.startswith("kgrl_search_") and ns.kgrl_base != "centre_search":  # the spiral's, on another base
            continue
        setattr(ns, option, value)
        filled.append(option)
    return tuple(filled)


def _check_options(ns) -> None:
    """Each option against the method's row of the table (ConfigError), before anything heavy."""
    m = METHODS[ns.method]
    if geometry_error(ns.task, ns.geometry):
        raise ConfigError(f"--{geometry_error(ns.task, ns.geometry)}")
    if ns.geometry == "mesh" and m.vision:
        raise ConfigError(f"--geometry mesh is for the sac and kgrl methods: the image sets and VAEs of {ns.method} "
                          "are made on the primitives")
    check_scalars(ns)
    if ns.total_steps is not None and (why := _keep_at_error(ns)):  # (given, or the resumed run's: else the preset's)
        raise ConfigError(why)
    if ns.demos is not None and not m.uses_kmp and not ns.resume:
        raise ConfigError(f"--demos is for the kgrl methods ({names(uses_kmp=True)}), not {ns.method!r}")
    if m.uses_ppo:  # PPO's settings are --ppo's; the SAC-loop options do not apply
        # (--no-overlap is what PPO does anyway: sweep.py passes it to every one-core trial)
        for flag, given_here in (("--sac", ns.sac), ("--overlap", ns.overlap is True),
                                 ("--no-time-obs", ns.no_time_obs), ("--cpu-matmul", ns.cpu_matmul),
                                 ("--privileged-critic", ns.privileged_critic), ("--obs-history", ns.obs_history)):
            if given_here:
                raise ConfigError(f"{flag} is for the SAC methods ({names(uses_sac=True)}), not {ns.method!r}")
        try:
            ns.ppo_overrides = {**METHOD_PPO_DEFAULTS.get(ns.method, {}), **parse_ppo_overrides(ns.ppo)}
            if runner_only := sorted(set(ns.ppo_overrides) & set(PPO_RUNNER_ONLY)):
                key = runner_only[0]
                raise ValueError(f"{key} is for rsl-rl's OnPolicyRunner, not run.py's loop ({PPO_RUNNER_ONLY[key]})")
            ppo_train_cfg(ns.task, ns.env, 1, **ns.ppo_overrides)  # checked now; sized below
        except ValueError as e:
            raise ConfigError(f"--ppo: {e}") from None
    elif ns.ppo:
        raise ConfigError(f"--ppo is for the ppo methods ({names(uses_ppo=True)}), not {ns.method!r}")
    try:
        ns.sac_overrides = parse_sac_overrides(ns.sac)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    if ns.cpu_matmul is not None:  # the option is --sac cpu_matmul=... under another name
        if ns.sac_overrides.get("cpu_matmul", ns.cpu_matmul) != ns.cpu_matmul:
            raise ConfigError(f"--cpu-matmul {ns.cpu_matmul} and --sac cpu_matmul={ns.sac_overrides['cpu_matmul']} "
                              "disagree; give one of them")
        ns.sac_overrides["cpu_matmul"] = ns.cpu_matmul
    if ns.kgrl_recipe is not None and not m.takes_recipe:
        raise ConfigError(f"--kgrl-recipe is for the kgrl methods on SAC ({names(takes_recipe=True)}), "
                          f"not {ns.method!r}")
    if ns.obs_history is not None and not 0 <= ns.obs_history <= 16:
        raise ConfigError(f"--obs-history {ns.obs_history}: steps of history, in [0, 16]")
    if ns.force_obs and ns.env == "forge":
        raise ConfigError("--force-obs is for --env factory: the Forge observation holds the force already")
    if ns.kgrl_time_action is not None:
        if not m.takes_recipe:  # (the kmp methods on SAC)
            raise ConfigError(f"--kgrl-time-action is for the kgrl methods on SAC ({names(takes_recipe=True)}), "
                              f"not {ns.method!r}")
        if not 0 <= ns.kgrl_time_action <= 10:
            raise ConfigError(f"--kgrl-time-action {ns.kgrl_time_action}: control steps per unit action, in [0, 10]")
    if ns.kgrl_base not in (None, "prior"):
        if not m.takes_recipe:  # (the kmp methods on SAC)
            raise ConfigError(f"--kgrl-base is for the kgrl methods on SAC ({names(takes_recipe=True)}), "
                              f"not {ns.method!r}")
        if ns.kgrl_time_action:
            raise ConfigError(f"--kgrl-base {ns.kgrl_base} with --kgrl-time-action: the base controller follows the "
                              "control step, the time action moves the prior's query; give one of them")
        if ns.kgrl_base == "centre_latent" and not ns.vision_probe_obs:
            raise ConfigError("--kgrl-base centre_latent steers by the camera's estimate of the part over the hole: "
                              "add --vision-probe-obs (a vision method), which gives the env that estimate")
    for flag, value, what, top in (("--kgrl-search-speed", ns.kgrl_search_speed_mm, "mm per control step", 1.0),
                                   ("--kgrl-search-press", ns.kgrl_search_press_mm, "mm below the TCP", 10.0)):
        if value is None:
            continue
        if not m.takes_recipe:  # (the kmp methods on SAC)
            raise ConfigError(f"{flag} is for the kgrl methods on SAC ({names(takes_recipe=True)}), "
                              f"not {ns.method!r}")
        if ns.kgrl_base is None and getattr(ns, "recipe_deferred", False):
            continue  # the base comes with the preset the device decides (checked again then)
        if ns.kgrl_base != "centre_search":
            raise ConfigError(f"{flag} sets the blind spiral search of --kgrl-base centre_search (the residual "
                              "recipe's kgrl), not of " + (f"--kgrl-base {ns.kgrl_base}" if ns.kgrl_base
                                                           not in (None, "prior") else "the prior"))
        if not (math.isfinite(value) and 0.0 < value <= top):
            raise ConfigError(f"{flag} {value}: {what}, in (0, {top:g}]")
    if ns.kgrl_residual_scale is not None:
        if ns.kgrl_base in (None, "prior") and ns.kgrl_residual_scale != 1.0:
            raise ConfigError("--kgrl-residual-scale scales the policy's actions on a base controller: give "
                              "--kgrl-base centre_search or centre_latent (on the prior the null space's scale is the "
                              "thesis's w)")
        if not (math.isfinite(ns.kgrl_residual_scale) and 0.0 < ns.kgrl_residual_scale <= 1.0):
            raise ConfigError(f"--kgrl-residual-scale {ns.kgrl_residual_scale}: a number in (0, 1]")
    if ns.kmp_reference is not None and not m.uses_kmp:
        raise ConfigError(f"--kmp-reference is for the kgrl methods ({names(uses_kmp=True)}), not {ns.method!r}")
    for _, flag, value in prior_table_flags(ns):
        if value is not None and not m.uses_kmp:
            raise ConfigError(f"{flag} is for the kgrl methods ({names(uses_kmp=True)}), not {ns.method!r}")
    if ns.vae is not None and not m.vision:
        raise ConfigError(f"--vae is for the vision methods ({names(vision=True)}), not {ns.method!r}")
    if ns.vision_probe_obs and not m.vision:
        raise ConfigError(f"--vision-probe-obs is for the vision methods ({names(vision=True)}), not {ns.method!r}")
    if ns.vision_probe_fit not in (None, "images") and not ns.vision_probe_obs:
        raise ConfigError(f"--vision-probe-fit {ns.vision_probe_fit} chooses the near-hole probe of --vision-probe-obs: "
                          "add --vision-probe-obs (a vision method)")
    if ns.run_dir is not None and ns.run_dir.exists() and not ns.run_dir.is_dir():
        raise ConfigError(f"--run-dir {ns.run_dir} is a file; give a directory (new, or a run's with --resume)")
    for flag, path in (("--run-dir", ns.run_dir), ("--cache-dir", ns.cache_dir)):  # (the default run dir: runs/train)
        if why := output_path_error(path if path is not None else Path("runs/train"), flag, may_exist=True):
            raise ConfigError(why)


def _check_sac_options(ns, provisional: str):
    """The SAC config checked before torch and Warp are imported, with the preset the device implies
    when it is given (a CUDA default is known only later; then it is checked again)."""
    m = METHODS[ns.method]
    checked = ns.sac_config
    if checked is None and not m.uses_ppo:
        try:
            checked = sac_config_for(ns, provisional)
        except ValueError as e:
            raise ConfigError(f"--sac: {e}") from None
    prior_only = [f for f in ("prior_anchor", "prior_ratio", "prior_rollouts") if getattr(checked, f, None)]
    rollouts = getattr(checked, "prior_rollouts_policy", "prior")
    if rollouts == "scripted":  # the SAC methods' demonstrations: the first rollouts and their buffer are theirs
        if m.uses_kmp:
            raise ConfigError(f"--sac prior_rollouts_policy=scripted is for the SAC methods "
                              f"({names(uses_sac=True, uses_kmp=False)}), not {ns.method!r}, whose first rollouts "
                              "are the prior's (prior) or the search's (search)")
        prior_only = [f for f in prior_only if f == "prior_anchor"]
    elif rollouts != "prior":
        prior_only.append("prior_rollouts_policy")
    if prior_only and not m.uses_kmp:
        hint = "" if prior_only[0] == "prior_anchor" else \
            "; the SAC methods learn from the demonstrator's rollouts with --sac prior_rollouts_policy=scripted"
        raise ConfigError(f"--sac {prior_only[0]}: acts with or learns from the KMP prior (a = 0), for the kgrl "
                          f"methods ({names(takes_recipe=True)}), not {ns.method!r}{hint}")
    if ns.kgrl_base not in (None, "prior") and not ns.resume and METHODS[ns.method].takes_recipe:
        reach_z = ns.kgrl_reach_floor_z if ns.kgrl_reach_floor_z is not None else \
            kgrl_recipe(ns, provisional)["reach_floor_z_mm"]
        if not reach_z:
            raise ConfigError(f"--kgrl-base {ns.kgrl_base} lightens the prior's ~20 mm press on a blocked part, as the "
                              "search does: it needs z reach, give --kgrl-reach-floor-z MM (e.g. 25; the thesis's null "
                              "space, --kgrl-recipe base, reaches ~2 mm there)")
        # (--kgrl-seat-press with a base: the base presses a part it found while steering 3 mm under the prior's z;
        # a part that goes in without being blocked is the prior's, held above its seat unless the prior presses:
        # docs/results/probe_closed_loop_40, 4 of the camera controller's 10 losses, all seated with 5 mm)
    if rollouts == "search" and ns.kgrl_base not in (None, "prior"):
        raise ConfigError(f"--sac prior_rollouts_policy=search with --kgrl-base {ns.kgrl_base}: a = 0 is already "
                          "that controller; leave prior_rollouts_policy at prior")
    if why := search_without_z_reach(ns, checked, provisional):
        raise ConfigError(why)
    if ns.privileged_critic and getattr(checked, "prior_anchor", False):
        raise ConfigError("--privileged-critic with the prior anchor (the kgrl recipe's prior_anchor): the anchor "
                          "chooses each action by the critic's value, which would bring privileged state to the "
                          "policy; add --sac prior_anchor=false")
    return checked


def _keep_at_error(ns) -> str | None:
    """Why --keep-at cannot be kept (a count past the run's transitions), or None."""
    if not ns.keep_at or max(ns.keep_at) <= ns.total_steps:
        return None
    whose = " (the counts its checkpoint plans: give --keep-at again)" if getattr(ns, "keep_at_planned", False) else ""
    return (f"--keep-at {max(ns.keep_at)}{whose}: past the run's --total-steps {ns.total_steps} (each N must be <= it; "
            "the end's policy is checkpoints/last.pt)")


def _check_given_demos(ns) -> None:
    if ns.demos is not None and not ns.resume:  # a missing, damaged or foreign file stops here
        check_demos_file(ns.demos, ns.task)


def check_demos_file(path, task: str) -> None:
    """A demonstration file that is missing, damaged or of another task: ConfigError."""
    from ..kmp.demos import DemoSet

    try:
        demo_task = DemoSet.load(path).task
    except (FileNotFoundError, ValueError) as e:
        raise ConfigError(f"--demos: {e}") from None
    if demo_task != task:
        raise ConfigError(f"--demos {path}: demonstrations of {demo_task}, not --task {task}")


def check_vae_file(path, task: str) -> None:
    """A vae.pt that is missing, of another task, damaged or not a VAE: ConfigError."""
    from ..tasks import VISION_LATENT_DIM
    from ..vision.vae import load_vae

    try:
        load_vae(path, expect={"task": task, "latent_dim": VISION_LATENT_DIM})
    except (FileNotFoundError, ValueError) as e:
        raise ConfigError(f"--vae: {e}") from None


def _apply_device_and_defaults(ns, provisional: str, checked) -> None:
    """Warp configured, the device checked, the preset's defaults filled in (torch and Warp load here)."""
    from ..runtime import configure_warp, default_device, device_error

    configure_warp(ns.verbose)
    ns.device = ns.device or default_device()
    if (why := device_error(ns.device)) is not None:
        raise ConfigError(why)
    preset = ns.preset or ("thesis" if ns.device.startswith("cuda") else "quick")
    # a CUDA default device: the thesis preset's recipe, not the guessed quick one's; a refusal the guess deferred
    # is made now when the guess holds
    deferred, ns.recipe_deferred = ns.recipe_deferred, False  # the device is known: every refusal is made now
    if (preset != provisional and ns.recipe_filled) or deferred:
        for option in ns.recipe_filled:
            setattr(ns, option, None)
        ns.recipe_filled = _fill_recipe_options(ns, preset)
        _check_options(ns)
        if deferred and preset == provisional:
            checked = _check_sac_options(ns, preset)
    ns.preset = preset
    m = METHODS[ns.method]
    if m.takes_recipe:
        ns.kgrl_recipe = ns.kgrl_recipe or default_kgrl_recipe(ns.preset, ns.task, ns.env, ns.action_dim)
    if ns.sac_config is None and not m.uses_ppo:
        try:
            ns.sac_config = checked if ns.preset == provisional else sac_config_for(ns, ns.preset)
        except ValueError as e:
            raise ConfigError(f"--sac: {e}") from None
        if why := search_without_z_reach(ns, ns.sac_config, ns.preset):  # (the preset may have changed)
            raise ConfigError(why)
    defaults = RUN_DEFAULTS[ns.preset]
    ns.num_envs = ns.num_envs or defaults["num_envs"]
    ns.total_steps = ns.total_steps or defaults["total_steps"]
    ns.checkpoint_every = ns.checkpoint_every or defaults["checkpoint_every"]
    if why := _keep_at_error(ns):
        raise ConfigError(why)
    if ns.eval_episodes is None:
        ns.eval_episodes = -(-EVAL_MIN_EPISODES // ns.num_envs)
    if m.uses_ppo and ns.ppo_cfg is None:  # minibatches of ~512 transitions for these worlds
        ns.ppo_cfg = ppo_train_cfg(ns.task, ns.env, ns.num_envs, **ns.ppo_overrides)


def _to_config(ns, payload: dict | None) -> RunConfig:
    """The frozen configuration; the prior's parameters and floors from the checkpoint on a resume."""
    run_dir = ns.run_dir or default_run_dir(ns)
    if not ns.resume and any((run_dir / name).exists() for name in RUN_FILES):  # a default name taken meanwhile
        raise ConfigError(f"--run-dir {run_dir} already holds a run; pass --resume to continue it or choose another "
                          "directory")
    recipe = kgrl_recipe(ns, ns.preset)
    changes = {key: float(given if given is not None else recipe.get(key, 0.0))
              for key, _, given in prior_table_flags(ns)}
    reference, kmp_params = ns.kmp_reference or "gmr", None
    if payload is not None and "prior" in payload["meta"]:  # the KMP parameters it was fitted with
        prior = payload["meta"]["prior"]
        kmp_params = {k: prior[k] for k in ("lam", "beta", "l")}
        reference = prior.get("reference", "gmr")
        for key, _, _ in prior_table_flags(ns):  # (a different one given is refused against the checkpoint)
            changes[key] = prior.get(key, 0.0)
    return RunConfig(
        task=ns.task, method=ns.method, env=ns.env, action_dim=ns.action_dim, seed=ns.seed, num_envs=ns.num_envs,
        preset=ns.preset, time_obs=not ns.no_time_obs, geometry=ns.geometry, label=ns.label,
        privileged_critic=bool(ns.privileged_critic), kgrl_time_action=int(ns.kgrl_time_action or 0),
        kgrl_base=ns.kgrl_base or "prior", kgrl_residual_scale=float(ns.kgrl_residual_scale or 1.0),
        kgrl_search_speed_mm=ns.kgrl_search_speed_mm, kgrl_search_press_mm=ns.kgrl_search_press_mm,
        tcp_velocity_obs=bool(ns.tcp_velocity_obs), force_obs=bool(ns.force_obs), obs_history=int(ns.obs_history or 0),
        vision_probe_obs=bool(ns.vision_probe_obs), vision_probe_fit=ns.vision_probe_fit or "images", probe=ns.probe,
        kgrl_recipe=ns.kgrl_recipe if METHODS[ns.method].takes_recipe else None,
        sac=ns.sac_config, ppo=ns.ppo_cfg, demos=ns.demos, num_demos=ns.num_demos, kmp_reference=reference,
        kmp_params=kmp_params, vae=ns.vae, total_steps=ns.total_steps,
        checkpoint_every=ns.checkpoint_every, eval_episodes=ns.eval_episodes, eval_seed=ns.eval_seed,
        keep_at=tuple(sorted(set(ns.keep_at or ()))), device=ns.device, run_dir=run_dir, resume=bool(ns.resume),
        cache_dir=ns.cache_dir,
        progress=not ns.no_progress, overlap=ns.overlap, eager_physics=bool(ns.eager_physics),
        verbose=bool(ns.verbose), **changes)


def _with_cpu_matmul(ns, config: RunConfig, payload: dict | None) -> RunConfig:
    """The config with the CPU matmul library that will run (never "auto"), so that config.json,
    metrics.json and the checkpoint record it: a resumed run's own; else "auto" resolved on this
    machine (agents/matmul_backend.py, kept in the cache directory); a given one that cannot run
    here is refused."""
    if config.sac is None:
        return config
    from ..agents.dense import onednn_available
    from ..agents.matmul_backend import CHOICE_FILE, choose_cpu_matmul

    given = ns.sac_overrides.get("cpu_matmul")  # --cpu-matmul or --sac cpu_matmul=
    backend = config.sac.cpu_matmul
    if payload is not None and "sac" in payload["meta"]:  # a run continues on the products it trained with
        backend = payload["meta"]["sac"]["cpu_matmul"]
        if given not in (None, "auto", backend):
            raise ConfigError(f"--resume: the run's SAC products ran on {backend}; --cpu-matmul {given} would change "
                              "its float32 results mid-run: resume without it")
    elif backend == "auto":
        backend = choose_cpu_matmul(config.sac, config.obs_dim, config.agent_action_dim, config.device,
                                    config.cache_dir / CHOICE_FILE, log=lambda m: print(f"train/run.py: {m}"),
                                    threads=ns.torch_threads)
    on_cpu = not str(config.device).startswith("cuda")
    if backend == "onednn" and not on_cpu and given == "onednn":
        raise ConfigError(f"--cpu-matmul onednn is a CPU library; on {config.device} the products run on cuBLAS: give "
                          "auto or torch")
    if backend == "onednn" and on_cpu and not onednn_available():
        import torch

        what = "--resume: the run's SAC products ran on oneDNN" if payload is not None else "--cpu-matmul onednn"
        raise ConfigError(f"{what}, which this torch ({torch.__version__}) does not provide; "
                          + ("evaluate it with train/evaluate.py --cpu-matmul torch" if payload is not None
                             else "give auto or torch"))
    return dataclasses.replace(config, sac=dataclasses.replace(config.sac, cpu_matmul=backend))


def _check_given_vae(config: RunConfig) -> None:
    if config.vae is not None:  # missing, the wrong task, damaged or not a VAE at all: stop before anything is built
        check_vae_file(config.vae, config.task)


def without_file_records(meta: dict) -> dict:
    """A run's meta less its file records (prior, VAE hash): compared by content, not as fields."""
    meta = dict(meta)
    meta.pop("prior", None)
    if "vision" in meta:
        meta["vision"] = {k: v for k, v in meta["vision"].items() if k not in ("vae_sha256", "probe", "probe_sha256")}
    return meta


def _check_against_checkpoint(ns, config: RunConfig, payload: dict) -> None:
    """A foreign checkpoint stops here, before anything is built."""
    from ..agents.checkpoint import check_meta

    try:
        saved = without_file_records(payload["meta"])  # checked above, by content
        # a checkpoint from before a SACConfig field existed holds that field's default
        if "sac" in saved:
            saved["sac"] = dataclasses.asdict(SACConfig(**saved["sac"]))
        now = config.meta()
        for m in (saved, now):  # the default geometry is not stored; name it in a mismatch
            m.setdefault("geometry", "primitives")
        check_meta(saved, now, config.ckpt_path)
    except ValueError as e:
        raise ConfigError(f"--resume: {e}") from None
    if config.method_row.uses_kmp and "prior" in payload["meta"]:  # the null space it learned in, before any build
        for key, flag, given in prior_table_flags(ns):
            was = payload["meta"]["prior"].get(key, 0.0)
            if given is not None and given != was:
                raise ConfigError(f"--resume: the run's {flag} was {was:g} mm, not {given:g}; resume without it")
