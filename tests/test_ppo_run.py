"""rsl-rl's PPO as a method of train/run.py (issue 29): its configuration, a stop in mid-rollout
against an uninterrupted run of the same seed, resume, kgrl_ppo starting at the prior with its
paired evaluation, evaluate.py on a PPO checkpoint, report.py's rows, and the refusals.

The runs use 2 worlds, 4 steps per world per PPO iteration (8 transitions) and [16, 16] networks,
so that they take seconds; kgrl_ppo uses synthetic demonstrations (nothing recorded)."""

from __future__ import annotations

import json
import math

import pytest
import torch
from scripts import load_script

from vkgrl_newton.agents.ppo_config import FACTORY_PPO, METHOD_PPO_DEFAULTS, parse_ppo_overrides, ppo_train_cfg

pytestmark = pytest.mark.usefixtures("torch_one_thread")

TINY_PPO = ["--num-envs", "2", "--device", "cpu", "--no-progress", "--ppo", "num_steps_per_env=4",
            "--ppo", "actor.hidden_dims=[16, 16]", "--ppo", "critic.hidden_dims=[16, 16]"]
PER_ITERATION = 2 * 4  # transitions per PPO iteration (worlds x num_steps_per_env)


@pytest.fixture(scope="module")
def run_py():
    return load_script("run")


@pytest.fixture(scope="module")
def demos_file(tmp_path_factory):
    from vkgrl_newton.kmp.demos import synthetic_demos

    return synthetic_demos("PegInsert", 8, action_dim=6, seed=1).save(tmp_path_factory.mktemp("demos") / "d.npz")


def test_ppo_configuration_overrides_by_dotted_path_and_refuses_the_unknown():
    cfg = ppo_train_cfg("PegInsert", "factory", 16, **parse_ppo_overrides(
        ["algorithm.learning_rate=3e-4", "actor.distribution_cfg.init_std=0.5", "num_steps_per_env=64",
         "actor.hidden_dims=[32, 32]", "algorithm.schedule=fixed"]))
    assert cfg["algorithm"]["learning_rate"] == 3e-4 and cfg["actor"]["distribution_cfg"]["init_std"] == 0.5
    assert cfg["actor"]["hidden_dims"] == [32, 32] and cfg["algorithm"]["schedule"] == "fixed"
    assert cfg["algorithm"]["num_mini_batches"] == 16 * 64 // 512  # minibatches of 512 transitions
    assert FACTORY_PPO["algorithm"]["learning_rate"] == 1e-4  # the template is untouched
    assert ppo_train_cfg("PegInsert", "factory", 2)["algorithm"]["num_mini_batches"] == 1  # at least one
    kgrl = ppo_train_cfg("PegInsert", "factory", 2, **METHOD_PPO_DEFAULTS["kgrl_ppo"])
    assert kgrl["start_at_prior"] is True and kgrl["actor"]["distribution_cfg"]["init_std"] == 0.1
    for items, message in ((["algorithm.gama=0.9"], "PPO setting 'algorithm.gama' unknown; allowed: "),
                           (["actor=1"], "PPO setting 'actor' unknown"),
                           (["algorithm.learning_rate=fast"], "'fast' is not a float"),
                           (["algorithm.num_learning_epochs=2.5"], "2.5 is not a int"),
                           (["check_for_nan=1"], "1 is not a bool"),
                           (["num_steps_per_env=0"], "must be an integer >= 1")):
        with pytest.raises(ValueError, match=message):
            ppo_train_cfg("PegInsert", "factory", 2, **parse_ppo_overrides(items))
    with pytest.raises(ValueError, match="expected KEY=VALUE"):
        parse_ppo_overrides(["learning_rate"])


@pytest.mark.parametrize("argv, message", [
    (["--method", "ppo", "--sac", "lr=1"], "--sac is for the SAC methods"),
    (["--method", "ppo", "--no-time-obs"], "--no-time-obs is for the SAC methods"),
    (["--method", "kgrl_ppo", "--overlap"], "--overlap is for the SAC methods"),
    (["--method", "sac", "--ppo", "num_steps_per_env=8"], "--ppo is for the ppo methods (ppo, kgrl_ppo, vision_ppo), not 'sac'"),
    (["--method", "ppo", "--ppo", "algorithm.gama=1"], "--ppo: PPO setting 'algorithm.gama' unknown"),
    (["--method", "ppo", "--kgrl-reach-floor", "3"], "--kgrl-reach-floor is for the kgrl methods"),
    (["--method", "ppo", "--ppo", "save_interval=5"], "save_interval is for rsl-rl's OnPolicyRunner"),
    (["--method", "ppo", "--ppo", "multi_gpu=1"], "multi_gpu is for rsl-rl's OnPolicyRunner"),
])
def test_run_ppo_bad_flags_are_one_line_errors(run_py, argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        run_py.main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert message in err


@pytest.mark.slow
def test_run_ppo_stop_in_mid_rollout_keeps_the_last_update_and_resumes(run_py, wp_cpu, tmp_path, monkeypatch,
                                                                         capsys):
    from vkgrl_newton.agents.checkpoint import load_checkpoint
    from vkgrl_newton.envs.assembly_env import AssemblyEnv

    def run(name, *extra):
        return run_py.main(["--method", "ppo", "--run-dir", str(tmp_path / name), "--eval-episodes", "0",
                            "--checkpoint-every", "1000", *TINY_PPO, *extra])

    # the reference: two PPO iterations, uninterrupted
    assert run("straight", "--total-steps", str(2 * PER_ITERATION)) == 0
    straight = load_checkpoint(tmp_path / "straight" / "checkpoints" / "last.pt")
    assert straight["counters"]["transitions"] == 2 * PER_ITERATION and straight["agent"]["iterations"] == 2

    # the same seed stopped on its 11th env step, in the third rollout: the checkpoint is the run at
    # the second update's end, bitwise the reference's (the partial rollout is dropped)
    calls = {"n": 0}
    real_step = AssemblyEnv.step

    def stopping_step(self, actions):
        calls["n"] += 1
        if calls["n"] == 11:
            raise KeyboardInterrupt
        return real_step(self, actions)

    monkeypatch.setattr(AssemblyEnv, "step", stopping_step)
    assert run("stopped", "--total-steps", str(5 * PER_ITERATION)) == 130
    monkeypatch.setattr(AssemblyEnv, "step", real_step)
    ckpt = tmp_path / "stopped" / "checkpoints" / "last.pt"
    stopped = load_checkpoint(ckpt)
    assert stopped["counters"]["transitions"] == 2 * PER_ITERATION and stopped["counters"]["env_steps"] == 8
    assert stopped["agent"]["iterations"] == 2
    for part in ("actor_state_dict", "critic_state_dict"):
        for k, v in straight["agent"][part].items():
            assert torch.equal(v, stopped["agent"][part][k]), (part, k)
    assert stopped["counters"]["wall_s"] > 0
    config = json.loads((tmp_path / "stopped" / "config.json").read_text())
    assert config["method"] == "ppo" and "sac" not in config and config["ppo"]["actor"]["hidden_dims"] == [16, 16]
    assert config["ppo"]["algorithm"]["gamma"] == 0.995 and config["ppo"]["start_at_prior"] is False  # Factory's

    # resumed to its plan (5 iterations): counters continue, the networks move
    assert run_py.main(["--run-dir", str(tmp_path / "stopped"), "--resume", "--no-progress"]) == 0
    done = load_checkpoint(ckpt)
    assert done["counters"]["transitions"] == 5 * PER_ITERATION and done["agent"]["iterations"] == 5
    assert any(not torch.equal(v, done["agent"]["actor_state_dict"][k])
               for k, v in stopped["agent"]["actor_state_dict"].items())
    from test_train import read_scalars

    scalars = read_scalars(tmp_path / "stopped" / "tb")
    assert len(scalars["train/value"]) == 5 and all(math.isfinite(v) for v in scalars["train/value"])
    assert "train/action_std" in scalars and "train/learning_rate" in scalars
    metrics = json.loads((tmp_path / "stopped" / "metrics.json").read_text())
    assert metrics["training"]["gradient_steps"] == 5 * 4 * 1  # iterations x epochs x minibatches
    assert metrics["training"]["resumed"] is True and "success_rate" not in metrics  # (no evaluation asked)
    # resuming a ppo run with --sac is refused like any SAC-only option; as a SAC method, by its identity
    for extra, message in ((["--sac", "lr=1"], "--sac is for the SAC methods"),
                           (["--method", "sac"], "method: checkpoint 'ppo', now 'sac'")):
        with pytest.raises(SystemExit) as e:
            run_py.main(["--run-dir", str(tmp_path / "stopped"), "--resume", "--total-steps", "80", *extra])
        assert e.value.code == 2 and message in capsys.readouterr().err.strip().splitlines()[-1]


@pytest.mark.slow
def test_run_kgrl_ppo_starts_at_the_prior_and_reports_the_paired_gain(run_py, wp_cpu, tmp_path, demos_file):
    from vkgrl_newton.agents.checkpoint import load_checkpoint

    run_dir = tmp_path / "kgrl_ppo"
    assert run_py.main(["--method", "kgrl_ppo", "--run-dir", str(run_dir), "--demos", str(demos_file),
                        "--total-steps", str(PER_ITERATION), "--eval-episodes", "1", "--cache-dir",
                        str(tmp_path / "cache"), *TINY_PPO]) == 0
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["method"] == "kgrl_ppo" and metrics["episodes"] == 2 and "ppo" not in metrics
    assert metrics["prior"]["demos"] == str(demos_file)
    gain = metrics["paired_gain"]["success_rate"]
    assert gain["n_pairs"] == 2
    assert gain["mean"] == pytest.approx(metrics["success_rate"] - metrics["prior_eval"]["success_rate"])
    config = json.loads((run_dir / "config.json").read_text())
    assert config["ppo"]["start_at_prior"] is True and config["ppo"]["actor"]["distribution_cfg"]["init_std"] == 0.1

    # the actor's mean starts at ~0 (the prior): the head's weights scaled by 1e-3, its bias 0
    from vkgrl_newton.agents.ppo import PPOAgent
    from vkgrl_newton.envs.assembly_env import AssemblyEnv, EnvConfig

    env = AssemblyEnv(EnvConfig(task="PegInsert", family="factory", action_dim=4, num_envs=2, device="cpu", seed=0))
    fresh = PPOAgent(env, config["ppo"])
    x = torch.randn(64, config["obs_dim"])
    assert fresh.act(x).abs().max() < 1e-2
    trained = PPOAgent(env, config["ppo"])
    trained.load_state_dict(load_checkpoint(run_dir / "checkpoints" / "last.pt")["agent"])
    assert trained.iterations == 1 and not torch.equal(trained.act(x), fresh.act(x))  # it learned, and loads
    default = PPOAgent(env, ppo_train_cfg("PegInsert", "factory", 2, **{"actor.hidden_dims": [16, 16]}))
    assert default.act(x).abs().max() > 1e-2  # Factory's start: an ordinary initialisation

    # evaluate.py reads a PPO checkpoint like a SAC one
    evaluate_py = load_script("evaluate")
    out = tmp_path / "eval.json"
    assert evaluate_py.main(["--checkpoint", str(run_dir / "checkpoints" / "last.pt"), "--num-envs", "2",
                             "--episodes", "1", "--json", str(out), "--cache-dir", str(tmp_path / "cache")]) == 0
    result = json.loads(out.read_text())
    assert result["policy"] == "kgrl_ppo" and result["episodes"] == 2

    # report.py: the PPO rows after the thesis's methods, with no thesis value beside them
    report_py = load_script("report")
    assert report_py.main([str(run_dir), "--out", str(tmp_path / "report"), "--reps", "100"]) == 0
    success = (tmp_path / "report" / "tables.md").read_text().split("## Table 6.2")[1].split("## Table")[0]
    row = next(ln for ln in success.splitlines() if ln.startswith("| PegInsert | kgrl_ppo"))
    assert f"{metrics['success_rate']:.3f} ± 0.000** (n=1) [—; —]" in row.split(" | ")[2]  # no thesis value
    assert "| PegInsert | factory | 4 | kgrl_ppo | 1 |" in (tmp_path / "report" / "prior_gain.md").read_text()
