"""The run library (vkgrl_newton/run): the method table and what derives from it, RunConfig through a
checkpoint, the gymnasium ids built as train/run.py builds, and a short run of every method row."""

import json
import math
import re
from pathlib import Path

import gymnasium as gym
import pytest
import torch
from scripts import ROOT, load_script, on_the_prior

from vkgrl_newton.registration import env_ids
from vkgrl_newton.run.config import ConfigError, RunConfig, build_parser
from vkgrl_newton.run.methods import METHODS, RUN_METHODS, methods_markdown, methods_where
from vkgrl_newton.run.resolve import Resolved, resolve

TINY_SAC = ["--num-envs", "2", "--device", "cpu", "--no-progress", "--sac", "learning_starts=8", "--sac",
            "batch_size=8", "--sac", "gradient_steps=2", "--sac", "hidden_dims=16,16", "--sac", "buffer_size=1000"]
TINY_PPO = ["--num-envs", "2", "--device", "cpu", "--no-progress", "--ppo", "num_steps_per_env=4",
            "--ppo", "actor.hidden_dims=[16, 16]", "--ppo", "critic.hidden_dims=[16, 16]"]


@pytest.fixture(scope="module")
def demos_file(tmp_path_factory):
    from vkgrl_newton.kmp.demos import synthetic_demos

    return synthetic_demos("PegInsert", 8, action_dim=6, seed=1).save(tmp_path_factory.mktemp("demos") / "d.npz")


@pytest.fixture(scope="module")
def vae_file(tmp_path_factory):
    from vkgrl_newton.vision import DenoisingVAE, VAEConfig, save_vae

    cfg = VAEConfig(resolution=32, channels=(8, 8, 8, 8, 8))
    return save_vae(tmp_path_factory.mktemp("vae") / "vae.pt", DenoisingVAE(cfg, torch.Generator().manual_seed(0)),
                    cfg, meta={"task": "PegInsert"})


def test_every_row_is_consistent_and_the_docs_table_is_the_tables():
    assert RUN_METHODS == tuple(METHODS) and len(set(RUN_METHODS)) == len(RUN_METHODS)
    for m in METHODS.values():
        assert m.takes_recipe == (m.learner == "sac" and m.action_path == "kmp")
        assert m.name.startswith("vision_") == m.vision  # the naming the reports and sweeps rely on
        assert ("kgrl" in m.name) == m.uses_kmp
    assert methods_where(uses_kmp=True) == ("kgrl", "vision_kgrl", "kgrl_ppo")
    doc = (ROOT / "docs" / "cli.md").read_text()
    block = re.search(r"<!-- methods:begin -->\n(.*?)<!-- methods:end -->", doc, re.S)
    assert block and block.group(1) == methods_markdown(), "docs/cli.md's table of methods is not methods_markdown()"
    with pytest.raises(ValueError, match="learner 'dqn'"):
        type(METHODS["sac"])("x", "dqn", "delta", False, False, "")


@pytest.mark.parametrize("argv, message", [
    (["--method", "sac", "--vae", "v.pt"], "--vae is for the vision methods (vision_sac, vision_kgrl, vision_ppo)"),
    (["--method", "vision_ppo", "--sac", "batch_size=8"], "--sac is for the SAC methods (sac, kgrl, vision_sac, "
                                                           "vision_kgrl)"),
    (["--method", "vision_ppo", "--demos", "d.npz"], "--demos is for the kgrl methods (kgrl, vision_kgrl, kgrl_ppo)"),
    (["--method", "kgrl_ppo", "--kgrl-recipe", "base"], "--kgrl-recipe is for the kgrl methods on SAC (kgrl, "
                                                         "vision_kgrl)"),
    (["--method", "vision_sac", "--ppo", "num_steps_per_env=4"], "--ppo is for the ppo methods (ppo, kgrl_ppo, "
                                                                 "vision_ppo)"),
])
def test_the_refusals_name_the_methods_of_the_table(argv, message):
    """Resolved without starting anything heavy: the refusal is a ConfigError whose text lists the rows."""
    with pytest.raises(ConfigError) as e:
        resolve(build_parser(), argv)
    assert message in str(e.value) and "\n" not in str(e.value)


_ENV_FIELDS = ("task", "method", "env", "action_dim", "seed", "num_envs", "preset", "geometry", "kgrl_recipe",
               "demos", "num_demos", "kmp_reference", "kmp_params", "reach_floor_mm", "reach_floor_z_mm", "seat_press_mm", "vae",
               "device", "cache_dir", "latent_dim", "obs_dim")


def test_every_gym_id_is_the_env_of_its_run_py_method(wp_cpu, tmp_path):
    """For each of the 48 ids: the RunConfig the id builds from equals train/run.py's of the same method,
    task, family and action space on the env's fields (the recipe's reach floors included)."""
    from vkgrl_newton.run.gym import gym_config

    assert len(env_ids()) == 48
    for name, kw in env_ids().items():
        assert gym.spec(name).kwargs == kw and kw["method"] in METHODS
        ours = gym_config(**kw, num_envs=16, device="cpu", cache_dir=tmp_path)
        resolved = resolve(build_parser(), ["--task", kw["task"], "--method", kw["method"], "--env", kw["family"],
                                            "--action-dim", str(kw["action_dim"]), "--num-envs", "16", "--device",
                                            "cpu", "--cache-dir", str(tmp_path), "--run-dir", str(tmp_path / "r")])
        assert isinstance(resolved, Resolved)
        run = resolved.config
        for f in _ENV_FIELDS:
            assert getattr(ours, f) == getattr(run, f), (name, f, getattr(ours, f), getattr(run, f))
        if METHODS[kw["method"]].takes_recipe:  # on a CPU: the quick preset's recipe, its floors in mm
            measured = (kw["task"], kw["family"], kw["action_dim"]) == ("PegInsert", "factory", 4)
            assert (ours.kgrl_recipe, ours.reach_floor_mm, ours.reach_floor_z_mm, ours.kgrl_base != "prior") == \
                (("residual", 4.0, 25.0, True) if measured else ("reach_keep_prior", 3.0, 25.0, False)), name
    base = gym_config("PegInsert", "factory", 4, "kgrl", device="cpu", kgrl_recipe="base")
    assert (base.reach_floor_mm, base.reach_floor_z_mm) == (0.0, 0.0)  # the thesis's null space, on request
    with pytest.raises(ValueError, match="kgrl_recipe='fast' is not allowed"):
        gym_config("PegInsert", "factory", 4, "kgrl", device="cpu", kgrl_recipe="fast")
    with pytest.raises(ValueError, match="kgrl_recipe='base' is not allowed"):
        gym_config("PegInsert", "factory", 4, "sac", device="cpu", kgrl_recipe="base")


def test_a_configuration_round_trips_through_its_checkpoint(wp_cpu, tmp_path, demos_file):
    """resolve() of a new run and resolve() of its --resume give the same RunConfig but for resume
    itself and what the resume asks anew (--total-steps); the checkpoint's kmp parameters are the run's."""
    run_py = load_script("run")
    run_dir = tmp_path / "kgrl"
    argv = ["--method", "kgrl", "--demos", str(demos_file), "--run-dir", str(run_dir), "--total-steps", "16",
            "--eval-episodes", "0", "--seed", "5", "--label", "rt", "--sac", "prior_rollouts=8", *TINY_SAC]
    fresh = resolve(build_parser(), argv).config
    assert run_py.main(argv) == 0
    again = resolve(build_parser(), ["--run-dir", str(run_dir), "--resume", "--total-steps", "32"])
    assert isinstance(again, Resolved)
    from vkgrl_newton.kmp.prior import KMP_BETA, KMP_L, KMP_LAMBDA

    back = again.config
    assert back.kmp_params == {"lam": KMP_LAMBDA, "beta": KMP_BETA, "l": KMP_L}  # recorded, read back
    assert back.resume and back.total_steps == 32
    import dataclasses

    assert dataclasses.replace(back, resume=False, total_steps=16, kmp_params=None, progress=True,
                               device="cpu") == dataclasses.replace(fresh, progress=True)
    assert json.loads((run_dir / "config.json").read_text())["label"] == "rt"


@pytest.mark.slow
@pytest.mark.parametrize("method", RUN_METHODS)
def test_every_method_row_trains_briefly_and_evaluates(method, wp_cpu, tmp_path, demos_file, vae_file):
    """Each row of the table through train/run.py: a few transitions, the final evaluation, metrics.json;
    the kmp rows also evaluate their prior on the same episodes, the vision rows read the latent."""
    m = METHODS[method]
    run_py = load_script("run")
    run_dir = tmp_path / method
    argv = ["--method", method, "--run-dir", str(run_dir), "--eval-episodes", "1", "--cache-dir", str(tmp_path / "c")]
    argv += ["--total-steps", "16", *TINY_SAC] if m.uses_sac else ["--total-steps", "16", *TINY_PPO]
    argv += ["--demos", str(demos_file)] if m.uses_kmp else []
    argv += ["--vae", str(vae_file)] if m.vision else []
    argv = on_the_prior(argv)  # (a given --vae: not with the residual recipe, the quick default here)
    if m.takes_recipe:
        argv += ["--sac", "prior_rollouts=8"]
    assert run_py.main(argv) == 0
    metrics = json.loads((run_dir / "metrics.json").read_text())
    config = json.loads((run_dir / "config.json").read_text())
    assert metrics["method"] == method and metrics["episodes"] == 2 and 0.0 <= metrics["success_rate"] <= 1.0
    assert config["obs_dim"] == 8 + (16 if m.vision else 0)
    assert ("prior_eval" in metrics) == m.uses_kmp and ("vision" in config) == m.vision
    assert ("ppo" in config) == m.uses_ppo and ("sac" in config) == m.uses_sac
    assert metrics["training"]["transitions"] >= 16 and math.isfinite(metrics["mean_contact_force"])
    evaluate_py = load_script("evaluate")
    out = tmp_path / f"{method}.json"
    assert evaluate_py.main(["--checkpoint", str(run_dir / "checkpoints" / "last.pt"), "--num-envs", "2",
                             "--episodes", "1", "--device", "cpu", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["policy"] == method


def test_the_library_public_names_load_lazily():
    """`import vkgrl_newton.run` costs no torch: a command line imports it before parsing."""
    import subprocess
    import sys

    code = ("import sys, vkgrl_newton.run, vkgrl_newton.run.config, vkgrl_newton.run.methods, "
            "vkgrl_newton.run.resolve; print('torch' in sys.modules, 'warp' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["False", "False"]
    assert Path(ROOT / "train" / "run.py").read_text().count("\n") <= 150
    assert Path(ROOT / "train" / "evaluate.py").read_text().count("\n") <= 150
