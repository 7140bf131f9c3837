"""Load a script of train/ as a module (they are files run from a checkout, not a package)."""

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# train/run.py's smallest SAC run: 2 worlds, tiny networks, updates from the 8th transition
TINY_RUN = ["--num-envs", "2", "--device", "cpu", "--no-progress", "--sac", "learning_starts=8", "--sac", "batch_size=8",
            "--sac", "gradient_steps=2", "--sac", "hidden_dims=16,16", "--sac", "buffer_size=1000"]


def load_script(name: str):
    """train/<name>.py as a fresh module object."""
    spec = importlib.util.spec_from_file_location(f"train_{name}", ROOT / "train" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def on_the_prior(argv: list[str]) -> list[str]:
    """run.py arguments with `--kgrl-recipe reach_keep_prior` added for a kgrl or vision_kgrl run that names no
    recipe: the tests of options on the KMP prior's null space (a = 0 the prior) keep it, where the quick preset's
    default on PegInsert Factory 4D is the residual recipe (a base controller as a = 0; run.presets.QUICK_KGRL_RECIPE)."""
    method = argv[argv.index("--method") + 1] if "--method" in argv else "kgrl"  # (run.py's default method)
    if method in ("kgrl", "vision_kgrl") and "--kgrl-recipe" not in argv and "--resume" not in argv:
        return [*argv, "--kgrl-recipe", "reach_keep_prior"]
    return list(argv)
