"""The captured control step (sim/physics.py, EnvConfig.graph=True) against the eager launches
(graph=False, the reference): two envs of the same config and seed, one eager and one captured,
the same inputs, and every observation, reward, done, body pose and contact-force statistic
bitwise equal at every step, across a time-out reset and a blow-up reset of one world. (Two eager
envs of one seed are bitwise equal too, measured: so a difference here is the graph's.)"""

import numpy as np
import pytest
import torch

E = 4
STEPS = 40
TIME_OUT_AT, BLOW_UP_AT = 14, 27  # control steps at which world 0..3 time out / world 1 blows up


def _make(wp_cpu, family, action_dim, graph, **sim):
    from vkgrl_newton.envs.assembly_env import AssemblyEnv, EnvConfig
    from vkgrl_newton.sim.scene import SimConfig

    return AssemblyEnv(EnvConfig(task="PegInsert", family=family, action_dim=action_dim, num_envs=E, device="cpu",
                                 seed=3, graph=graph, sim=SimConfig(**sim)))


def _record(env, obs, rew, dones, extras):
    import warp as wp

    return {
        "obs": obs["policy"].clone(), "reward": rew.clone(), "dones": dones.clone(),
        "time_outs": extras["time_outs"].clone(), "physics_resets": extras["physics_resets"].clone(),
        "body_q": wp.to_torch(env.state_0.body_q).clone(), "joint_qd": wp.to_torch(env.state_0.joint_qd).clone(),
        "force_smoothed": env.force_smoothed_w.clone(), "force_sum": env.force_norm_sum.clone(),
        "force_peak": env.force_peak.clone(), "force_count": env.force_count.clone(),
        "final_obs": extras["final_observations"]["policy"].clone() if "final_observations" in extras else None,
    }


def _rollout(env, path, steps=STEPS, hook=None):
    """`steps` control steps of a deterministic policy: Factory's delta actions pressing down with
    a seeded wobble (contact within a few steps), or the scripted demonstrator's poses 3 cm lower."""
    from vkgrl_newton.envs.scripted import ScriptedInserter

    g = torch.Generator().manual_seed(11)
    inserter = ScriptedInserter(seed=0)
    inserter.reset(env)
    out = []
    for i in range(steps):
        if hook is not None:
            hook(i, env)
        if i == TIME_OUT_AT:  # every world times out on this step: the auto-reset runs
            env.episode_length_buf[:] = env.max_episode_length - 1
        if i == BLOW_UP_AT:  # world 1 blows up on this step: it alone is reset
            env._state_views(env.state_0)["joint_qd"][1, env.scene.held_qd_start:env.scene.held_qd_start + 6] = 1e3
        if path == "step":
            a = 0.3 * (2 * torch.rand(E, env.num_actions, generator=g) - 1)
            a[:, 2] = -0.7
            result = env.step(a)
        else:
            pos, quat = inserter.act(env)
            result = env.step_pose(pos - torch.tensor([0.0, 0.0, 0.03]), quat)  # 3 cm low: in contact soon
        out.append(_record(env, *result))
        if i in (TIME_OUT_AT, BLOW_UP_AT):
            inserter.reset(env)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("family,action_dim,path", [
    ("factory", 4, "step"), ("forge", 6, "step"), ("factory", 6, "step_pose"), ("forge", 4, "step_pose")])
def test_graph_equals_eager(wp_cpu, family, action_dim, path):
    eager, graph = _make(wp_cpu, family, action_dim, False), _make(wp_cpu, family, action_dim, True)
    assert graph.physics.captures == 1  # the reset's settle: first unit eager, the rest one graph
    assert torch.equal(wp_cpu.to_torch(eager.state_0.body_q), wp_cpu.to_torch(graph.state_0.body_q))
    ref, got = _rollout(eager, path), _rollout(graph, path)
    assert eager.physics.captures == 0 and graph.physics.captures == 2  # + the control step's graph
    # the rollout went through what it is meant to cover
    assert ref[TIME_OUT_AT]["time_outs"].all() and ref[TIME_OUT_AT]["final_obs"] is not None
    assert ref[BLOW_UP_AT]["physics_resets"].tolist() == [False, True, False, False]
    assert max(r["force_peak"].max().item() for r in ref) > 0.5  # in contact (N)
    assert eager.contact_overflows_total == 0  # PegInsert's default buffers hold its contacts
    # bitwise: the SAME kernels, eager or replayed from a captured graph, on this machine (a CPU with other
    # roundings changes both rollouts alike; the comparison never crosses machines)
    for i, (a, b) in enumerate(zip(ref, got)):
        for key in a:
            if a[key] is None:
                assert b[key] is None, (i, key)
            else:
                assert torch.equal(a[key], b[key]), f"step {i}: {key} differs, max {(a[key] - b[key]).abs().max()}"


@pytest.mark.slow
def test_reallocated_array_triggers_a_recapture(wp_cpu):
    """The env's command buffer is replaced by a new one (the pose path writes the command there
    before each control step): a graph still reading the old buffer would track the old command,
    so the results equal the eager env's only if the stepper captured again."""
    import warp as wp

    captures = []

    def reallocate(i, env):
        captures.append(env.physics.captures)
        if i == 3:
            env.cmd_pos_w = env.cmd_pos_w.clone()
            env.physics.controller.cmd_pos_w = wp.from_torch(env.cmd_pos_w, dtype=wp.vec3)

    eager, graph = _make(wp_cpu, "factory", 6, False), _make(wp_cpu, "factory", 6, True)
    ref = _rollout(eager, "step_pose", steps=6, hook=reallocate)
    got = _rollout(graph, "step_pose", steps=6, hook=reallocate)
    # settle graph; step 0 eager (first unit), step 1 captures; step 3 captures again, then replays
    assert captures[6:] == [1, 1, 2, 2, 3, 3] and graph.physics.captures == 3
    for a, b in zip(ref, got):
        assert torch.equal(a["body_q"], b["body_q"]) and torch.equal(a["obs"], b["obs"])
    assert not torch.equal(ref[3]["body_q"], ref[2]["body_q"])  # the commands moved the arm meanwhile


@pytest.mark.slow
def test_contact_overflow_is_counted_and_warned(wp_cpu):
    """Buffers too small for the grasp's contacts (> 2 per world): counted, reported, warned, never
    silent, and the same count in the graph as in the eager reference."""
    counts = {}
    for graph in (False, True):
        with pytest.warns(RuntimeWarning, match="nconmax"):
            env = _make(wp_cpu, "factory", 4, graph, nconmax=2, njmax=8)
            logged = [env.step(torch.zeros(E, 4))[3]["log"]["/contact_overflows"] for _ in range(3)]
        assert logged[0] > 0  # the reset's settle overflowed: reported with the first step
        # counted per world and substep (a shared-buffer overflow flags every world), read before any
        # reset's settle of the step, so the total only ever lags the device counters
        assert env.contact_overflows_total <= int(env.contact_overflow_substeps.sum())
        counts[graph] = (logged, env.contact_overflow_substeps.clone(), env.physics.overflow_bits.numpy().copy())
    assert counts[False][0] == counts[True][0]
    assert torch.equal(counts[False][1], counts[True][1])
    np.testing.assert_array_equal(counts[False][2], counts[True][2])
    bits = int(np.bitwise_or.reduce(counts[True][2]))
    from newton.solvers import SolverMuJoCo

    assert bits & int(SolverMuJoCo.OverflowBits.CONTACT_PIPELINE | SolverMuJoCo.OverflowBits.SOLVER_NCONMAX)


@pytest.mark.slow
def test_throughput_cli_times_both_modes(wp_cpu, tmp_path):
    import json

    from vkgrl_newton.tools import throughput

    out = tmp_path / "t.json"
    assert throughput.main(["--num-worlds", "1", "--steps", "1", "--warmup", "2", "--device", "cpu",
                            "--json", str(out)]) == 0
    results = json.loads(out.read_text())["results"]
    assert [(r["task"], r["num_worlds"], r["mode"]) for r in results] == [("PegInsert", 1, "eager"),
                                                                          ("PegInsert", 1, "graph")]
    for r in results:
        # float64 reciprocal and product: <= 2 u64 * 1e3 ~ 2e-13 (IEEE); 1e-6 bounds it
        assert r["env_steps_per_s"] > 0 and abs(r["ms_per_env_step"] * r["env_steps_per_s"] - 1e3) < 1e-6
    assert "split_ms_per_env_step" in results[0] and results[1]["speedup"] > 0
    with pytest.raises(SystemExit):  # never overwritten
        throughput.main(["--num-worlds", "1", "--steps", "1", "--json", str(out)])
    with pytest.raises(SystemExit):
        throughput.main(["--graph", "sometimes"])
    with pytest.raises(SystemExit):  # the graph's recording would be timed
        throughput.main(["--warmup", "1", "--json", str(tmp_path / "u.json")])
    # with the task camera and an encoder: the eager split has a vision stage, and it is not
    # also counted as "python" (the split sums to the profiled step)
    out = tmp_path / "v.json"
    assert throughput.main(["--num-worlds", "1", "--steps", "1", "--warmup", "0", "--device", "cpu", "--graph", "off",
                            "--vision", "quick", "--json", str(out)]) == 0
    (r,) = json.loads(out.read_text())["results"]
    split = r["split_ms_per_env_step"]
    assert r["vision"] == "quick" and split["vision"] > 0
    # "python" is the profiled total minus the stages: the sum is the total up to float64
    # rounding of ~7 additions (~1e-15 relative)
    assert sum(split.values()) == pytest.approx(r["profiled_ms_per_env_step"], rel=1e-9)
    with pytest.raises(SystemExit):
        throughput.main(["--vision", "blurry", "--json", str(tmp_path / "w.json")])


@pytest.mark.slow
def test_collision_once_per_physics_step(wp_cpu):
    """SimConfig(collide_every_substep=False): one collide per physics step, its contacts used by
    all of its substeps (the default collides before every substep)."""
    from vkgrl_newton.sim.scene import SimConfig

    with pytest.raises(ValueError, match="collide_every_substep"):
        SimConfig(collide_every_substep="no")
    for every, per_step in ((True, 4), (False, 1)):
        env = _make(wp_cpu, "factory", 4, False, collide_every_substep=every)
        calls = []
        collide = env.physics.pipeline.collide
        env.physics.pipeline.collide = lambda *a, **k: (calls.append(1), collide(*a, **k))
        env.step(torch.zeros(E, 4))
        assert len(calls) == 8 * per_step
