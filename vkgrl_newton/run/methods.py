"""The one table of learning methods: each row says how a method learns and acts.

A method is a learner (`sac`: this project's SAC, agents/sac.py; `ppo`: rsl-rl's PPO, agents/ppo.py),
an action path (`delta`: Factory's delta-pose mapping, `env.step`; `kmp`: the KMP prior's null
space, thesis eq. 4.36, envs/kgrl_action.py) and the observation parts (proprioception, plus for a
vision method the frozen VAE latent of the task camera, eq. 5.6). Everything else derives from the
row: which options apply (`--kgrl-recipe`, `--demos`, `--vae`, `--sac`, `--ppo`, ...), the refusal
texts that name the methods an option is for, the builder's choices and docs/cli.md's lists.

Adding a method is one row here (plus its learner in agents/ if it is a new one). Plain data: no
torch, importable by a command line before it parses its arguments.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["Method", "METHODS", "THESIS_METHODS", "RUN_METHODS", "get_method", "methods_where", "names", "OPTION_RULES",
           "methods_markdown"]


@dataclass(frozen=True)
class Method:
    name: str
    learner: str  # "sac" | "ppo"
    action_path: str  # "delta" (Factory's delta pose, env.step) | "kmp" (the prior's null space, step_pose)
    vision: bool  # the policy observation adds the frozen VAE's latent (eq. 5.6)
    thesis: bool  # one of the thesis's four methods (Table 6.x)
    summary: str

    def __post_init__(self) -> None:
        if self.learner not in ("sac", "ppo"):
            raise ValueError(f"Method {self.name!r}: learner {self.learner!r} must be 'sac' or 'ppo'")
        if self.action_path not in ("delta", "kmp"):
            raise ValueError(f"Method {self.name!r}: action_path {self.action_path!r} must be 'delta' or 'kmp'")

    @property
    def uses_kmp(self) -> bool:
        """Acts through the KMP prior (its demonstrations, tables, reach floors, prior evaluation)."""
        return self.action_path == "kmp"

    @property
    def uses_ppo(self) -> bool:
        return self.learner == "ppo"

    @property
    def uses_sac(self) -> bool:
        return self.learner == "sac"

    @property
    def takes_recipe(self) -> bool:
        """SAC on the KMP's null space: the KGRL recipes (run.presets.KGRL_RECIPES) apply."""
        return self.uses_sac and self.uses_kmp


_ROWS = (
    Method("sac", "sac", "delta", False, True, "SAC on Factory's delta-pose actions (thesis 5.3)"),
    Method("kgrl", "sac", "kmp", False, True, "SAC in the null space of the KMP prior (thesis eq. 4.36)"),
    Method("vision_sac", "sac", "delta", True, True, "SAC with the frozen VAE latent of the task camera"),
    Method("vision_kgrl", "sac", "kmp", True, True, "KGRL with the frozen VAE latent (the thesis's method)"),
    Method("ppo", "ppo", "delta", False, False, "rsl-rl's PPO with Isaac Lab Factory's settings (a baseline)"),
    Method("kgrl_ppo", "ppo", "kmp", False, False, "rsl-rl's PPO in the KMP prior's null space (a baseline)"),
    Method("vision_ppo", "ppo", "delta", True, False, "rsl-rl's PPO with the frozen VAE latent (a baseline)"),
)
METHODS: dict[str, Method] = {m.name: m for m in _ROWS}
RUN_METHODS = tuple(METHODS)  # train/run.py --method's choices, in the table's order
THESIS_METHODS = tuple(m.name for m in _ROWS if m.thesis)


def get_method(name: str) -> Method:
    if name not in METHODS:
        raise ValueError(f"method {name!r} is not known; methods: {list(METHODS)}")
    return METHODS[name]


def methods_where(**what) -> tuple[str, ...]:
    """The names of the rows whose attributes (or properties) equal `what`, e.g. methods_where(uses_kmp=True)."""
    return tuple(m.name for m in _ROWS if all(getattr(m, k) == v for k, v in what.items()))


def names(**what) -> str:
    """methods_where(...) as the refusal texts write it: "kgrl, vision_kgrl, kgrl_ppo"."""
    return ", ".join(methods_where(**what))


# which train/run.py options apply to a method, by the row's properties (the refusals in run/resolve.py
# check the same properties); docs/cli.md's table of methods is methods_markdown()'s output
OPTION_RULES = (
    ("--sac, --overlap, --no-time-obs, --cpu-matmul, --privileged-critic, --obs-history", "uses_sac"),
    ("--ppo", "uses_ppo"),
    ("--kgrl-recipe, --kgrl-time-action, --kgrl-base, --kgrl-residual-scale, --kgrl-search-speed, --kgrl-search-press",
     "takes_recipe"),
    ("--demos, --num-demos, --kmp-reference, --kgrl-reach-floor[-z], --kgrl-seat-press", "uses_kmp"),
    ("--vae, --vision-probe-obs, --vision-probe-fit", "vision"),
)


def methods_markdown() -> str:
    """The method table as docs/cli.md shows it (a test holds the two equal)."""
    head = "| method | learner | action path | vision latent | options that apply beyond the common ones |"
    rows = [head, "|---|---|---|---|---|"]
    for m in _ROWS:
        opts = "; ".join(f"`{o}`" for o, prop in OPTION_RULES if getattr(m, prop))
        path = "KMP null space (`step_pose`)" if m.uses_kmp else "delta pose (`step`)"
        rows.append(f"| `{m.name}` | {m.learner} | {path} | {'yes' if m.vision else 'no'} | {opts} |")
    return "\n".join(rows) + "\n"
