"""A run's configuration: the command line's options, `RunConfig` (frozen, every default resolved)
and `resolve`, which turns the options (or a run directory's checkpoint, on `--resume`) into one.

Every refusal of an option is a `ConfigError` raised here, with the text the command line prints
(train/run.py turns it into one line and exit 2). What a method allows comes from its row of the
method table (run/methods.py). Light imports only at module level: a command line answers --help
and every argument error before torch, Warp or Newton load.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
import time
from dataclasses import dataclass
from pathlib import Path

from ..agents.sac_config import CPU_MATMUL_CHOICES, SAC_PRESETS, SACConfig, make_sac_config
from ..cli_types import (EVAL_SEED_BITS, add_cache_dir_option, add_device_option, add_eager_physics_flag,
                         add_eval_seed_option, add_kmp_reference_option, add_verbose_flag, positive_int, seed_error)
from ..results.curves import CURVES_FILE
from ..results.paired import EVAL_SEED
from ..tasks import ACTION_DIMS, FAMILIES, GEOMETRIES, TASKS, VISION_LATENT_DIM, observation_dim
from .methods import METHODS, RUN_METHODS, Method, names
from .presets import EVAL_MIN_EPISODES, KGRL_RECIPES, NO_RECIPE, RUN_DEFAULTS, default_kgrl_recipe

__all__ = ["RunConfig", "ConfigError", "build_parser", "parse_sac_overrides", "kgrl_recipe", "RUN_FILES",
           "search_without_z_reach", "unavailable", "explicit_args", "add_cpu_matmul_option"]

# what a run writes in its directory; one holding any of them holds a run (other files, such as a
# sweep's train.log, may sit beside them)
# --kgrl-seat-press's ceiling (mm): 2 N at Factory's z gain of 100 N/m, the scale of the demonstrator's own press
# (4-6 mm at 250 N/m); more would only grind the part on the hole's face
SEAT_PRESS_MAX_MM = 20.0
RUN_FILES = ("config.json", "checkpoints", "tb", "metrics.json", CURVES_FILE)


class ConfigError(ValueError):
    """An option (or a checkpoint's configuration) that cannot run: the one line the command line prints."""


# envs.evaluation.SearchParams' speed_mm and press_mm, the centre_search base's unless --kgrl-search-speed /
# --kgrl-search-press (literals: this module loads before torch; tests/test_kgrl_base checks them against it)
SEARCH_SPEED_MM = 0.3
SEARCH_PRESS_MM = 1.0
# the RunConfig fields of the centre_search base's settings and the search's own value of each: None in a RunConfig
# (and absent from the meta and a = 0's cache key) where the run searches at that value
SEARCH_SETTINGS = {"kgrl_search_speed_mm": SEARCH_SPEED_MM, "kgrl_search_press_mm": SEARCH_PRESS_MM}


@dataclass(frozen=True)
class RunConfig:
    """Everything a run is: identity (what a resume must match), plan (what it was asked to do) and
    how it runs. Built by `resolve` from a command line or a checkpoint; nothing changes it after."""
    task: str = "PegInsert"
    method: str = "kgrl"
    env: str = "factory"
    action_dim: int = 4
    seed: int = 0
    num_envs: int = 16
    preset: str = "quick"
    time_obs: bool = True
    geometry: str = "primitives"
    label: str | None = None
    kgrl_recipe: str | None = None  # the takes_recipe methods' (run.presets.KGRL_RECIPES), else None
    sac: SACConfig | None = None  # the SAC learner's configuration (None for PPO)
    # an asymmetric critic (Factory's): the SAC critics also read the env's privileged state (the
    # `critic` observation group, envs.assembly_env.AssemblyEnv.privileged_state); the actor never does
    privileged_critic: bool = False
    # KMP time as an action (the kmp methods on SAC; the thesis's future work): a_t moves the prior's query
    # by 1 + round(k a_t) control steps per step (envs.kgrl_action); 0: none, the thesis
    kgrl_time_action: int = 0
    # what a = 0 stands for (the kmp methods on SAC; envs.evaluation.BASE_CONTROLLERS): the KMP prior (the thesis), or
    # a controller of the ceiling under the policy's actions (a residual): centre_search, centre_latent
    kgrl_base: str = "prior"
    kgrl_residual_scale: float = 1.0  # with a base: the policy's actions scaled by it before they are added
    # with the centre_search base: its spiral's speed along the arc, mm per control step, and z commanded this far
    # below the TCP while searching; None: the search's own (SEARCH_SPEED_MM, SEARCH_PRESS_MM; a value given equal
    # to it is stored as None, so that it is the same run)
    kgrl_search_speed_mm: float | None = None
    kgrl_search_press_mm: float | None = None
    # the policy's extra inputs (envs.assembly_env.EnvConfig; deviations from eq. 5.5): the TCP's velocity,
    # and in Factory the smoothed contact force (Forge's observation has it)
    tcp_velocity_obs: bool = False
    force_obs: bool = False
    obs_history: int = 0  # the SAC methods: the last K (input, action) pairs stacked onto the input (envs.history)
    # the vision methods: the near-hole probe's estimate of the held part over the hole (world x, y, from the latent;
    # prepare.vision.load_or_make_probe) appended to the latent (envs.camera_latent)
    vision_probe_obs: bool = False
    # what that probe is fitted on (prepare.vision.PROBE_FITS): the VAE's image set (images), or that and the camera
    # controller's own frames (closed_loop: prepare.closed_loop)
    vision_probe_fit: str = "images"
    probe: Path | None = None  # its probe file: a resumed or evaluated run's recorded one (None: the cache's)
    ppo: dict | None = None  # rsl-rl's runner configuration (ppo methods)
    # the prior (kmp methods): your demonstrations or the scripted ones, the KMP's reference and
    # parameters (None: kmp.prior's defaults; a resumed run's own), the action path's reach floors (mm)
    demos: Path | None = None
    num_demos: int = 16
    kmp_reference: str = "gmr"
    kmp_params: dict | None = None
    reach_floor_mm: float = 0.0
    reach_floor_z_mm: float = 0.0
    seat_press_mm: float = 0.0  # --kgrl-seat-press: the prior's z lowered from its seat on (0: the thesis)
    vae: Path | None = None  # vision methods: a given vae.pt (None: the cache's for the task and preset)
    # the plan
    total_steps: int = 30_000
    checkpoint_every: int = 4_800
    eval_episodes: int = 8
    eval_seed: int = EVAL_SEED
    keep_at: tuple[int, ...] = ()  # --keep-at: transition counts whose policy is kept (checkpoints/at_<N>.pt)
    # how it runs
    device: str = "cpu"
    run_dir: Path = Path("runs/train/run")
    resume: bool = False
    cache_dir: Path = Path("runs/cache")
    progress: bool = True
    overlap: bool | None = None  # None: on for a CPU device
    eager_physics: bool = False
    verbose: bool = False

    def __post_init__(self):
        # a search setting equal to the search's own is the run without it (one meta, one a = 0 cache key)
        for name, default in SEARCH_SETTINGS.items():
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, None if float(value) == default else float(value))

    @property
    def method_row(self) -> Method:
        return METHODS[self.method]

    @property
    def latent_dim(self) -> int:
        return VISION_LATENT_DIM if self.method_row.vision else 0

    @property
    def vision_width(self) -> int:
        """The vision slot's width: the latent, plus the probe's x, y with vision_probe_obs (envs.camera_latent's
        LATERAL_DIM, a literal here: the command line parses before torch loads)."""
        return self.latent_dim + (2 if self.vision_probe_obs else 0)

    @property
    def obs_dim(self) -> int:
        """The policy input's width: observation_dim(), the same function the env uses, less time if ablated,
        plus the KMP query's phase with the time action."""
        width = (observation_dim(self.env, self.vision_width, self.tcp_velocity_obs, self.force_obs)
                 - (0 if self.time_obs else 1) + (1 if self.kgrl_time_action else 0))
        # envs.history.stacked_width (torch-free here: the command line parses before torch loads)
        return width + self.obs_history * (width + self.agent_action_dim)

    @property
    def agent_action_dim(self) -> int:
        """The learner's action width: the env's, plus the time action's a_t."""
        return self.action_dim + (1 if self.kgrl_time_action else 0)

    @property
    def ckpt_path(self) -> Path:
        return self.run_dir / "checkpoints" / "last.pt"

    @property
    def prior_table_changes(self) -> dict:
        """What the run changes of its prior's tables (mm): the reach floors and the seat press (prior_record)."""
        return {"reach_floor_mm": self.reach_floor_mm, "reach_floor_z_mm": self.reach_floor_z_mm,
                "seat_press_mm": self.seat_press_mm}

    def plan(self) -> dict:
        """What a run was asked to do beyond its identity; a resumed run keeps it unless given again."""
        return {"total_steps": self.total_steps, "checkpoint_every": self.checkpoint_every,
                "eval_episodes": self.eval_episodes, "eval_seed": self.eval_seed,
                **({"keep_at": list(self.keep_at)} if self.keep_at else {})}  # (absent unless asked: older runs')

    def kept_path(self, n: int) -> Path:
        """--keep-at N: the policy at the first step at or past N transitions (no replay buffer: it evaluates,
        train/evaluate.py --checkpoint, and does not resume)."""
        return self.run_dir / "checkpoints" / f"at_{n}.pt"

    def vae_path(self) -> Path:
        """The run's vae.pt: the given one, or the cached one of the task and preset (made when missing)."""
        from ..prepare.vision import VISION_PRESETS, default_vae_dir

        if self.vae is not None:
            return Path(self.vae)
        return default_vae_dir(self.cache_dir, self.task, VISION_PRESETS[self.preset]) / "vae.pt"

    def probe_path(self) -> Path:
        """The run's near-hole probe (vision_probe_obs): the recorded one, or the cache's for its VAE (made when
        missing: prepare.vision.load_or_make_probe)."""
        from ..prepare.vision import VISION_PRESETS, default_probe_path

        return Path(self.probe) if self.probe is not None else default_probe_path(
            self.cache_dir, self.task, VISION_PRESETS[self.preset], fit=self.vision_probe_fit)

    def meta(self) -> dict:
        """What identifies a run; a resumed run must match it field by field. The learner's configuration:
        "sac" (the SACConfig) or, for the ppo methods, "ppo" (the rsl-rl runner configuration)."""
        meta = {"task": self.task, "method": self.method, "env": self.env, "action_dim": self.action_dim,
                "seed": self.seed, "num_envs": self.num_envs, "preset": self.preset, "time_obs": self.time_obs,
                "obs_dim": self.obs_dim}
        if self.method_row.uses_ppo:
            meta["ppo"] = self.ppo
        else:
            meta["sac"] = dataclasses.asdict(self.sac)
        if self.geometry != "primitives":  # absent in the default case, so older checkpoints still resume
            meta["geometry"] = self.geometry
        if self.label:  # absent unless given, so older runs still resume
            meta["label"] = self.label
        if self.privileged_critic:  # absent unless asked, so older runs still resume
            meta["privileged_critic"] = True
        if self.kgrl_time_action:  # likewise
            meta["kgrl_time_action"] = self.kgrl_time_action
        if self.kgrl_base != "prior":  # likewise
            meta["kgrl_base"] = self.kgrl_base
        if self.kgrl_residual_scale != 1.0:  # likewise
            meta["kgrl_residual_scale"] = self.kgrl_residual_scale
        for name in SEARCH_SETTINGS:  # likewise
            if getattr(self, name) is not None:
                meta[name] = getattr(self, name)
        for name in ("tcp_velocity_obs", "force_obs", "vision_probe_obs"):  # likewise
            if getattr(self, name):
                meta[name] = True
        if self.obs_history:  # likewise
            meta["obs_history"] = self.obs_history
        if self.vision_probe_fit != "images":  # likewise
            meta["vision_probe_fit"] = self.vision_probe_fit
        if self.kgrl_recipe not in (None, "base"):  # absent for base, as in runs before recipes
            meta["kgrl_recipe"] = self.kgrl_recipe
        if self.method_row.vision:
            meta["vision"] = {"vae": str(self.vae_path()), "latent_dim": VISION_LATENT_DIM}
        return meta


def build_parser(doc: str | None = None) -> argparse.ArgumentParser:
    """train/run.py's options (`doc`: its docstring, for --help)."""
    ap = argparse.ArgumentParser(description=(doc or "Train a policy").split("\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=doc)
    ap.add_argument("--task", default="PegInsert", choices=sorted(TASKS))
    ap.add_argument("--method", default="kgrl", choices=RUN_METHODS,
                    help="; ".join(f"{m.name}: {m.summary}" for m in METHODS.values()))
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
    ap.add_argument("--privileged-critic", action="store_true", default=None,
                    help="the SAC methods: an asymmetric critic (Isaac Lab Factory's): the critics also read state no "
                         "policy observes (the held part against its assembled pose, the noiseless target, the part's "
                         "pose in the hand, the contact force); the actor reads the same inputs as without it. A "
                         "deviation from the thesis (eq. 5.5). Needs --sac prior_anchor=false (the anchor picks "
                         "actions by the critic's value)")
    ap.add_argument("--tcp-velocity-obs", action="store_true", default=None,
                    help="the policy also observes the TCP's linear and angular velocity (world; Factory's finite "
                         "differences over the control step). A deviation from eq. 5.5; not yet ablated")
    ap.add_argument("--force-obs", action="store_true", default=None,
                    help="Factory: the policy also observes the smoothed contact force (with Forge's 1 N noise; the "
                         "KGRL paper's actor reads the wrench). A deviation from eq. 5.5; not yet ablated")
    ap.add_argument("--vision-probe-obs", action="store_true", default=None,
                    help="vision methods: the policy also reads the camera's estimate of the held part over the hole: "
                         "the cached VAE's latent through a near-hole probe fitted on the VAE's own images with their "
                         "privileged geometry (as a pose estimator is trained in simulation), world x, y. Not with "
                         "--vae. A deviation from eq. 5.6")
    ap.add_argument("--vision-probe-fit", default=None, choices=("images", "closed_loop"),
                    help="with --vision-probe-obs: what the near-hole probe is fitted on. images (default): the VAE's "
                         "image set. closed_loop: that and the frames of the camera controller (--kgrl-base "
                         "centre_latent's a = 0) steering by the image-set probe on 128 episodes of their own (eval "
                         "seed 20000), labelled in simulation as DAgger does: the estimate is then trained where that "
                         "controller steers by it. Made once per VAE (~5 min on a CPU core)")
    ap.add_argument("--obs-history", type=int, default=None, metavar="K",
                    help="the SAC methods: the policy's input carries its last K inputs and actions (zeros before the "
                         "episode began; envs.history), a feed-forward form of Factory's LSTM actor. 0 (default): none, "
                         "the thesis. A deviation from eq. 5.5; not yet ablated")
    ap.add_argument("--kgrl-time-action", type=int, default=None, metavar="K",
                    help="kgrl, vision_kgrl: KMP time as an action (the thesis's future work, Chapter 7): one more "
                         "action dimension a_t moves the prior's query by 1 + round(K a_t) control steps per step, so "
                         "that a blocked part can be lifted and tried again; the query's phase becomes a policy input. "
                         "a = 0 is still the prior. 0 (default): none, the thesis. A deviation; not yet ablated")
    ap.add_argument("--kgrl-base", default=None, choices=("prior", "centre_search", "centre_latent"),
                    help="kgrl, vision_kgrl: what a = 0 stands for. prior (default): the KMP prior, the thesis. Else a "
                         "controller of the ceiling (docs/results/oracle_noise_40), nothing privileged, with the "
                         "policy's actions added to its own (a residual, as ResiP): centre_search (blind: once "
                         "blocked, the search's spiral about the observed target) or centre_latent (once blocked, "
                         "steer by the camera's estimate of the part over the hole; needs --vision-probe-obs). The "
                         "prior evaluated beside the policy is then that controller (a = 0). A deviation from eq. 4.36; "
                         "not with --kgrl-time-action or --sac prior_rollouts_policy=search")
    ap.add_argument("--kgrl-residual-scale", type=float, default=None, metavar="S",
                    help="with --kgrl-base: the policy's actions are scaled by S in (0, 1] before they are added to the "
                         "base's (ResiP's residual scale: a bounded correction, smaller exploration around the base). "
                         "Default 1")
    ap.add_argument("--kgrl-search-speed", dest="kgrl_search_speed_mm", type=float, default=None, metavar="MM",
                    help="with --kgrl-base centre_search (the residual recipe's kgrl): the blind spiral's speed along "
                         "its arc, mm per control step, in (0, 1]. Default 0.3 (the ceiling's search). At 0.3 the part "
                         "often passes over the hole without dropping in; 0.15 seats 0.609 of PegInsert Factory 4D's "
                         "paired episodes with a = 0 pressing 1 mm, against 0.258 (docs/results/search_reach_40)")
    ap.add_argument("--kgrl-search-press", dest="kgrl_search_press_mm", type=float, default=None, metavar="MM",
                    help="with --kgrl-base centre_search: z commanded MM below the TCP while the spiral searches, in "
                         "(0, 10]. Default: 2.5 under kgrl's residual recipe, else 1 (the ceiling's search). 2.5 seats "
                         "0.711 of PegInsert Factory 4D's paired episodes with a = 0, against 0.258 at 1 "
                         "(docs/results/search_reach_40)")
    ap.add_argument("--kgrl-recipe", default=None, choices=sorted(KGRL_RECIPES),
                    help=f"{names(takes_recipe=True)}: the defaults under --sac, the reach floors and the seat press: "
                         "reach_keep_prior (the quick preset's but on PegInsert Factory 4D: beats the prior on paired "
                         "episodes, docs/results.md), "
                         "base (the thesis preset's: the thesis's null space; the quick default until issue 28) or "
                         "residual (reach_keep_prior's learner on a fixed controller as a = 0, scaled 0.2, with 4 mm "
                         "floors and the seat pressed 5 mm: --kgrl-base centre_search --kgrl-search-press 2.5 for "
                         "kgrl, centre_latent with --vision-probe-obs --vision-probe-fit closed_loop for vision_kgrl; "
                         "options given win; the quick preset's on PegInsert Factory 4D, docs/results/recipe_40). "
                         "Default: the preset's, or on --resume the run's")
    ap.add_argument("--ppo", metavar="KEY=VALUE", action="append", default=[],
                    help="ppo methods: override an rsl-rl PPO setting by its dotted path, e.g. --ppo "
                         "num_steps_per_env=32 --ppo algorithm.learning_rate=3e-4 (default: Isaac Lab Factory's, "
                         "agents/ppo_config.py; kgrl_ppo starts at actor.distribution_cfg.init_std=0.1)")
    add_device_option(ap)
    add_cpu_matmul_option(ap, "the SAC methods' CPU matmul library: auto (the default: the faster one on this machine, "
                              "timed once on the run's network shapes and kept in --cache-dir), onednn or torch (MKL). "
                              "The one that ran is recorded in config.json, metrics.json and the checkpoint; a resumed "
                              "run keeps its own")
    ap.add_argument("--geometry", default="primitives", choices=GEOMETRIES,
                    help="GearMesh/NutThread collision geometry (mesh: tooth/thread meshes with SDFs on CUDA; "
                         "the scripted demonstrations are recorded on it too)")
    ap.add_argument("--run-dir", type=Path, default=None,
                    help="default runs/train/<task>_<method>_<env>_<D>d_seed<S>_<date-time>")
    ap.add_argument("--resume", action="store_true", help="continue the run in --run-dir from its last checkpoint")
    ap.add_argument("--no-time-obs", action="store_true",
                    help="drop normalized time from the policy input (thesis A.1; the KMP still uses it)")
    ap.add_argument("--checkpoint-every", type=positive_int, default=None, help="transitions between checkpoints")
    ap.add_argument("--keep-at", type=positive_int, nargs="+", default=None, metavar="N",
                    help="keep the policy as it is at N transitions (each N <= --total-steps; the first step at or "
                         "past N) in checkpoints/at_<N>.pt, without the replay buffer: points of a learning curve that "
                         "train/evaluate.py --checkpoint evaluates on the run's own evaluation episodes. Training is "
                         "unchanged")
    ap.add_argument("--eval-episodes", type=int, default=None,
                    help="final deterministic evaluation: episodes per world, all worlds at once (0: none; default: "
                         f"enough for >= {EVAL_MIN_EPISODES} episodes, a success rate's standard error <= 0.045); "
                         "KGRL methods evaluate their prior (a = 0) on the same episodes")
    add_eval_seed_option(ap, EVAL_SEED)
    ap.add_argument("--demos", type=Path, default=None, help="KGRL: your own demonstrations (npz)")
    ap.add_argument("--num-demos", type=int, default=16, help="KGRL: scripted demonstrations to record")
    add_kmp_reference_option(ap, None)
    ap.add_argument("--kgrl-reach-floor", type=float, default=None, metavar="MM",
                    help="KGRL: a saturated action moves the x and y command at least MM mm at every step (default: "
                         "the recipe's, reach_keep_prior 3, base 0: the thesis's null space, ~1 mm late in PegInsert; "
                         "a deviation, see kmp.tables.with_reach_floor and docs/log/benchmarks.md)")
    ap.add_argument("--kgrl-reach-floor-z", type=float, default=None, metavar="MM",
                    help="KGRL: likewise for z (default: the recipe's, reach_keep_prior 25, base 0: the thesis's, ~2 mm "
                         "late in PegInsert, while the prior presses a blocked peg ~20 mm into the face; a "
                         "deviation, see docs/log/benchmarks.md)")
    ap.add_argument("--kgrl-seat-press", type=float, default=None, metavar="MM",
                    help="KGRL: lower the prior's z MM mm from where it reaches its seat (ramped over 10 steps), so "
                         "that a = 0 presses the part home (default 0: the thesis's prior, fitted to the measured "
                         "seated pose, does not press; a deviation, see kmp.tables.with_seat_press and "
                         "docs/results/ceiling_40)")
    ap.add_argument("--vae", type=Path, default=None,
                    help="vision methods: your own trained vae.pt (train/train_vae.py) instead of the cached one")
    add_cache_dir_option(ap)
    ap.add_argument("--label", default=None,
                    help="a name for the run's variant (e.g. the options it tries), recorded in config.json and "
                         "metrics.json; train/report.py shows runs of another label as another row")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--overlap", action=argparse.BooleanOptionalAction, default=None,
                    help="step the env in a worker thread while the SAC update of the previous transitions runs "
                         "(a one-update policy lag; default: on for a CPU device, off on CUDA, not yet measured there)")
    add_eager_physics_flag(ap)
    add_verbose_flag(ap)
    return ap


def add_cpu_matmul_option(parser, help: str) -> None:
    """--cpu-matmul {auto,onednn,torch} (agents/matmul_backend.py), None when not given."""
    parser.add_argument("--cpu-matmul", default=None, choices=CPU_MATMUL_CHOICES, help=help)


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


def explicit_args(parser: argparse.ArgumentParser, argv) -> set[str]:
    """The options given on the command line (not defaults)."""
    for action in parser._actions:
        action.default = None
    ns = parser.parse_args(argv)
    return {k for k, v in vars(ns).items() if v is not None and v is not False and v != []}  # (0 is given)


def kgrl_recipe(ns, preset: str) -> dict:
    """The run's KGRL_RECIPES entry: --kgrl-recipe, else the preset's (the base recipe's zero floors and no
    SAC fields for the methods without one)."""
    if not METHODS[ns.method].takes_recipe:
        return NO_RECIPE
    return KGRL_RECIPES[ns.kgrl_recipe or default_kgrl_recipe(preset, ns.task, ns.env, ns.action_dim)]


def sac_config_for(ns, preset: str) -> SACConfig:
    """The preset's SACConfig under the recipe's fields and --sac's (ValueError names a bad one)."""
    return make_sac_config(preset, **{**kgrl_recipe(ns, preset)["sac"], **ns.sac_overrides})


def search_without_z_reach(ns, sac_config, preset: str) -> str | None:
    """The refusal of prior_rollouts_policy=search where the run's z reach floor (given, else the recipe's
    of `preset`) is 0; None otherwise. A resumed run keeps the floors its checkpoint records."""
    reach_z = ns.kgrl_reach_floor_z if ns.kgrl_reach_floor_z is not None else kgrl_recipe(ns, preset)["reach_floor_z_mm"]
    if getattr(sac_config, "prior_rollouts_policy", "prior") == "search" and METHODS[ns.method].uses_kmp \
            and not ns.resume and not reach_z:
        return ("--sac prior_rollouts_policy=search lightens the prior's ~20 mm press on a blocked part: it needs "
                "z reach, give --kgrl-reach-floor-z MM (e.g. 25; the thesis's null space reaches ~2 mm there)")
    return None


def prior_table_flags(ns) -> tuple:
    """(prior-record key, flag, value given or None) of what a run changes of its prior's tables: the two
    reach floors and the seat press (mm each)."""
    return (("reach_floor_mm", "--kgrl-reach-floor", ns.kgrl_reach_floor),
            ("reach_floor_z_mm", "--kgrl-reach-floor-z", ns.kgrl_reach_floor_z),
            ("seat_press_mm", "--kgrl-seat-press", ns.kgrl_seat_press))


def unavailable(ns) -> str | None:
    """Why this combination cannot run yet, or None."""
    from ..envs.assembly_env import TASK_GEOMETRY

    if ns.task not in TASK_GEOMETRY:
        return f"task {ns.task!r} is not simulated yet; available tasks: {sorted(TASK_GEOMETRY)}"
    return None


def default_run_dir(ns) -> Path:
    return Path("runs/train") / (f"{ns.task}_{ns.method}_{ns.env}_{ns.action_dim}d_"
                                 f"seed{ns.seed}_{time.strftime('%Y%m%d-%H%M%S')}")


def check_scalars(ns) -> None:
    """The option values that are wrong whatever the method (ConfigError)."""
    if ns.eval_episodes is not None and ns.eval_episodes < 0:
        raise ConfigError(f"--eval-episodes {ns.eval_episodes}: must be >= 0 (episodes per world; 0: no final "
                          "evaluation)")
    if ns.label is not None and not re.fullmatch(r"[A-Za-z0-9_.-]{1,40}", ns.label):
        raise ConfigError(f"--label {ns.label!r}: 1-40 characters of letters, digits, '_', '.', '-'")
    if why := seed_error("--eval-seed", ns.eval_seed, EVAL_SEED_BITS):
        raise ConfigError(why)
    if ns.num_demos < 2:
        raise ConfigError(f"--num-demos {ns.num_demos}: must be >= 2")
    if why := seed_error("--seed", ns.seed):
        raise ConfigError(why)
    for flag, value, top in (("--kgrl-reach-floor", ns.kgrl_reach_floor, 50),
                             ("--kgrl-reach-floor-z", ns.kgrl_reach_floor_z, 50),
                             ("--kgrl-seat-press", ns.kgrl_seat_press, SEAT_PRESS_MAX_MM)):
        if value is not None and METHODS[ns.method].uses_kmp and not (math.isfinite(value) and 0 <= value <= top):
            raise ConfigError(f"{flag} must be a number of mm in [0, {top:g}], got {value}")
