"""--kgrl-base: a = 0 of a KGRL policy stands for a controller of the ceiling, the policy's actions added to its own
(envs.kgrl_action.KGRLActionPath.set_base, envs.evaluation.base_controller), and the run options around it."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch


def fake_env(num_envs: int, seed: int = 0):
    """test_ceiling's fake env with what the base reads besides (the TCP, the vision slot) and step_pose recording
    its command."""
    from test_ceiling import fake_env as ceiling_env

    env = ceiling_env(num_envs, seed)
    env.sent, env.cfg, env.vision_source = [], SimpleNamespace(vision_latent_dim=0), None
    g = torch.Generator().manual_seed(seed + 1)
    env.tcp_p = env.target_frame_pos_w + 1e-3 * torch.randn(num_envs, 3, generator=g)

    def privileged():
        raise AssertionError("the base controller read a privileged pose")

    env.held_pose = privileged
    env.tcp_pose = lambda: (env.tcp_p, torch.zeros(num_envs, 4))
    env.step_pose = lambda pos, quat: env.sent.append((pos.clone(), quat.clone())) or "stepped"
    return env


def prior_tables():
    from vkgrl_newton.kmp.demos import synthetic_demos
    from vkgrl_newton.kmp.prior import fit_prior

    return fit_prior(synthetic_demos("PegInsert", 6, action_dim=6, seed=0), action_dim=4)


class ConstantBase:
    """A base controller that asks for fixed actions and keeps what it was given."""

    def __init__(self, b: torch.Tensor):
        self.b, self.inputs = b, []

    def actions(self, env, inputs):
        self.inputs.append(inputs.clone())
        return self.b


def test_the_policy_acts_on_top_of_the_base_and_a_zero_action_is_the_base(wp_cpu):
    """step(a) commands the pose of clip(a + b) (the plain path's pose of those actions, float64 clip), the base is
    called once a step with the TCP relative to the observed target (what a policy observes), and a = 0 is b."""
    from vkgrl_newton.envs.kgrl_action import KGRLActionPath

    tables = prior_tables()
    env = fake_env(3)
    b = torch.tensor([[0.5, -0.25, 0.0, 0.1], [0.9, 0.9, -0.9, 0.0], [0.0, 0.0, 0.0, 0.0]])
    base = ConstantBase(b)
    path = KGRLActionPath(tables, env)
    path.set_base(base)
    plain = KGRLActionPath(tables, env)
    a = torch.tensor([[0.25, 0.5, -0.75, 0.0], [0.3, -0.2, -0.4, 1.0], [-0.1, 0.2, 0.3, -0.4]])
    want_a = np.clip(a.double().numpy() + b.double().numpy(), -1.0, 1.0)  # 0.9 + 0.3 and -0.9 - 0.4 saturate
    assert want_a[1, 0] == 1.0 and want_a[1, 2] == -1.0
    for n, actions, expect in ((0, a, want_a), (7, a, want_a), (8, torch.zeros_like(a), b.double().numpy())):
        env.step_index.fill_(n)
        env.episode_length_buf.fill_(n)
        assert path.step(actions) == "stepped"
        pos, quat = (t.clone() for t in plain.pose(torch.from_numpy(expect).float()))
        torch.testing.assert_close(env.sent[-1][0], pos, rtol=0, atol=0)
        torch.testing.assert_close(env.sent[-1][1], quat, rtol=0, atol=0)
    assert len(base.inputs) == 3  # once a control step
    want_rel = (env.tcp_p - env.target_frame_pos_w).numpy()
    for x in base.inputs:
        np.testing.assert_array_equal(x[:, 1:4].numpy(), want_rel)
    # with a residual scale the policy's actions are scaled before they are added
    path.set_base(base, residual_scale=0.2)
    env.step_index.fill_(9)
    path.step(a)
    want_s = np.clip(0.2 * a.double().numpy() + b.double().numpy(), -1.0, 1.0)
    want_pos = plain.pose(torch.from_numpy(want_s).float())[0].clone()
    # The two poses differ only by the float32 rounding of 0.2 a + b (two roundings, each <= 2^-24 relative, of terms
    # <= 0.2 |a| + |b|) carried through zeta = w a and the kernel's eta = m + G zeta, plus one rounding of the result
    d_a = 2.0 ** -23 * (0.2 * a.abs() + b.abs()).double()  # (E, 4) on x, y, z, yaw
    w = path.scale.double()
    G = path.tables.gain.double()[9][:3][:, [0, 1, 2, 5]]  # (3, 4): the rows of x, y, z; the 4D action's columns
    bound = float((G.abs() @ (w * d_a).T).max()) + 2.0 ** -24 * float(want_pos.abs().max())
    assert bound < 1e-5  # (a bound far below the 0.06 mm clearance: the check still sees a wrong scale)
    torch.testing.assert_close(env.sent[-1][0], want_pos, rtol=0, atol=bound)
    for bad in (0.0, 1.5, float("nan")):
        with pytest.raises(ValueError, match="residual_scale"):
            path.set_base(base, residual_scale=bad)
    # without a base the actions pass as they are
    path.set_base(None)
    assert path.with_base(a) is a
    path.set_base(base)
    with pytest.raises(ValueError, match="actions must have shape"):
        path.with_base(a[:, :3])


def test_the_base_controllers_are_the_ceilings_with_the_runs_reach(wp_cpu):
    """centre_search and centre_latent are tools/ceiling.py's controllers (issue 28's oracle settings with the task's
    blocked test, the 0.3 mm settle, the 3 mm press) in the run's own action path; prior is none; centre_latent reads
    the last two entries of the env's vision slot (the probe's estimate) and needs the probe."""
    from vkgrl_newton.envs.evaluation import (BASE_CONTROLLERS, ORACLE_PUSH_MM, REST_HEIGHT, KMPCentrePolicy,
                                              base_controller, task_search_params)
    from vkgrl_newton.envs.kgrl_action import KGRLActionPath
    from vkgrl_newton.tools.ceiling import CEILING_GEOMETRY, oracle_params

    for task, geometry in CEILING_GEOMETRY.items():  # one blocked test, two geometry tables
        assert REST_HEIGHT[task] == geometry.rest_height
        assert task_search_params(task) == replace(oracle_params(task), settle_mm=0.3)
    assert task_search_params("PegInsert").blocked_mm == 15.0  # issue 28's, 0.6 of the 25 mm hole
    assert BASE_CONTROLLERS == ("prior", "centre_search", "centre_latent")
    env = fake_env(2)
    path = KGRLActionPath(prior_tables(), env, reach_floor=3e-3, reach_floor_z=25e-3)
    assert base_controller("prior", path, "PegInsert") is None
    search = base_controller("centre_search", path, "PegInsert")
    assert isinstance(search, KMPCentrePolicy) and search.spiral and search.lateral_estimate is None
    assert search.path is path and search.params == task_search_params("PegInsert") and search.push_mm == ORACLE_PUSH_MM
    with pytest.raises(ValueError, match="allowed: prior, centre_search, centre_latent"):
        base_controller("oracle", path, "PegInsert")
    with pytest.raises(ValueError, match="--vision-probe-obs"):
        base_controller("centre_latent", path, "PegInsert")
    # an env whose vision slot carries the probe's estimate: 16 latent entries + world x, y
    latent = torch.randn(2, 18, generator=torch.Generator().manual_seed(1))
    env.cfg.vision_latent_dim = 18
    env.vision_source = SimpleNamespace(probe=object())
    reads = []
    env.current_vision_latent = lambda: reads.append(1) or latent
    camera = base_controller("centre_latent", path, "PegInsert")
    assert not camera.spiral and camera.params == task_search_params("PegInsert")
    np.testing.assert_array_equal(camera.lateral_estimate(env).numpy(), latent[:, 16:].numpy())
    assert reads == [1]
    env.vision_source = SimpleNamespace(probe=None)  # the camera without the probe
    with pytest.raises(ValueError, match="--vision-probe-obs"):
        base_controller("centre_latent", path, "PegInsert")


def test_the_base_steers_once_blocked_and_the_policy_adds_to_it(wp_cpu):
    """The centre_search base in a path: the step's command is the plain path's pose of clip(a + the base's actions),
    the base's computed by a twin controller fed the same observations: zeta = 0 until the blocked test holds (the
    step is a's alone), the spiral about the observed target after."""
    from vkgrl_newton.envs.evaluation import base_controller
    from vkgrl_newton.envs.kgrl_action import KGRLActionPath

    tables = prior_tables()
    env = fake_env(2)
    path = KGRLActionPath(tables, env, reach_floor=3e-3, reach_floor_z=25e-3)
    base = base_controller("centre_search", path, "PegInsert")
    path.set_base(base)
    plain = KGRLActionPath(tables, env, reach_floor=3e-3, reach_floor_z=25e-3)
    twin = base_controller("centre_search", plain, "PegInsert")
    mean = path.tables.mean.numpy()
    a = torch.tensor([[0.05, -0.05, 0.02, 0.0], [0.0, 0.0, 0.0, 0.0]])
    moved = 0
    for n in range(90):
        env.step_index.fill_(n)
        env.episode_length_buf.fill_(n)
        # the TCP held 20 mm above the prior's seat from step 1, off the observed target: blocked at n_min (60)
        rel = torch.tensor([[0.5e-3, -0.4e-3, 0.0], [-0.2e-3, 0.7e-3, 0.0]])
        rel[:, 2] = float(mean[-1, 2] + 20e-3) if n >= 1 else float(mean[0, 2])
        env.tcp_p = env.target_frame_pos_w + rel
        b = twin.actions(env, torch.cat([torch.zeros(2, 1), env.tcp_p - env.target_frame_pos_w], -1))
        path.step(a)
        want = torch.from_numpy(np.clip(a.double().numpy() + b.double().numpy(), -1.0, 1.0)).float()
        torch.testing.assert_close(env.sent[-1][0], plain.pose(want)[0].clone(), rtol=0, atol=0)
        if n < 60:
            assert bool((b == 0).all()), n  # the prior until blocked
        moved += int(bool((b != 0).any()))
    assert base.since.tolist() == [60, 60] and moved == 30  # blocked at n_min, then searching every step


def test_the_option_is_recorded_refused_where_it_cannot_hold_and_rebuilt_by_evaluate(tmp_path):
    import argparse

    from scripts import on_the_prior
    from vkgrl_newton.run.config import ConfigError, build_parser
    from vkgrl_newton.run.evaluate import evaluation_config
    from vkgrl_newton.run.resolve import resolve

    def run(*argv):  # (on the prior's recipe: the options one by one, as before the residual recipe was the default)
        return resolve(build_parser(), [*on_the_prior(list(argv)), "--device", "cpu", "--run-dir", str(tmp_path / "r"),
                                        "--cpu-matmul", "torch"]).config

    camera = run("--method", "vision_kgrl", "--vision-probe-obs", "--kgrl-base", "centre_latent")
    assert camera.kgrl_base == "centre_latent" and camera.meta()["kgrl_base"] == "centre_latent"
    blind = run("--method", "kgrl", "--kgrl-base", "centre_search")
    assert blind.meta()["kgrl_base"] == "centre_search" and blind.obs_dim == run("--method", "kgrl").obs_dim
    for plain in (run("--method", "kgrl"), run("--method", "kgrl", "--kgrl-base", "prior")):
        assert plain.kgrl_base == "prior" and "kgrl_base" not in plain.meta()  # older runs still resume
    with pytest.raises(ConfigError, match="--kgrl-base is for the kgrl methods on SAC"):
        run("--method", "sac", "--kgrl-base", "centre_search")
    with pytest.raises(ConfigError, match="--kgrl-base is for the kgrl methods on SAC"):
        resolve(build_parser(), ["--method", "kgrl_ppo", "--kgrl-base", "centre_search", "--device", "cpu",
                                 "--run-dir", str(tmp_path / "p")])
    with pytest.raises(ConfigError, match="add --vision-probe-obs"):
        run("--method", "vision_kgrl", "--kgrl-base", "centre_latent")
    with pytest.raises(ConfigError, match="with --kgrl-time-action"):
        run("--method", "kgrl", "--kgrl-base", "centre_search", "--kgrl-time-action", "2")
    with pytest.raises(ConfigError, match="it needs z reach"):  # the thesis's null space: ~2 mm of z there
        run("--method", "kgrl", "--kgrl-base", "centre_search", "--kgrl-recipe", "base")
    with pytest.raises(ConfigError, match="it needs z reach"):
        run("--method", "kgrl", "--kgrl-base", "centre_search", "--kgrl-reach-floor-z", "0")
    assert run("--method", "kgrl", "--kgrl-base", "centre_search", "--kgrl-recipe", "base", "--kgrl-reach-floor-z",
               "25").reach_floor_z_mm == 25.0
    # a base with the prior's seat pressed (a part that goes in unblocked is the prior's): accepted, recorded
    pressed = run("--method", "kgrl", "--kgrl-base", "centre_search", "--kgrl-seat-press", "5")
    assert pressed.seat_press_mm == 5.0 and pressed.kgrl_base == "centre_search"
    # the parser's choices are the controllers' (the command line parses before torch loads: a literal there)
    from vkgrl_newton.envs.evaluation import BASE_CONTROLLERS

    action = next(a for a in build_parser()._actions if a.dest == "kgrl_base")
    assert tuple(action.choices) == BASE_CONTROLLERS
    with pytest.raises(ConfigError, match="prior_rollouts_policy=search with --kgrl-base"):
        run("--method", "kgrl", "--kgrl-base", "centre_search", "--sac", "prior_rollouts_policy=search")
    scaled = run("--method", "kgrl", "--kgrl-base", "centre_search", "--kgrl-residual-scale", "0.2")
    assert scaled.kgrl_residual_scale == 0.2 and scaled.meta()["kgrl_residual_scale"] == 0.2
    assert "kgrl_residual_scale" not in blind.meta()
    for bad in ("0", "1.5", "nan"):
        with pytest.raises(ConfigError, match="a number in \\(0, 1\\]"):
            run("--method", "kgrl", "--kgrl-base", "centre_search", "--kgrl-residual-scale", bad)
    with pytest.raises(ConfigError, match="give --kgrl-base centre_search or centre_latent"):
        run("--method", "kgrl", "--kgrl-residual-scale", "0.5")
    args = argparse.Namespace(task="PegInsert", env="factory", action_dim=4, seed=0, num_envs=2, no_time_obs=False,
                              geometry=None, demos=None, kmp_reference="gmr", device="cpu", cache_dir=tmp_path,
                              eager_physics=False, policy=None)
    assert evaluation_config(args, {"meta": blind.meta()}).kgrl_base == "centre_search"
    assert evaluation_config(args, {"meta": scaled.meta()}).kgrl_residual_scale == 0.2
    assert evaluation_config(args, {"meta": run("--method", "kgrl").meta()}).kgrl_base == "prior"


@pytest.mark.slow
def test_a_run_on_a_base_trains_resumes_and_its_checkpoint_evaluates_on_it(wp_cpu, tmp_path, capsys):
    import json

    from scripts import TINY_RUN, load_script

    run_dir = tmp_path / "base"
    tiny = [*TINY_RUN, "--cpu-matmul", "torch"]
    # the base through the residual recipe (its options filled in by resolve, as the test below checks)
    argv = ["--method", "kgrl", "--kgrl-recipe", "residual", "--run-dir", str(run_dir), "--eval-episodes", "0",
            "--cache-dir", str(tmp_path / "cache"), "--num-demos", "2", *tiny]
    assert load_script("run").main([*argv, "--total-steps", "16"]) == 0
    config = json.loads((run_dir / "config.json").read_text())
    assert (config["kgrl_base"], config["kgrl_residual_scale"], config["kgrl_recipe"]) == ("centre_search", 0.2,
                                                                                          "residual")
    assert config["kgrl_search_press_mm"] == 2.5  # the recipe's
    # a resume keeps the run's base and recipe (given again or not) and refuses another
    assert load_script("run").main(["--resume", "--run-dir", str(run_dir), "--total-steps", "32", "--no-progress"]) == 0
    assert json.loads((run_dir / "config.json").read_text()) == {**config, "total_steps": 32}
    with pytest.raises(SystemExit) as refused:
        load_script("run").main(["--resume", "--run-dir", str(run_dir), "--kgrl-base", "prior", "--total-steps", "48",
                                 "--no-progress"])
    assert refused.value.code == 2
    capsys.readouterr()
    with pytest.raises(SystemExit) as refused:  # nor another search press
        load_script("run").main(["--resume", "--run-dir", str(run_dir), "--kgrl-search-press", "1.5", "--total-steps",
                                 "48", "--no-progress"])
    assert refused.value.code == 2 and "kgrl_search_press_mm" in capsys.readouterr().err
    # a run of the recipe before its press was 2.5 (its meta without a press: 1 mm, the search's own) resumes at 1 mm
    old_dir = tmp_path / "press_one"
    old_argv = [*argv, "--kgrl-search-press", "1"]
    old_argv[old_argv.index(str(run_dir))] = str(old_dir)
    assert load_script("run").main([*old_argv, "--total-steps", "16"]) == 0
    old_config = json.loads((old_dir / "config.json").read_text())
    assert "kgrl_search_press_mm" not in old_config and old_config["kgrl_recipe"] == "residual"
    assert load_script("run").main(["--resume", "--run-dir", str(old_dir), "--total-steps", "32", "--no-progress"]) == 0
    assert json.loads((old_dir / "config.json").read_text()) == {**old_config, "total_steps": 32}
    out = tmp_path / "eval.json"
    assert load_script("evaluate").main(["--checkpoint", str(run_dir / "checkpoints" / "last.pt"), "--num-envs", "2",
                                         "--episodes", "1", "--device", "cpu", "--json", str(out),
                                         "--cache-dir", str(tmp_path / "cache")]) == 0
    assert json.loads(out.read_text())["episodes"] == 2


def test_the_residual_recipe_is_the_measured_options_and_gives_way_to_given_ones(tmp_path):
    """--kgrl-recipe residual (run.presets): the RunConfig of docs/results/base_floor4_40's arms (kgrl's with
    search_reach_40's firmer press), which gave the options one by one on reach_keep_prior, but for the recipe's
    name; an option given wins, one whose prerequisite is given otherwise is left out, what cannot go with the recipe
    is refused naming it; the gym id's config is run.py's."""
    import dataclasses

    from vkgrl_newton.run.config import ConfigError, build_parser
    from vkgrl_newton.run.gym import gym_config
    from vkgrl_newton.run.resolve import resolve

    def run(*argv):
        return resolve(build_parser(), [*argv, "--device", "cpu", "--run-dir", str(tmp_path / "r"), "--cpu-matmul",
                                        "torch", "--cache-dir", str(tmp_path)]).config

    floors = ["--kgrl-residual-scale", "0.2", "--kgrl-seat-press", "5", "--kgrl-reach-floor", "4"]
    measured = {"kgrl": ["--kgrl-base", "centre_search", "--kgrl-search-press", "2.5", *floors],
                "vision_kgrl": ["--vision-probe-obs", "--vision-probe-fit", "closed_loop", "--kgrl-base", "centre_latent",
                                *floors]}
    for method, options in measured.items():
        recipe = run("--method", method, "--kgrl-recipe", "residual")
        by_hand = run("--method", method, *options, "--kgrl-recipe", "reach_keep_prior")
        assert (recipe.kgrl_recipe, by_hand.kgrl_recipe) == ("residual", "reach_keep_prior")
        assert dataclasses.replace(recipe, kgrl_recipe="reach_keep_prior") == by_hand, method
        assert recipe.meta()["kgrl_recipe"] == "residual" and recipe.reach_floor_z_mm == 25.0
        kw = {f: getattr(recipe, f) for f in ("kgrl_base", "kgrl_residual_scale", "vision_probe_obs",
                                              "vision_probe_fit", "seat_press_mm", "reach_floor_mm", "reach_floor_z_mm",
                                              "kgrl_recipe", "latent_dim", "obs_dim", "kgrl_search_press_mm")}
        gym = gym_config("PegInsert", "factory", 4, method, device="cpu", cache_dir=tmp_path, kgrl_recipe="residual")
        assert {f: getattr(gym, f) for f in kw} == kw, method
    assert run("--method", "vision_kgrl", "--kgrl-recipe", "residual").kgrl_base == "centre_latent"
    # given options win; a residual scale without a base, or a probe fit without the probe, is not filled in
    on_prior = run("--method", "vision_kgrl", "--kgrl-recipe", "residual", "--kgrl-base", "prior")
    assert (on_prior.kgrl_base, on_prior.kgrl_residual_scale, on_prior.vision_probe_obs) == ("prior", 1.0, True)
    # nor the blind spiral's press off its base; the press given wins, 1 mm being the search's own (the recipe's
    # before docs/results/search_reach_40), which the meta leaves out as for any run at the search's defaults
    blind_on_prior = run("--method", "kgrl", "--kgrl-recipe", "residual", "--kgrl-base", "prior")
    assert (blind_on_prior.kgrl_base, blind_on_prior.kgrl_search_press_mm) == ("prior", None)
    assert run("--method", "kgrl", "--kgrl-recipe", "residual").kgrl_search_press_mm == 2.5
    at_one = run("--method", "kgrl", "--kgrl-recipe", "residual", "--kgrl-search-press", "1")
    assert at_one.kgrl_search_press_mm is None and "kgrl_search_press_mm" not in at_one.meta()
    assert run("--method", "kgrl", "--kgrl-recipe", "residual", "--kgrl-search-speed", "0.15").kgrl_search_speed_mm \
        == 0.15
    assert run("--method", "kgrl", "--kgrl-recipe", "residual", "--kgrl-residual-scale", "0.5",
               "--kgrl-reach-floor", "3").kgrl_residual_scale == 0.5
    assert run("--method", "kgrl", "--kgrl-recipe", "residual", "--kgrl-reach-floor", "3").reach_floor_mm == 3.0
    # the quick preset's default here (run.presets.QUICK_KGRL_RECIPE); the other recipes set no run options: the
    # quick default elsewhere and the thesis's, as before
    assert run("--method", "vision_kgrl").kgrl_base == "centre_latent"
    for plain in (run("--method", "vision_kgrl", "--task", "GearMesh"), run("--method", "vision_kgrl", "--env", "forge"),
                  run("--method", "vision_kgrl", "--kgrl-recipe", "reach_keep_prior")):
        assert (plain.kgrl_recipe, plain.kgrl_base, plain.vision_probe_obs, plain.seat_press_mm) == \
            ("reach_keep_prior", "prior", False, 0.0)
    assert run("--method", "kgrl", "--preset", "thesis").kgrl_base == "prior"
    for argv, message in ((["--method", "vision_kgrl", "--kgrl-recipe", "residual", "--vae", str(tmp_path / "v.pt")],
                           "--vae with --kgrl-recipe residual: "),
                          (["--method", "kgrl", "--kgrl-recipe", "residual", "--kgrl-time-action", "2"],
                           "--kgrl-time-action with --kgrl-recipe residual: ")):
        with pytest.raises(ConfigError, match=message) as e:
            run(*argv)
        assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="vae with the KGRL recipe residual"):
        gym_config("PegInsert", "factory", 4, "vision_kgrl", device="cpu", vae=tmp_path / "v.pt", kgrl_recipe="residual")


def test_the_prior_evaluation_a_run_reuses_is_its_own_bases(tmp_path):
    """a = 0 is the base controller: the cached evaluation of a = 0 (run.train.prior_evaluation_key) is keyed by the
    base, and centre_latent's by the VAE and probe files it steers by (their sha256, against hashlib's)."""
    import hashlib

    from vkgrl_newton.run.config import RunConfig
    from vkgrl_newton.run.train import prior_evaluation_key

    env = SimpleNamespace(num_envs=2, device="cpu", cfg=SimpleNamespace(vision_latent_dim=18))
    path = SimpleNamespace(tables=SimpleNamespace(mean=torch.zeros(3, 6), gain=torch.zeros(3, 6, 6)))
    vae, probe = tmp_path / "vae.pt", tmp_path / "probe.npz"
    vae.write_bytes(b"vae")
    probe.write_bytes(b"probe")
    common = {"method": "vision_kgrl", "vae": vae, "vision_probe_obs": True, "probe": probe, "cache_dir": tmp_path}
    keys = {base: prior_evaluation_key(RunConfig(kgrl_base=base, **common), env, path)
            for base in ("prior", "centre_search", "centre_latent")}
    assert len({str(sorted(k.items())) for k in keys.values()}) == 3
    assert keys["centre_latent"]["vae_sha256"] == hashlib.sha256(b"vae").hexdigest()
    assert keys["centre_latent"]["probe_sha256"] == hashlib.sha256(b"probe").hexdigest()
    assert "probe_sha256" not in keys["prior"] and "probe_sha256" not in keys["centre_search"]
    scaled = prior_evaluation_key(RunConfig(kgrl_base="centre_latent", kgrl_residual_scale=0.2, **common), env, path)
    assert scaled == keys["centre_latent"]  # the scale leaves a = 0 alone
    # the same base through another null space (reach floors: the gain) is another a = 0; the mean alone is the same
    wider = SimpleNamespace(tables=SimpleNamespace(mean=torch.zeros(3, 6), gain=torch.ones(3, 6, 6)))
    assert prior_evaluation_key(RunConfig(kgrl_base="centre_search", **common), env, path) != \
        prior_evaluation_key(RunConfig(kgrl_base="centre_search", **common), env, wider)
    assert prior_evaluation_key(RunConfig(**common), env, path) == prior_evaluation_key(RunConfig(**common), env, wider)
    # --force-obs draws from the generator of the episodes' resets: other episodes
    assert prior_evaluation_key(RunConfig(method="kgrl", force_obs=True), env, path) != \
        prior_evaluation_key(RunConfig(method="kgrl"), env, path)
    probe.write_bytes(b"another probe")
    assert prior_evaluation_key(RunConfig(kgrl_base="centre_latent", **common), env, path) != keys["centre_latent"]


def test_a_base_on_a_pressed_prior_steers_and_settles_on_the_pressed_tables(wp_cpu):
    """--kgrl-seat-press with a base: the base's a = 0 and its settled z are the pressed prior's (kmp.tables.
    with_seat_press, the path's own tables): its mean is the pressed mean, its seat the pressed seat, and its settled
    z ORACLE_PUSH_MM under the pressed z."""
    from vkgrl_newton.envs.evaluation import ORACLE_PUSH_MM, base_controller
    from vkgrl_newton.envs.kgrl_action import KGRLActionPath
    from vkgrl_newton.kmp.tables import with_seat_press

    tables = prior_tables()
    env = fake_env(2)
    path = KGRLActionPath(tables, env, reach_floor=3e-3, reach_floor_z=25e-3, seat_press=5e-3)
    base = base_controller("centre_search", path, "PegInsert")
    want = with_seat_press(tables, 5e-3).mean.to(torch.float64)
    torch.testing.assert_close(base.mean, want, rtol=0, atol=0)
    # (seat_z is the same float64 read of the same float32 entry: exact. The press: a difference of two float32 z's
    # of ~0.05 m, each rounded to ~4e-9 m; 1e-6 is far outside that and far inside a wrong press's millimetres)
    assert base.seat_z == float(want[-1, 2]) and float(tables.mean[-1, 2]) - base.seat_z == pytest.approx(5e-3, abs=1e-6)
    m = base.mean[-1:, :3]
    z = base._settled_z(env, torch.zeros(1, 3, dtype=torch.float64), m)
    assert float(z) == pytest.approx(float(want[-1, 2]) - 1e-3 * ORACLE_PUSH_MM, abs=1e-12)


def test_the_runs_last_line_names_its_a0():
    """run.py's closing line says what a = 0 was: the prior, or the base controller of --kgrl-base (the residual
    recipe's, the quick default on PegInsert Factory 4D), whose success is not the prior's."""
    from vkgrl_newton.run.train import paired_line

    gain = {"mean": 0.25, "ci_low": 0.1, "ci_high": 0.4, "n_pairs": 128, "a_mean": 0.5, "b_mean": 0.25,
            "confidence": 0.95, "reps": 100}
    metrics = {"success_rate": 0.5, "prior_eval": {"success_rate": 0.25}, "paired_gain": {"success_rate": gain}}
    assert paired_line(metrics).startswith("success 0.500, the prior 0.250 on the same 128 episodes: gain +0.250")
    line = paired_line({**metrics, "kgrl_base": "centre_latent"})
    assert line.startswith("success 0.500, its a = 0 (the centre_latent controller) 0.250 on the same 128 episodes")


@pytest.mark.parametrize("extra, on_cpu", [
    (["--kgrl-time-action", "2"], r"--kgrl-time-action with the quick preset's KGRL recipe for PegInsert factory 4D "
                                  r"\(residual\)"),
    (["--kgrl-reach-floor-z", "0"], r"--kgrl-base centre_search .* needs z reach"),
])
def test_a_refusal_of_the_guessed_quick_recipe_waits_for_the_device(extra, on_cpu, monkeypatch, tmp_path):
    """Neither --device nor --preset: the preset is the quick one's guess until Warp names the device. On a CUDA
    machine the run is the thesis preset's (recipe base, a = 0 the prior), which takes these options; the residual
    recipe's refusal is made only where the quick preset holds (here a CPU)."""
    from vkgrl_newton import runtime
    from vkgrl_newton.run.config import ConfigError, build_parser
    from vkgrl_newton.run.resolve import resolve

    argv = ["--method", "kgrl", "--run-dir", str(tmp_path / "r"), *extra]
    monkeypatch.setattr(runtime, "default_device", lambda: "cuda:0")
    monkeypatch.setattr(runtime, "device_error", lambda device, flag="--device": None)
    config = resolve(build_parser(), argv).config
    assert (config.preset, config.kgrl_recipe, config.kgrl_base, config.device) == ("thesis", "base", "prior", "cuda:0")
    monkeypatch.setattr(runtime, "default_device", lambda: "cpu")
    with pytest.raises(ConfigError, match=on_cpu):
        resolve(build_parser(), argv)
    with pytest.raises(ConfigError, match=on_cpu):  # a CPU named: refused at once, as before
        resolve(build_parser(), [*argv, "--device", "cpu"])


def test_the_blind_bases_spiral_runs_at_the_given_speed_and_press(wp_cpu, tmp_path):
    """--kgrl-search-speed MM: the centre_search base's spiral (KMPCentrePolicy) follows spiral_offset at MM per step:
    its commanded x, y over the blocked steps is the Archimedean spiral's arc at that speed (closed form: the arc of
    r = b theta from 0 to theta is b theta^2 / 2 to first order, so after k steps at v the radius is sqrt(2 b v k));
    the option is recorded, keys a = 0's cached evaluation, is rebuilt by evaluate and refused off centre_search."""
    import argparse
    import math

    from vkgrl_newton.envs.evaluation import base_controller, task_search_params
    from vkgrl_newton.envs.kgrl_action import KGRLActionPath
    from vkgrl_newton.run.config import ConfigError, RunConfig, build_parser
    from vkgrl_newton.run.evaluate import evaluation_config
    from vkgrl_newton.run.resolve import resolve
    from vkgrl_newton.run.train import prior_evaluation_key

    env = fake_env(1)
    path = KGRLActionPath(prior_tables(), env, reach_floor=4e-3, reach_floor_z=25e-3)
    slow = base_controller("centre_search", path, "PegInsert", search_speed_mm=0.15)
    assert slow.params == replace(task_search_params("PegInsert"), speed_mm=0.15)
    assert base_controller("centre_search", path, "PegInsert").params.speed_mm == 0.3
    mean = path.tables.mean.numpy()
    radii = {}
    for n in range(120):  # blocked 20 mm above the seat from step 1, the TCP on the observed target: found at 60
        env.step_index.fill_(n)
        env.episode_length_buf.fill_(n)
        rel = torch.tensor([[0.0, 0.0, float(mean[-1, 2] + 20e-3) if n >= 1 else float(mean[0, 2])]])
        env.tcp_p = env.target_frame_pos_w + rel
        slow.actions(env, torch.cat([torch.zeros(1, 1), rel], -1))
        if n >= 60:  # the wanted x, y before the lead (the TCP sits at 0, so want = (1 + track) spiral)
            radii[n - 60] = float(slow._last[0][0, :2].norm()) / (1.0 + slow.params.track)
    assert slow.since.tolist() == [60]
    b = 1.2e-3 / (2 * math.pi)
    for k in (20, 40, 59):
        want = math.sqrt(2 * b * 0.15e-3 * k)  # float64 closed form of spiral_offset's radius
        assert abs(radii[k] - want) < 1e-12, (k, radii[k], want)
    for bad in (0.0, -0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="search_speed_mm"):
            base_controller("centre_search", path, "PegInsert", search_speed_mm=bad)
    with pytest.raises(ValueError, match="not of 'prior'"):
        base_controller("prior", path, "PegInsert", search_speed_mm=0.15)
    # --kgrl-search-press: while searching, z is commanded that far below the TCP (the spiral's own x, y unchanged)
    pressed = base_controller("centre_search", path, "PegInsert", search_press_mm=2.5)
    assert pressed.params == replace(task_search_params("PegInsert"), press_mm=2.5)
    for n in range(62):
        env.step_index.fill_(n)
        env.episode_length_buf.fill_(n)
        z = float(mean[-1, 2] + 20e-3) if n >= 1 else float(mean[0, 2])
        rel = torch.tensor([[0.0, 0.0, z]])
        env.tcp_p = env.target_frame_pos_w + rel
        pressed.actions(env, torch.cat([torch.zeros(1, 1), rel], -1))
    # (the observed z, float32, in float64 less 2.5 mm: one float64 rounding)
    assert pressed.since.tolist() == [60] and abs(float(pressed._last[0][0, 2]) - (float(rel[0, 2]) - 2.5e-3)) < 1e-15
    for bad in (0.0, 11.0, float("inf")):
        with pytest.raises(ValueError, match="search_press_mm"):
            base_controller("centre_search", path, "PegInsert", search_press_mm=bad)

    def run(*argv):
        return resolve(build_parser(), [*argv, "--device", "cpu", "--run-dir", str(tmp_path / "r"), "--cpu-matmul",
                                        "torch", "--cache-dir", str(tmp_path)]).config

    cfg = run("--method", "kgrl", "--kgrl-recipe", "residual", "--kgrl-search-speed", "0.15")
    assert cfg.kgrl_base == "centre_search" and cfg.kgrl_search_speed_mm == 0.15
    assert cfg.meta()["kgrl_search_speed_mm"] == 0.15
    assert "kgrl_search_speed_mm" not in run("--method", "kgrl", "--kgrl-recipe", "residual").meta()
    with pytest.raises(ConfigError, match="not of the prior"):
        run("--method", "kgrl", "--kgrl-recipe", "reach_keep_prior", "--kgrl-search-speed", "0.15")
    with pytest.raises(ConfigError, match="not of --kgrl-base centre_latent"):
        run("--method", "vision_kgrl", "--kgrl-recipe", "residual", "--kgrl-search-speed", "0.15")
    for bad in ("0", "2", "nan"):
        with pytest.raises(ConfigError, match="mm per control step, in \\(0, 1\\]"):
            run("--method", "kgrl", "--kgrl-recipe", "residual", "--kgrl-search-speed", bad)
    both = run("--method", "kgrl", "--kgrl-recipe", "residual", "--kgrl-search-press", "2.5")
    assert both.kgrl_search_press_mm == 2.5 and both.meta()["kgrl_search_press_mm"] == 2.5
    assert "kgrl_search_speed_mm" not in both.meta()
    for bad in ("0", "11", "nan"):
        with pytest.raises(ConfigError, match="mm below the TCP, in \\(0, 10\\]"):
            run("--method", "kgrl", "--kgrl-recipe", "residual", "--kgrl-search-press", bad)
    with pytest.raises(ConfigError, match="--kgrl-search-press sets the blind spiral search"):
        run("--method", "kgrl", "--kgrl-recipe", "reach_keep_prior", "--kgrl-search-press", "2.5")
    args = argparse.Namespace(task="PegInsert", env="factory", action_dim=4, seed=0, num_envs=2, no_time_obs=False,
                              geometry=None, demos=None, kmp_reference="gmr", device="cpu", cache_dir=tmp_path,
                              eager_physics=False, policy=None)
    assert evaluation_config(args, {"meta": cfg.meta()}).kgrl_search_speed_mm == 0.15
    assert evaluation_config(args, {"meta": both.meta()}).kgrl_search_press_mm == 2.5
    # a residual run from before the recipe's 2.5 (no press in its meta) is rebuilt at the search's own 1 mm
    old_meta = {k: v for k, v in both.meta().items() if k != "kgrl_search_press_mm"}
    assert evaluation_config(args, {"meta": old_meta}).kgrl_search_press_mm is None
    key_env = SimpleNamespace(num_envs=2, device="cpu", cfg=SimpleNamespace(vision_latent_dim=0))
    tables = SimpleNamespace(tables=SimpleNamespace(mean=torch.zeros(3, 6), gain=torch.zeros(3, 6, 6)))
    assert prior_evaluation_key(RunConfig(method="kgrl", kgrl_base="centre_search", kgrl_search_speed_mm=0.15),
                                key_env, tables) != \
        prior_evaluation_key(RunConfig(method="kgrl", kgrl_base="centre_search"), key_env, tables)
    assert prior_evaluation_key(RunConfig(method="kgrl", kgrl_base="centre_search", kgrl_search_press_mm=2.5),
                                key_env, tables) != \
        prior_evaluation_key(RunConfig(method="kgrl", kgrl_base="centre_search"), key_env, tables)


def test_the_search_options_defaults_methods_guessed_recipe_and_build(monkeypatch, tmp_path):
    """The search options' defaults are SearchParams' for every task, and a value given equal to one is the run
    without the option (the residual recipe's press given is the recipe's run); a method without a base is refused as
    --kgrl-base is; with neither --device nor --preset the refusal another option causes is that option's, and on a
    CUDA default (the thesis preset: a = 0 the prior) the search option is refused; build_action_path hands the run's
    values to the base."""
    from vkgrl_newton import runtime
    from vkgrl_newton.envs import evaluation
    from vkgrl_newton.envs.evaluation import task_search_params
    from vkgrl_newton.run.build import build_action_path
    from vkgrl_newton.run.config import SEARCH_PRESS_MM, SEARCH_SPEED_MM, ConfigError, RunConfig, build_parser
    from vkgrl_newton.run.resolve import resolve
    from vkgrl_newton.tools.ceiling import CEILING_GEOMETRY

    for task in CEILING_GEOMETRY:
        assert (task_search_params(task).speed_mm, task_search_params(task).press_mm) == (SEARCH_SPEED_MM,
                                                                                        SEARCH_PRESS_MM)

    def run(*argv, device=("--device", "cpu")):
        return resolve(build_parser(), [*argv, *device, "--run-dir", str(tmp_path / "r"), "--cpu-matmul", "torch",
                                        "--cache-dir", str(tmp_path)]).config

    plain = run("--method", "kgrl", "--kgrl-recipe", "residual")  # (its press the recipe's 2.5, its speed the search's)
    assert run("--method", "kgrl", "--kgrl-recipe", "residual", "--kgrl-search-speed", "0.3",
               "--kgrl-search-press", "2.5") == plain
    on_by_hand = run("--method", "kgrl", "--kgrl-recipe", "reach_keep_prior", "--kgrl-base", "centre_search")
    assert run("--method", "kgrl", "--kgrl-recipe", "reach_keep_prior", "--kgrl-base", "centre_search",
               "--kgrl-search-speed", "0.3", "--kgrl-search-press", "1") == on_by_hand
    assert RunConfig(kgrl_search_speed_mm=0.3, kgrl_search_press_mm=1.0) == RunConfig()  # however it is built
    with pytest.raises(ConfigError, match="--kgrl-search-press is for the kgrl methods on SAC"):
        run("--method", "sac", "--kgrl-search-press", "2.5")
    with pytest.raises(ConfigError, match="--kgrl-search-speed is for the kgrl methods on SAC"):
        resolve(build_parser(), ["--method", "kgrl_ppo", "--kgrl-search-speed", "0.15", "--device", "cpu",
                                 "--run-dir", str(tmp_path / "p")])
    # the guessed quick recipe: --privileged-critic with its prior anchor is the refusal, on a CPU default
    monkeypatch.setattr(runtime, "device_error", lambda device, flag="--device": None)
    monkeypatch.setattr(runtime, "default_device", lambda: "cpu")
    with pytest.raises(ConfigError, match="--privileged-critic with the prior anchor"):
        run("--method", "kgrl", "--kgrl-search-press", "2.5", "--privileged-critic", device=())
    assert run("--method", "kgrl", "--kgrl-search-press", "2.5", device=()).kgrl_search_press_mm == 2.5
    monkeypatch.setattr(runtime, "default_device", lambda: "cuda:0")
    with pytest.raises(ConfigError, match="--kgrl-search-press sets the blind spiral search .* not of the prior"):
        run("--method", "kgrl", "--kgrl-search-press", "2.5", device=())
    # build_action_path: the base gets the run's search values
    seen = {}
    monkeypatch.setattr(evaluation, "base_controller", lambda name, path, task, **kw: seen.update(name=name, **kw))
    monkeypatch.setattr("vkgrl_newton.run.build.prior_tables", lambda cfg, log=print: (prior_tables(), None))
    cfg = RunConfig(method="kgrl", kgrl_base="centre_search", kgrl_search_speed_mm=0.15, kgrl_search_press_mm=2.5,
                    reach_floor_mm=4.0, reach_floor_z_mm=25.0)
    build_action_path(cfg, fake_env(1), log=lambda *a: None)
    assert seen == {"name": "centre_search", "search_speed_mm": 0.15, "search_press_mm": 2.5}
